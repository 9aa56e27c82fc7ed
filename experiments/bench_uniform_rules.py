"""`"dopri8-uniform"` differentiated (JAX through its loop) against diffrax's Dopri8.

Issue 26 removed the uniform solver's own derivative rules (a variational equation in
forward mode, `solve/sensitivity.py`; a plain-field backward pass in reverse mode,
`solve/twin.py`) because diffrax's Dopri8 differentiated faster. Measured with this script
at the commit before the removal (one process, medians, a loaded 2-core machine, XLA's
defaults, 2026-11-26; lab rig, c = 1e-3, 10 s, 1001 saves, rtol 1e-8, 10 parameters):

| | its rules | JAX through the loop | diffrax Dopri8 |
|---|---|---|---|
| `jax.jacfwd` of phi(ts) | 209 ms | 436 ms | 177 ms |
| `jax.grad` of sum(phi^2) | 237 ms | 498 ms | 113 ms |

Sweeps, the solver's reason to exist, never differentiate.

Run: `python experiments/bench_uniform_rules.py [fwd-uniform fwd-diffrax grad-uniform
grad-diffrax]` (compiling the reverse passes takes minutes).
"""

from __future__ import annotations

import sys
import time

from _bench import median_time, setup_jax

jax = setup_jax()
import jax.numpy as jnp  # noqa: E402

import crank_jax as cj  # noqa: E402

PARAMS = ("L", "b", "s", "m_c", "m_p", "m_s", "I_c", "I_p", "k", "c")
VARIANTS = {"fwd-uniform": (jax.jacfwd, "dopri8-uniform", "forward"),
            "fwd-diffrax": (jax.jacfwd, "dopri8", "forward"),
            "grad-uniform": (jax.grad, "dopri8-uniform", "reverse"),
            "grad-diffrax": (jax.grad, "dopri8", "reverse")}


def main(which):
    mech = cj.load_scene("lab-rig").mech.replace(c=1e-3)
    ts = jnp.linspace(0.0, 10.0, 1001)
    theta0 = jnp.array([float(getattr(mech, n)) for n in PARAMS])

    def phi(theta, solver, adjoint):
        m = mech.replace(**dict(zip(PARAMS, theta)))
        return cj.simulate(m, 1.0, 0.0, ts, solver=solver, rtol=1e-8, atol=1e-10,
                           adjoint=adjoint).phi

    def timed(f, reps):
        t0 = time.perf_counter()
        jax.block_until_ready(f(theta0))
        comp = time.perf_counter() - t0
        return comp, median_time(lambda: jax.block_until_ready(f(theta0)), reps, warmup=0,
                                 budget_s=float("inf"))

    _, base = timed(jax.jit(lambda th: phi(th, "dopri8-uniform", "forward")), 15)
    print(f"forward solve (dopri8-uniform) {base * 1e3:.1f} ms", flush=True)
    for name in which or list(VARIANTS):
        tr, solver, adjoint = VARIANTS[name]
        if tr is jax.grad:
            f = jax.jit(jax.grad(lambda th, s=solver, a=adjoint: jnp.sum(phi(th, s, a) ** 2)))
        else:
            f = jax.jit(jax.jacfwd(lambda th, s=solver, a=adjoint: phi(th, s, a)))
        comp, t = timed(f, 7)
        print(f"{name}: {t * 1e3:.1f} ms (compile {comp:.1f} s)", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
