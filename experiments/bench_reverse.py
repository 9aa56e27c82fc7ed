"""Reverse mode: `jax.grad` of a scalar loss over 10 parameters against one forward solve,
under XLA's defaults and with the CPU flags, beside plain diffrax.

The lab rig with c = 1e-3, phi0 = 1 rad, 10 s, 1001 samples, rtol 1e-8 / atol 1e-10;
theta = (L, b, s, m_c, m_p, m_s, I_c, I_p, k, c); the loss `sum(w * phi(ts))` with fixed
weights w. Measured in one process per setting (the flags are read when JAX starts), each
ratio to the forward solve of that same process:

- one forward solve: the same function of theta under `jax.jit` (default solver);
- crank-jax grad: `jax.grad` through `simulate` (default solver, `adjoint="reverse"`:
  the discrete adjoint of its steps, crank_jax/solve/adjoint.py);
- plain diffrax grad: `diffrax.diffeqsolve` with `Dopri8`, a `PIDController` at the same
  tolerances, `SaveAt(ts=...)` and diffrax's default adjoint (checkpointed reverse
  mode), on the model's own vector field (`cj.model.CrankField`), as a user would write it.

With the CPU flags also the backward program of before 2026-11-28 (each step's VJP with
respect to the parameters too, experiments/_reverse_programs.py), compiled and measured in
the same process. Goals (issue 40): the crank-jax grad <= 3x one forward solve with the
CPU flags, <= 4x with XLA's defaults. Writes
experiments/results/gradients_reverse{,_cpu_flags}.json.

Run: `python experiments/bench_reverse.py [--smoke]` (runs both settings).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

import numpy as np
from _bench import CLOCK, median_time, save, setup_jax, use_clock

PARAMS = ("L", "b", "s", "m_c", "m_p", "m_s", "I_c", "I_p", "k", "c")
GOALS = {"": 4.0, "_cpu_flags": 3.0}  # issue 40 (issue 26: 6x under the defaults)
OLD = "crank-jax grad, one VJP per step with the parameters (before 2026-11-28)"


def measure(smoke: bool, tag: str) -> None:
    """One setting's rows, in this process (its XLA_FLAGS as started)."""
    jax = setup_jax()
    import diffrax
    import jax.numpy as jnp

    import crank_jax as cj

    t1, samples = (1.0, 101) if smoke else (10.0, 1001)
    repeats = 1 if smoke else 21
    mech = cj.load_scene("lab-rig").mech.replace(c=1e-3)
    ts = jnp.linspace(0.0, t1, samples)
    w = jnp.sin(jnp.arange(samples) * 0.7)
    theta0 = jnp.array([float(getattr(mech, n)) for n in PARAMS])

    def crank(theta):
        m = mech.replace(**dict(zip(PARAMS, theta)))
        return cj.simulate(m, 1.0, 0.0, ts, rtol=1e-8, atol=1e-10).phi

    def plain(theta):
        field = cj.model.CrankField(mech.replace(**dict(zip(PARAMS, theta))), cj.NoLoad(),
                                    cj.NoLoad())
        term = diffrax.ODETerm(lambda t, y, args: jnp.stack(field(t, (y[0], y[1]))))
        sol = diffrax.diffeqsolve(term, diffrax.Dopri8(), t0=ts[0], t1=ts[-1], dt0=None,
                                  y0=jnp.array([1.0, 0.0]), saveat=diffrax.SaveAt(ts=ts),
                                  stepsize_controller=diffrax.PIDController(rtol=1e-8,
                                                                            atol=1e-10),
                                  max_steps=200_000)
        return sol.ys[:, 0]

    from crank_jax.runtime.xla_flags import backward_program
    from crank_jax.solve import adjoint

    def compiled(fn, before=None):
        # Compiled ahead (`lower`), so that `jax.clear_caches` (a fresh trace of the
        # backward pass, which JAX would otherwise reuse) leaves it as it is.
        jax.clear_caches()
        keep = adjoint._deferred
        if before is not None:
            adjoint._deferred = before
        try:
            return jax.jit(fn).lower(theta0).compile()
        finally:
            adjoint._deferred = keep

    cases = [("one forward solve (jit, default solver)", crank),
             ("crank-jax grad (default solver, adjoint=\"reverse\")",
              jax.grad(lambda th: jnp.sum(w * crank(th))))]
    if backward_program() == "loop":  # the program of the CPU flags before 2026-11-28, beside it
        from _reverse_programs import per_step
        cases.append((OLD, jax.grad(lambda th: jnp.sum(w * crank(th))), per_step()))
    cases.append(("plain diffrax Dopri8 grad (RecursiveCheckpointAdjoint)",
                  jax.grad(lambda th: jnp.sum(w * plain(th)))))
    rows, grads = [], {}
    for label, fn, *before in cases:
        t0 = time.perf_counter()
        fn = compiled(fn, *before)
        out = jax.block_until_ready(fn(theta0))
        comp = time.perf_counter() - t0
        t = median_time(lambda fn=fn: jax.block_until_ready(fn(theta0)), repeats,
                        budget_s=60.0)
        # Also on the other clock: XLA runs the backward pass's large kernels on both cores
        # under its defaults, which the process CPU clock counts twice and a user's wall
        # clock once (the forward solve is one thread either way).
        clock = CLOCK["name"]
        use_clock("wall" if clock == "cpu" else "cpu")
        other = median_time(lambda fn=fn: jax.block_until_ready(fn(theta0)), repeats,
                            budget_s=60.0)
        use_clock(clock)
        if "grad" in label:
            grads[label] = np.asarray(out)
        rows.append({"method": label, "time_s": t, "ratio": t / rows[0]["time_s"] if rows
                     else 1.0, "compile_s": comp, "other_clock_s": other,
                     "other_clock_ratio": other / rows[0]["other_clock_s"] if rows else 1.0})
        print(rows[-1], flush=True)
    g, ref = grads[rows[1]["method"]], grads[rows[-1]["method"]]
    agree = float(np.max(np.abs(g - ref)) / np.max(np.abs(ref)))
    extra = {}
    if OLD in grads:  # the same sum in another order: equal to rounding
        extra["grad_vs_per_step_rel"] = float(np.max(np.abs(g - grads[OLD]))
                                              / np.max(np.abs(grads[OLD])))
    save("gradients_reverse" + tag,
         {"t1": t1, "samples": samples, "params": PARAMS, "rows": rows,
          "grad_vs_plain_diffrax_rel": agree, **extra, "load_avg": os.getloadavg(),
          "goal": {"ratio": GOALS[tag], "met": rows[1]["ratio"] <= GOALS[tag]}}, smoke)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--clock", choices=("wall", "cpu"), default="cpu",
                    help="time on the process CPU clock (default: a shared machine) or wall")
    ap.add_argument("--setting", choices=("defaults", "cpu_flags"),
                    help="measure one setting in this process (the parent runs both)")
    a = ap.parse_args(argv)
    if a.setting is not None:
        use_clock(a.clock)
        measure(a.smoke, "" if a.setting == "defaults" else "_cpu_flags")
        return
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "src"))
    from crank_jax.runtime.xla_flags import with_cpu_flags

    for setting in ("defaults", "cpu_flags"):
        env = dict(os.environ)
        env.pop("XLA_FLAGS", None)
        if setting == "cpu_flags":
            env["XLA_FLAGS"] = with_cpu_flags(None)
        cmd = [sys.executable, __file__, "--setting", setting, "--clock", a.clock]
        subprocess.run(cmd + (["--smoke"] if a.smoke else []), env=env, check=True)


if __name__ == "__main__":
    main()
