"""Parameter identification: fit a scene's parameters to one or more crank-angle records.

`fit` reads as its steps, each in its own module: check the request
([`request`][]), take start values from the data ([`start`][]), build the least-squares
problem ([`problem`][]), plan the shooting and the step budget ([`plan`][],
[`strategy`][]), optimise
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
import functools
import math
import time
import warnings
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from ..data import Data
from ..scene import Scene
from . import channels as ch
from .measurement import fitted_channels
from .motion_start import motion_start
from .optimise import Run, least_squares, minimise_optax, termination
from .plan import Plan, basis, make_plan, recoordinate, recoordinate_basis, shooting
from .problem import Problem
from .profile import hessian_disagreement, profile_likelihood
from .programs import Subspace, jacobian_at
from .request import FitRequest, free_names, normalise
from .result import (
    ConvergenceWarning,
    FitResult,
    IdentifiabilityWarning,
    Profile,
    with_wrapped_angles,
)
from .start import regressor_start
from .strategy import (
    AUTO_PERIODS,
    SEGMENT_PERIODS,
    far_from_noise,
    noise_unit,
    perturb,
    record_segments,
    stall_rms,
)
from .uncertainty import assess, undefined

__all__ = ["fit", "FitResult", "Profile", "IdentifiabilityWarning", "ConvergenceWarning",
           "FREE_NAMES", "AUTO_PERIODS", "SEGMENT_PERIODS", "regressor_start"]

#: Names that can be free (the mechanism fields, load amplitudes and initial state).
FREE_NAMES: tuple[str, ...] = free_names()
#: Extra starts tried when a fit stalls far from the noise level.
ESCALATION_STARTS = 4
#: The extra starts stop once they have taken as many LM iterations as the tries before
#: them, or this many if those took fewer (see `_optimise`): room for every extra start
#: at the default budget of 100. Iterations, not seconds: a fit's outcome and its
#: iteration count do not depend on the machine's load. (A floor of 100 cut the starts
#: that found a slide-only rotating record's branch: experiments/rotating_rig.py.)
ESCALATION_ITERATIONS = 100 * ESCALATION_STARTS
#: Two converged tries whose costs differ by less than this many noise-level units
#: (`sigma^2`: a chi-squared difference of 1) reached the same minimum.
REPRODUCED = 0.5


def _attempt(req: FitRequest, plan: Plan, shoot: Problem, z0: np.ndarray, zk: np.ndarray,
             desc: str) -> Run:
    """One optimisation of `shoot` from `zk` (flat directions held at `z0`), then a
    single-shooting polish when `shoot` is multiple shooting."""
    ss = plan.single
    # Multiple shooting has its own coordinates (linear, see `build_problem`): the flat
    # directions held fixed, and the estimate handed to the polish, are mapped across.
    Bg = plan.Bg if shoot is ss else recoordinate_basis(ss, shoot, plan.Bg,
                                                        recoordinate(shoot, ss, z0))
    B = basis(Bg, z0.shape[0])
    problem = shoot if req.method == "lm" else dataclasses.replace(shoot, adjoint="reverse")
    # LM's tests are judged in the data's units (the residuals' noise level), and its
    # stall counts as convergence only near that level.
    sigma = ch.known_sigma(req)
    run_fn = (functools.partial(least_squares, stall_rms=stall_rms(plan.noise, sigma),
                                noise=noise_unit(plan.noise, sigma))
              if req.method == "lm" else minimise_optax)
    run = _guarded(run_fn, Subspace(problem, jnp.asarray(z0), jnp.asarray(B)),
                   B.T @ (zk - z0), req.max_steps, req.tol, desc, req.progress)
    run = run._replace(z=z0 + B @ run.z)
    if shoot is ss:
        return run
    zp = recoordinate(shoot, ss, run.z)
    if not np.isfinite(run.cost):
        return run._replace(z=zp)
    pol = _guarded(run_fn if req.method == "lm" else least_squares,
                   Subspace(ss, jnp.asarray(zp), jnp.asarray(plan.Bg)),
                   np.zeros(plan.Bg.shape[1]), req.max_steps, req.tol, desc + " (polish)",
                   req.progress)
    # The estimate is the polish's, on the single-shooting cost: whether it converged is
    # the polish's verdict (multiple shooting only brought it near; its own stall on the
    # continuity defects says nothing about the point reported).
    return Run(zp + plan.Bg @ pol.z, pol.cost, run.iterations + pol.iterations,
               pol.converged, pol.message, pol.termination)


def _guarded(run, *args) -> Run:
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


def _multistart(req, plan, shoot, z0, count, seed, label, until=None
                ) -> list[tuple[Run, str]]:
    """`count` optimisations: from `z0` (unless `label` names an escalation), then from
    perturbed points. Each run comes with its label, e.g. "multistart start 2 of 4".
    `until(runs)`: when given and true after a run, the rest are not started."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(count):
        zk = z0 if k == 0 and not label else perturb(z0, shoot.names, shoot.log, rng)
        name = (label + (f" start {k + 1} of {count}" if count > 1 else "")).strip()
        out.append((_attempt(req, plan, shoot, z0, zk, f"fit {name}".strip()), name))
        if until is not None and until(out):
            break
    return out


