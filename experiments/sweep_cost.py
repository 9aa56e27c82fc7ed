"""What a sweep compiles and what it costs.

    python experiments/sweep_cost.py            # full run
    python experiments/sweep_cost.py --smoke    # seconds, for CI

1. "Skip what a scene doesn't need": XLA's cost analysis (`crank_jax.sweep_cost`) and the
   run time of one chunk, for scenes with and without bodies, loads and outputs, and with
   the scene's own structure against every term compiled in (`Structure()`).
2. Bucketing: a sweep whose samples span a stiff tail, with and without sorting by the
   linearised fastest rate (lockstep batches cost their slowest member's steps).
3. Solvers: what `"auto"` (the policy's fused `dopri8-uniform` on a sweep's uniform save
   times) costs against Tsit5 and Dopri8 at the scene's tolerance, with the error of each
   against an rtol = 1e-12 reference.

Writes experiments/results/sweep_cost[_smoke].json.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.runtime.io import atomic_write  # noqa: E402

RESULTS = Path(__file__).resolve().parents[1] / "experiments" / "results"


def _time_sweep(scene, spec, outputs, repeats, **kw):
    cj.run_sweep(scene, spec, outputs, **kw)  # compile
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        r = cj.run_sweep(scene, spec, outputs, **kw)
        times.append(time.perf_counter() - t0)
    return r, float(np.median(times))


def structure_cost(smoke):
    rig = cj.load_scene("lab-rig")
    pend = cj.load_scene("pendulum")
    n = 64 if smoke else 512
    kw = dict(n=n, t1=1.0, num_saves=101, chunk_size=n, solver="tsit5")
    cases = [
        ("lab rig, peak_phi", rig, {"k": "normal(2,0.1)"}, ("peak_phi",), None),
        # (a mean: an amplitude with no frequency has no effect, and a sweep refuses it)
        ("lab rig, P0 varied at const(0)", rig, {"k": "normal(2,0.1)", "P0": "const(0)"},
         ("peak_phi",), None),
        ("lab rig, harmonic P varied", rig, {"k": "normal(2,0.1)", "P1": "normal(1,0.1)",
                                             "P_freq_hz": 3.0}, ("peak_phi",), None),
        ("lab rig, + final_energy", rig, {"k": "normal(2,0.1)"},
         ("peak_phi", "final_energy"), None),
        ("lab rig, + peak_O (reactions)", rig, {"k": "normal(2,0.1)"},
         ("peak_phi", "peak_O"), None),
        ("pendulum (crank only), own structure", pend, {"c": "uniform(0,1e-3)"},
         ("peak_phi",), None),
        ("pendulum, every term compiled in", pend, {"c": "uniform(0,1e-3)"},
         ("peak_phi",), cj.model.ModelTerms()),
    ]
    rows = []
    for name, scene, spec, outs, structure in cases:
        cost = cj.sweep_cost(scene, spec, outs, num_saves=101, structure=structure)
        if structure is None:
            _, t = _time_sweep(scene, spec, outs, 1 if smoke else 3, **kw)
        else:
            t = None  # sweep() always compiles its own structure; cost analysis only
        rows.append(dict(case=name, **cost, time_per_sample_us=None if t is None
                         else t / n * 1e6))
        print(rows[-1], flush=True)
    return rows


def bucketing(smoke):
    rig = cj.load_scene("lab-rig")
    n = 64 if smoke else 1024
    rng = np.random.default_rng(0)
    # 95% ordinary shafts, 5% stiff ones (ten times the natural frequency).
    k = np.where(rng.uniform(size=n) < 0.05, 200.0, rng.normal(2.0, 0.1, size=n))
    spec = {"k": k}
    rows = []
    for sort in (False, True):
        r, t = _time_sweep(rig, spec, ("peak_phi",), 1 if smoke else 3, t1=2.0,
                           num_saves=101, chunk_size=64, solver="tsit5", sort=sort)
        rows.append(dict(sorted=sort, n=n, time_s=t, total_steps=int(r.num_steps.sum()),
                         all_ok=bool(np.all(r.ok))))
        print(rows[-1], flush=True)
    return rows


def solvers(smoke):
    rig = cj.load_scene("lab-rig")
    n = 64 if smoke else 256
    spec = {"k": "uniform(1.5,2.5)", "c": "uniform(0.001,0.003)"}
    kw = dict(n=n, t1=2.0, num_saves=201, chunk_size=n)
    tight = rig.__class__(rig.mech, rtol=1e-12, atol=1e-14, t1=rig.t1, samples=rig.samples)
    ref = cj.run_sweep(tight, spec, ("phi",), solver="dopri8", **kw).outputs["phi"]
    rows = []
    for solver in ("auto", "tsit5", "dopri8"):
        r, t = _time_sweep(rig, spec, ("phi",), 1 if smoke else 3, solver=solver, **kw)
        rows.append(dict(solver=solver, ran=sorted({cj.solve.SOLVERS[i] for i in r.solver}), n=n,
                         rtol=float(rig.rtol), time_per_sample_us=t / n * 1e6,
                         mean_steps=float(r.num_steps.mean()),
                         max_error_rad=float(np.max(np.abs(r.outputs["phi"] - ref)))))
        print(rows[-1], flush=True)
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--smoke", action="store_true")
    a = p.parse_args(argv)
    res = dict(date=datetime.date.today().isoformat(),
               machine=f"{platform.machine()}, {os.cpu_count()} CPU cores",
               jax=jax.__version__, smoke=a.smoke,
               structure_cost=structure_cost(a.smoke), bucketing=bucketing(a.smoke),
               solvers=solvers(a.smoke), shared_machine="2 cores shared with other jobs")
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"sweep_cost{'_smoke' if a.smoke else ''}.json"
    with atomic_write(path) as f:
        json.dump(res, f, indent=1)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
