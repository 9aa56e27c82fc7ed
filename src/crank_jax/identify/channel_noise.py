"""A fit's channels: the crank angle they tell, their noise levels, the reweighting of
their residuals by the levels found, and the per-channel report.

Residuals are in the first channel's unit: a channel's are weighted by the first
channel's noise level over its own, so every channel counts by its noise. Unknown levels
are estimated from the record first (`noise_level`), then from the fit's own residuals,
and the fit is repeated from its estimate while they move by more than
[`REWEIGHT_TOLERANCE`][] (iteratively reweighted least squares: at its fixed point each
channel's weight is its residuals' own level, the maximum-likelihood weighting).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import numpy as np

from ..records.data import Data
from ..runtime.arrays import device_array
from .angle import angle_estimate, motion_period
from .diagnostics import residual_diagnostics
from .measurement import fitted_channels
from .problem import Problem
from .programs import residuals_at
from .request import FitRequest
from .start import half_window, noise_level, smooth_derivatives
from .uncertainty import channel_rows

__all__ = ["channel_angles", "channel_sigmas", "model_angles", "known_sigma", "first_channel",
           "reweighted", "reweight", "unknown_levels", "new_levels", "channel_report",
           "residual_levels", "with_channels", "first_unit", "angle_records", "segment_states",
           "REWEIGHT_TOLERANCE", "REWEIGHT_ROUNDS"]

#: Refit while a channel's estimated noise level moves by more than this factor.
REWEIGHT_TOLERANCE = 1.25
#: At most this many refits.
REWEIGHT_ROUNDS = 3


def model_angles(req: FitRequest, ss: Problem, r) -> list[np.ndarray]:
    """The start model's crank angle at each record's samples, estimated from its channel
    readings as the data's is (`angle.py`), so the two compare like with like."""
    out = []
    for d, a, fitted, st in zip(req.records, req.angles, fitted_channels(ss, r), req.states):
        model = Data(d.ts, None, d.load, d.torque, source=d.source, channels=fitted,
                     sensors=tuple(s for s, _ in d.outputs()))
        est = angle_estimate(model, req.scene.mech, _direction(st), float(a[0]))
        out.append(a if est is None or not np.all(np.isfinite(est)) else est)
    return out


def first_unit(req: FitRequest) -> str:
    """The SI unit of the first channel, the unit of the fit's residuals."""
    from ..model.outputs import SI_UNITS

    return SI_UNITS[first_channel(req)]


def with_channels(req: FitRequest) -> FitRequest:
    """`req` with each record's crank angle (`channel_angles`) and each channel's noise
    level (`channel_sigmas`)."""
    req = dataclasses.replace(req, angles=channel_angles(req))
    return dataclasses.replace(req, sigmas=channel_sigmas(req))


def _direction(state) -> float:
    return -1.0 if state[1] < 0 else 1.0


def channel_angles(req: FitRequest) -> tuple[np.ndarray, ...]:
    """Each record's crank angle as its channels tell it (`angle.py`); for a record with
    only slider speed or acceleration, the scene's motion simulated over it."""
    out = []
    for d, st, (load, torque) in zip(req.records, req.states, req.loads):
        est = angle_estimate(d, req.scene.mech, _direction(st), st[0])
        if est is None:
            ts = d.ts if d.ts[0] == 0.0 else np.concatenate([[0.0], d.ts])
            traj = req.scene.simulate(ts, load=load, torque=torque, throw=False)
            est = np.asarray(traj.phi)[-d.n:]
        out.append(np.asarray(est, dtype=float))
    return tuple(out)


#: A channel's noise level is at least this fraction of its data's spread (a noiseless
#: synthetic channel would otherwise get an infinite weight).
_MIN_RELATIVE_NOISE = 1e-9