def _best(runs):
    """The run to report, with its label: the lowest-cost converged run; if none
    converged, the lowest-cost one (a run with no finite cost only if no other is left)."""
    ok = [(r, lab) for r, lab in runs if np.isfinite(r.cost)]
    return min(ok, key=lambda x: (not x[0].converged, x[0].cost)) if ok else runs[0]


def _rms(run: Run, n: int) -> float:
    return math.sqrt(2 * run.cost / max(n, 1)) if np.isfinite(run.cost) else math.inf


def _optimise(req: FitRequest, plan: Plan) -> tuple[Run, int, list[str]]:
    """The planned optimisation(s), escalated when they stall far from the noise level:
    multiple shooting (one segment per two observed periods), then a second start (the
    motion's, or the scene's when the first was the motion's), then more starts.

    Where the plan shoots multiply (the start's predicted drift is large), the first
    attempt starts from whichever of the scene's values and the motion's start
    ([`motion_start`][]) has the lower cost: a generic start far off (a drive level 30%
    low) crawled for hundreds of iterations through a slipped branch that the motion's
    start never enters (experiments/misfit_rig.py).

    Escalation is for what it can mend: a phase slip over a record's periods. A record
    with no observed period (a transient, a creep, a step) cannot slip a cycle, so its
    stall is the model's answer, reported at once. Escalation ends at the first try that
    reaches the noise level; or once a converged minimum has been reached from two
    different starts (within [`REPRODUCED`][] noise-level units of cost: the model's best
    from here, on a record it cannot fully explain); or once the extra starts have taken
    as many LM iterations as the tries before them (at least
    [`ESCALATION_ITERATIONS`][]). Iterations and costs, never wall time, decide, so the
    same fit does the same tries, and reports the same result, on any machine.

    **Returns:** the best run, the total iterations, notes."""
    n = plan.single.n_residuals
    escalate = (req.shooting == "auto" and req.segments is None and req.method == "lm"
                and any(p is not None for p in plan.periods))
    # (Solved only where it is used: it compiles the equation of motion's program.)
    early = escalate and req.multistart == 1 and plan.shoot is not plan.single
    zm = _motion_point(req, plan) if early else None
    moved_first = (zm is not None
                   and _start_cost(plan.shoot, zm) < _start_cost(plan.shoot, plan.z0))
    notes = []
    if moved_first:
        runs = [(_attempt(req, plan, plan.shoot, plan.z0, zm, "fit (from the motion)"), "")]
        notes.append("the fit started from the motion (a start from the motion: the "
                      "parameters that enter the equation of motion linearly, solved from "
                      "the smoothed record), whose cost was below the scene's values'")
    else:
        runs = _multistart(req, plan, plan.shoot, plan.z0, req.multistart, req.seed, "")
    if req.multistart > 1:
        best = _best(runs)[0]
        distinct = sum(r.cost > best.cost * (1 + 1e-3) + 1e-300 for r, _ in runs
                       if np.isfinite(r.cost))
        notes.append(f"multistart: {sum(r.converged for r, _ in runs)} of {req.multistart} "
                     f"starts converged; {distinct} ended at a higher cost than the best")
    first = _best(runs)[0]
    tried = []
    unit2 = noise_unit(plan.noise, ch.known_sigma(req)) ** 2

    def go_on():
        best = _best(runs)[0]
        return _stalled(best, n, plan, req) and not _reproduced(runs, unit2)

    if escalate and plan.shoot is plan.single and go_on():
        nseg = [record_segments(float(d.ts[-1] - d.ts[0]), p)
                for d, p in zip(req.records, plan.periods)]
        ms, z0 = shooting(req, plan, nseg)
        label = f"multiple shooting ({'+'.join(map(str, nseg))} segments)"
        runs += [(r, lab) for r, lab in _multistart(req, plan, ms, z0, 1, req.seed, label)]
        tried.append(label)
    if escalate and req.multistart == 1 and not moved_first and go_on():
        # (After a first start from the motion, the scene's values, whose cost was higher,
        # are no second opinion worth their iterations: they crawled 200 iterations through
        # a slipped branch on a slide-only record. The extra starts below are.)
        if not early:
            zm = _motion_point(req, plan)
        if zm is not None:
            runs.append(_from_point(req, plan, zm, "a start from the motion"))
            tried.append(runs[-1][1])
    if escalate and req.multistart == 1 and go_on():
        budget = max(ESCALATION_ITERATIONS, sum(r.iterations for r, _ in runs))

        def enough(done):
            every = runs + done
            return (not _stalled(done[-1][0], n, plan, req) or _reproduced(every, unit2)
                    or sum(r.iterations for r, _ in done) >= budget)

        # Around the best point so far (basin hopping): a start that comes back to it
        # confirms it, one that finds a lower minimum replaces it.
        more = _multistart(req, plan, plan.shoot, _in_shoot(plan, _best(runs)[0].z),
                           ESCALATION_STARTS, req.seed + 1, "multistart", until=enough)
        runs += more
        tried.append(f"{len(more)} more start{'s' if len(more) > 1 else ''}"
                     + (f" (of {ESCALATION_STARTS}: {budget} iterations spent)"
                        if len(more) < ESCALATION_STARTS and _stalled(more[-1][0], n, plan,
                                                                      req)
                        and not _reproduced(runs, unit2) else ""))
    best, label = _best(runs)
    unit = ch.first_unit(req)  # the residuals are in the first channel's unit
    if tried:
        won = "the first attempt" if best is first else label
        why = "did not converge" if not first.converged else (
            f"stalled at rms {_rms(first, n):.3g} {unit}, far above the record's noise "
            f"level ({plan.noise:.3g} {unit})" if _stalled(first, n, plan, req) else
            f"converged at rms {_rms(first, n):.3g} {unit}, far above the record's noise "
            f"level ({plan.noise:.3g} {unit})")
        notes.append(f"the {plan.strategy} fit {why}; tried {' and '.join(tried)}; the "
                     f"result is {won} (rms {_rms(best, n):.3g} {unit}"
                     + (", the lowest-cost converged try)" if best.converged
                        else ", the lowest-cost try: none converged)"))
        if _reproduced(runs, unit2):
            notes.append(f"the minimum at rms {_rms(best, n):.3g} {unit} was reached from "
                         "more than one start: the model's best from here, not a local "
                         "minimum of one start; the misfit above the noise level is the "
                         "model's (see the residuals' whiteness)")
        if best is not first:
            plan.strategy = (label if label.startswith("multiple")
                             else f"{plan.strategy}, {label}")
    elif len(runs) > 1 and not best.converged:
        notes.append(f"none of the {len(runs)} starts converged; the result is the "
                     f"lowest-cost one ({label}, rms {_rms(best, n):.3g} {unit})")
    if moved_first and best is first:
        plan.strategy = f"{plan.strategy}, a start from the motion"
    return best, sum(r.iterations for r, _ in runs), notes


