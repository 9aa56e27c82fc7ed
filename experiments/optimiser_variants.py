"""Issue 38, item 1: why does LM crawl on records the model cannot fully explain? The
same fits under other optimisers, counted in the same iterations.

The fit's optimiser is MINPACK's Levenberg-Marquardt (`scipy.optimize.least_squares(
method="lm")`, Marquardt's scaling, `identify/optimize.py`), driven by the fit's own
termination tests in the data's units. This script swaps the optimiser under those same
tests (every variant gets the same residuals, Jacobians, stop tests and escalation) and
runs the rotating-rig stand-ins of `misfit_rig.py`:

- `lm`: the default (MINPACK LM, `x_scale="jac"`);
- `trf`: scipy's trust-region reflective method (`tr_solver="exact"`, `x_scale="jac"`);
- `dogbox`: scipy's dogleg in a box;
- `geodesic`: LM with geodesic acceleration (Transtrum and Sethna, "Improvements to the
  Levenberg-Marquardt algorithm for nonlinear least-squares minimization", 2012), a
  prototype written here (no well-kept Python library has it): the second directional
  derivative of the residuals along the LM step by one extra residual evaluation, the
  step `v + a/2`, accepted when `2|a| <= 0.75 |v|`. Each of its iterations costs one more
  evaluation than LM's.

Counted per case: the tries the strategy made (`attempt`), each try's iterations (Jacobian
evaluations, what the fit reports as LM iterations), the verdict and rms of the result.

    python experiments/optimiser_variants.py [--cases friction,angle] [--variants lm,trf]

Writes experiments/results/optimiser_variants.json. Each case and variant runs in a fresh
process; wall times on the shared machine are rough, the iterations are not.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from types import SimpleNamespace

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
VARIANTS = ("lm", "trf", "dogbox", "geodesic")


def geodesic_lm(fun, x0, jac, max_nfev=10_000, alpha=0.75, h=0.1):
    """LM with geodesic acceleration (a prototype; see the module). Marquardt's scaling
    with memory (the largest diagonal of `J^T J` seen), damping down by 3 after a success,
    up by 10 after a failure. Stops when the fit's tests (inside `jac`) stop it, after
    `max_nfev` evaluations, or when the damping overflows."""
    x = np.asarray(x0, float).copy()
    r = fun(x)
    cost = 0.5 * r @ r
    J = jac(x)
    D = np.maximum(np.sum(J * J, axis=0), 1e-300)
    lam, nfev = 1e-3, 1
    while nfev < max_nfev:
        JtJ, g = J.T @ J, J.T @ r
        D = np.maximum(D, np.sum(J * J, axis=0))
        A = JtJ + lam * np.diag(D)
        v = np.linalg.solve(A, -g)
        rv = fun(x + h * v)
        nfev += 1
        a = np.linalg.solve(A, -(J.T @ (2.0 / h * ((rv - r) / h - J @ v))))
        if 2 * np.linalg.norm(a * np.sqrt(D)) > alpha * np.linalg.norm(v * np.sqrt(D)):
            lam *= 10.0
            continue
        step = v + 0.5 * a
        rn = fun(x + step)
        nfev += 1
        cn = 0.5 * rn @ rn
        if np.isfinite(cn) and cn < cost:
            x, r, cost = x + step, rn, cn
            lam = max(lam / 3.0, 1e-12)
            J = jac(x)
        else:
            lam *= 10.0
            if lam > 1e16:
                return SimpleNamespace(x=x, status=2, message="no progress")
    return SimpleNamespace(x=x, status=0, message="evaluation budget spent")


def _swap_optimiser(variant: str, log: list) -> None:
    """Make `scipy.optimize.least_squares`, as `identify/optimize.py` imports it at each
    call, run `variant` under the same callbacks, logging each run's Jacobian calls."""
    import scipy.optimize as so

    plain = so.least_squares

    def swapped(fun, x0, jac=None, method="lm", **kw):
        calls = [0]

        def counted(x):
            calls[0] += 1
            return jac(x)

        t = time.perf_counter()
        try:
            if variant == "geodesic":
                return geodesic_lm(fun, x0, counted, max_nfev=kw.get("max_nfev", 10_000))
            if variant in ("trf", "dogbox"):
                kw.pop("max_nfev", None)
                kw["tr_solver"] = "exact"
                method = variant
            return plain(fun, x0, jac=counted, method=method, **kw)
        finally:
            log.append({"coordinates": len(x0), "jacobians": calls[0],
                        "seconds": round(time.perf_counter() - t, 2)})

    so.least_squares = swapped


def one(case: str, variant: str) -> dict:
    """Fit `misfit_rig` case `case` with `variant`; the tries and the result."""
    sys.path.insert(0, HERE)
    import misfit_rig

    from crank_jax.identify import attempt as at

    runs, tries = [], []
    _swap_optimiser(variant, runs)
    plain_attempt = at.attempt

    def attempt(req, plan, shoot, z0, zk, desc):
        r = plain_attempt(req, plan, shoot, z0, zk, desc)
        tries.append({"try": desc, "iterations": r.iterations, "converged": r.converged,
                      "rms": at.run_rms(r, plan.single.n_residuals)})
        return r

    at.attempt = attempt
    t = time.perf_counter()
    res = misfit_rig.case(case)
    return {"iterations": res.iterations, "converged": res.converged,
            "verdict": (res.termination or {}).get("verdict"), "rms": res.rms_residual,
            "values": {n: res.values[n] for n in res.names},
            "seconds": round(time.perf_counter() - t, 2), "tries": tries,
            "optimiser_runs": runs}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", default="friction,angle,slide")
    p.add_argument("--variants", default=",".join(VARIANTS))
    p.add_argument("--out", default=os.path.join(HERE, "results", "optimiser_variants.json"))
    p.add_argument("--one", nargs=2, help=argparse.SUPPRESS)  # a child: case, variant
    a = p.parse_args()
    if a.one:
        print("RESULT " + json.dumps(one(*a.one)), flush=True)
        return
    variants = [v for v in a.variants.split(",") if v]
    bad = [v for v in variants if v not in VARIANTS]
    if bad:
        raise SystemExit(f"--variants: unknown {bad[0]!r}; choose from {', '.join(VARIANTS)}")
    sys.path.insert(0, HERE)
    from _bench import machine

    from crank_jax.runtime.io import atomic_write

    out = {"machine": machine(), "cases": {},
           "note": "shared 2-core machine (other jobs ran): wall times rough, iterations exact"}
    for case in [c for c in a.cases.split(",") if c]:
        for v in variants:
            text = subprocess.run([sys.executable, __file__, "--one", case, v],
                                  capture_output=True, text=True, check=True).stdout
            row = json.loads(text.split("RESULT ", 1)[1])
            out["cases"].setdefault(case, {})[v] = row
            print(case, v, row["iterations"], row["verdict"], f"{row['rms']:.6g}",
                  [t["iterations"] for t in row["tries"]], flush=True)
    with atomic_write(a.out) as f:
        json.dump(out, f, indent=2)
        f.write("\n")


if __name__ == "__main__":
    main()
