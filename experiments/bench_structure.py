"""Skip what a scene doesn't need: the compiled solve of a scene holds only the terms and
outputs the scene uses.

Compiles `simulate` under `jax.jit` (its parameters traced, so the terms come from the
`structure` passed, the scene's `Scene.structure`; no in-program checks; solver
"dopri8-uniform", 10 s, 1001 samples) for:
the pendulum preset (crank only: no coupler, slider, spring, loads), the lab rig (every
body), the lab rig with a harmonic slider force and crank torque, and the lab rig with
every derived output. Records the optimised HLO's instruction count, XLA's flop estimate,
and the run time (median of 31). Fewer terms: fewer instructions and less time per step.

Run: `python experiments/bench_structure.py [--smoke]`.
"""

from __future__ import annotations

import argparse
import re

import jax.numpy as jnp
from _bench import median_time, save, setup_jax

jax = setup_jax()
import crank_jax as cj  # noqa: E402
from crank_jax.solve import OUTPUTS  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true")
    smoke = ap.parse_args(argv).smoke
    ts = jnp.linspace(0.0, 1.0 if smoke else 10.0, 101 if smoke else 1001)
    lab, pend = cj.load_scene("lab-rig"), cj.load_scene("pendulum")
    loads = (cj.HarmonicLoad(0.0, 5.0, 3.0), cj.HarmonicLoad(0.0, 0.05, 4.0))
    cases = [("pendulum (crank only)", pend, cj.NoLoad(), cj.NoLoad(), ()),
             ("lab rig", lab, cj.NoLoad(), cj.NoLoad(), ()),
             ("lab rig + P(t) + tau(t)", lab, *loads, ()),
             ("lab rig + every output", lab, cj.NoLoad(), cj.NoLoad(),
              tuple(sorted(OUTPUTS)))]
    rows = []
    for label, scene, load, torque, outputs in cases:
        kw = dict(solver="dopri8-uniform", max_steps=200_000, adjoint="forward",
                  structure=scene.structure, outputs=outputs, throw=False, checks=False)

        def solve(mech, load, torque, phi0, dphi0, ts, rtol, atol, kw=kw):
            return cj.simulate(mech, phi0, dphi0, ts, load=load, torque=torque, rtol=rtol,
                               atol=atol, **kw)

        args = (scene.mech, load, torque, jnp.asarray(1.0), jnp.asarray(0.0), ts,
                jnp.asarray(1e-8), jnp.asarray(1e-10))
        compiled = jax.jit(solve).lower(*args).compile()
        text = compiled.as_text()
        n_instr = len(re.findall(r"^\s+\S+ = ", text, re.M))
        cost = compiled.cost_analysis()
        cost = cost[0] if isinstance(cost, list) else cost
        # 31 repeats: a single solve is a few ms, and the machine is shared (an earlier
        # 7-repeat run put the loaded scene at 16 ms against 6 ms unloaded: noise).
        # Timed through the program just compiled and inspected (one compilation per case).
        t = median_time(lambda: jax.block_until_ready(compiled(*args)), 1 if smoke else 31,
                        warmup=1 if smoke else 3)
        tr = compiled(*args)
        rows.append({"case": label, "hlo_instructions": n_instr,
                     "flops_estimate": float(cost.get("flops", float("nan"))),
                     "time_s": t, "steps": int(tr.num_steps)})
        print(rows[-1], flush=True)
    save("structure", {"rows": rows}, smoke)


if __name__ == "__main__":
    main()