def _reproduced(runs, unit2: float) -> bool:
    """Whether the lowest-cost converged run's minimum was reached by another converged
    run too (costs within [`REPRODUCED`][] noise-level units `unit2`)."""
    ok = [r for r, _ in runs if r.converged and np.isfinite(r.cost)]
    if len(ok) < 2:
        return False
    low = min(r.cost for r in ok)
    return sum(r.cost - low <= REPRODUCED * unit2 for r in ok) >= 2


def _start_cost(problem: Problem, z: np.ndarray) -> float:
    """The cost `0.5 |r|^2` of `problem` at `z` (inf where a solve fails), from the
    residuals-and-sensitivities program the LM compiles anyway."""
    r, failed, _, _ = jacobian_at(problem, jnp.asarray(z))
    r = np.asarray(r)
    return 0.5 * float(r @ r) if int(failed) == 0 and np.all(np.isfinite(r)) else math.inf


def _motion_point(req: FitRequest, plan: Plan) -> np.ndarray | None:
    """The start values the motion gives (`motion_start`), in `plan.shoot`'s coordinates
    (the records' states and segment states as planned), or None when it gives none."""
    ss, shoot = plan.single, plan.shoot
    z = plan.z0[:ss.p] if shoot is ss else recoordinate(shoot, ss, plan.z0)
    try:
        zs = motion_start(ss, z, req.records, req.angles, plan.periods)
    except (ValueError, RuntimeError, FloatingPointError, np.linalg.LinAlgError):
        # A start the motion cannot give (a user force that fails off its record's path,
        # say) is no start: the random restarts follow, as before.
        zs = None
    if zs is None:
        return None
    return zs if shoot is ss else np.concatenate([recoordinate(ss, shoot, zs),
                                                  plan.z0[shoot.p:]])


