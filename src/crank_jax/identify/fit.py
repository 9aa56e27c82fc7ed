"""Parameter identification: fit a scene's parameters to one or more crank-angle records.

`fit` reads as its steps, each in its own module: check the request
([`request`][]), take start values from the data ([`start`][]), build the least-squares
problem ([`problem`][]), plan the shooting and the step budget ([`strategy`][]), optimise
([`optimise`][]), escalate if the fit stalls far from the noise level, then the
uncertainty and identifiability at the estimate ([`uncertainty`][]) and the result
([`result`][]).

Which optimiser to use:

- `method="lm"` (default): Levenberg-Marquardt (MINPACK's, through scipy, on the host),
  with the residuals and the Jacobian from one compiled program: forward-mode
  sensitivities through the ODE solve (`jax.jacfwd`). Best for the
  usual problem: one or a few records, up to a dozen or two parameters. It converges in a
  handful of iterations and its Jacobian is needed for the uncertainty anyway.
- `method="optax"`: Adam, then L-BFGS, on the sum of squares with reverse-mode gradients
  (one backward solve, whatever the number of parameters). Use it for large problems (many
  records or many multiple-shooting segments, so many coordinates). It needs more
  iterations than LM.

Multiple shooting: each segment starts from its own state, and continuity at the shared
samples is a weighted residual; the result is then polished by single shooting (so the
estimate and its uncertainty are those of the ordinary least-squares problem).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from ..data import Data
from ..scene import Scene
from . import channels as ch
from .angle import motion_period
from .measurement import fitted_channels
from .optimise import Run, least_squares, minimise_optax
from .problem import Problem, build_problem, linear_frequency, pick_solver
from .profile import profile_likelihood
from .programs import Subspace, jacobian_at
from .request import STATE_NAMES, FitRequest, free_names, normalise
from .result import ConvergenceWarning, FitResult, IdentifiabilityWarning, Profile
from .start import half_window, regressor_start, smooth_derivatives
from .strategy import (
    AUTO_PERIODS,
    MAX_ODE_STEPS,
    SEGMENT_PERIODS,
    SMALL_ODE_BUDGET,
    absurd_frequency,
    absurd_start,
    far_from_noise,
    n_segments,
    ode_budget,
    perturb,
    record_segments,
)
from .uncertainty import RANK_TOL, assess, undefined

__all__ = ["fit", "FitResult", "Profile", "IdentifiabilityWarning", "ConvergenceWarning",
           "FREE_NAMES", "AUTO_PERIODS", "SEGMENT_PERIODS", "regressor_start"]

#: Names that can be free (the mechanism fields, load amplitudes and initial state).
FREE_NAMES: tuple[str, ...] = free_names()
#: Extra starts tried when a fit stalls far from the noise level.
ESCALATION_STARTS = 4


@dataclasses.dataclass
class _Plan:
    """What the fit works with, once the start solve has been looked at."""

    single: Problem  # single shooting, with the fit's step budget
    shoot: Problem  # the problem optimised (multiple shooting, or `single`)
    z0: np.ndarray  # start coordinates of `shoot`
    Bg: np.ndarray  # (p, q) basis of the global directions optimised (flat ones held)
    start: dict  # start value of every reported name
    noise: float  # the records' noise level, rad
    periods: list  # observed period of each record, s (or None)
    notes: list
    strategy: str
    start_g: dict  # start values of the global names
    states: list  # start state of each record
    solver: str
    abort: str | None = None


def _starts(req: FitRequest, periods) -> tuple[dict, list, list]:
    """Start values of the global names, each record's start state, and notes."""
    start, notes = dict(req.start), []
    if req.init == "regressor":
        # On the angle the channels tell: the regressor form is written in phi.
        reg, notes = regressor_start(req.scene.mech, ch.angle_records(req), req.free, periods)
        start.update(reg)
    states = []
    for d, a, per, fixed in zip(req.records, req.angles, periods, req.states):
        # The state at the first sample from a smoothed fit to the first samples: the
        # scene's state is at t = 0, and real records start anywhere.
        ps, dps, _ = smooth_derivatives(d.ts, a, half_window(d.ts, per), [0])
        states.append((float(ps[0]) if "phi0" in req.free else fixed[0],
                       float(dps[0]) if "dphi0" in req.free else fixed[1]))
    return start, states, notes


