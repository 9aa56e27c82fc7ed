"""Host callbacks in a fit's programs on diffrax's solvers, and what removing them costs.

A program holding a host callback (an `eqx.error_if` under equinox's default mode "raise":
two `jax.pure_callback`s each) is refused by the program store (`persistent.py`), so a
fit on diffrax's solvers compiled its residual and Jacobian programs in every process.
Traced at diffrax 0.7.2, equinox 0.13.8, optimistix/lineax as installed (2026-11-26),
the callbacks come from:

- `diffeqsolve`'s check of `SaveAt(ts=...)` (diffrax/_integrate.py, `_check_subsaveat_ts`:
  "saveat.ts must be increasing ...", "... must lie between t0 and t1"): two `error_if`s,
  emitted whenever the save times are traced (they are the fit's data, array leaves of
  its programs), in every diffrax solver's program;
- with an implicit solver (`"kvaerno5"`) in forward mode (the LM Jacobian), also
  optimistix's implicit-function JVP of the stage root find (optimistix/_ad.py,
  `lx.linear_solve(operator, jvp_diff, linear_solver)`, `throw` left at True): lineax's
  `result.error_if`. diffrax calls `optx.root_find(..., throw=False)` with the default
  `ImplicitAdjoint()`, and no public argument reaches that linear solve's `throw`.

Three forms of the save, on the lab rig's fit programs (single shooting, 2 s; multiple
shooting, 8 segments, 4 s), in one process:

- `SaveAt(ts)`: as before issue 26's change (`_SaveAtTs` below);
- in steps: what `Diffrax` does now for an explicit solver in forward mode with the save
  times checked by the caller (`solve(checks=False)`, the fit's solves): each accepted
  step saves its dense output at the times it reaches, in the solver's state
  (`solve/saves.py`);
- dense: `SaveAt(dense=True)`, then `sol.evaluate(ts)` (`_DenseSaves` below), diffrax's
  other public form without the check; its buffers are `max_steps` steps of every stage,
  per solve and per tangent, whatever the steps taken (the fit's budgets are 32768 and
  200000, `identify/strategy.py`).

Measured 2026-11-26 (2-core shared CPU, other jobs running, XLA's defaults, medians of
5; ms per call, SaveAt(ts) / in steps / dense; `results/diffrax_callbacks.json`):

| solver, segments, budget | residuals | Jacobian |
|---|---|---|
| dopri5, 1, 32768 | 1.2 / 1.3 / 5.2 | 7.1 / 12.1 / 20.4 |
| dopri5, 1, 200000 | 1.2 / 1.3 / 5.0 | 7.4 / 7.8 / 84 |
| dopri8, 8, 32768 | 1.9 / 1.4 / 34 | 11.2 / 9.4 / 283 |
| dopri8, 8, 200000 | 1.2 / 1.4 / 180 | 8.5 / 10.1 / 2072 |
| kvaerno5, 1, 32768 | 198 / 188 / 197 | 346 / 355 / 378 |

The in-steps form holds no callback on the explicit solvers and gives the `SaveAt(ts)`
numbers bit for bit (every output of both programs, every row); its times are those of
`SaveAt(ts)` within this machine's noise (the dopri5 Jacobian at 32768 ran on a busier
moment: the same program took 7.8 ms in the next row). The dense form is equal to 1.1e-16
but 24-240x slower on multiple shooting (up to 11x on single shooting), with peak memory
1.3 GB -> 4.1 GB at the larger budget. kvaerno5 keeps `SaveAt(ts)` (implicit), and its
Jacobian would hold lineax's check whatever the save: 6 callbacks, 2 with the dense form.

Run: `python experiments/diffrax_callbacks.py [--smoke]`; writes
experiments/results/diffrax_callbacks.json.
"""

from __future__ import annotations

import argparse
import re
import resource
import time

import numpy as np
from _bench import median_time, save, setup_jax

jax = setup_jax()
import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.identify.problem import build_problem, pick_solver  # noqa: E402
from crank_jax.identify.programs import jacobian_at, residuals_at  # noqa: E402
from crank_jax.solve import Diffrax, Solution  # noqa: E402


class _SaveAtTs(Diffrax):
    """`Diffrax` as before issue 26's change: `SaveAt(ts)` whatever `solve(checks=...)`."""

    def unchecked(self):
        return self