def _in_shoot(plan: Plan, z: np.ndarray) -> np.ndarray:
    """A run's estimate `z` (single-shooting coordinates first) in `plan.shoot`'s
    coordinates, its segment states as planned; `plan.z0` where `z` is not finite."""
    ss, shoot = plan.single, plan.shoot
    if not np.all(np.isfinite(z)):
        return plan.z0
    if shoot is ss:
        return np.asarray(z[:ss.p], dtype=float)
    return np.concatenate([recoordinate(ss, shoot, z), plan.z0[shoot.p:]])


def _from_point(req: FitRequest, plan: Plan, zk: np.ndarray, label: str
                ) -> tuple[Run, str]:
    """One optimisation of `plan.shoot` from `zk`, labelled `label`."""
    return _attempt(req, plan, plan.shoot, plan.z0, zk, f"fit ({label})"), label


def _stalled(run: Run, n: int, plan: Plan, req: FitRequest) -> bool:
    return not run.converged or far_from_noise(_rms(run, n), plan.noise, ch.known_sigma(req))


def _result(req, plan, best: Run, iterations, notes, t_begin) -> FitResult:
    ss = plan.single
    # (`plan.z0` may be multiple shooting's coordinates; the start values are not.)
    z_hat = (best.z[:ss.p] if np.all(np.isfinite(best.z))
             else ss.to_z([plan.start[n] for n in ss.names]))
    converged, message = best.converged, best.message
    if plan.abort:  # nothing was solved, and nothing more is
        r_hat, values = ss.no_residuals(), np.asarray(ss.values(z_hat))
        rms, unc, more, diag = float("nan"), undefined(ss.p, "did not converge"), [], None
    else:
        r_hat, values, rms, unc, more, diag = assess(ss, z_hat, converged, ch.known_sigma(req))
    term = best.termination
    if converged and not math.isfinite(rms):
        converged, message = False, "the ODE solve fails at the final estimate"
        term = None
    if plan.abort:
        term = termination("refused", plan.abort)
    elif term is None:  # the optax method, or a failure outside LM's loop
        term = termination("converged" if converged else "failed", message)
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
        if converged and np.all(np.isfinite(unc.ci95[j])):
            note = hessian_disagreement(prof, float(values[j]), tuple(unc.ci95[j]))
            notes += [note] if note else []

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
        fitted_channels=fitted_channels(ss, r_hat), termination=term)


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
    force=None,
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
      starts positive is fitted in log space; the friction terms `T_c`, `c_s`, `F_s` and
      any field that cannot be negative and starts at 0 as `ref |z|` (always valid; a
      true 0 gets the interval `[0, v + 1.96 se]`); the others (a signed offset, the
      loads and states) in linear coordinates.
    - `init`: `"scene"` (the scene's values), `"regressor"` (masses, inertias, k and c
      from the linear regressor form) or a dict of start values. Free `phi0`/`dphi0` always
      start from a local fit to the first samples.
    - `method`: `"lm"` or `"optax"` (see the module notes for which to use).
    - `shooting`: `"auto"` (judged from the record's zero crossings against the start
      model's; escalates to multiple shooting, then to more starts, when the fit stalls far
      above the record's noise level), `"single"` or `"multiple"`; `segments` fixes their
      number.
    - `multistart`: number of starts (the first is `init`; the others perturb the
      log-parameters by a factor `exp(N(0, 0.5^2))`); the lowest-cost converged start
      wins (if none converged, the lowest-cost one, and the warnings say so).
    - `seed`: seed of the multistart perturbations.
    - `max_steps`: iteration budget per start, 1 to `request.MAX_ITERATIONS` (default
      100 for LM, 2000 for optax).
    - `tol`: relative and absolute tolerance of the optimiser's termination test.
    - `sigma`: the noise standard deviation (rad) if known, within `request.SIGMA_RANGE`;
      default: from the residuals.
    - `profile`: a reported name whose profile likelihood to compute.
    - `window`: `(t_start, t_end)`, s: fit only the samples in it (either end None: open),
      e.g. to trim a release transient.
    - `progress`: show progress bars on stderr. `warn`: emit Python warnings
      ([`IdentifiabilityWarning`][], [`ConvergenceWarning`][]) besides `result.warnings`.
    - `per_record`: free names that take a separate value in each record (reported as
      `name[i]`); the others are shared.
    - `force`: a user's force term, as `simulate` takes it (an `eqx.Module` callable
      `f(t, phi, dphi) -> N*m`); its float fields can be freed as `force.<field>` (or
      `force.<field>[i]` for an array's elements).

    Records may carry any sensor channels (`phi`, `dphi`, `x_s`, `v_s`, `a_s`, see
    [`Data`][]): each is compared with the model's reading `scale h + offset` and
    weighted by its noise level (`sigma` a dict, channel -> SI level; a number is the
    first channel's; unknown levels are estimated from the record, then from the
    residuals). Offsets can be freed as `<channel>_offset`.

    **Returns:** a [`FitResult`][]. A fit that fails or does not converge returns
    `converged=False` with a message (and finite values: the last good iterate or the
    start); it never raises for a numerical failure. A record with no motion above its
    noise, one that moves more than pi between samples, or one the start values cannot
    follow is refused before any optimisation, with `converged=False` and a message
    naming it. Mistakes in the request (unknown names, too few samples, a start value
    outside a parameter's domain, a profile of a name that is not free, an option out
    of its range) raise `ValueError` before any compute.
    """
    t_begin = time.perf_counter()
    req = normalise(scene, data, free, init=init, method=method, shooting=shooting,
                    segments=segments, multistart=multistart, seed=seed, max_steps=max_steps,
                    tol=tol, sigma=sigma, profile=profile, window=window, progress=progress,
                    warn=warn, per_record=per_record, force=force)
    req = ch.with_channels(req)
    plan = make_plan(req)
    if plan.abort:
        best, iterations, notes = Run(plan.z0, float("nan"), 0, False, plan.abort), 0, []
    else:
        best, iterations, notes = _optimise(req, plan)
        req, best, iterations = ch.reweight(req, plan, best, iterations, notes, _attempt)
    res = with_wrapped_angles(_result(req, plan, best, iterations, notes, t_begin))
    if req.warn:
        if res.identifiable is False:
            warnings.warn("; ".join(res.unidentifiable_directions), IdentifiabilityWarning,
                          stacklevel=2)
        if not res.converged:
            warnings.warn(f"fit did not converge: {res.message}", ConvergenceWarning,
                          stacklevel=2)
    return res
