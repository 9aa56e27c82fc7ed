"""One optimisation of a fit (with the single-shooting polish after multiple shooting),
tries from perturbed starts, and the choice of the run to report;
[`escalation`][crank_jax.identify.escalation] decides which tries to make."""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from ..runtime.arrays import device_array
from ..runtime.xla_flags import backward_program
from ..solve.adjoints import DiscreteAdjoint
from .fit_options import Method
from .fit_plan import basis, recoordinate, recoordinate_basis
from .optax_fit import minimize_optax
from .optimize import least_squares
from .outcome import Run, termination
from .problem import Problem
from .programs import InValues, Subspace, jacobian_at
from .request import FitRequest
from .stages import Plan
from .strategy import AT_ZERO, noise_unit, perturb, stall_rms

__all__ = ["attempt", "guarded", "multistart", "best_run", "run_rms", "in_range"]


def attempt(req: FitRequest, plan: Plan, shoot: Problem, z0: np.ndarray, zk: np.ndarray,
             desc: str) -> Run:
    """One optimisation of `shoot` from `zk` (flat directions held at `z0`), then a
    single-shooting polish when `shoot` is multiple shooting."""
    ss = plan.single
    # Multiple shooting has its own coordinates (linear, see `build_problem`): the flat
    # directions held fixed, and the estimate handed to the polish, are mapped across.
    Bg = plan.Bg if shoot is ss else recoordinate_basis(ss, shoot, plan.Bg,
                                                        recoordinate(shoot, ss, z0))
    B = basis(Bg, z0.shape[0], shoot.state_on)
    # Gradient methods: reverse mode, its backward program chosen here, at the edge.
    problem = shoot if req.method is Method.LM else dataclasses.replace(
        shoot, adjoint=DiscreteAdjoint(backward=backward_program()))
    run_fn = _optimizer(req)
    run = guarded(run_fn, Subspace(problem, device_array(z0), device_array(B)),
                   B.T @ (zk - z0), req.max_steps, req.tol, desc, req.progress)
    run = run._replace(z=z0 + B @ run.z)
    if shoot is not ss:
        zp = recoordinate(shoot, ss, run.z)
        if not np.isfinite(run.cost):
            return run._replace(z=zp)
        # The estimate is the polish's, on the single-shooting cost, and so is the verdict
        # (multiple shooting only brought it near; its stall on the continuity defects
        # says nothing about the point reported).
        pol = _single_from(run_fn if req.method is Method.LM else least_squares, req, ss, zp,
                           np.asarray(plan.Bg), desc + " (polish)")
        run = pol._replace(iterations=run.iterations + pol.iterations)
    return in_range(plan, off_the_bound(req, plan, run, desc))


def in_range(plan: Plan, run: Run) -> Run:
    """`run`, not converged where its estimate (single-shooting coordinates) ran off the
    physical range ([`Ranges`][crank_jax.identify.physical.Ranges]): a point far along a
    flat, absurd direction is no converged minimum, whatever the step test said. The
    escalation then treats it as the failed try it is."""
    ss = plan.single
    if plan.ranges is None or not np.all(np.isfinite(run.z[:ss.p])):
        return run
    why = plan.ranges.ran_off(ss.names, ss.host_values(run.z[:ss.p]))
    if why is None:
        return run
    return run._replace(converged=False, message=why, termination=termination("ran off", why))


def _single_from(run_fn, req: FitRequest, ss: Problem, z: np.ndarray, B: np.ndarray,
                 desc: str) -> Run:
    """One optimisation of the single-shooting problem `ss` over the directions `B` from
    `z` (the polish, the runs held at and released from a bound), in value coordinates
    ([`InValues`][crank_jax.identify.programs.InValues]: near the minimum its valleys are
    the equation of motion's linear balances); its estimate in `ss`'s coordinates."""
    view = InValues(ss, z, B)
    run = guarded(run_fn, view, np.zeros(view.B.shape[1]), req.max_steps, req.tol, desc,
                  req.progress)
    return run._replace(z=view.lift(run.z) if np.all(np.isfinite(run.z)) else z)


def _optimizer(req: FitRequest):
    """The optimiser of `req`: LM with its tests judged in the data's units (the
    residuals' noise level; a stall counts as convergence only near that level), or
    optax's."""
    if req.method is not Method.LM:
        return minimize_optax
    return functools.partial(least_squares, stall_rms=stall_rms(req.noise),
                             noise=noise_unit(req.noise), at_bounds=True)


