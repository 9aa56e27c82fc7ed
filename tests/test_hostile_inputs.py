"""Regression tests of issue 24's hostile inputs in the command line and the data layer:
non-regular input files, degenerate records, time scales float64 cannot resolve, option
values whose messages must name the option, and options checked before a record is read.
"""

import os
import threading
from pathlib import Path

import numpy as np
import pytest

import crank_jax as cj
from crank_jax.cli import main


def _run_guarded(argv, fifo: Path, timeout: float = 20.0) -> int:
    """`main(argv)` in a thread; if it is still blocked (in opening `fifo`) after
    `timeout` s, release it by opening the FIFO's writing end, and fail."""
    out = {}
    th = threading.Thread(target=lambda: out.setdefault("code", main(argv)), daemon=True)
    th.start()
    th.join(timeout)
    if th.is_alive():
        while th.is_alive():  # each open of the reading end gets an empty stream
            try:
                os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
            except OSError:  # no reader at this moment
                pass
            th.join(0.05)
        pytest.fail(f"{argv[0]} waited on the FIFO {fifo}")
    return out["code"]


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this platform")
@pytest.mark.parametrize("slot", ["fit-data", "fit-more-data", "validate-data", "scene"])
def test_fifo_input_is_refused_at_once(tmp_path, capsys, slot):
    # Issue 24 (9): a DATA path that was a FIFO with no writer waited forever.
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    rec = tmp_path / "d.csv"
    cj.save_data(cj.synthesize(cj.load_scene("lab-rig"), t1=0.05, rate=100.0), rec)
    out = str(tmp_path / "r.json")
    argv = {"fit-data": ["fit", fifo, "lab-rig", "--out", out],
            "fit-more-data": ["fit", rec, "lab-rig", "--more-data", fifo, "--out", out],
            "validate-data": ["validate", "lab-rig", fifo, "--out", out],
            "scene": ["fit", rec, fifo, "--out", out]}[slot]
    code = _run_guarded([str(a) for a in argv], fifo)
    err = capsys.readouterr().err
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and "regular file" in err, err
    option = {"fit-data": "DATA", "fit-more-data": "--more-data", "validate-data": "DATA",
              "scene": str(fifo)}[slot]
    assert option in err, err


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this platform")
def test_load_data_refuses_a_fifo_unopened(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    with pytest.raises(cj.DataError, match="FIFO"):
        cj.load_data(fifo)  # would block in open() if it tried
    with pytest.raises(cj.DataError, match="directory"):
        cj.load_data(tmp_path)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        cj.load_data(tmp_path / "nope.csv")


def _record(path: Path, ts) -> Path:
    path.write_text("t,phi\n" + "".join(f"{float(t)!r},{0.1 * i!r}\n" for i, t in enumerate(ts)))
    return path


@pytest.mark.parametrize("ts,match", [
    # Issue 24 (7): an internal error (exit 1) from the overflowing span ...
    ([-1.7e308, -1e308, -1.0, 0.0, 1.0, 1e308, 1.7e308], r"column 't' runs from -1.7e\+308 s "
     r"\(line 2\) to 1.7e\+308 s \(line 8\); a record may span at most"),
    # ... and "SVD did not converge" with numpy warnings on stderr for samples 1e-300 s apart
    ([i * 1e-300 for i in range(8)], r"line 3: t = 1e-300 s is only 1e-300 s after the previous"),
    # times near 1e8 s a few float64 spacings apart
    ([1e8 + i * 1.5e-8 for i in range(8)], "subtract the start time"),
])
def test_unresolvable_times_are_refused_naming_the_row(tmp_path, capsys, ts, match):
    rec = _record(tmp_path / "d.csv", ts)
    with pytest.raises(cj.DataError, match=match):
        cj.load_data(rec)
    code = main(["fit", str(rec), "lab-rig", "--quiet", "--out", str(tmp_path / "r.json")])
    err = capsys.readouterr().err
    assert code == 2 and len(err.splitlines()) == 1 and err.startswith("crank-jax: error: ")
    with pytest.raises(cj.DataError, match="after the previous|span at most"):
        cj.Data(ts, [0.1 * i for i in range(len(ts))])  # the library's own arrays too


def test_times_at_the_bounds_are_accepted():
    from crank_jax.records.data import MAX_TIME_SPAN, MIN_TIME_STEP

    cj.Data([0.0, 1.0, 2.0, 3.0, MAX_TIME_SPAN], [0.0] * 5)
    cj.Data([i * MIN_TIME_STEP * (1 + 1e-9) for i in range(5)], [0.0] * 5)
    cj.Data([1.7e9 + i * 1e-3 for i in range(5)], [0.0] * 5)  # Unix times, 1 kHz


@pytest.mark.parametrize("argv,option", [
    # Issue 24 (10): these said "expected non-negative integer", "ts must increase
    # strictly", "sample 0: column 'phi' is inf" or "ts ... got shape (1,)".
    (["synth", "lab-rig", "--seed", "-1"], "--seed"),
    (["fit", "{d}/d.csv", "lab-rig", "--seed", "-1"], "--seed"),
    (["sweep", "lab-rig", "--n", "2", "--seed", "-1", "--out", "{d}/x.npz"], "--seed"),
    (["demo", "--noise-seed", "-5"], "--noise-seed"),
    (["synth", "lab-rig", "--rate", "1e9", "--t-start", "1e8", "--t1", "100000000.001"],
     "--rate"),
    (["synth", "lab-rig", "--transient", "1e308"], "--transient"),
    (["synth", "lab-rig", "--noise-std", "1e308"], "--noise-std"),
    (["synth", "lab-rig", "--drop", "0.999999"], "--drop"),
])
def test_messages_name_the_option(tmp_path, capsys, argv, option):
    cj.save_data(cj.synthesize(cj.load_scene("lab-rig"), t1=0.05, rate=100.0), tmp_path / "d.csv")
    argv = [a.replace("{d}", str(tmp_path)) for a in argv]
    if argv[0] == "synth":
        argv += ["--out", str(tmp_path / "o.csv")]
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2 and len(err.splitlines()) == 1, err
    assert option in err and "sample 0" not in err and "shape" not in err, err
    assert not (tmp_path / "o.csv").exists()


@pytest.mark.parametrize("kwargs,match", [
    (dict(seed=-1), r"`seed=` must be an integer >= 0"),
    (dict(transient=1e308), r"`transient=` 1e\+308 is out of range: use a finite "
                            r"value from -1e\+06 to 1e\+06 rad"),
    (dict(noise_std=1e308), r"`noise_std=` 1e\+308 is out of range"),
    (dict(drop=0.999999), r"`drop=` 0.999999 left 1 of the 2001 samples"),
    (dict(rate=1e9, t_start=1e8, t1=1e8 + 1e-3), r"`rate=` 1e\+09 Hz .* near t1 = "
                                                 r"1e\+08 s one spacing is 1.49e-08 s"),
])
def test_synthesize_names_the_argument(kwargs, match):
    with pytest.raises(ValueError, match=match):
        cj.synthesize(cj.load_scene("lab-rig"), **kwargs)


def test_synthesize_rate_bound_gives_times_data_accepts():
    # The largest rate the spacing check allows near t1 (for t1 far from 0) gives sample
    # times t_start + i / rate that Data accepts; synthesize builds them the same way.
    from crank_jax.records.data import MIN_STEP_ULPS, MIN_TIME_STEP

    for t_start in (0.0, 1e-3, 1e5, 1e8, 1.7e9):
        t1 = t_start + 1e-2
        ulp = float(np.spacing(t1))
        rate = 1 / (max(MIN_TIME_STEP, MIN_STEP_ULPS * ulp) + 2 * ulp)
        with pytest.raises(ValueError, match="`rate=`"):  # just above the bound: refused
            cj.synthesize(cj.load_scene("lab-rig"), t_start=t_start, t1=t1,
                          rate=rate * (1 + 1e-6))
        ts = t_start + np.arange(int((t1 - t_start) * rate)) / rate
        cj.Data(ts, np.zeros_like(ts))


@pytest.mark.parametrize("rtol", ["0.5", "0.999999", "0.0100001"])
def test_loose_rtol_is_refused_naming_the_option(tmp_path, capsys, rtol):
    # Issue 24 (12): a looser tolerance made a solve fail (or, near rtol = 1, finish with a
    # wrong trajectory: near-buckling took 30 steps over 20 s) where a tighter one passed.
    code = main(["simulate", "lab-rig", "--rtol", rtol, "--out", str(tmp_path / "o.csv")])
    err = capsys.readouterr().err
    assert code == 2 and "--rtol must be at most 0.01" in err, err
    scene = tmp_path / "s.toml"
    scene.write_text(cj.scene_to_toml(cj.load_scene("lab-rig")).replace(
        "rtol = 1e-08", f"rtol = {rtol}"))
    with pytest.raises(cj.SceneError, match=r"\[solver\] rtol must be .* <= 0.01"):
        cj.load_scene(scene)


def test_simulate_has_the_max_steps_its_advice_names(tmp_path, capsys):
    # Issue 24 (12): the advice said "try increasing max_steps", which simulate lacked.
    out = str(tmp_path / "o.csv")
    code = main(["simulate", "lab-rig", "--max-steps", "150", "--quiet", "--out", out])
    err = capsys.readouterr().err
    assert code == 1 and "raise --max-steps" in err and "`max_steps`" not in err, err
    assert not Path(out).exists()
    assert main(["simulate", "lab-rig", "--max-steps", "5000", "--quiet", "--out", out]) == 0
    for bad in ("0", "2147483648"):
        assert main(["simulate", "lab-rig", "--max-steps", bad, "--out", out]) == 2
        assert "--max-steps must be from 1 to" in capsys.readouterr().err


def test_other_commands_name_no_option_they_lack():
    import argparse

    from crank_jax.cli.main import _solver_advice

    msg = "The maximum number of solver steps was reached. Try increasing `max_steps`."
    for command in ("synth", "fit", "validate", "demo"):
        text = _solver_advice(msg, argparse.Namespace(command=command))
        assert "max_steps" not in text and "--t1" in text, text
        assert text.startswith("The maximum number of solver steps was reached.")


def _constant_record(path: Path, value: float, n: int = 400, seed: int = 0) -> Path:
    """A record at `value` rad plus rounding-sized wobble (a few ulps), 100 Hz."""
    rng = np.random.default_rng(seed)
    phi = value + rng.integers(-2, 3, n) * np.spacing(value)
    path.write_text("t,phi\n" + "".join(f"{i / 100!r},{float(p)!r}\n"
                                         for i, p in enumerate(phi)))
    return path


@pytest.mark.parametrize("value", [0.1, 1234.5, 1e-20])
def test_validate_refuses_a_constant_record(tmp_path, capsys, value):
    # Issue 24 (5): fit_percent = -5.4e17 for a constant record, whose spread was float
    # rounding noise (only a spread of exactly 0 was caught).
    rec = _constant_record(tmp_path / "c.csv", value)
    out = tmp_path / "v.json"
    code = main(["validate", "lab-rig", str(rec), "--quiet", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and len(err.splitlines()) == 1, err
    assert "constant angle" in err and "fit_percent is undefined" in err, err
    assert not out.exists()
    with pytest.raises(cj.DataError, match="constant angle"):
        cj.validate(cj.load_scene("lab-rig"), cj.load_data(rec))


def test_spread_check_passes_small_real_motion():
    from crank_jax.validation.kstep import _check_spread

    d = cj.Data(np.arange(10) * 0.01, np.zeros(10))
    _check_spread(1234.5 + 1e-9 * np.sin(np.arange(50)), d, 0.0)  # 1 nrad at 1234.5 rad
    _check_spread(1e-20 * np.sin(np.arange(50)), d, 0.0)  # any motion about 0
    with pytest.raises(cj.DataError):
        _check_spread(np.zeros(50), d, 0.0)


@pytest.mark.parametrize("options,named", [
    # Issue 24 (11): these failed only after the whole record was read (5.9 s for a
    # 3e6-row CSV). A record that is broken on its last line tells which came first.
    (["--multistart", "0"], "--multistart"),
    (["--free", "zz"], "--free"),
    (["--free", "k,P1"], "--free: P1 cannot be free"),
    (["--profile", "m_c"], "--profile"),
    (["--segments", "3", "--shooting", "single"], "--segments"),
    (["--sigma", "-1"], "--sigma"),
    (["--max-steps", "0"], "--max-steps"),
    (["--out", "{d}/no/r.json"], "--out"),
])
def test_fit_options_are_checked_before_the_record_is_read(tmp_path, capsys, options, named):
    rec = tmp_path / "d.csv"
    rows = "".join(f"{i / 100!r},{np.sin(i / 100)!r}\n" for i in range(200))
    rec.write_text("t,phi\n" + rows + "9,not-a-number\n")
    argv = ["fit", str(rec), "lab-rig"] + [o.replace("{d}", str(tmp_path)) for o in options]
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2 and named in err and "not-a-number" not in err, err


def test_validate_outputs_are_checked_before_the_record_is_read(tmp_path, capsys):
    rec = tmp_path / "d.csv"
    rec.write_text("t,phi\n0,0\n1,x\n")
    for option, value in (("--out", "{d}/no/v.json"), ("--plot", "{d}/p.xyz")):
        argv = ["validate", "lab-rig", str(rec), "--out", str(tmp_path / "v.json"),
                option, value.replace("{d}", str(tmp_path))]
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert option in err and "line 3" not in err, err


def test_a_successful_run_has_an_empty_stderr(tmp_path):
    # Issue 24 (14): a run that recovered from a stored program that does not parse (it
    # recompiles) printed XLA's "E... wire_format_lite.cc:578] String field ... contains
    # invalid UTF-8 data" on stderr, though it succeeded.
    import re
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items()
           if k not in ("CRANK_JAX_NO_CACHE", "JAX_LOGGING_LEVEL")}
    env["CRANK_JAX_CACHE_DIR"] = str(tmp_path / "cache")

    def run():
        p = subprocess.run([sys.executable, "-m", "crank_jax", "linearize", "lab-rig", "--json"],
                           env=env, capture_output=True, text=True, timeout=300)
        assert p.returncode == 0 and p.stderr == "", p.stderr
        return p.stdout

    first = run()
    damaged = 0
    for f in (tmp_path / "cache").rglob("*"):
        blob = f.read_bytes() if f.is_file() else b""
        new = re.sub(rb"(jit_linearize_[0-9a-f]{14})[0-9a-f]{2}",
                     lambda m: m.group(1) + b"\xff\xfe", blob)
        if new != blob:
            f.write_bytes(new)  # a program name that is not UTF-8: its parse fails
            damaged += 1
    assert damaged, "no stored program found to damage"
    assert run() == first


@pytest.mark.parametrize("rtol", [0.5, 0.999999, 0.011])
def test_library_refuses_a_loose_rtol(rtol):
    # Issue 24 (12): the library's simulate takes the same bound as the CLI and scene files.
    sc = cj.load_scene("lab-rig")
    with pytest.raises(ValueError, match="rtol must be a finite number >= 1e-15 .* and <= 0.01"):
        cj.simulate(sc.mech, 1.0, 0.0, np.linspace(0.0, 1.0, 11), rtol=rtol)
