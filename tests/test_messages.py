"""Issue 37 (15, 16, 18): internal errors and unclear messages. Each bad input gets one
line naming the field, option or variable and the fix, exit status 2, no traceback, and
before any work (these commands are refused before anything is compiled)."""

from __future__ import annotations

import errno
import importlib.resources
import os
from pathlib import Path

import pytest

import crank_jax as cj
import crank_jax.bayes.priors as priors_module
import crank_jax.runtime.io as io_module
import crank_jax.scene as scene_module
from crank_jax.cli import main


def _lab_toml() -> str:
    return importlib.resources.files("crank_jax").joinpath("scenes/lab-rig.toml").read_text()


def _error(argv, capsys) -> str:
    """Run the CLI; assert exit 2 with one line on stderr, and return that line."""
    capsys.readouterr()
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("crank-jax: error: "), (code, err)
    assert "Traceback" not in err[0] and "internal error" not in err[0], err
    return err[0]


@pytest.fixture(scope="module")
def record(tmp_path_factory) -> Path:
    """A short lab-rig record (synthesised without any solve: its values do not matter
    to commands refused before the work)."""
    path = tmp_path_factory.mktemp("rec") / "rec.csv"
    path.write_text("t,phi\n" + "".join(f"{i * 0.01!r},{0.1 * (i % 7)!r}\n" for i in range(20)))
    return path


# --- 15: internal errors -------------------------------------------------------------


@pytest.mark.parametrize("prior", ['"lognormal(2, 1e-300)"', '"normal(2, 1e-300)"',
                                   '"uniform(2, 2.000000000000001)"'])
def test_a_prior_too_narrow_is_named(tmp_path, capsys, record, prior):
    # lognormal(2, 1e-300) raised ZeroDivisionError (an internal error, exit 1) after the
    # fit that starts the chains.
    scene = tmp_path / "s.toml"
    scene.write_text(_lab_toml() + f"\n[priors]\nk = {prior}\n")
    err = _error(["posterior", record, scene, "--free", "k,phi0,dphi0", "--out",
                  tmp_path / "p.json"], capsys)
    assert "[priors].k" in err and "narrower" in err and "widen the prior" in err, err
    with pytest.raises(ValueError, match="narrower"):
        priors_module.parse_priors({"k": prior.strip('"')}, ("k",))


def test_prior_precision_of_a_narrow_prior_is_finite():
    # The guard 1 / max(sd, 1e-300) ** 2 divided by zero: (1e-300) ** 2 underflows.
    from types import SimpleNamespace

    import numpy as np

    from crank_jax.bayes.priors import prior_arrays, prior_precision

    codes, params = prior_arrays(("phi0",), priors_module.parse_priors(
        {"phi0": "normal(1e-140, 1e-149)"}, ("phi0",)))
    # A coordinate scaled by 1e20: the prior's sd in it is 1e-169, whose square is 0.
    problem = SimpleNamespace(values=lambda z: np.asarray(z), log=[False], ref=[1e20])
    assert np.isfinite(prior_precision(codes, params, problem, np.array([1e-140]))).all()


