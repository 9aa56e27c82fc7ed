"""Sweeps over one CPU device and over one per core: the time of a warm `cj.sweep`.

A fresh process per device count (JAX fixes its CPU devices when it starts): the lab rig
with k ~ normal(2, 0.1) and c ~ uniform(0.005, 0.02), `n` samples, the default outputs,
chunks of 1024; the first sweep compiles, the median of the next ones is reported. Both
processes run with XLA's defaults, so the difference is the devices alone.

Run: `python experiments/bench_sweep_devices.py [--smoke] [--n 20000]`.
"""

from __future__ import annotations

import argparse
import os

from _bench import child_json, save, setup_jax

setup_jax()

CHILD = """
import json, time, jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import crank_jax as cj
scene = cj.load_scene("lab-rig")
spec = {"k": "normal(2.0,0.1)", "c": "uniform(0.005,0.02)"}
times, res = [], None
for _ in range(__REPEATS__ + 1):
    t = time.perf_counter()
    res = cj.run_sweep(scene, spec, n=__N__, seed=1)
    times.append(time.perf_counter() - t)
print(json.dumps({"devices": jax.device_count(), "first_s": times[0],
                  "warm_s": float(np.median(times[1:])), "ok": int(res.ok.sum()),
                  "outputs_sum": sum(float(np.sum(v)) for v in res.outputs.values())}))
"""


def run(devices: int, n: int, repeats: int) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env.update(JAX_NUM_CPU_DEVICES=str(devices), CRANK_JAX_NO_CACHE="1")
    code = CHILD.replace("__REPEATS__", str(repeats)).replace("__N__", str(n))
    return child_json(code, (), env)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--n", type=int, default=20_000)
    a = ap.parse_args(argv)
    n, repeats = (2048, 1) if a.smoke else (a.n, 3)
    cores = len(os.sched_getaffinity(0))
    rows = [run(d, n, repeats) for d in sorted({1, cores})]
    for r in rows:
        print(r, flush=True)
    # The same samples on any number of devices: the same results.
    same = len({(r["ok"], round(r["outputs_sum"], 6)) for r in rows}) == 1
    save("sweep_devices", {"n": n, "rows": rows, "same_results": same}, a.smoke)


if __name__ == "__main__":
    main()