def _problem(req: FitRequest, start, states, nseg, budget, solver) -> Problem:
    recs = [(d, lo, to, s[0], s[1]) for d, (lo, to), s in zip(req.records, req.loads, states)]
    periods = [motion_period(d.ts, a) for d, a in zip(req.records, req.angles)]
    omega = next((2 * math.pi / p for p in periods if p), None)
    return build_problem(req.scene.mech, recs, req.free, start, nseg, solver=solver,
                         rtol=float(req.scene.rtol), atol=float(req.scene.atol),
                         max_steps=budget, adjoint="forward", omega=omega,
                         angles=req.angles, sigmas=req.sigmas, per_record=req.per_record)


def _start_solve(req, start, states, solver):
    """The single-shooting problem at the smallest budget that solves the start, the
    start coordinates, and there the residuals, failures, steps and sensitivities."""
    for budget in (SMALL_ODE_BUDGET, MAX_ODE_STEPS):
        ss = _problem(req, start, states, [1] * len(req.records), budget, solver)
        z = ss.to_z([start[n] if n in start else _state(n, states, start) for n in ss.names])
        r, failed, steps, J = (np.asarray(x) for x in jacobian_at(ss, jnp.asarray(z)))
        if int(failed) == 0 or budget == MAX_ODE_STEPS:
            return ss, z, r, int(failed), int(steps), J


def _state(name: str, states, start) -> float:
    base, _, idx = name.partition("[")
    if base not in STATE_NAMES:  # a per-record parameter starts where its name does
        return start[base]
    i = int(idx[:-1]) if idx else 0
    return states[i][STATE_NAMES.index(base)]


def _flat_basis(J0: np.ndarray) -> np.ndarray:
    """(p, q) basis of the directions to optimise, from the sensitivities at the start
    (N, p). Directions in which the residuals are exactly flat (the common scale) are held
    fixed: the optimiser would otherwise wander along them, and the reported point is the
    one on the ridge nearest to the start."""
    p = J0.shape[1]
    if not np.all(np.isfinite(J0)):
        return np.eye(p)
    _, s0, Vt0 = np.linalg.svd(J0, full_matrices=False)
    keep = s0 > RANK_TOL * s0[0]
    return np.eye(p) if np.all(keep) else Vt0[keep].T


def _basis(Bg: np.ndarray, n_coords: int) -> np.ndarray:
    """The global basis, with every segment state (after the p globals) free."""
    p, q = Bg.shape
    B = np.zeros((n_coords, q + n_coords - p))
    B[:p, :q] = Bg
    B[p:, q:] = np.eye(n_coords - p)
    return B


def _plan(req: FitRequest) -> _Plan:
    periods = [motion_period(d.ts, a) for d, a in zip(req.records, req.angles)]
    noise = req.sigmas[ch.first_channel(req)]
    start, states, notes = _starts(req, periods)
    mech_start = req.scene.mech.replace(**{n: v for n, v in start.items()
                                           if n in req.scene.mech.as_dict()})
    solver = pick_solver(mech_start, req.loads[0][0], float(req.scene.rtol), req.scene.solver)
    multi = len(req.records) > 1
    too_far = next((f"record {d.source}: {a}" if multi else a
                    for a, d in ((absurd_frequency(linear_frequency(mech_start, lo), p), d)
                                 for (lo, _), p, d in zip(req.loads, periods, req.records))
                    if a), None)
    if too_far:
        return _aborted(req, start, states, solver, too_far, notes)
    ss, z_start, r0, failed0, steps0, J0 = _start_solve(req, start, states, solver)
    full_start = {n: float(v) for n, v in zip(ss.names, np.asarray(ss.values(z_start)))}
    plan = _Plan(ss, ss, z_start, np.eye(ss.p), full_start, noise, periods, notes,
                 "single shooting", start, states, solver)
    spans = [float(d.ts[-1] - d.ts[0]) for d in req.records]
    if failed0 > 0:
        plan.abort = "the ODE solve fails at the start values; choose other start values"
        return plan
    plan.abort = next((a for a in (absurd_start(steps0, sp, p) for sp, p
                                   in zip(spans, periods)) if a), None)
    if plan.abort:
        return plan
    plan.Bg = _flat_basis(J0)
    budget = ode_budget(steps0)
    if budget != ss.max_steps:
        ss = plan.single = _problem(req, start, states, [1] * len(req.records), budget,
                                    solver)
    model = ch.model_angles(req, ss, r0)
    segs = [n_segments(sp, p, motion_period(d.ts, m), req.shooting, req.segments)
            for d, sp, p, m in zip(req.records, spans, periods, model)]
    if max(s for s, _ in segs) > 1:
        plan.shoot, plan.z0 = _shooting(req, plan, [s for s, _ in segs])
        plan.strategy = f"multiple shooting ({'+'.join(str(s) for s, _ in segs)} segments)"
    if req.shooting == "auto" and req.segments is None:
        plan.notes.append(f"{plan.strategy}: {segs[0][1]}")
    return plan


