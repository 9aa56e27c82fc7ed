"""The fit's escalation: which tries a fit makes when the planned one stalls far from the
noise level (multiple shooting, a start from the motion, more starts around the best
point), and when it stops. Iterations and costs decide, never wall time.
"""

from __future__ import annotations

import math

import numpy as np

from ..runtime.arrays import device_array
from . import attempt as at
from .fit_options import Method, ShootingMode
from .fit_plan import recoordinate, record_spans, shooting
from .motion_start import motion_start
from .outcome import Run
from .problem import Problem
from .programs import jacobian_at
from .request import FitRequest
from .stages import FitState, Plan, Shooting
from .strategy import far_from_noise, noise_unit, record_segments

__all__ = ["optimize_fit", "ESCALATION_STARTS", "ESCALATION_ITERATIONS", "REPRODUCED",
           "PROGRESS"]

#: Extra starts tried when a fit stalls far from the noise level.
ESCALATION_STARTS = 4
#: The extra starts stop once they have taken as many LM iterations as the tries before
#: them, or this many if those took fewer: room for every extra start at the default
#: budget of 100 (a floor of 100 cut the starts that found a slide-only rotating record's
#: branch: experiments/rotating_rig.py).
ESCALATION_ITERATIONS = 100 * ESCALATION_STARTS
#: Two converged tries whose costs differ by less than this many noise-level units
#: (`sigma^2`: a chi-squared difference of 1) reached the same minimum.
REPRODUCED = 0.5
#: An escalation try that converges without lowering the best converged cost by more
#: than this many `sigma^2` ends the escalation (see `_no_progress`).
PROGRESS = 1.0


def optimize_fit(state: FitState) -> FitState:
    """The planned optimisation(s), escalated when they stall far from the noise level:
    multiple shooting (one segment per two observed periods), then a second start (the
    motion's, or the scene's when the first was the motion's), then more starts.

    Where the plan shoots multiply, the first attempt starts from whichever of the
    scene's values and the motion's start ([`motion_start`][]) costs less: a generic start
    far off crawled for hundreds of iterations through a slipped branch that the motion's
    start never enters (experiments/misfit_rig.py). A record with no observed period
    cannot slip a cycle: its stall is the model's answer, not escalated. Escalation ends
    at the first try near the noise level, once a minimum is reached from two starts
    (within [`REPRODUCED`][]), at a converged try that makes no [`PROGRESS`][], or once
    the extra starts have spent their iterations ([`ESCALATION_ITERATIONS`][]): never
    wall time, so the same fit makes the same tries on any machine.

    **Returns:** `state` with the best run, the iterations of every try, the notes and the
    shooting that won."""
    req, plan = state.req, state.plan
    escalate = (req.shooting is ShootingMode.AUTO and req.segments is None
                and req.method is Method.LM
                and any(p is not None for p in plan.periods))
    one = escalate and req.multistart == 1
    # (Solved only where it is used: it compiles the equation of motion's program.)
    early = one and plan.shoot is not plan.single
    zm = _motion_point(req, plan) if early else None
    moved_first = (zm is not None
                   and _start_cost(plan.shoot, zm) < _start_cost(plan.shoot, plan.z0))
    runs, notes = _first_tries(req, plan, zm if moved_first else None)
    first = at.best_run(runs)[0]
    tried, escalated = [], None

    def go_on():
        return not _settled(req, plan, runs, at.best_run(runs)[0])

    if escalate and plan.shoot is plan.single and go_on():
        nseg = [record_segments(sp, p) for sp, p in zip(record_spans(req), plan.periods)]
        ms, z0 = shooting(req, plan, nseg)
        escalated = Shooting("multiple", tuple(nseg))
        runs += at.multistart(req, plan, ms, z0, 1, req.seed, escalated.label)
        tried.append(escalated.label)
    if one and not moved_first and go_on():
        # (After a first start from the motion, the scene's values, whose cost was higher,
        # are no second opinion worth their iterations: they crawled 200 iterations through
        # a slipped branch on a slide-only record. The extra starts below are.)
        zm = zm if early else _motion_point(req, plan)
        if zm is not None:
            label = "a start from the motion"
            runs.append((at.attempt(req, plan, plan.shoot, plan.z0, zm, f"fit ({label})"),
                         label))
            tried.append(label)
    if one and go_on():
        tried.append(_hop(req, plan, runs))
    best, won = _conclude(req, plan, runs, first, tried, moved_first, notes, escalated)
    return state.but(best=best, iterations=sum(r.iterations for r, _ in runs),
                     notes=(*state.notes, *notes), shooting=won)


def _first_tries(req: FitRequest, plan: Plan, zm: np.ndarray | None):
    """The planned tries: one from the motion's start `zm` when given, else `multistart`
    from the plan's. **Returns:** `(runs, notes)`."""
    if zm is not None:
        runs = [(at.attempt(req, plan, plan.shoot, plan.z0, zm, "fit (from the motion)"), "")]
        return runs, ["the fit started from the motion (a start from the motion: the "
                      "parameters that enter the equation of motion linearly, solved from "
                      "the smoothed record), whose cost was below the scene's values'"]
    runs = at.multistart(req, plan, plan.shoot, plan.z0, req.multistart, req.seed, "")
    if req.multistart <= 1:
        return runs, []
    best = at.best_run(runs)[0]
    distinct = sum(r.cost > best.cost * (1 + 1e-3) + 1e-300 for r, _ in runs
                   if np.isfinite(r.cost))
    return runs, [f"multistart: {sum(r.converged for r, _ in runs)} of {req.multistart} "
                  f"starts converged; {distinct} ended at a higher cost than the best"]


