"""The plan of a fit, before any optimisation: start values from the data, the start
solve, and what it decides (refuse at once, the step budget, the flat directions held
fixed, single or multiple shooting). Each record is judged by itself: one with no motion
above its noise, or one the start values cannot follow, refuses the fit, named in the
message when there are several.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..model.outputs import SI_UNITS
from ..runtime.arrays import device_array
from ..simulation import linearize
from ..solve.adjoints import ForwardSensitivities
from . import channel_noise as ch
from .angle import motion_period
from .fit_options import Init, ShootingMode
from .outcome import FAILS_AT_START
from .physical import load_scale, ranges
from .problem import Problem, build_problem, linear_frequency, pick_solver
from .programs import jacobian_at
from .request import LOAD_NAMES, STATE_NAMES, FitRequest
from .stages import Plan, Shooting, Shot
from .start import half_window, noise_level, observed_period, regressor_start, smooth_derivatives
from .strategy import (
    MAX_ODE_STEPS,
    SMALL_ODE_BUDGET,
    absurd_frequency,
    absurd_start,
    aliased,
    n_segments,
    no_motion,
    ode_budget,
    refusal,
)
from .uncertainty import RANK_TOL

__all__ = ["make_plan", "plan_steps", "start_solve", "constant_channel", "CONSTANT_EPS",
           "shooting", "basis", "recoordinate", "recoordinate_basis", "single_problem",
           "record_spans"]


def _starts(req: FitRequest, periods) -> tuple[dict, list, list]:
    """Start values of the global names, each record's start state, and notes."""
    start, notes = dict(req.start), []
    if req.init is Init.REGRESSOR:
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


def _problem(req: FitRequest, start, states, nseg, budget, solver, linear: bool = False
             ) -> Problem:
    recs = [(d, lo, to, s[0], s[1]) for d, (lo, to), s in zip(req.records, req.loads, states)]
    periods = [motion_period(d.ts, a) for d, a in zip(req.records, req.angles)]
    omega = next((2 * math.pi / p for p in periods if p), None)
    # A load that starts at 0 takes its unit from the records (see `load_scale`).
    zero_load = any(n in LOAD_NAMES and start.get(n) == 0 for n in req.free)
    torque = (load_scale(_start_mech(req, start), req.records, req.angles, periods)
              if zero_load else None)
    return build_problem(req.scene.mech, recs, req.free, start, nseg, solver=solver,
                         rtol=float(req.scene.rtol), atol=float(req.scene.atol),
                         max_steps=budget, adjoint=ForwardSensitivities(), omega=omega,
                         angles=req.angles, sigmas=req.sigmas, per_record=req.per_record,
                         force=req.force, linear=linear, torque=torque)


def _start_mech(req: FitRequest, start: dict):
    """The scene's mechanism at the start values."""
    return req.scene.mech.replace(**{n: v for n, v in start.items()
                                     if n in req.scene.mech.as_dict()})


def single_problem(req: FitRequest, start, states, budget, solver) -> Problem:
    """The single-shooting problem of `req` at the start values `start` and record states
    `states` (the posterior samples this very model)."""
    return _problem(req, start, states, [1] * len(req.records), budget, solver)


def _start_solve(req, start, states, solver, periods):
    """The single-shooting problem at the smallest budget that solves the start, the
    start coordinates, and there the residuals, failures, steps per record (R,) and
    sensitivities. A record whose solve runs out of the small budget, already absurd for
    what it shows (see `absurd_start`), is not tried again at the large one. A generator
    (see [`plan_steps`][]): it yields each `(problem, z)` to solve and is sent
    `jacobian_at`'s host arrays there."""
    for budget in (SMALL_ODE_BUDGET, MAX_ODE_STEPS):
        ss = single_problem(req, start, states, budget, solver)
        z = _start_z(ss, start, states)
        r, failed, steps, J = yield ss, z
        absurd = any(absurd_start(int(n), sp, p, turns=_turns(a)) for n, sp, p, a in
                     zip(np.atleast_1d(steps), record_spans(req), periods, req.angles))
        if int(failed) == 0 or budget == MAX_ODE_STEPS or absurd:
            return ss, z, r, int(failed), np.atleast_1d(steps).astype(int), J


#: A channel whose spread (rms about its mean) is at most this many float64 epsilons of
#: its largest magnitude is constant up to rounding (as `validate.MIN_SPREAD_EPS`).
CONSTANT_EPS = 1024