def _aborted(req, start, states, solver, why: str, notes) -> _Plan:
    """A plan that stops before any solve (see `absurd_frequency`)."""
    ss = _problem(req, start, states, [1] * len(req.records), SMALL_ODE_BUDGET, solver)
    z = ss.to_z([start[n] if n in start else _state(n, states, start) for n in ss.names])
    full = {n: float(v) for n, v in zip(ss.names, np.asarray(ss.values(z)))}
    return _Plan(ss, ss, z, np.eye(ss.p), full, float("nan"), [], notes, "none", start,
                 states, solver, abort=why)


def _shooting(req: FitRequest, plan: _Plan, nseg) -> tuple[Problem, np.ndarray]:
    """A multiple-shooting problem and its start coordinates."""
    ms = _problem(req, plan.start_g, plan.states, nseg, plan.single.max_steps, plan.solver)
    return ms, np.concatenate([plan.z0[:plan.single.p], ch.segment_states(ms, req)])


def _attempt(req: FitRequest, plan: _Plan, shoot: Problem, z0: np.ndarray, zk: np.ndarray,
             desc: str) -> Run:
    """One optimisation of `shoot` from `zk` (flat directions held at `z0`), then a
    single-shooting polish when `shoot` is multiple shooting."""
    ss = plan.single
    B = _basis(plan.Bg, z0.shape[0])
    problem = shoot if req.method == "lm" else dataclasses.replace(shoot, adjoint="reverse")
    run_fn = least_squares if req.method == "lm" else minimise_optax
    run = _guarded(run_fn, Subspace(problem, jnp.asarray(z0), jnp.asarray(B)),
                   B.T @ (zk - z0), req.max_steps, req.tol, desc, req.progress)
    run = run._replace(z=z0 + B @ run.z)
    if shoot is ss or not np.isfinite(run.cost):
        return run
    zp = run.z[:ss.p]
    pol = _guarded(least_squares, Subspace(ss, jnp.asarray(zp), jnp.asarray(plan.Bg)),
                   np.zeros(plan.Bg.shape[1]), req.max_steps, req.tol, desc + " (polish)",
                   req.progress)
    return Run(zp + plan.Bg @ pol.z, pol.cost, run.iterations + pol.iterations,
               run.converged and pol.converged,
               pol.message if not pol.converged else run.message)


def _guarded(run, *args) -> Run:
    """Run an optimiser; any failure inside the solve becomes `converged=False`."""
    try:
        return run(*args)
    except (RuntimeError, ValueError, FloatingPointError) as e:
        first = next((ln.strip() for ln in str(e).splitlines() if ln.strip()), type(e).__name__)
        return Run(np.asarray(args[1]), float("nan"), 0, False, f"the fit failed: {first}")