def _hop(req: FitRequest, plan: Plan, runs: list) -> str:
    """Extra starts around the best point so far (basin hopping), appended to `runs`: a
    start that comes back to it confirms it, one that finds a lower minimum replaces it.
    They stop as the escalation does (see `optimize_fit`). **Returns:** what was tried,
    in words."""
    budget = max(ESCALATION_ITERATIONS, sum(r.iterations for r, _ in runs))

    def enough(done):
        return (_settled(req, plan, runs + done, done[-1][0])
                or sum(r.iterations for r, _ in done) >= budget)

    more = at.multistart(req, plan, plan.shoot, _in_shoot(plan, at.best_run(runs)[0].z),
                         ESCALATION_STARTS, req.seed + 1, "multistart", until=enough)
    runs += more
    cut_short = (len(more) < ESCALATION_STARTS and _stalled(more[-1][0], plan, req)
                 and not _reproduced(runs, _unit2(req, plan)))
    return (f"{len(more)} more start{'s' if len(more) > 1 else ''}"
            + (f" (of {ESCALATION_STARTS}: {budget} iterations spent)" if cut_short else ""))


def _conclude(req: FitRequest, plan: Plan, runs, first: Run, tried: list[str],
              moved_first: bool, notes: list[str], escalated: Shooting | None
              ) -> tuple[Run, Shooting]:
    """The run to report among `runs`, and the shooting that won (`escalated`: that of the
    escalation to multiple shooting, if tried); says in `notes` what the escalation tried
    and why."""
    shot = plan.shooting
    n = plan.single.n_residuals
    best, label = at.best_run(runs)
    unit = req.unit  # the residuals are in the first channel's unit
    if tried:
        won = "the first attempt" if best is first else label
        how = "stalled" if _stalled(first, plan, req) else "converged"
        why = "did not converge" if not first.converged else (
            f"{how} at rms {at.run_rms(first, n):.3g} {unit}, far above the record's noise "
            f"level ({req.noise:.3g} {unit})")
        notes.append(f"the {plan.shooting.label} fit {why}; tried {' and '.join(tried)}; the "
                     f"result is {won} (rms {at.run_rms(best, n):.3g} {unit}"
                     + (", the lowest-cost converged try)" if best.converged
                        else ", the lowest-cost try: none converged)"))
        if _reproduced(runs, _unit2(req, plan)):
            notes.append(f"the minimum at rms {at.run_rms(best, n):.3g} {unit} was reached from "
                         "more than one start: the model's best from here, not a local "
                         "minimum of one start; the misfit above the noise level is the "
                         "model's (see the residuals' whiteness)")
        if best is not first:
            shot = (escalated if escalated is not None and label == escalated.label
                    else shot.won_by(label))
    elif len(runs) > 1 and not best.converged:
        notes.append(f"none of the {len(runs)} starts converged; the result is the "
                     f"lowest-cost one ({label}, rms {at.run_rms(best, n):.3g} {unit})")
    if moved_first and best is first:
        shot = shot.won_by("a start from the motion")
    return best, shot


def _unit2(req: FitRequest, plan: Plan) -> float:
    """The noise-level unit of cost, `sigma^2`."""
    return noise_unit(req.noise) ** 2


def _settled(req: FitRequest, plan: Plan, runs, last: Run) -> bool:
    """Whether the search ends after `runs`: `last` converged near the noise level, the
    best minimum was reached twice, or the latest converged try made no progress."""
    unit2 = _unit2(req, plan)
    return (not _stalled(last, plan, req) or _reproduced(runs, unit2)
            or _no_progress(runs, unit2))


def _reproduced(runs, unit2: float) -> bool:
    """Whether the lowest-cost converged run's minimum was reached by another converged
    run too (costs within [`REPRODUCED`][] noise-level units `unit2`)."""
    ok = [r for r, _ in runs if r.converged and np.isfinite(r.cost)]
    if len(ok) < 2:
        return False
    low = min(r.cost for r in ok)
    return sum(r.cost - low <= REPRODUCED * unit2 for r in ok) >= 2


def _no_progress(runs, unit2: float) -> bool:
    """Whether the latest converged try failed to lower the best converged cost before
    it by [`PROGRESS`][] noise-level units `unit2`: the escalation stops there. Far above
    the noise (a model that cannot follow the record), a try that finds no lower minimum
    says the search from here is done; it does not wait for a level it cannot reach."""
    ok = [r.cost for r, _ in runs if r.converged and np.isfinite(r.cost)]
    return len(ok) >= 2 and min(ok[:-1]) - ok[-1] <= PROGRESS * unit2


def _start_cost(problem: Problem, z: np.ndarray) -> float:
    """The cost `0.5 |r|^2` of `problem` at `z` (inf where a solve fails), from the
    residuals-and-sensitivities program the LM compiles anyway."""
    r, failed, _, _ = jacobian_at(problem, device_array(z))
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


def _stalled(run: Run, plan: Plan, req: FitRequest) -> bool:
    """Not converged, or converged far from the noise level."""
    return not run.converged or far_from_noise(at.run_rms(run, plan.single.n_residuals),
                                               req.noise)