def channel_sigmas(req: FitRequest) -> dict[str, float]:
    """Each channel's noise level, SI: given (`sigma`: a dict, or a number for the first
    channel) or estimated from the record alone (`noise_level`, the largest over the
    records)."""
    given = dict(req.sigma) if isinstance(req.sigma, dict) else {}
    if req.sigma is not None and not isinstance(req.sigma, dict):
        given[first_channel(req)] = float(req.sigma)
    out: dict[str, float] = {}
    for d in req.records:
        for s, y in d.outputs():
            level = max(noise_level(d.ts, y), _MIN_RELATIVE_NOISE * float(np.std(y)),
                        1e-300)
            out[s.name] = max(out.get(s.name, 0.0), level)
    out.update(given)
    return out




def known_sigma(req: FitRequest) -> float | None:
    """The noise level of the weighted residuals (the first channel's unit) when every
    channel's is given, else None (estimated from the residuals)."""
    names = {s.name for d in req.records for s, _ in d.outputs()}
    if isinstance(req.sigma, dict):
        return req.sigmas[first_channel(req)] if names <= set(req.sigma) else None
    return float(req.sigma) if req.sigma is not None and len(names) == 1 else None


def first_channel(req: FitRequest) -> str:
    return req.records[0].outputs()[0][0].name


def residual_levels(ss: Problem, r: np.ndarray) -> dict[str, float]:
    """Each channel's rms residual (SI) in the single-shooting residuals `r` of `ss`."""
    r = np.asarray(r)
    return {name: float(np.sqrt(np.mean((r[rows] / w) ** 2)))
            for name, (rows, _, w) in channel_rows(ss).items()}


def reweighted(problem: Problem, sigmas: dict[str, float]) -> Problem:
    """`problem` with each channel weighted by the first channel's level over its own
    (`sigmas`, SI); the weights are array leaves, so nothing recompiles."""
    first = problem.exps[0].channels[0]
    new = tuple(device_array([sigmas[first] / sigmas[n] for n in e.channels], float)
                for e in problem.exps)
    return eqx.tree_at(lambda p: tuple(e.weight for e in p.exps), problem, new)


def unknown_levels(req: FitRequest) -> list[str]:
    """The channels whose noise level the fit estimates (not given)."""
    names = list(dict.fromkeys(s.name for d in req.records for s, _ in d.outputs()))
    given = set(req.sigma) if isinstance(req.sigma, dict) else (
        {first_channel(req)} if req.sigma is not None else set())
    return [n for n in names if n not in given]


def new_levels(req: FitRequest, ss: Problem, z: np.ndarray) -> dict[str, float] | None:
    """The channels' noise levels from the residuals at `z` (the unknown ones only; degrees
    of freedom shared out by sample count), or None when none moves by more than
    [`REWEIGHT_TOLERANCE`][] (or the solve fails)."""
    unknown = unknown_levels(req)
    if len(req.sigmas) < 2 or not unknown:
        return None
    r, failed, _ = (np.asarray(x) for x in residuals_at(ss, device_array(z)))
    if int(failed) > 0 or not np.all(np.isfinite(r)):
        return None
    dof = math.sqrt(ss.n_residuals / max(ss.n_residuals - ss.p, 1))
    found = {n: max(v * dof, 1e-300) for n, v in residual_levels(ss, r).items()
             if n in unknown}
    moved = any(max(found[n] / req.sigmas[n], req.sigmas[n] / found[n]) > REWEIGHT_TOLERANCE
                for n in found)
    return {**req.sigmas, **found} if moved else None


def channel_report(ss: Problem, r: np.ndarray, sigmas: dict[str, float], converged: bool
                   ) -> dict[str, dict]:
    """Per channel: `rms` (SI), `sigma` (the level its residuals were weighted by),
    `n_samples`, `ljung_box_p` (None unless converged with finite residuals) and `unit`."""
    from ..model.outputs import SI_UNITS

    r = np.asarray(r)
    out = {}
    for name, (rows, lengths, w) in channel_rows(ss).items():
        e = r[rows] / w
        ok = bool(np.all(np.isfinite(e)))
        p = None
        if converged and ok and min(lengths) > 5:
            p = float(residual_diagnostics(e, lengths=lengths).ljung_box_p)
        out[name] = {"rms": float(np.sqrt(np.mean(e**2))) if ok else float("nan"),
                     "sigma": float(sigmas[name]), "n_samples": int(rows.shape[0]),
                     "ljung_box_p": p, "unit": SI_UNITS[name]}
    return out


