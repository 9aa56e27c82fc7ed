"""Saved trajectories (`save_trajectories=`, `--save-trajectories`): streamed to disk per
chunk, read lazily, equal to the trajectories a sweep returns in memory, kept by a
resumed sweep, refused up front when the disk is too small."""

import json

import numpy as np
import pytest

import crank_jax as cj

# L = uniform(0, 0.25) (r = 0.05) makes some samples invalid (L <= r): they have no trajectory.
SPEC = {"k": "normal(2.0,0.1)", "L": "uniform(0.0,0.25)"}
KW = dict(n=12, seed=3, t1=0.3, num_saves=11, chunk_size=2)


class _Stop(Exception):
    pass


@pytest.fixture(scope="module")
def whole(lab_rig):
    """The reference: the whole trajectories, in memory."""
    return cj.run_sweep(lab_rig, SPEC, ("peak_phi", "phi", "dphi"), **KW)


def test_saved_trajectories_equal_the_in_memory_ones_subsampled(lab_rig, whole, tmp_path):
    res = cj.run_sweep(lab_rig, SPEC, ("peak_phi",), save_trajectories=tmp_path / "tr",
                   trajectory_every=3, **KW)
    np.testing.assert_array_equal(res.outputs["peak_phi"], whole.outputs["peak_phi"])
    assert "phi" not in res.outputs  # they were streamed to disk, not kept
    tr = cj.load_trajectories(tmp_path / "tr")
    np.testing.assert_array_equal(tr.ts, whole.ts[::3])
    assert tr.n == 12 and tr.manifest["complete"]
    ok = np.flatnonzero(whole.ok)
    invalid = np.flatnonzero(whole.status == cj.sweep.STATUS.index("invalid"))
    assert ok.size >= 6 and invalid.size >= 1
    got = tr[ok]
    for k in ("phi", "dphi"):
        np.testing.assert_array_equal(got[k], whole.outputs[k][ok][:, ::3])
    np.testing.assert_array_equal(tr[int(ok[0])]["phi"], whole.outputs["phi"][ok[0], ::3])
    with pytest.raises(KeyError, match="no trajectory"):
        tr[int(invalid[0])]
    # Chunk by chunk, memory-mapped: every solved sample exactly once.
    seen = []
    for idx, arrays in tr.chunks():
        assert isinstance(arrays["phi"], np.memmap)
        np.testing.assert_array_equal(arrays["dphi"], whole.outputs["dphi"][idx][:, ::3])
        seen += idx.tolist()
    assert sorted(seen) == sorted(np.flatnonzero(whole.status != 1).tolist())


def test_a_resumed_sweep_keeps_the_saved_trajectories(lab_rig, whole, tmp_path):
    ck, tr = tmp_path / "ck", tmp_path / "tr"

    def stop(done, total):
        if done >= 6:
            raise _Stop

    with pytest.raises(_Stop):
        cj.run_sweep(lab_rig, SPEC, ("peak_phi",), checkpoint=ck, save_trajectories=tr,
                 callback=stop, **KW)
    with pytest.raises(ValueError, match="has not finished"):
        cj.load_trajectories(tr)
    saved = sorted(tr.glob("chunk-*.phi.npy"))
    assert saved
    # A checkpointed chunk whose trajectory file went missing is computed again; the
    # others are read from the checkpoint and their files left alone.
    saved[0].unlink()
    kept = {p: p.stat().st_mtime_ns for p in saved[1:]}
    res = cj.run_sweep(lab_rig, SPEC, ("peak_phi",), checkpoint=ck, save_trajectories=tr, **KW)
    assert kept == {p: p.stat().st_mtime_ns for p in saved[1:]} and saved[0].exists()
    np.testing.assert_array_equal(res.outputs["peak_phi"], whole.outputs["peak_phi"])
    got = cj.load_trajectories(tr)[np.flatnonzero(whole.ok)]
    np.testing.assert_array_equal(got["phi"], whole.outputs["phi"][whole.ok])


def _flip(path, at=-8):
    raw = bytearray(path.read_bytes())
    raw[at] ^= 0x01
    path.write_bytes(bytes(raw))


