"""What the fit's solver costs to compile and to run: the fused `"dopri8-adaptive"` (the
fit's solves through `simulate`'s core: forward mode by the variational equation, its
stages in a loop, `loop_stages`; the segments of multiple shooting, each with its own save
times, as a `vmap`) against diffrax's `Dopri8` (diffrax's `ForwardMode`: what the fit ran
before issue 26). `--unrolled`: the fused solver with its variational stages unrolled (the
fit's solver from issue 26 until 2026-11-27).

The end-to-end benchmark's fit (lab rig, k, c, phi0, dphi0 from k = 2.4, c = 0.004, 5 s
at 200 Hz, 1 mrad noise: multiple shooting, 12 segments), in a fresh process per solver
with no compilation cache: the first fit (compilation included), then three more fits of
other noise seeds (warm: the programs compiled). Each solver runs in its own process, so
neither inherits the other's compiled programs.

Run: `python experiments/fit_solver_tradeoff.py [--unrolled]` (about a minute) writes
`experiments/results/fit_solver_tradeoff.json`.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

from _bench import save

CHILD = r'''
import json, sys, time
t0 = time.perf_counter()
import jax
jax.config.update("jax_enable_x64", True)
import crank_jax as cj
from crank_jax.identify import plan
from crank_jax.solve import solver_named
if sys.argv[1] == "unrolled":  # the fused solver, its variational stages unrolled
    from crank_jax import AdaptiveDopri8
    AdaptiveDopri8.with_loop_stages = lambda self: self
elif sys.argv[1] != "default":  # the fit's solver, whatever the policy would pick
    plan.pick_solver = lambda *a, **k: solver_named(sys.argv[1])
lab = cj.load_scene("lab-rig")
start = cj.Scene(lab.mech.replace(k=2.4, c=0.004), phi0=1.0, name="start")
data = [cj.synthesize(lab, t1=5.0, rate=200.0, noise_std=1e-3, seed=s) for s in (1, 10, 11, 12)]
t1 = time.perf_counter()
first = cj.fit(start, data[0], progress=False)
t2 = time.perf_counter()
warm = [cj.fit(start, d, progress=False) for d in data[1:]]
t3 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "first_fit_s": t2 - t1, "warm_fit_s": (t3 - t2) / 3,
                  "shooting": first.shooting, "iterations": first.iterations,
                  "converged": first.converged and all(w.converged for w in warm),
                  "k": first.values["k"], "c": first.values["c"]}))
'''


def main() -> None:
    env = dict(os.environ, CRANK_JAX_NO_CACHE="1")
    out = {}
    solvers = ("default", "dopri8") + (("unrolled",) if "--unrolled" in sys.argv else ())
    for solver in solvers:
        p = subprocess.run([sys.executable, "-c", CHILD, solver], env=env, check=True,
                           capture_output=True, text=True)
        out[solver] = json.loads(p.stdout.strip().splitlines()[-1])
        print(solver, out[solver], flush=True)
    save("fit_solver_tradeoff", out, False)


if __name__ == "__main__":
    main()