def constant_channel(d) -> str | None:
    """A message when a channel of record `d` is constant up to float rounding, else None
    (the motion is judged on the angle the channels tell: a constant slide beside a
    moving angle passed, and the fit spent hundreds of iterations on it)."""
    for sensor, y in d.outputs():
        y = np.asarray(y, dtype=float)
        spread = float(np.std(y))
        if spread <= CONSTANT_EPS * np.finfo(np.float64).eps * float(np.max(np.abs(y))):
            return (f"channel {sensor.name} (column {sensor.column!r}) is constant "
                    f"({float(y.mean()):.6g} {SI_UNITS[sensor.name]} in all {y.size} "
                    "samples): it shows no motion; check the column and its unit, or leave "
                    "the channel out (`channels=`)")
    return None


def _turns(angle: np.ndarray) -> float:
    """Net turns of a record's crank (its angle as the channels tell it)."""
    return abs(float(angle[-1] - angle[0])) / (2 * math.pi)


def record_spans(req: FitRequest) -> list[float]:
    """Each record's length, s."""
    return [float(d.ts[-1] - d.ts[0]) for d in req.records]


def _start_z(ss: Problem, start, states) -> np.ndarray:
    """The start coordinates of `ss`: `start`'s values, each record's state `states`."""
    return ss.to_z([start[n] if n in start else _state(n, states, start) for n in ss.names])


def _state(name: str, states, start) -> float:
    base, _, idx = name.partition("[")
    if base not in STATE_NAMES:  # a per-record parameter starts where its name does
        return start[base]
    i = int(idx[:-1]) if idx else 0
    return states[i][STATE_NAMES.index(base)]


def _flat_basis(J0: np.ndarray) -> np.ndarray:
    """(p, q) basis of the directions to optimise, from the sensitivities at the start
    (N, p): exactly flat ones (the common scale) are held, so the point reported is the
    one on the ridge nearest to the start."""
    p = J0.shape[1]
    if not np.all(np.isfinite(J0)):
        return np.eye(p)
    _, s0, Vt0 = np.linalg.svd(J0, full_matrices=False)
    keep = s0 > RANK_TOL * s0[0]
    return np.eye(p) if np.all(keep) else Vt0[keep].T


def basis(Bg: np.ndarray, n_coords: int, on: np.ndarray | None = None) -> np.ndarray:
    """The global basis, with every segment state (after the p globals) free, or those
    where `on` (n_coords - p,) bool is (an inactive row's state is held)."""
    p, q = Bg.shape
    free = np.eye(n_coords - p)
    if on is not None:
        free = free[:, np.asarray(on, dtype=bool)]
    B = np.zeros((n_coords, q + free.shape[1]))
    B[:p, :q] = Bg
    B[p:, q:] = free
    return B


def make_plan(req: FitRequest) -> Plan:
    """The plan of `req`'s fit (see the module's docstring): [`plan_steps`][] with each
    start solve run here. That generator yields each start solve it needs, `(problem, z)`,
    is sent [`start_solve`][]'s arrays there, and returns the plan, so that many records'
    start solves can run side by side (`fleet.fit_many`)."""
    steps = plan_steps(req)
    try:
        ask = next(steps)
        while True:
            ask = steps.send(start_solve(*ask))
    except StopIteration as done:
        return done.value


def start_solve(ss: Problem, z: np.ndarray) -> tuple:
    """`jacobian_at(ss, z)` as host arrays: residuals, failures, steps per record,
    sensitivities."""
    return tuple(np.asarray(x) for x in jacobian_at(ss, device_array(z)))


