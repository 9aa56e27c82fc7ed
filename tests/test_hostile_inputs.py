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
