"""A sweep over two processes (`crank-jax sweep --distributed`, coordinator on the
loopback address, JAX's CPU collectives) writes the same file as one process with as many
devices; only process 0 writes."""

import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
ARGS = ["sweep", "lab-rig", "--vary", "k=normal(2,0.1)", "--vary", "c=uniform(0.005,0.02)",
        "--n", "6", "--t1", "0.5", "--samples", "11", "--outputs", "peak_phi,final_energy",
        "--chunk-size", "2", "--quiet"]


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


def test_two_processes_write_what_one_process_writes(tmp_path):
    port = _free_port()
    procs = [subprocess.Popen(
        [sys.executable, "-m", "crank_jax", *ARGS, "--out", str(tmp_path / f"p{i}.npz"),
         "--distributed"], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True, env=_env(JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{port}",
                            JAX_NUM_PROCESSES="2", JAX_PROCESS_ID=str(i),
                            JAX_NUM_CPU_DEVICES="1")) for i in range(2)]
    for p in procs:
        _, err = p.communicate(timeout=600)
        assert p.returncode == 0, err[-2000:]
    assert (tmp_path / "p0.npz").exists() and not (tmp_path / "p1.npz").exists()
    subprocess.run([sys.executable, "-m", "crank_jax", *ARGS, "--out",
                    str(tmp_path / "one.npz")], env=_env(JAX_NUM_CPU_DEVICES="2"),
                   check=True, timeout=600, capture_output=True)
    with np.load(tmp_path / "p0.npz") as a, np.load(tmp_path / "one.npz") as b:
        assert a.files == b.files
        for k in a.files:
            np.testing.assert_array_equal(a[k], b[k])


def test_an_unreachable_coordinator_ends_with_one_line_in_bounded_time(tmp_path):
    import time

    t0 = time.monotonic()
    p = subprocess.run(
        [sys.executable, "-m", "crank_jax", *ARGS, "--out", str(tmp_path / "x.npz"),
         "--distributed"], cwd=tmp_path, capture_output=True, text=True, timeout=300,
        env=_env(JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{_free_port()}", JAX_NUM_PROCESSES="2",
                 JAX_PROCESS_ID="1", JAX_NUM_CPU_DEVICES="1",
                 CRANK_JAX_DISTRIBUTED_TIMEOUT="5"))
    assert p.returncode == 1, p.stderr[-2000:]
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith("crank-jax: error:")]
    assert len(lines) == 1 and "did not answer within 5 s" in lines[0], p.stderr[-2000:]
    assert time.monotonic() - t0 < 120
    assert not (tmp_path / "x.npz").exists()
