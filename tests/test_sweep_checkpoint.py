"""Resumable sweeps (`checkpoint=`, `--checkpoint`): a resumed sweep computes only the
missing chunks and equals an uninterrupted one; other plans, damaged chunks and unusable
directories are handled."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import equinox as eqx
import numpy as np
import pytest

import crank_jax as cj

SPEC = {"k": "normal(2.0,0.1)", "c": "uniform(0.005,0.02)"}
KW = dict(n=12, seed=3, t1=0.3, num_saves=11, chunk_size=2)
OUTS = ("peak_phi", "final_energy")


class _Stop(Exception):
    pass


def _equal(a, b):
    assert np.array_equal(a.status, b.status) and np.array_equal(a.num_steps, b.num_steps)
    for k in a.outputs:
        np.testing.assert_array_equal(a.outputs[k], b.outputs[k])


def test_a_resumed_sweep_computes_only_the_missing_chunks_and_equals_a_whole_one(
        lab_rig, tmp_path):
    whole = cj.run_sweep(lab_rig, SPEC, OUTS, **KW)
    ckpt = tmp_path / "ck"

    def stop_after_two(done, total):
        if done >= 4:  # two chunks of 2 (one device in the tests' process)
            raise _Stop

    with pytest.raises(_Stop):
        cj.run_sweep(lab_rig, SPEC, OUTS, checkpoint=ckpt, callback=stop_after_two, **KW)
    saved = sorted(ckpt.glob("chunk-*.npz"))
    assert 0 < len(saved) < 6
    # Damage one saved chunk: it is detected and computed again.
    raw = bytearray(saved[0].read_bytes())
    raw[-40] ^= 0xFF
    saved[0].write_bytes(bytes(raw))
    kept = {p: p.stat().st_mtime_ns for p in saved[1:]}
    resumed = cj.run_sweep(lab_rig, SPEC, OUTS, checkpoint=ckpt, **KW)
    _equal(resumed, whole)
    # The good chunks were read, not computed and written again; the damaged one was.
    assert kept == {p: p.stat().st_mtime_ns for p in saved[1:]}
    assert saved[0].read_bytes() != bytes(raw)
    assert len(list(ckpt.glob("chunk-*.npz"))) == 6
    # A third run reads everything and computes nothing new (every chunk file unchanged).
    stamps = {p: p.stat().st_mtime_ns for p in ckpt.glob("chunk-*.npz")}
    again = cj.run_sweep(lab_rig, SPEC, OUTS, checkpoint=ckpt, **KW)
    _equal(again, whole)
    assert stamps == {p: p.stat().st_mtime_ns for p in ckpt.glob("chunk-*.npz")}


def test_another_plan_is_refused_naming_what_differs(lab_rig, tmp_path):
    ckpt = tmp_path / "ck"
    cj.run_sweep(lab_rig, SPEC, OUTS, checkpoint=ckpt, **{**KW, "n": 2})
    with pytest.raises(ValueError, match=r"holds another sweep: its seed differ"):
        cj.run_sweep(lab_rig, SPEC, OUTS, checkpoint=ckpt, **{**KW, "n": 2, "seed": 4})
    with pytest.raises(ValueError, match=r"its scene differ"):
        cj.run_sweep(eqx.tree_at(lambda s: s.phi0, lab_rig, 0.2), SPEC, OUTS, checkpoint=ckpt,
                 **{**KW, "n": 2})
    with pytest.raises(ValueError, match=r"its samples differ"):
        cj.run_sweep(lab_rig, {"k": "normal(2.0,0.2)"}, OUTS, checkpoint=ckpt, **{**KW, "n": 2})


@pytest.mark.parametrize("first, second", [
    ("normal(2,0.1)", "normal(2.0000004,0.1)"),
    ("const(100000)", "const(100000.4)"),
])
def test_plans_are_compared_exactly_not_by_their_printed_text(lab_rig, tmp_path, first,
                                                              second):
    """Issue 37 item 5: the manifest held `%g` text, so these pairs were one plan and the
    second run reused the first's chunks with exit 0."""
    ckpt = tmp_path / "ck"
    kw = {**KW, "n": 2}
    cj.run_sweep(lab_rig, {"k": "normal(2.0,0.1)", "phi0": first}, OUTS, checkpoint=ckpt, **kw)
    with pytest.raises(ValueError, match=r"its samples differ"):
        cj.run_sweep(lab_rig, {"k": "normal(2.0,0.1)", "phi0": second}, OUTS, checkpoint=ckpt,
                 **kw)