class _DenseSaves(Diffrax):
    """`Diffrax` saving through dense output: `SaveAt(dense=True)`, then the solution's
    interpolation at `ts` (the form with no `SaveAt(ts)` check)."""

    def run(self, field, ts, y0, args, *, rtol, atol, max_steps, adjoint, throw, prepare,
            rate=None, step_ts=None, jump_ts=None):
        adj = {"reverse": diffrax.RecursiveCheckpointAdjoint,
               "forward": diffrax.ForwardMode, "direct": diffrax.DirectAdjoint}[adjoint]()
        flat0 = jnp.stack([y0[0], y0[1]]) if isinstance(y0, (list, tuple)) else y0

        def flat_field(t, y, a):
            fld, inner = a
            return jnp.stack(fld(t, (y[0], y[1]), inner)) if isinstance(y0, (list, tuple)) \
                else fld(t, y, inner)

        controller = diffrax.PIDController(rtol=rtol, atol=atol)
        if step_ts is not None or jump_ts is not None:
            controller = diffrax.ClipStepSizeController(controller, step_ts=step_ts,
                                                        jump_ts=jump_ts)
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(flat_field), self.solver, t0=ts[0], t1=ts[-1], dt0=None,
            y0=flat0, args=(prepare(field), args), saveat=diffrax.SaveAt(dense=True),
            stepsize_controller=controller, max_steps=max_steps, adjoint=adj, throw=throw)
        ys = jax.vmap(sol.evaluate)(ts)
        if isinstance(y0, (list, tuple)):
            ys = type(y0)([ys[:, 0], ys[:, 1]])
        steps = sol.stats["num_steps"] + sol.stats.get("num_rejected_steps", 0)
        return Solution(ys, sol.result, steps)


def _callbacks(lowered_text: str) -> int:
    """Host callbacks in a lowered program: its custom calls into Python (what the program
    store refuses, `persistent.py`). Counted in the lowered text, not the jaxpr: lineax's
    check is inside its `linear_solve` primitive, which emits it only when lowered."""
    return len(re.findall(r"custom_call[^\n]*python[^\n]*callback", lowered_text))


def _problem(solver, nseg: int, t1: float, budget: int):
    lab = cj.load_scene("lab-rig")
    data = cj.synthesize(lab, t1=t1, rate=100.0, noise_std=1e-3, seed=1)
    prob = build_problem(lab.mech, [(data, lab.load, lab.torque, 1.0, 0.0)],
                         ("k", "c", "phi0", "dphi0"), {"k": 2.0, "c": 0.002}, [nseg],
                         solver=solver, rtol=1e-8, atol=1e-10, max_steps=budget)
    z = jnp.concatenate([jnp.asarray(prob.to_z([2.1, 0.0025, 1.0, 0.0])),
                         0.5 * jnp.ones(prob.n_extra)])
    return prob, z


def _measure(prob, z, repeats: int) -> dict:
    out = {}
    for program in (residuals_at, jacobian_at):
        f = jax.jit(lambda z, program=program: program.fn(prob, z))
        t = time.perf_counter()
        values = [np.asarray(x) for x in jax.block_until_ready(f(z))]
        first = time.perf_counter() - t
        median = median_time(lambda f=f: jax.block_until_ready(f(z)), repeats, warmup=0,
                             budget_s=float("inf"))
        text = f.lower(z).as_text()
        out[program.name] = {"callbacks": _callbacks(text), "first_s": first,
                             "median_ms": 1e3 * median, "values": values}
    return out


def _diff(a: list, b: list) -> float:
    """Largest absolute difference over the programs' outputs (0.0: bitwise equal)."""
    return max(float(np.nanmax(np.abs(x.astype(float) - y.astype(float)), initial=0.0))
               if not np.array_equal(x, y, equal_nan=True) else 0.0 for x, y in zip(a, b))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--smoke", action="store_true")
    a = ap.parse_args()
    lab = cj.load_scene("lab-rig")
    cases = [("dopri5", 1, 2.0), ("dopri8", 8, 4.0), ("kvaerno5", 1, 2.0)]
    budgets = (4096,) if a.smoke else (32768, 200_000)
    rows = []
    for name, nseg, t1 in cases[:2] if a.smoke else cases:
        plain = pick_solver(lab.mech, lab.load, 1e-8, name)
        forms = {"SaveAt(ts)": _SaveAtTs(plain.solver), "in steps": plain,
                 "dense": _DenseSaves(plain.solver)}
        for budget in budgets:
            got = {}
            for form, solver in forms.items():
                prob, z = _problem(solver, nseg, t1, budget)
                got[form] = _measure(prob, z, 1 if a.smoke else 5)
            row = {"solver": name, "segments": nseg, "record_s": t1, "budget": budget,
                   "peak_rss_mb_so_far": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
                   / 1024}
            for prog in got["SaveAt(ts)"]:
                ref = got["SaveAt(ts)"][prog]["values"]
                row[prog] = {k: {f: got[f][prog][k] for f in forms}
                             for k in ("callbacks", "median_ms")}
                row[prog]["max_abs_diff"] = {f: _diff(ref, got[f][prog]["values"])
                                             for f in forms}
            print(row, flush=True)
            rows.append(row)
    save("diffrax_callbacks", {"rows": rows}, a.smoke)


if __name__ == "__main__":
    main()
