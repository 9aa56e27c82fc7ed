"""Regression tests of issue 24's hostile inputs in the command line and the data layer:
non-regular input files, degenerate records, time scales float64 cannot resolve, option
values whose messages must name the option, and options checked before a record is read.
"""

import os
import threading
from pathlib import Path

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
    from crank_jax.data import MAX_TIME_SPAN, MIN_TIME_STEP

    cj.Data([0.0, 1.0, 2.0, 3.0, MAX_TIME_SPAN], [0.0] * 5)
    cj.Data([i * MIN_TIME_STEP * (1 + 1e-9) for i in range(5)], [0.0] * 5)
    cj.Data([1.7e9 + i * 1e-3 for i in range(5)], [0.0] * 5)  # Unix times, 1 kHz
