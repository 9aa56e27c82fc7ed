"""Gradients: the full sensitivity Jacobian d phi(ts) / d theta against one forward solve.

theta = the 10 parameters (L, b, s, m_c, m_p, m_s, I_c, I_p, k, c) of the lab rig with
c = 1e-3, phi0 = 1 rad, 10 s, 1001 samples, rtol 1e-8 / atol 1e-10: J has shape (1001, 10).
Measured side by side in one run (medians):

- the baseline: one forward solve as the Jacobians run it, the same function of theta
  under `jax.jit` (default solver); beside it, a concrete `crank_jax.simulate` call, which
  also pays its host-side input checks and dispatch (before 2026-11-24 this concrete call
  was the baseline, which flattered every ratio by that fixed cost);
- forward mode: `jax.jacfwd` through `simulate(adjoint="forward")`, with the default
  `"dopri8-adaptive"` solver (whose JVP steps the variational equation beside the
  solution, see `crank_jax.solve.variational`), the same with its stages in a loop (the
  fit's: `AdaptiveDopri8(loop_stages=True)`), the same solver with JAX's tangents carried
  through its steps (the default's forward mode before 2026-11-26; here
  `simulate(adjoint="direct")`, which steps the same loop; until 2026-11-28 this row called
  the inner loop `solve_adaptive` directly: the same Jacobian to 3e-16 and the same time
  within the machine's noise, 10 s case), the `"dopri8-uniform"` solver (JAX's forward mode
  through its loop since issue 26; its own variational rule, measured slower than
  diffrax's, was removed) and with diffrax's adaptive Dopri8
  (`diffrax.ForwardMode`);
- reverse mode: `jax.jacrev` through `simulate(adjoint="reverse")` (one backward pass per
  output sample, so 1001 of them, batched by `vmap`), both solvers.

Each Jacobian is jitted; compile time is reported separately. Target (c): the best
Jacobian <= 5x one default forward solve. Issue 9 target 4: the forward-sensitivity
Jacobian with the default's solver (`jacfwd, dopri8-adaptive`) <= 4x one forward solve.

Run: `python experiments/bench_gradients.py [--smoke]`.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _bench import RESULTS, median_time, save, setup_jax, use_clock

jax = setup_jax()
import jax.numpy as jnp  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax import AdaptiveDopri8  # noqa: E402

PARAMS = ("L", "b", "s", "m_c", "m_p", "m_s", "I_c", "I_p", "k", "c")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--tag", default="", help="suffix of the results file (e.g. _cpu_flags)")
    ap.add_argument("--forward-only", action="store_true", help="skip the jacrev variants")
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                    help="time on the wall clock or the process CPU clock (shared machines)")
    a = ap.parse_args(argv)
    use_clock(a.clock)
    smoke = a.smoke
    t1, samples = (1.0, 101) if smoke else (10.0, 1001)
    # Milliseconds each: many repeats, so that the median holds on a shared machine (the
    # slow reverse-mode rows stop at their time budget).
    repeats = 1 if smoke else 31
    mech = cj.load_scene("lab-rig").mech.replace(c=1e-3)
    ts = jnp.linspace(0.0, t1, samples)
    theta0 = jnp.array([float(getattr(mech, n)) for n in PARAMS])

    def phi(theta, solver, adjoint):
        m = mech.replace(**dict(zip(PARAMS, theta)))
        if solver == "tangents":  # the default's solver, JAX's tangents through its steps
            solver, adjoint = "dopri8-adaptive", "direct"
        return cj.simulate(m, 1.0, 0.0, ts, solver=solver, rtol=1e-8, atol=1e-10,
                           adjoint=adjoint).phi

    # The reference is the forward solve as the Jacobians run it: the same function of
    # theta under `jax.jit` (traced parameters, default solver). A concrete `simulate`
    # call also pays its host-side checks and dispatch; it is listed for comparison.
    fwd = jax.jit(lambda th: phi(th, "auto", "forward"))
    jax.block_until_ready(fwd(theta0))
    base = median_time(lambda: jax.block_until_ready(fwd(theta0)), repeats)
    concrete = median_time(
        lambda: jax.block_until_ready(cj.simulate(mech, 1.0, 0.0, ts).phi), repeats)
    rows = [{"method": "one forward solve (the same function of theta, jit, default solver)",
             "time_s": base, "ratio": 1.0, "compile_s": None},
            {"method": "one concrete `simulate` call (default solver; host checks included)",
             "time_s": concrete, "ratio": concrete / base, "compile_s": None}]
    print(rows[0], rows[1], sep="\n", flush=True)
    variants = [("jacfwd, dopri8-adaptive (default)", jax.jacfwd, "dopri8-adaptive", "forward"),
                ("jacfwd, dopri8-adaptive, stages in a loop (the fit's: loop_stages)",
                 jax.jacfwd, AdaptiveDopri8(loop_stages=True), "forward"),
                ("jacfwd, dopri8-adaptive, tangents through the steps (before 2026-11-26)",
                 jax.jacfwd, "tangents", "forward"),
                ("jacfwd, dopri8-uniform", jax.jacfwd, "dopri8-uniform", "forward"),
                ("jacfwd, diffrax Dopri8 (ForwardMode)", jax.jacfwd, "dopri8", "forward")]
    if smoke:  # CI: the default and the reference (tests/test_uniform.py has the uniform's)
        variants = [variants[0], variants[4]]
    if not (smoke or a.forward_only):
        variants += [("jacrev, dopri8-uniform", jax.jacrev, "dopri8-uniform", "reverse"),
                     ("jacrev, diffrax Dopri8 (RecursiveCheckpoint)", jax.jacrev, "dopri8",
                      "reverse")]
    jacs = {}
    for label, tr, solver, adjoint in variants:
        f = jax.jit(tr(lambda th, solver=solver, adjoint=adjoint: phi(th, solver, adjoint)))
        J, comp, t = _compiled_and_timed(f, theta0, repeats)
        jacs[label] = np.asarray(J)
        rows.append({"method": label, "time_s": t, "ratio": t / base, "compile_s": comp,
                     "shape": list(J.shape)})
        print(rows[-1], flush=True)
    # One tangent (d phi / d k) through the default solver. Every parameter of theta has a
    # tangent here, so the variational path steps all 10 columns: a JVP costs what the
    # Jacobian costs (a direction through fewer parameters steps fewer columns).
    for adjoint in ("forward", "direct"):
        one = jax.jit(lambda th, adjoint=adjoint: jax.jvp(
            lambda th: phi(th, "auto", adjoint), (th,),
            (jnp.eye(len(PARAMS))[PARAMS.index("k")],))[1])
        _, comp, t = _compiled_and_timed(one, theta0, repeats)
        how = ("" if adjoint == "forward" else
               ", adjoint=\"direct\" (tangents through the steps)")
        rows.append({"method": f"jvp, one tangent (k), dopri8-adaptive (default){how}",
                     "time_s": t, "ratio": t / base, "compile_s": comp, "shape": [samples]})
        print(rows[-1], flush=True)
    # The Jacobians agree (relative to the largest sensitivity of each parameter).
    ref = jacs["jacfwd, diffrax Dopri8 (ForwardMode)"]
    scale = np.max(np.abs(ref), axis=0)
    agree = {k: float(np.max(np.abs(v - ref) / scale)) for k, v in jacs.items()}
    best = min((r for r in rows if r["compile_s"] is not None  # the Jacobians
                and not r["method"].startswith("jvp")),
               key=lambda r: r["time_s"])
    target = {"goal": 5.0, "best_method": best["method"], "ratio": best["ratio"]}
    fwd = next(r for r in rows if r["method"] == "jacfwd, dopri8-adaptive (default)")
    target4 = {"goal": 4.0, "method": fwd["method"], "ratio": fwd["ratio"]}
    print("agreement:", agree, "\ntarget (c):", target, "\nissue 9 target 4:", target4)
    if a.forward_only and not smoke:
        rows += _kept_reverse_rows()
    save("gradients" + a.tag, {"t1": t1, "samples": samples, "params": PARAMS, "rows": rows,
                       "max_rel_disagreement": agree, "target_c": target,
                       "target_4": target4}, smoke)


def _compiled_and_timed(f, x, repeats):
    """(f(x), the first call's time (compilation included), the median of `repeats` more
    calls), all of a jitted `f`."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(f(x))
    comp = time.perf_counter() - t0
    t = median_time(lambda: jax.block_until_ready(f(x)), repeats, warmup=0, budget_s=60.0)
    return out, comp, t


def _kept_reverse_rows() -> list[dict]:
    """The jacrev rows of the previous results file, labelled with the run they come from
    (a `--forward-only` run does not time them; their ratio is to that run's forward
    solve)."""
    import json

    path = RESULTS / "gradients.json"
    if not path.exists():
        return []
    old = json.loads(path.read_text())
    when = old.get("machine", {}).get("date", "an earlier run")
    out = []
    for r in old.get("rows", []):
        if r["method"].startswith("jacrev"):
            label = r["method"] if "not rerun" in r["method"] else (
                f"{r['method']} (not rerun: from the run of {when}, ratio to that run's "
                "forward solve)")
            out.append(dict(r, method=label))
    return out


if __name__ == "__main__":
    main()