@pytest.mark.parametrize("env,name", [
    ({"JAX_COORDINATOR_ADDRESS": "nonsense"}, "JAX_COORDINATOR_ADDRESS"),
    ({"JAX_COORDINATOR_ADDRESS": "host:99999"}, "JAX_COORDINATOR_ADDRESS"),
    ({"CRANK_JAX_DISTRIBUTED_TIMEOUT": "abc"}, "CRANK_JAX_DISTRIBUTED_TIMEOUT"),
    ({"CRANK_JAX_DISTRIBUTED_TIMEOUT": "-5"}, "CRANK_JAX_DISTRIBUTED_TIMEOUT"),
    ({"JAX_NUM_PROCESSES": "two"}, "JAX_NUM_PROCESSES"),
    ({"JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "2"}, "JAX_PROCESS_ID"),
])
def test_bad_environment_variables_are_named(tmp_path, capsys, monkeypatch, env, name):
    # JAX_COORDINATOR_ADDRESS=nonsense raised JAX's IndexError (exit 1); a bad timeout said
    # "invalid literal for int() with base 10: 'abc'".
    for k in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID",
              "CRANK_JAX_DISTRIBUTED_TIMEOUT"):
        monkeypatch.delenv(k, raising=False)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    err = _error(["sweep", "lab-rig", "--n", "2", "--out", tmp_path / "s.npz",
                  "--distributed"], capsys)
    assert f"environment variable {name}=" in err, err
    assert not (tmp_path / "s.npz").exists()


# --- 16: posterior --draws that would exhaust memory -------------------------------------


def test_posterior_refuses_draws_beyond_memory(tmp_path, capsys, record):
    err = _error(["posterior", record, "lab-rig", "--draws", "1000000000", "--out",
                  tmp_path / "p.json"], capsys)
    assert "--draws" in err and "GiB" in err and "give --draws <= " in err, err
    assert "draws=" not in err and "`" not in err, err
    limit = int(err.split("give --draws <= ")[1].split()[0])
    from crank_jax.bayes.posterior import check_posterior_memory, posterior_bytes

    check_posterior_memory(limit, 4, 500, 4)  # the count it names fits
    with pytest.raises(ValueError,
                       match=r"^`draws=` 1000 x `chains=` 4 .* give `draws=` <= 999 ") as e:
        check_posterior_memory(1000, 4, 500, 4, max_memory=posterior_bytes(999, 4, 500, 4))
    check_posterior_memory(1000, 4, 500, 4, max_memory=posterior_bytes(1000, 4, 500, 4))
    err = _error(["posterior", record, "lab-rig", "--warmup", "10000000000", "--out",
                  tmp_path / "p.json"], capsys)
    assert "--" not in str(e.value)
    assert "--warmup" in err and "give --warmup <= " in err and "warmup=" not in err, err


# --- 18: unclear messages -------------------------------------------------------------


def test_posterior_reads_a_scene_with_a_byte_order_mark(tmp_path, capsys, record):
    # fit accepted it, posterior said "Invalid statement (at line 1, column 1)": the
    # [priors] table was read by a second reader without the BOM's handling.
    scene = tmp_path / "bom.toml"
    scene.write_bytes(b"\xef\xbb\xbf" + (_lab_toml() + '\n[priors]\nk = "lognormal(2, 0)"\n')
                      .encode())
    err = _error(["posterior", record, scene, "--free", "k,phi0", "--out",
                  tmp_path / "p.json"], capsys)
    assert "[priors].k" in err and "zero width" in err, err
    assert priors_module.load_priors(scene) == {"k": "lognormal(2, 0)"}


@pytest.mark.parametrize("argv", [
    ["design", "lab-rig", "--free", "k,c", "--t1", "1", "--rate", "100",
     "--torque-amplitude", "0.1", "--seed", "-1", "--out", "{d}/d.json", "--scene-out",
     "{d}/d.toml"],
    ["posterior", "{rec}", "lab-rig", "--seed", "-1", "--out", "{d}/p.json"],
])
def test_negative_seeds_name_the_option(tmp_path, capsys, record, argv):
    # design --seed -1 showed numpy's "expected non-negative integer".
    argv = [a.replace("{d}", str(tmp_path)).replace("{rec}", str(record)) for a in argv]
    err = _error(argv, capsys)
    assert "--seed" in err and "from 0 to" in err, err


@pytest.mark.parametrize("free,want", [
    ("tau_gain", '[torque] input = "COLUMN"'), ("P_gain", '[load] input = "COLUMN"'),
    ("tau1", '[torque] kind = "harmonic"'), ("P0", '[load] kind = "constant"')])
def test_free_load_names_say_what_the_scene_needs(tmp_path, capsys, record, free, want):
    # --free tau_gain said "(or, for tau_gai0, a constant one)": the name cut short.
    err = _error(["fit", record, "lab-rig", "--free", free, "--out", tmp_path / "f.json"],
                 capsys)
    assert f"{free} cannot be free" in err and want in err and "gai0" not in err, err


@pytest.fixture(scope="module")
def input_scene(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("inp") / "motor.toml"
    path.write_text(_lab_toml().replace("[initial]",
                                        '[torque]\ninput = "volts"\ngain = 0.02\n\n[initial]'))
    return path


@pytest.mark.parametrize("command", ["synth", "simulate", "sweep", "design"])
def test_input_driven_scene_is_refused_in_cli_terms_before_the_work(tmp_path, capsys,
                                                                    input_scene, command):
    # These said "... or give InputLoad a signal", design after 10 s of work.
    extra = {"synth": ["--out", tmp_path / "o.csv"],
             "simulate": ["--out", tmp_path / "o.csv"],
             "sweep": ["--n", "2", "--out", tmp_path / "s.npz"],
             "design": ["--free", "k,c", "--t1", "0.5", "--rate", "100",
                        "--torque-amplitude", "0.1", "--out", tmp_path / "d.json",
                        "--scene-out", tmp_path / "d.toml"]}[command]
    err = _error([command, input_scene, *extra], capsys)
    assert "InputLoad" not in err and "[torque]" in err and "'volts' column" in err, err
    assert f"crank-jax {command}` reads no record" in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("extra,want", [
    (["--save-every", "2"], "--save-every thins the saved trajectories"),
    (["--checkpoint", ""], "--checkpoint is empty"),
    (["--save-trajectories", " "], "--save-trajectories is empty"),
    (["--checkpoint", "{d}/s.npz"], "--out and --checkpoint name the same path"),
    (["--checkpoint", "{d}/c", "--save-trajectories", "{d}/./c"],
     "--checkpoint and --save-trajectories name the same path"),
])
def test_sweep_directory_options_are_checked_before_the_work(tmp_path, capsys, monkeypatch,
                                                             extra, want):
    # --save-every without --save-trajectories was ignored; --checkpoint '' wrote into the
    # current directory; --checkpoint X --out X failed only after the sweep.
    monkeypatch.chdir(tmp_path)
    extra = [a.replace("{d}", str(tmp_path)) for a in extra]
    err = _error(["sweep", "lab-rig", "--n", "2", "--out", tmp_path / "s.npz", *extra], capsys)
    assert want in err, err
    assert list(tmp_path.iterdir()) == []


def _no_space(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_full_disk_names_the_file_and_loses_nothing(tmp_path, capsys, monkeypatch):
    # It was a bare "[Errno 28] No space left on device".
    out = tmp_path / "o.csv"
    out.write_text("the previous output\n")
    monkeypatch.setattr(io_module.os, "fsync", _no_space)
    err = _error(["synth", "lab-rig", "--t1", "0.05", "--rate", "100", "--out", out], capsys)
    assert f"could not write {str(out)!r}: the disk is full" in err and "[Errno" not in err
    assert "free some space" in err, err
    assert out.read_text() == "the previous output\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.csv"]  # no temporary file


def test_a_full_disk_outside_the_atomic_writers_is_one_line(tmp_path, capsys, monkeypatch):
    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp_path / "chunk.npy"))

    monkeypatch.setattr(scene_module, "load_scene", full)
    err = _error(["synth", "lab-rig", "--out", tmp_path / "o.csv"], capsys)
    assert "could not write" in err and "chunk.npy" in err and "the disk is full" in err, err