def test_damaged_or_swapped_files_are_refused_and_computed_again(lab_rig, whole, tmp_path):
    """Issue 37 item 7: a byte-flipped or swapped `.npy` was returned as it was (off by
    1.51 rad), and a resume kept the damaged chunk."""
    ck, tr = tmp_path / "ck", tmp_path / "tr"
    cj.run_sweep(lab_rig, SPEC, ("peak_phi",), checkpoint=ck, save_trajectories=tr, **KW)
    ok = np.flatnonzero(whole.ok)
    phis = sorted(tr.glob("chunk-*.phi.npy"))
    assert len(phis) >= 3
    _flip(phis[0])
    with pytest.raises(ValueError, match=f"{phis[0].name}.* damaged or not this chunk's"):
        cj.load_trajectories(tr)[ok]
    with pytest.raises(ValueError, match="damaged"):
        list(cj.load_trajectories(tr).chunks())
    # A resume computes the damaged chunk again; the others are kept.
    kept = {p: p.stat().st_mtime_ns for p in phis[1:]}
    cj.run_sweep(lab_rig, SPEC, ("peak_phi",), checkpoint=ck, save_trajectories=tr, **KW)
    assert kept == {p: p.stat().st_mtime_ns for p in phis[1:]}
    got = cj.load_trajectories(tr)[ok]
    np.testing.assert_array_equal(got["phi"], whole.outputs["phi"][ok])
    # Files of the same shape swapped between fields, or between chunks: refused.
    a, b = tr / phis[1].name, tr / phis[1].name.replace(".phi.", ".dphi.")
    data_a, data_b = a.read_bytes(), b.read_bytes()
    a.write_bytes(data_b)
    b.write_bytes(data_a)
    with pytest.raises(ValueError, match="not this chunk's"):
        cj.load_trajectories(tr)[ok]
    a.write_bytes(data_a)
    b.write_bytes(data_b)
    same = [p for p in phis if np.load(p).shape == np.load(phis[1]).shape and p != phis[1]]
    phis[1].write_bytes(same[0].read_bytes())
    with pytest.raises(ValueError, match="not this chunk's"):
        cj.load_trajectories(tr)[ok]


def test_a_store_of_another_sweep_or_a_file_is_refused(lab_rig, tmp_path):
    tr = tmp_path / "tr"
    cj.run_sweep(lab_rig, SPEC, ("peak_phi",), save_trajectories=tr, **{**KW, "n": 2})
    with pytest.raises(ValueError, match="holds another sweep's trajectories: its plan"):
        cj.run_sweep(lab_rig, SPEC, ("peak_phi",), save_trajectories=tr,
                 **{**KW, "n": 2, "seed": 9})
    with pytest.raises(ValueError, match="its every, ts differ"):
        cj.run_sweep(lab_rig, SPEC, ("peak_phi",), save_trajectories=tr, trajectory_every=2,
                 **{**KW, "n": 2})
    (tmp_path / "f").write_text("x")
    with pytest.raises(ValueError, match="is a file, not a directory"):
        cj.run_sweep(lab_rig, SPEC, ("peak_phi",), save_trajectories=tmp_path / "f", **KW)
    with pytest.raises(ValueError, match="not a crank-jax trajectory manifest"):
        (tmp_path / "g").mkdir()
        (tmp_path / "g" / "manifest.json").write_text(json.dumps({"format": "x"}))
        cj.load_trajectories(tmp_path / "g")


def test_cli_refuses_trajectories_larger_than_the_free_disk_up_front(tmp_path, capsys,
                                                                     monkeypatch):
    import shutil

    from crank_jax import cli

    real = shutil.disk_usage
    monkeypatch.setattr(shutil, "disk_usage",
                        lambda p: real(p)._replace(free=10_000))
    argv = ["sweep", "lab-rig", "--vary", "k=normal(2,0.1)", "--n", "100", "--quiet",
            "--samples", "101", "--out", str(tmp_path / "x.npz"),
            "--save-trajectories", str(tmp_path / "tr")]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    # 100 samples x 101 times x 2 fields x 8 B + 100 x 8 B of indices = 0.1624 MB.
    assert err.count("\n") == 1 and "need 0.000162 GB" in err and "10000" not in err, err
    assert "0.00001 GB free" in err or "1e-05 GB free" in err, err
    assert not (tmp_path / "tr").exists() and not (tmp_path / "x.npz").exists()
    assert cli.main(argv + ["--save-every", "0"]) == 2
    assert "--save-every must be >= 1" in capsys.readouterr().err
