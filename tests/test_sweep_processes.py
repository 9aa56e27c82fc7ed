"""Sweeps over two processes on this machine (coordinator on the loopback address, JAX's
CPU collectives), through the CLI (`crank-jax sweep --distributed`) and the library
(`cj.sweep.initialize_distributed` then `cj.sweep`): the result equals one process's bit for bit,
only process 0 writes, a checkpoint is shared and resumed, and a process that dies or a
coordinator that never answers ends the others with one line in bounded time."""

import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
# Small on purpose: each process compiles the chunk (about 10 s), the solves take little.
SWEEP = ["--vary", "k=normal(2,0.1)", "--vary", "c=uniform(0.005,0.02)", "--n", "6",
         "--t1", "0.5", "--samples", "11", "--chunk-size", "2"]
ARGS = ["sweep", "lab-rig", *SWEEP, "--outputs", "peak_phi,final_energy", "--quiet"]


def _env(**extra):
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS",)}
    env.update(CRANK_JAX_NO_CACHE="1", JAX_PLATFORMS="cpu",
               PYTHONPATH=os.pathsep.join([str(ROOT / "src"), env.get("PYTHONPATH", "")]))
    env.update(extra)
    return env


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start(argvs, tmp_path, port, only=None, **env):
    """One process per argv list (`python *argv`), process i with JAX_PROCESS_ID=i and one
    CPU device, all joined at the coordinator 127.0.0.1:port; `only`: {i: environment}
    of process i alone."""
    return [subprocess.Popen(
        [sys.executable, *argv], cwd=tmp_path, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True,
        env=_env(JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{port}",
                 JAX_NUM_PROCESSES=str(len(argvs)), JAX_PROCESS_ID=str(i),
                 JAX_NUM_CPU_DEVICES="1", **env, **(only or {}).get(i, {})))
        for i, argv in enumerate(argvs)]


def _cli(tmp_path, *extra, args=ARGS, tag="p", n=2):
    """`crank-jax sweep --distributed` argv lists, process i writing --out tag{i}.npz
    (and `{i}` in `extra` replaced by i)."""
    return [["-m", "crank_jax", *args, "--distributed", *(a.format(i=i) for a in extra),
             "--out", str(tmp_path / f"{tag}{i}.npz")] for i in range(n)]


def _finish(procs, timeout=600):
    out = []
    for p in procs:
        _, err = p.communicate(timeout=timeout)
        out.append((p.returncode, err))
    return out


def _one_process(tmp_path, *extra, args=ARGS) -> Path:
    """The reference: one process with as many devices (2) as the two processes hold."""
    path = tmp_path / "one.npz"
    subprocess.run([sys.executable, "-m", "crank_jax", *args, *extra, "--out", str(path)],
                   env=_env(JAX_NUM_CPU_DEVICES="2"), check=True, timeout=600,
                   capture_output=True)
    return path


def _assert_same_file(a, b):
    with np.load(a) as x, np.load(b) as y:
        assert x.files == y.files
        for k in x.files:
            np.testing.assert_array_equal(x[k], y[k], err_msg=k)