def reweight(req: FitRequest, plan, best, iterations: int, notes: list, attempt):
    """Refit by single shooting from the estimate `best` (a `Run`) while the channels'
    noise levels, from the residuals, move (see the module); `attempt(req, plan, problem,
    z0, zk, label)` is the fit's one optimisation, and `plan` takes the last weights.
    **Returns:** `(req, best, iterations)`."""
    converged_before = best.converged
    for _ in range(REWEIGHT_ROUNDS):
        if not (np.isfinite(best.cost) and np.all(np.isfinite(best.z))):
            break
        z = best.z[:plan.single.p]
        levels = new_levels(req, plan.single, z)
        if levels is None:
            break
        req = dataclasses.replace(req, sigmas=levels)
        plan.single = reweighted(plan.single, levels)
        plan.noise = levels[first_channel(req)]
        run = attempt(req, plan, plan.single, z, z, "fit (channels reweighted)")
        iterations += run.iterations
        if np.isfinite(run.cost):
            best = run
    if best.converged and not converged_before:
        _superseded(notes)
    if best.converged and np.all(np.isfinite(best.z)):
        req = _settle(req, plan, best, notes)
    if len(req.sigmas) > 1:
        notes.append("channel noise levels: " + ", ".join(
            f"{n} {v:.3g}" for n, v in req.sigmas.items()) + " (SI; "
            + ("given" if not unknown_levels(req) else "estimated from the residuals")
            + "); each channel's residuals are weighted by them")
    return req, best, iterations


def _settle(req: FitRequest, plan, best, notes: list) -> FitRequest:
    """A converged fit's channels weighted, for its uncertainty and report, by the levels
    of its own final residuals where the refits stopped before those settled: the level a
    channel reports is then its residuals' (a stale level 35x its residuals' made k's
    standard error 35x too wide). **Returns:** `req` with those levels; `plan` takes them."""
    levels = new_levels(req, plan.single, best.z[:plan.single.p])
    if levels is None:
        return req
    moved = [f"{n} {req.sigmas[n]:.3g} -> {levels[n]:.3g}" for n in levels
             if levels[n] != req.sigmas[n]]
    notes.append(f"the channels' noise levels had not settled after {REWEIGHT_ROUNDS} refits "
                 f"({', '.join(moved)}, SI): the uncertainty weights each channel by its "
                 "final residuals' level")
    plan.single = reweighted(plan.single, levels)
    plan.noise = levels[first_channel(req)]
    return dataclasses.replace(req, sigmas=levels)


def _superseded(notes: list) -> None:
    """Qualify, in place, the notes saying that no try converged, once a refit with the
    channels reweighted did: one run never says both "converged" and "none converged"."""
    for i, note in enumerate(notes):
        if "none converged" in note or note.startswith("none of the"):
            notes[i] = (f"{note}; with the channels then reweighted by their residuals' "
                        "levels, the refit from that try converged: the result is that refit")


def angle_records(req: FitRequest) -> list[tuple[Data, object, object]]:
    """`(record, load, torque)` with each record's data replaced by the angle its
    channels tell (for the regressor start, which is written in phi)."""
    return [(Data(d.ts, a, source=d.source), lo, to)
            for d, a, (lo, to) in zip(req.records, req.angles, req.loads)]


def segment_states(problem: Problem, req: FitRequest) -> np.ndarray:
    """Start coordinates of the multiple-shooting segment states of `problem`, from the
    smoothed angle the channels tell (`req.angles`)."""
    out = []
    for e, d, a in zip(problem.exps, req.records, req.angles):
        first = np.asarray(e.seg.first)[1:]
        if first.size == 0:
            continue
        ps, dps, _ = smooth_derivatives(d.ts, a, half_window(d.ts, motion_period(
            d.ts, a)), first)
        for p_, dp in zip(ps, dps):
            out += [p_ / float(e.ref_phi), dp / float(e.ref_dphi)]
    return np.asarray(out, dtype=float)