def plan_steps(req: FitRequest):
    """[`make_plan`][] as a generator of its start solves (see [`make_plan`][])."""
    periods = [observed_period(d.ts, a) for d, a in zip(req.records, req.angles)]
    start, states, notes = _starts(req, periods)
    mech_start = _start_mech(req, start)
    # The start model linearised once under each record's slider force: the solver's
    # choice (the first record's) and the frequency test read it.
    lins = [linearize(mech_start, lo) for lo, _ in req.loads]
    solver = pick_solver(mech_start, req.loads[0][0], float(req.scene.rtol), req.scene.solver,
                         lin=lins[0])
    # Motion is judged on the angle the channels tell; the fit's residuals and their
    # noise level are in the first channel's unit.
    noises = [noise_level(d.ts, a) for d, a in zip(req.records, req.angles)]
    quiet = refusal(req.records, (no_motion(ang, n) or constant_channel(d) or aliased(ang)
                                  for d, ang, n in zip(req.records, req.angles, noises)))
    too_far = quiet or refusal(req.records, (absurd_frequency(linear_frequency(lin), p)
                                             for lin, p in zip(lins, periods)))
    if too_far:
        return _aborted(req, start, states, solver, too_far, notes)
    ss, z_start, r0, failed0, steps0, J0 = yield from _start_solve(req, start, states, solver,
                                                                   periods)
    plan = Plan(ss, ss, z_start, np.eye(ss.p), _values(ss, z_start), periods,
                tuple(notes), Shooting(Shot.SINGLE), start, states, solver,
                ranges=ranges(mech_start, req.records, req.angles, periods, start))
    spans = record_spans(req)
    # Each record judged by its own solve: one absurd record among good ones is as
    # absurd as alone (the steps of the slowest record against the periods of another
    # let a record of 10^4 turns through).
    abort = refusal(req.records, (absurd_start(int(n), sp, p, ss.max_steps, _turns(ang))
                                  for n, sp, p, ang in zip(steps0, spans, periods, req.angles)))
    if abort is None and failed0 > 0:
        abort = FAILS_AT_START
    if abort:
        return dataclasses.replace(plan, abort=abort)
    budget = ode_budget(int(np.max(steps0)))
    if budget != ss.max_steps:
        ss = single_problem(req, start, states, budget, solver)
    model = ch.model_angles(req, ss, r0)
    segs = [n_segments(sp, p, observed_period(d.ts, m), req.shooting, req.segments,
                       _turns(a), _turns(m), blind=not any(s.name == "phi"
                                                           for s, _ in d.outputs()))
            for d, a, sp, p, m in zip(req.records, req.angles, spans, periods, model)]
    # A crank that turns has the time of a turn for its cycle: escalation cuts its
    # record per two turns, as an oscillation's per two periods.
    # (`shoot` too: the problem optimised is the one at the fit's budget, not the start
    # solve's, whose budget may be the smaller.)
    plan = dataclasses.replace(
        plan, single=ss, shoot=ss, Bg=_flat_basis(J0),
        periods=[p if p else (sp / t if t >= 1 else None) for p, sp, t in
                 zip(periods, spans, (_turns(a) for a in req.angles))])
    if max(s for s, _ in segs) > 1:
        shoot, z0 = shooting(req, plan, [s for s, _ in segs])
        plan = dataclasses.replace(plan, shoot=shoot, z0=z0,
                                   shooting=Shooting(Shot.MULTIPLE, tuple(s for s, _ in segs)))
    if req.shooting is ShootingMode.AUTO and req.segments is None:
        plan = dataclasses.replace(
            plan, notes=(*plan.notes, f"{plan.shooting.label}: {segs[0][1]}"))
    return plan


def _aborted(req, start, states, solver, why: str, notes) -> Plan:
    """A plan that stops before any solve (see `absurd_frequency`)."""
    ss = single_problem(req, start, states, SMALL_ODE_BUDGET, solver)
    z = _start_z(ss, start, states)
    return Plan(ss, ss, z, np.eye(ss.p), _values(ss, z), [], tuple(notes),
                Shooting(Shot.NONE), start, states, solver, abort=why)


def _values(ss: Problem, z: np.ndarray) -> dict[str, float]:
    """The reported names' values at `ss`'s coordinates `z`."""
    return {n: float(v) for n, v in zip(ss.names, ss.host_values(z))}


def shooting(req: FitRequest, plan: Plan, nseg) -> tuple[Problem, np.ndarray]:
    """A multiple-shooting problem, in linear coordinates (see `build_problem`), and its
    start coordinates (from the single-shooting start `plan.z0`)."""
    ms = _problem(req, plan.start_g, plan.states, nseg, plan.single.max_steps, plan.solver,
                  linear=True)
    z = recoordinate(plan.single, ms, plan.z0[:plan.single.p])
    return ms, np.concatenate([z, ch.segment_states(ms, req)])


def recoordinate(src: Problem, dst: Problem, z: np.ndarray) -> np.ndarray:
    """The reported parameters at `src`'s coordinates `z` (its first `p` entries) in
    `dst`'s coordinates (p,). A value at 0 (a linear coordinate's bound) is taken a hair
    above it where `dst` has it in log space."""
    v = src.host_values(z[:src.p])
    v = np.where(dst.log, np.maximum(v, np.finfo(float).tiny), v)
    return dst.to_z(v)


def recoordinate_basis(src: Problem, dst: Problem, Bg: np.ndarray, z: np.ndarray
                       ) -> np.ndarray:
    """An orthonormal basis, in `dst`'s coordinates, of the directions `Bg` (p, q) spans in
    `src`'s at `z` (to first order: the map is diagonal), so that flat directions held in
    single shooting stay held in multiple shooting."""
    v = src.host_values(z[:src.p])
    dv = np.where(src.log, v, np.asarray(src.ref))  # d value / d z_src
    dz = np.where(dst.log, 1.0 / np.where(dst.log, v, 1.0), 1.0 / np.asarray(dst.ref))
    q, _ = np.linalg.qr((dv * dz)[:, None] * Bg)
    return q