def test_two_processes_write_what_one_process_writes_and_share_a_checkpoint(tmp_path):
    ck = tmp_path / "ck"
    for code, err in _finish(_start(_cli(tmp_path, "--checkpoint", str(ck),
                                         "--save-trajectories", str(tmp_path / "tr{i}"),
                                         "--save-every", "2"), tmp_path, _free_port())):
        assert code == 0, err[-2000:]
    # Process 0 writes --out and the trajectories; process 1 was given other paths and
    # writes nothing.
    assert (tmp_path / "p0.npz").exists() and not (tmp_path / "p1.npz").exists()
    assert not (tmp_path / "tr1").exists()
    one = _one_process(tmp_path, "--save-trajectories", str(tmp_path / "tr"),
                       "--save-every", "2")
    _assert_same_file(tmp_path / "p0.npz", one)
    saved = sorted(p.name for p in (tmp_path / "tr").iterdir())
    assert saved == sorted(p.name for p in (tmp_path / "tr0").iterdir())
    assert len(saved) == 1 + 4 * 3  # the manifest, 3 files and checksums for 3 chunks
    for name in saved:
        a, b = tmp_path / "tr" / name, tmp_path / "tr0" / name
        if name.endswith(".npy"):
            np.testing.assert_array_equal(np.load(a), np.load(b), err_msg=name)
        else:
            assert a.read_text() == b.read_text()
    # Process 0 wrote every chunk (6 samples in chunks of 2).
    chunks = sorted(ck.glob("chunk-*.npz"))
    assert len(chunks) == 3
    # Resume as after a kill of every process that left one chunk, through the library
    # (`cj.sweep.initialize_distributed` then `cj.run_sweep(..., checkpoint=)`, the same plan): the
    # two processes compute the two missing chunks, and each gets the whole result, the
    # one-process result bit for bit.
    kept = chunks[0].stat().st_mtime_ns
    for c in chunks[1:]:
        c.unlink()
    script = tmp_path / "lib.py"
    script.write_text(LIBRARY.format(ck=str(ck)))
    for code, err in _finish(_start([[str(script), str(tmp_path / f"lib{i}.npz")]
                                     for i in range(2)], tmp_path, _free_port())):
        assert code == 0, err[-2000:]
    assert chunks[0].stat().st_mtime_ns == kept and len(list(ck.glob("chunk-*.npz"))) == 3
    for i in range(2):
        _assert_same_file(tmp_path / f"lib{i}.npz", one)


# The library path: the same sweep as ARGS; every process saves the result it got.
LIBRARY = textwrap.dedent("""
    import sys
    import jax
    jax.config.update("jax_enable_x64", True)
    import crank_jax as cj
    cj.sweep.initialize_distributed()  # JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES, _PROCESS_ID
    assert jax.process_count() == 2 and jax.device_count() == 2
    res = cj.run_sweep(cj.load_scene("lab-rig"),
                   {{"k": "normal(2,0.1)", "c": "uniform(0.005,0.02)"}},
                   ("peak_phi", "final_energy"), n=6, t1=0.5, num_saves=11, chunk_size=2,
                   checkpoint={ck!r})
    res.save(sys.argv[1])
    """)


def _wait_for(pred, timeout=600):
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.2)


@pytest.mark.parametrize("dies", [1, pytest.param(0, marks=pytest.mark.slow)])
def test_a_process_that_dies_ends_the_other_with_one_line_in_bounded_time(tmp_path, dies):
    """Kill one process (its command, SIGKILL) in the middle of the run: the other ends
    with one line and exit 1 within a bound (a peer's collective times out after about
    30 s; the coordinator's death is seen at once), and writes nothing."""
    ck = tmp_path / "ck"
    args = [*ARGS[:ARGS.index("--n") + 1], "400", *ARGS[ARGS.index("--n") + 2:]]
    procs = _start(_cli(tmp_path, "--checkpoint", str(ck), args=args), tmp_path,
                   _free_port(), CRANK_JAX_DISTRIBUTED_TIMEOUT="10")
    _wait_for(lambda: len(list(ck.glob("chunk-*.npz"))) >= 2)
    procs[dies].send_signal(signal.SIGKILL)
    t0 = time.monotonic()
    [(code, err)] = _finish([procs[1 - dies]], timeout=300)
    procs[dies].communicate()
    assert time.monotonic() - t0 < 120
    assert code == 1, err[-3000:]
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("crank-jax: error:"), err[-3000:]
    assert "rerun every process" in lines[0].lower(), lines[0]
    assert "Traceback" not in err and "@ 0x" not in err
    assert not (tmp_path / "p0.npz").exists() and not (tmp_path / "p1.npz").exists()