def off_the_bound(req: FitRequest, plan: Plan, run: Run, desc: str) -> Run:
    """`run` (single-shooting coordinates), or a better end where it stalled with a
    folded parameter (a friction term, `value = ref |z|`) at its bound 0, where the cost
    has a kink and LM crawls (`least_squares(at_bounds=True)` stops it there;
    experiments/misfit_rig.py, case `friction`). As an active-set method does, those
    parameters are held at 0 while LM finishes the others; then, where the cost falls
    into the feasible side (`J_i . r < 0`, `J` at `z_i = 0+`), they are released from
    their one-dimensional Gauss-Newton step and LM runs over all. The run reported is the
    best of these (converged first, then cost); its iterations are all of them."""
    if run.converged or req.method is not Method.LM or not np.isfinite(run.cost):
        return run
    ss = plan.single
    z = np.asarray(run.z[:ss.p], dtype=float)
    at0 = [i for i in range(ss.n_global) if ss.folded[i] and abs(z[i]) < AT_ZERO]
    if not at0:
        return run
    run_fn = _optimizer(req)
    zc = z.copy()
    zc[at0] = 0.0
    Bh = np.asarray(plan.Bg, dtype=float).copy()
    Bh[at0, :] = 0.0
    U, S, _ = np.linalg.svd(Bh, full_matrices=False)
    Bh = U[:, S > 1e-9]  # orthonormal again, the held coordinates' directions removed
    held = _single_from(run_fn, req, ss, zc, Bh, desc + " (friction held at 0)")
    zc = held.z
    tries = [run, held]
    r, failed, _, J = jacobian_at(ss, device_array(zc))
    r, J = np.asarray(r), np.asarray(J)
    grad = J[:, at0].T @ r
    if int(failed) == 0 and np.all(np.isfinite(grad)) and np.any(grad < 0):
        zr = zc.copy()
        for i, g in zip(at0, grad):
            if g < 0:
                zr[i] = -g / max(float(J[:, i] @ J[:, i]), 1e-300)
        # (Without the stop at a bound: released from the constrained minimum, a run
        # that comes back to the bound crawls there to its own verdict.)
        tries.append(_single_from(functools.partial(run_fn, at_bounds=False), req, ss, zr,
                                  np.asarray(plan.Bg), desc + " (friction released)"))
    finite = [t for t in tries if np.isfinite(t.cost)]
    best = min(finite, key=lambda t: (not t.converged, t.cost))
    return best._replace(iterations=sum(t.iterations for t in tries))


def guarded(run, *args) -> Run:
    """Run an optimiser; any failure inside the solve becomes `converged=False`."""
    try:
        return run(*args)
    except (RuntimeError, ValueError, FloatingPointError) as e:
        first = next((ln.strip() for ln in str(e).splitlines() if ln.strip()), type(e).__name__)
        return Run(np.asarray(args[1]), float("nan"), 0, False,
                   f"the fit failed: {_solver_words(first)}")


def _solver_words(message: str) -> str:
    """A solver's message in the fit's words: diffrax advises "Try increasing
    `max_steps`", an ODE step budget that the fit sets itself (`strategy.ode_budget`) and
    that no option of `fit` sets (its `max_steps` counts LM iterations)."""
    if "maximum number of solver steps" in message.lower():
        return ("the ODE solve ran out of its step budget: the parameters make the model far "
                "stiffer or faster than the record; choose start values nearer the truth")
    return message


def multistart(req, plan, shoot, z0, count, seed, label, until=None
                ) -> list[tuple[Run, str]]:
    """`count` optimisations: from `z0` (unless `label` names an escalation), then from
    perturbed points. Each run comes with its label, e.g. "multistart start 2 of 4".
    `until(runs)`: when given and true after a run, the rest are not started."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(count):
        zk = (z0 if k == 0 and not label
              else perturb(z0, shoot.names, shoot.log, rng, shoot.folded))
        name = (label + (f" start {k + 1} of {count}" if count > 1 else "")).strip()
        out.append((attempt(req, plan, shoot, z0, zk, f"fit {name}".strip()), name))
        if until is not None and until(out):
            break
    return out


def best_run(runs):
    """The run to report, with its label: the lowest-cost converged run; if none
    converged, the lowest-cost one (a run with no finite cost only if no other is left)."""
    ok = [(r, lab) for r, lab in runs if np.isfinite(r.cost)]
    return min(ok, key=lambda x: (not x[0].converged, x[0].cost)) if ok else runs[0]


def run_rms(run: Run, n: int) -> float:
    return math.sqrt(2 * run.cost / max(n, 1)) if np.isfinite(run.cost) else math.inf