@pytest.mark.skipif(os.fsencode("\udcff") != b"\xff", reason="file names are not bytes here")
def test_a_file_name_that_is_not_utf8_reaches_the_report_and_plot(tmp_path, capsys):
    # --report failed after the fit: "'utf-8' codec can't encode character '\udcff'";
    # --plot crashed in matplotlib's font layout (an internal error).
    rec = tmp_path / os.fsdecode(b"lab\xff.csv")
    cj.save_data(cj.synthesize(cj.load_scene("lab-rig"), t1=0.5, rate=100.0,
                               noise_std=1e-3, seed=1), rec)
    html, png = tmp_path / "r.html", tmp_path / "p.png"
    code = main(["fit", str(rec), "lab-rig", "--free", "k,phi0,dphi0", "--quiet",
                 "--report", str(html), "--plot", str(png)])
    assert code == 0, capsys.readouterr().err
    page = html.read_text(encoding="utf-8")
    assert "lab\\xff.csv" in page and png.stat().st_size > 0


def test_a_constant_channel_is_refused_before_any_solve():
    # A constant slide beside a moving angle passed the no-motion check (judged on the
    # angle) and the fit ran 636 Levenberg-Marquardt iterations on it.
    mech = cj.SliderCrank(r=0.05, L=0.2, b=0.1, s=0.01, m_c=0.5, m_p=0.3, m_s=0.4, I_c=1e-3,
                          I_p=2e-3, k=0.0, c=1e-3, g=9.81)
    scene = cj.Scene(mech, torque=cj.ConstantLoad(0.05), phi0=0.0, dphi0=10.0, t1=0.3)
    ts = [i * 0.01 for i in range(31)]
    data = cj.Data(ts, [10.0 * t for t in ts], channels={"x_s": [0.25] * len(ts)},
                   source="two.csv")
    res = cj.fit(scene, data, free=("c", "phi0", "dphi0"), max_steps=3, progress=False,
                 warn=False)
    assert not res.converged and res.iterations == 0, (res.iterations, res.message)
    assert "channel x_s (column 'x_s') is constant (0.25 m in all 31 samples)" in res.message