def test_a_run_that_never_forms_ends_with_one_line_in_bounded_time_exit_2(tmp_path):
    """Process 1 whose coordinator never answers, and process 0 whose peer never comes,
    each end with one line and exit 2 within the timeout (5 s here; JAX itself would
    abort with a stack dump, or wait 300 s)."""
    t0 = time.monotonic()
    procs = [subprocess.Popen(
        [sys.executable, *_cli(tmp_path, n=1, tag=f"x{i}")[0]], cwd=tmp_path,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env=_env(JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{_free_port()}", JAX_NUM_PROCESSES="2",
                 JAX_PROCESS_ID=str(i), JAX_NUM_CPU_DEVICES="1",
                 CRANK_JAX_DISTRIBUTED_TIMEOUT="5")) for i in range(2)]
    (c0, e0), (c1, e1) = _finish(procs, timeout=300)
    assert time.monotonic() - t0 < 120
    for code, err in ((c0, e0), (c1, e1)):
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1, err[-3000:]
        assert lines[0].startswith("crank-jax: error: --distributed:"), err[-3000:]
    assert "did not answer within 5 s" in e1
    assert "not every process joined" in e0 and "within 5 s" in e0
    assert not list(tmp_path.glob("x*.npz"))


@pytest.mark.parametrize("extra, field", [(["--seed", "1"], "seed"), (["--n", "8"], "n"),
                                          (["--vary", "phi0=const(0.3)"], "samples")])
def test_processes_given_different_sweeps_are_refused_on_every_process(tmp_path, extra,
                                                                       field):
    """Issue 37 item 8: process 1 with another --seed, --n or --vary wrote, with process
    0, a file that mixed both plans, exit 0. Now both refuse before any work: one line,
    exit 2, naming what differs; nothing written."""
    argvs = _cli(tmp_path)
    argvs[1] += extra
    for code, err in _finish(_start(argvs, tmp_path, _free_port())):
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1, err[-3000:]
        assert "different sweeps: process(es) 1 differ from process 0 in" in lines[0]
        assert lines[0].split(" in ")[1].startswith(field + ";"), lines[0]
    assert not list(tmp_path.glob("p*.npz"))


# Issue 37 items 9 and 10: with the program store on, a second two-process run loaded the
# stored programs onto `jax.devices()[:1]` (process 0's device) also in process 1, which
# then failed ("Fetching value for `jax.Array` that spans non-addressable devices"); and a
# peer slower than Gloo's 30 s (compiling on a loaded machine) made the other's collective
# fail. Here the second run, on the warm store, has process 1 wait 40 s before its first
# collective.
@pytest.mark.slow  # a 40 s wait on top of two two-process runs
def test_a_warm_store_and_a_slow_peer_still_give_the_result(tmp_path):
    cache = {"CRANK_JAX_NO_CACHE": "", "CRANK_JAX_CACHE_DIR": str(tmp_path / "cache")}
    for code, err in _finish(_start(_cli(tmp_path, tag="cold"), tmp_path, _free_port(),
                                    **cache)):
        assert code == 0, err[-2000:]
    assert list((tmp_path / "cache" / "crank-jax-programs").glob("*.xla"))
    slow = {1: {"CRANK_JAX_TEST_COLLECTIVE_DELAY": "40"}}
    for code, err in _finish(_start(_cli(tmp_path, tag="warm"), tmp_path, _free_port(),
                                    only=slow, **cache)):
        assert code == 0, err[-2000:]
    _assert_same_file(tmp_path / "cold0.npz", tmp_path / "warm0.npz")


@pytest.mark.slow
def test_two_processes_resume_after_both_are_killed(tmp_path):
    """SIGKILL both processes in the middle of a checkpointed run, rerun both: the result
    is the uninterrupted one-process result, bit for bit."""
    ck = tmp_path / "ck"
    args = [*ARGS[:ARGS.index("--n") + 1], "200", *ARGS[ARGS.index("--n") + 2:]]
    procs = _start(_cli(tmp_path, "--checkpoint", str(ck), args=args), tmp_path,
                   _free_port())
    _wait_for(lambda: len(list(ck.glob("chunk-*.npz"))) >= 3)
    for p in procs:
        p.send_signal(signal.SIGKILL)
    for p in procs:
        p.communicate()
    done = len(list(ck.glob("chunk-*.npz")))
    assert 3 <= done < 100 and not (tmp_path / "p0.npz").exists()
    for code, err in _finish(_start(_cli(tmp_path, "--checkpoint", str(ck), args=args),
                                    tmp_path, _free_port())):
        assert code == 0, err[-2000:]
    _assert_same_file(tmp_path / "p0.npz", _one_process(tmp_path, args=args))
