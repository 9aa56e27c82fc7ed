"""A sweep on a GPU against the CPU of the same machine: per-trajectory cost of many
lab-rig trajectories (10 s, 1001 saves each), and errors of members against a reference.

Both runs use `cj.sweep` as users do: the lab rig, k ~ normal(2, 0.1), c ~ uniform(0.005,
0.02), outputs peak_phi, final_phi, final_dphi, the scene's tolerances (rtol 1e-8, atol
1e-10) and its `"auto"` solver. On the GPU: one chunk compiles, then `--n` samples are
timed (chunks of `--chunk`; `--n 0`: no GPU run); on the CPU, one JAX device per core,
`--n-cpu` samples in chunks of `--cpu-chunk` (0: no CPU run).
The errors: 32 members of the GPU run solved again, alone, by `"dopri8"` at rtol = atol =
1e-13 on the CPU (the reference), and the same members from the CPU run.

Run: `python experiments/sweep_gpu.py [--n 100000] [--chunk 16384] [--n-cpu 4096]`;
writes experiments/results/sweep_gpu.json (or `--out`).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_num_cpu_devices", len(os.sched_getaffinity(0)))

import equinox as eqx  # noqa: E402
import numpy as np  # noqa: E402

import crank_jax as cj  # noqa: E402

SPEC = {"k": "normal(2.0,0.1)", "c": "uniform(0.005,0.02)"}
OUTS = ("peak_phi", "final_phi", "final_dphi")


def _timed(scene, n, chunk, devices, spec=SPEC, **kw):
    t = time.perf_counter()
    res = cj.run_sweep(scene, spec, OUTS, n=n, seed=1, chunk_size=chunk, devices=devices, **kw)
    return res, time.perf_counter() - t


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--chunk", type=int, default=16384)
    ap.add_argument("--n-cpu", type=int, default=4096)
    ap.add_argument("--cpu-chunk", type=int, default=1024)
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"
                                         / "sweep_gpu.json"))
    a = ap.parse_args(argv)
    scene = cj.load_scene("lab-rig")
    cpus = jax.devices("cpu")
    try:
        gpus = jax.devices("gpu")
    except RuntimeError:
        gpus = []
    out = {"what": __doc__.splitlines()[0], "jax": jax.__version__, "n": a.n,
           "chunk": a.chunk, "cpu_devices": len(cpus),
           "gpu": [d.device_kind for d in gpus], "t1_s": float(scene.t1),
           "saves": int(scene.samples)}
    runs = {}
    for name, devices, n, chunk in (("gpu", gpus if a.n else [], a.n, a.chunk),
                                    ("cpu", cpus if a.n_cpu else [], a.n_cpu, a.cpu_chunk)):
        if not devices:
            continue
        _, first = _timed(scene, chunk, chunk, devices)  # compiles
        res, warm = _timed(scene, n, chunk, devices)
        runs[name] = res
        out[name] = {"n": n, "first_s": first, "warm_s": warm,
                     "per_trajectory_us": 1e6 * warm / n, "counts": res.counts()}
        print(name, out[name], flush=True)
    # Errors of 32 members against a reference solved alone at rtol = atol = 1e-13.
    some = np.arange(32)
    ref_scene = eqx.tree_at(lambda s: (s.rtol, s.atol), scene,
                            (np.float64(1e-13), np.float64(1e-13)))
    explicit = {k: v[some] for k, v in next(iter(runs.values())).samples.items()}
    ref, _ = _timed(ref_scene, some.size, 1, cpus[:1], spec=explicit, solver="dopri8")
    assert ref.ok.all()
    for name, res in runs.items():
        assert np.array_equal(res.samples["k"][some], explicit["k"])
        out[name]["max_abs_error_vs_reference"] = {
            k: float(np.max(np.abs(res.outputs[k][some] - ref.outputs[k]))) for k in OUTS}
    if {"gpu", "cpu"} <= runs.keys():
        m = min(a.n, a.n_cpu)
        assert np.array_equal(runs["gpu"].samples["k"][:m], runs["cpu"].samples["k"][:m])
        out["max_abs_gpu_minus_cpu"] = {
            k: float(np.max(np.abs(runs["gpu"].outputs[k][:m] - runs["cpu"].outputs[k][:m])))
            for k in OUTS}
        out["cpu_over_gpu_per_trajectory"] = (out["cpu"]["per_trajectory_us"]
                                              / out["gpu"]["per_trajectory_us"])
    print(json.dumps(out, indent=1))
    Path(a.out).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
