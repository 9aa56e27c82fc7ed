"""Traced parameters cost what constants do: the step loop's kernels with the packed
coefficients (`CrankField.packed()`, model/coefficients.py) against the field that forms
its parameter parts inside the loop, and against constants.

For several scenes (the lab rig, with a slider offset, with friction, the crank-only
pendulum, everything at once), `solve_adaptive` (10 s, 1001 saves, rtol 1e-9) is compiled
inside `jax.jit` three ways: the plain `CrankField` with every parameter traced, its
packed form with every parameter traced (what `simulate` steps), and the plain field with
the parameters compiled in as constants (which XLA folds: the reference, though a value
change would recompile). For each: the kernels (fusions) of the inner step
loop's body and their operands per iteration (read from the optimised HLO), the
loop-carried values, and the run time (median). Also the cost per element, in a batch
of 10^4 inside a loop, of float64 `jnp.sin` + `jnp.cos` and `jax.lax.rsqrt` against the
arithmetic forms of trig.py that a lockstep batch uses, alone and inside a kernel of
cheap ops (where a scalar library call keeps the whole kernel from vectorising).
Written to results/fusion.json.

Run: `python experiments/bench_fusion.py [--smoke]`.
"""

from __future__ import annotations

import argparse
import re

from _bench import median_time, save, setup_jax

jax = setup_jax()
import jax.numpy as jnp  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.model import CrankField, ModelTerms, trig  # noqa: E402
from crank_jax.solve.adaptive import solve_adaptive  # noqa: E402


def _step_loop(compiled) -> dict:
    """Kernels, their operands and the loop-carried values of the innermost step loop
    (the while body with the most fusions)."""
    comps = [c for c in compiled.as_text().split("\n\n") if c.strip()]
    bodies = [c for c in comps if " fusion(" in c and "arg_tuple" in c.split("\n")[0]]
    body = max(bodies, key=lambda c: c.count(" fusion("))
    calls = [line.split(" fusion(")[1] for line in body.split("\n") if " fusion(" in line]
    carried = body.split("\n")[0].split("->")[0]
    return {"kernels": len(calls),
            "kernel_operands": sum(c.split(")")[0].count("%") for c in calls),
            "loop_carried": len(re.findall(r"(?:f64|s64|s32|pred)\[", carried))}


def _elementwise(smoke: bool) -> list[dict]:
    """ns per element of each function, in a jitted loop of 100 passes over 10^4 angles."""
    x0 = jnp.linspace(-3.0, 3.0, 10_000)
    cheap = lambda x: x * x * x * 0.1 + x * x * 0.3 + x * 0.2 + 1 / (x * x + 2)  # noqa: E731
    cases = {"sin + cos": (lambda x: jnp.sin(x) + jnp.cos(x),
                           lambda x: sum(trig.sincos(x, trig.ARITHMETIC))),
             "1/sqrt": (lambda x: jax.lax.rsqrt(x * x + 1),
                        lambda x: trig.rsqrt(x * x + 1, trig.ARITHMETIC)),
             "1/sqrt + 10 cheap ops": (lambda x: jax.lax.rsqrt(x * x + 1) + cheap(x),
                                       lambda x: trig.rsqrt(x * x + 1, trig.ARITHMETIC)
                                       + cheap(x))}
    rows = []
    for name, (lib, ours) in cases.items():
        row = {"function": name}
        for label, fn in (("jax_ns", lib), ("trig_ns", ours)):
            loop = jax.jit(lambda x, fn=fn: jax.lax.fori_loop(
                0, 100, lambda i, c: c + 1e-9 * fn(c), x))
            loop(x0)  # traced and compiled here
            t = median_time(lambda loop=loop: jax.block_until_ready(loop(x0)),
                            1 if smoke else 21, warmup=1)
            row[label] = t / 100 / x0.size * 1e9
        rows.append(row)
        print(row, flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true")
    smoke = ap.parse_args(argv).smoke
    lab = cj.load_scene("lab-rig").mech.replace(c=1e-3)
    cases = {"lab rig": lab}
    if not smoke:
        cases.update({"lab rig + offset e": lab.replace(e=0.01),
                      "lab rig + friction": lab.replace(T_c=0.01, c_s=0.5, F_s=0.2),
                      "pendulum (crank only)": cj.load_scene("pendulum").mech,
                      "every term": lab.replace(e=0.01, T_c=0.01, c_s=0.5, F_s=0.2)})
    ts = jnp.linspace(0.0, 1.0 if smoke else 10.0, 101 if smoke else 1001)
    y0 = (jnp.array(1.0), jnp.array(0.0))
    rows = []
    for label, mech in cases.items():
        st = ModelTerms.of(mech)

        def solve(m, packed, st=st):
            field = CrankField(m, cj.NoLoad(), cj.NoLoad(), st)
            field = field.packed() if packed else field
            return solve_adaptive(field, y0, ts, 1e-9, 1e-11, max_steps=100_000)[0][0]

        variants = {"CrankField, traced": (lambda m: solve(m, False), (mech,)),
                    "packed, traced (simulate's)": (lambda m: solve(m, True), (mech,)),
                    "CrankField, constants": (lambda mech=mech: solve(mech, False), ())}
        ref = None
        for name, (fn, args) in variants.items():
            jitted = jax.jit(fn)
            row = {"case": label, "field": name, **_step_loop(jitted.lower(*args).compile())}
            phi = jitted(*args)
            ref = phi if ref is None else ref
            row["max_diff_rad"] = float(jnp.max(jnp.abs(phi - ref)))
            row["time_s"] = median_time(lambda: jax.block_until_ready(jitted(*args)),
                                        1 if smoke else 31, warmup=1 if smoke else 3)
            rows.append(row)
            print(row, flush=True)
    save("fusion", {"rows": rows, "rtol": 1e-9, "samples": int(ts.shape[0]),
                    "elementwise": _elementwise(smoke)}, smoke)


if __name__ == "__main__":
    main()
