"""Per-trajectory cost of a sweep over CPU devices x processes, in one run.

For each layout (1, 2, 4 CPU devices in all, over 1 or 2 processes on this machine, the
processes joined by `cj.sweep.initialize_distributed` on the loopback address) fresh processes
run the same sweep: the lab rig, k ~ normal(2, 0.1), c ~ uniform(0.005, 0.02), `n`
samples over `t1` s, the default outputs, chunks of `chunk`. The first sweep compiles;
the time of the second (warm) one, on process 0, divided by `n`, is the per-trajectory
cost. Every layout solves the same samples (the relative spread of the outputs' sums
over the layouts is recorded; it should be at round-off, 1e-12 or less). The
machine has 2 cores: layouts with more devices than cores show the cost of
oversubscription, not more speed.

Run: `python experiments/sweep_scaling.py [--n 1024] [--t1 1.0]`; writes
`experiments/results/sweep_scaling.json`.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

CHILD = """
import json, sys, time, jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import crank_jax as cj
if int(sys.argv[1]) > 1:
    cj.sweep.initialize_distributed()
scene = cj.load_scene("lab-rig")
spec = {"k": "normal(2.0,0.1)", "c": "uniform(0.005,0.02)"}
kw = dict(n=int(sys.argv[2]), seed=1, t1=float(sys.argv[3]), chunk_size=int(sys.argv[4]))
t = time.perf_counter()
cj.run_sweep(scene, spec, **kw)
first = time.perf_counter() - t
t = time.perf_counter()
res = cj.run_sweep(scene, spec, **kw)
warm = time.perf_counter() - t
if jax.process_index() == 0:
    print(json.dumps({"devices": jax.device_count(), "processes": jax.process_count(),
                      "first_s": first, "warm_s": warm, "ok": int(res.ok.sum()),
                      "outputs_sum": sum(float(np.sum(v)) for v in res.outputs.values())}))
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(devices: int, processes: int, n: int, t1: float, chunk: int) -> dict:
    """One layout: `processes` processes with `devices // processes` CPU devices each."""
    port = _free_port()
    procs = []
    for i in range(processes):
        env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
        env.update(JAX_NUM_CPU_DEVICES=str(devices // processes), CRANK_JAX_NO_CACHE="1",
                   JAX_PLATFORMS="cpu", JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{port}",
                   JAX_NUM_PROCESSES=str(processes), JAX_PROCESS_ID=str(i))
        procs.append(subprocess.Popen(
            [sys.executable, "-c", CHILD, str(processes), str(n), str(t1), str(chunk)],
            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    outs = [p.communicate(timeout=1800) for p in procs]
    for p, (_, err) in zip(procs, outs, strict=True):
        if p.returncode:
            raise RuntimeError(f"layout {devices}x{processes} failed: {err[-2000:]}")
    row = json.loads(outs[0][0].strip().splitlines()[-1])
    row["per_trajectory_us"] = 1e6 * row["warm_s"] / n
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1024)
    ap.add_argument("--t1", type=float, default=1.0)
    ap.add_argument("--chunk", type=int, default=256)
    a = ap.parse_args(argv)
    t0, load = time.time(), os.getloadavg()
    rows = []
    for devices in (1, 2, 4):
        for processes in (1, 2):
            if devices % processes:
                continue
            rows.append(run(devices, processes, a.n, a.t1, a.chunk))
            print(rows[-1], flush=True)
    sums = [r["outputs_sum"] for r in rows]
    spread = (max(sums) - min(sums)) / abs(sums[0])
    out = {"what": __doc__.splitlines()[0], "n": a.n, "t1_s": a.t1, "chunk": a.chunk,
           "cores": len(os.sched_getaffinity(0)), "load_average_at_start": load,
           "load_average_at_end": os.getloadavg(),
           "outputs_sum_relative_spread": spread, "rows": rows,
           "wall_s": time.time() - t0,
           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    path = Path(__file__).resolve().parent / "results" / "sweep_scaling.json"
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