def _multistart(req, plan, shoot, z0, count, seed, label) -> list[tuple[Run, str]]:
    """`count` optimisations: from `z0` (unless `label` names an escalation), then from
    perturbed points. Each run comes with its label, e.g. "multistart start 2 of 4"."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(count):
        zk = z0 if k == 0 and not label else perturb(z0, shoot.names, shoot.log, rng)
        name = (label + (f" start {k + 1} of {count}" if count > 1 else "")).strip()
        out.append((_attempt(req, plan, shoot, z0, zk, f"fit {name}".strip()), name))
    return out


def _best(runs):
    ok = [(r, lab) for r, lab in runs if np.isfinite(r.cost)]
    return min(ok, key=lambda x: (not x[0].converged, x[0].cost)) if ok else runs[0]


def _rms(run: Run, n: int) -> float:
    return math.sqrt(2 * run.cost / max(n, 1)) if np.isfinite(run.cost) else math.inf


def _optimise(req: FitRequest, plan: _Plan) -> tuple[Run, int, list[str]]:
    """The planned optimisation(s), escalated when they stall far from the noise level:
    multiple shooting (one segment per two observed periods), then more starts.

    **Returns:** the best run, the total iterations, notes."""
    runs = _multistart(req, plan, plan.shoot, plan.z0, req.multistart, req.seed, "")
    notes = []
    if req.multistart > 1:
        best = _best(runs)[0]
        distinct = sum(r.cost > best.cost * (1 + 1e-3) + 1e-300 for r, _ in runs
                       if np.isfinite(r.cost))
        notes.append(f"multistart: {sum(r.converged for r, _ in runs)} of {req.multistart} "
                     f"starts converged; {distinct} ended at a higher cost than the best")
    n = plan.single.n_residuals
    first = _best(runs)[0]
    tried = []
    escalate = req.shooting == "auto" and req.segments is None and req.method == "lm"
    if escalate and plan.shoot is plan.single and _stalled(first, n, plan, req):
        nseg = [record_segments(float(d.ts[-1] - d.ts[0]), p)
                for d, p in zip(req.records, plan.periods)]
        ms, z0 = _shooting(req, plan, nseg)
        label = f"multiple shooting ({'+'.join(map(str, nseg))} segments)"
        runs += [(r, lab) for r, lab in _multistart(req, plan, ms, z0, 1, req.seed, label)]
        tried.append(label)
    if escalate and req.multistart == 1 and _stalled(_best(runs)[0], n, plan, req):
        runs += _multistart(req, plan, plan.shoot, plan.z0, ESCALATION_STARTS, req.seed + 1,
                            "multistart")
        tried.append(f"{ESCALATION_STARTS} more starts")
    best, label = _best(runs)
    if tried:
        won = "the first attempt" if best is first else label
        notes.append(f"the {plan.strategy} fit stalled at rms {_rms(first, n):.3g} rad, far "
                     f"above the record's noise level ({plan.noise:.3g} rad); tried "
                     f"{' and '.join(tried)}; the best (rms {_rms(best, n):.3g} rad) is "
                     f"{won}")
        if best is not first:
            plan.strategy = (label if label.startswith("multiple")
                             else f"{plan.strategy}, {label}")
    return best, sum(r.iterations for r, _ in runs), notes


def _stalled(run: Run, n: int, plan: _Plan, req: FitRequest) -> bool:
    return not run.converged or far_from_noise(_rms(run, n), plan.noise, ch.known_sigma(req))



def _result(req, plan, best: Run, iterations, notes, t_begin) -> FitResult:
    ss = plan.single
    z_hat = best.z[:ss.p] if np.all(np.isfinite(best.z)) else plan.z0[:ss.p]
    converged, message = best.converged, best.message
    if plan.abort:  # nothing was solved, and nothing more is
        r_hat, values = ss.no_residuals(), np.asarray(ss.values(z_hat))
        rms, unc, more, diag = float("nan"), undefined(ss.p, "did not converge"), [], None
    else:
        r_hat, values, rms, unc, more, diag = assess(ss, z_hat, converged, ch.known_sigma(req))
    if converged and not math.isfinite(rms):
        converged, message = False, "the ODE solve fails at the final estimate"
    notes = more + notes + plan.notes
    if not converged:
        notes.insert(0, f"fit did not converge: {message}; no standard errors are given")
    prof = None
    if req.profile is not None:
        j = ss.names.index(req.profile)
        c = unc.covariance_z[j, j]
        se_z = math.sqrt(max(c, 0.0)) if np.isfinite(c) else float("nan")
        prof = profile_likelihood(ss, z_hat, j, se_z, ss.n_residuals, req.max_steps, req.tol,
                                  req.progress)

    def show(i):
        return converged and bool(np.isfinite(unc.stderr[i]))

    names = ss.names
    return FitResult(
        names=names,
        values={nm: float(values[i]) for i, nm in enumerate(names)},
        start={nm: float(plan.start[nm]) for nm in names},
        stderr={nm: float(unc.stderr[i]) if show(i) else None for i, nm in enumerate(names)},
        ci95={nm: (float(unc.ci95[i, 0]), float(unc.ci95[i, 1])) if show(i) else None
              for i, nm in enumerate(names)},
        correlation=unc.correlation, condition_number=float(unc.condition_number),
        singular_values=unc.singular_values,
        identifiable=bool(unc.identifiable) if converged else None,
        unidentifiable_directions=list(unc.directions) if converged else [],
        rms_residual=rms, n_samples=int(ss.n_residuals), converged=bool(converged),
        iterations=int(iterations), seconds=time.perf_counter() - t_begin, warnings=notes,
        message=message, method=req.method,
        shooting=("multiple" + plan.strategy.split("multiple shooting", 1)[1].split(",")[0]
                  if plan.strategy.startswith("multiple") else "single"),
        mech=ss.unpack(jnp.asarray(z_hat))[0], data=list(req.records),
        fitted=ss.fitted(r_hat), profile=prof, strategy=plan.strategy, diagnostics=diag,
        channels=ch.channel_report(ss, r_hat, req.sigmas, converged),
        fitted_channels=fitted_channels(ss, r_hat))


def fit(
    scene: Scene | Sequence[Scene],
    data: Data | Sequence[Data],
    free: Sequence[str] = ("k", "c", "phi0", "dphi0"),
    *,
    init: str | dict[str, float] = "scene",
    method: str = "lm",
    shooting: str = "auto",
    segments: int | None = None,
    multistart: int = 1,
    seed: int = 0,
    max_steps: int | None = None,
    tol: float = 1e-8,
    sigma: float | None = None,
    profile: str | None = None,
    window: tuple[float | None, float | None] | None = None,
    progress: bool = True,
    warn: bool = True,
    per_record: Sequence[str] = (),
) -> FitResult:
    """Fit free parameters of a scene to crank-angle records by least squares.

    **Arguments:**

    - `scene`: the [`Scene`][] giving the fixed values, the start values and the loads; or
      one scene per record (they may differ only in loads and initial state).
    - `data`: a [`Data`][] record, or a sequence of them (a multi-experiment fit: the
      mechanism is shared, each record has its own initial state and loads). A record's
      own `load`/`torque` replace its scene's.
    - `free`: names from [`FREE_NAMES`][]: the mechanism fields, the load amplitudes `P0`,
      `P1`, `tau0`, `tau1` (the scene's constant or harmonic load) and `phi0`, `dphi0`
      (the state at each record's first sample). A field that cannot be negative and
      starts positive is fitted in log space; others (a signed offset, a friction that
      starts at 0) in linear coordinates.
    - `init`: `"scene"` (the scene's values), `"regressor"` (masses, inertias, k and c
      from the linear regressor form) or a dict of start values. Free `phi0`/`dphi0` always
      start from a local fit to the first samples.
    - `method`: `"lm"` or `"optax"` (see the module notes for which to use).
    - `shooting`: `"auto"` (judged from the record's zero crossings against the start
      model's; escalates to multiple shooting, then to more starts, when the fit stalls far
      above the record's noise level), `"single"` or `"multiple"`; `segments` fixes their
      number.
    - `multistart`: number of starts (the first is `init`; the others perturb the
      log-parameters by a factor `exp(N(0, 0.5^2))`); the lowest cost wins.
    - `seed`: seed of the multistart perturbations.
    - `max_steps`: iteration budget per start (default 100 for LM, 2000 for optax).
    - `tol`: relative and absolute tolerance of the optimiser's termination test.
    - `sigma`: the noise standard deviation (rad) if known; default: from the residuals.
    - `profile`: a reported name whose profile likelihood to compute.
    - `window`: `(t_start, t_end)`, s: fit only the samples in it (either end None: open),
      e.g. to trim a release transient.
    - `progress`: show progress bars on stderr. `warn`: emit Python warnings
      ([`IdentifiabilityWarning`][], [`ConvergenceWarning`][]) besides `result.warnings`.

    **Returns:** a [`FitResult`][]. A fit that fails or does not converge returns
    `converged=False` with a message (and finite values: the last good iterate or the
    start); it never raises for a numerical failure. Mistakes in the request (unknown
    names, too few samples, a start value outside a parameter's domain, a profile of a
    name that is not free) raise `ValueError` before any compute.
    """
    t_begin = time.perf_counter()
    req = normalise(scene, data, free, init=init, method=method, shooting=shooting,
                    segments=segments, multistart=multistart, seed=seed, max_steps=max_steps,
                    tol=tol, sigma=sigma, profile=profile, window=window, progress=progress,
                    warn=warn, per_record=per_record)
    req = ch.with_channels(req)
    plan = _plan(req)
    if plan.abort:
        best, iterations, notes = Run(plan.z0, float("nan"), 0, False, plan.abort), 0, []
    else:
        best, iterations, notes = _optimise(req, plan)
        req, best, iterations = ch.reweight(req, plan, best, iterations, notes, _attempt)
    res = _result(req, plan, best, iterations, notes, t_begin)
    if req.warn:
        if res.identifiable is False:
            warnings.warn("; ".join(res.unidentifiable_directions), IdentifiabilityWarning,
                          stacklevel=2)
        if not res.converged:
            warnings.warn(f"fit did not converge: {res.message}", ConvergenceWarning,
                          stacklevel=2)
    return res