def test_a_chunk_of_another_plan_is_computed_again_without_a_manifest(lab_rig, tmp_path):
    """Issue 37 item 6: with `manifest.json` deleted, another sweep into the directory
    read the first one's chunks (same sample indices) and returned their outputs."""
    ckpt = tmp_path / "ck"
    kw = {**KW, "n": 4, "sort": False}  # the same chunk indices in both plans
    cj.run_sweep(lab_rig, {"phi0": np.array([0.5, 0.6, 0.7, 0.8])}, OUTS, checkpoint=ckpt, **kw)
    (ckpt / "manifest.json").unlink()
    other = {"phi0": np.array([1.0, 1.1, 1.2, 1.3])}
    got = cj.run_sweep(lab_rig, other, OUTS, checkpoint=ckpt, **kw)
    _equal(got, cj.run_sweep(lab_rig, other, OUTS, **kw))


def test_a_checkpoint_that_is_a_file_or_not_a_directory_is_refused(lab_rig, tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(ValueError, match="is a file, not a directory"):
        cj.run_sweep(lab_rig, SPEC, OUTS, checkpoint=f, **KW)
    with pytest.raises(ValueError, match="cannot create the directory"):
        cj.run_sweep(lab_rig, SPEC, OUTS, checkpoint=f / "sub", **KW)


@pytest.mark.slow
def test_the_cli_resumes_after_sigkill(tmp_path):
    env = dict(os.environ, CRANK_JAX_NO_CACHE="1", JAX_PLATFORMS="cpu",
               PYTHONPATH=str(Path(__file__).resolve().parent.parent / "src"))
    base = [sys.executable, "-m", "crank_jax", "sweep", "lab-rig", "--vary",
            "k=normal(2,0.1)", "--n", "400", "--chunk-size", "8", "--t1", "1", "--quiet"]
    ck = tmp_path / "ck"
    p = subprocess.Popen(base + ["--out", str(tmp_path / "a.npz"), "--checkpoint", str(ck)],
                         env=env)
    deadline = time.time() + 600
    while len(list(ck.glob("chunk-*.npz"))) < 3 and time.time() < deadline:
        time.sleep(0.2)
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    done = len(list(ck.glob("chunk-*.npz")))
    assert done >= 3 and not (tmp_path / "a.npz").exists()
    subprocess.run(base + ["--out", str(tmp_path / "a.npz"), "--checkpoint", str(ck)],
                   env=env, check=True, timeout=900)
    subprocess.run(base + ["--out", str(tmp_path / "b.npz")], env=env, check=True,
                   timeout=900)
    with np.load(tmp_path / "a.npz") as a, np.load(tmp_path / "b.npz") as b:
        assert a.files == b.files
        for k in a.files:
            np.testing.assert_array_equal(a[k], b[k])


def test_cli_checkpoint_errors_are_one_line(tmp_path, capsys):
    from crank_jax import cli

    f = tmp_path / "file"
    f.write_text("x")
    argv = ["sweep", "lab-rig", "--vary", "k=normal(2,0.1)", "--n", "2", "--quiet",
            "--out", str(tmp_path / "x.npz"), "--checkpoint", str(f)]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "is a file, not a directory" in err and err.count("\n") == 1


@pytest.mark.parametrize("field", ["checkpoint", "save_trajectories"])
def test_an_empty_directory_path_is_refused_before_any_file_is_written(
        lab_rig, tmp_path, monkeypatch, field):
    # `Path("")` is the working directory: the sweep wrote its manifest and chunks there.
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match=f"{field}: the path is empty"):
        cj.run_sweep(lab_rig, SPEC, OUTS, **{field: ""}, **KW)
    assert list(tmp_path.iterdir()) == []
