"""A fit's channels during and after the fit: the start model's crank angle, their
residuals' weights by the levels found (the refits that find them are
[`reweight`][crank_jax.identify.reweight]'s), and the per-channel report.

Residuals are in the first channel's unit: a channel's are weighted by the first
channel's noise level over its own, so every channel counts by its noise. Unknown levels
are estimated from the record first (when the request is made, see
[`channels`][crank_jax.identify.channels]), then from the fit's own residuals,
and the fit is repeated from its estimate while they move by more than
[`REWEIGHT_TOLERANCE`][] (iteratively reweighted least squares: at its fixed point each
channel's weight is its residuals' own level, the maximum-likelihood weighting).
"""

from __future__ import annotations

import math

import equinox as eqx
import numpy as np

from ..records.data import Data
from ..runtime.arrays import device_array
from ..stats.diagnostics import residual_diagnostics
from .angle import angle_estimate, motion_period
from .channels import direction
from .measurement import channel_weights, fitted_channels
from .problem import Problem
from .programs import residuals_at
from .request import FitRequest
from .start import half_window, smooth_derivatives
from .uncertainty import channel_rows

__all__ = ["model_angles", "reweighted", "new_levels", "channel_report", "residual_levels",
           "angle_records", "segment_states", "REWEIGHT_TOLERANCE"]

#: Refit while a channel's estimated noise level moves by more than this factor.
REWEIGHT_TOLERANCE = 1.25


def model_angles(req: FitRequest, ss: Problem, r) -> list[np.ndarray]:
    """The start model's crank angle at each record's samples, estimated from its channel
    readings as the data's is (`angle.py`), so the two compare like with like."""
    out = []
    for d, a, fitted, st in zip(req.records, req.angles, fitted_channels(ss, r), req.states):
        model = Data(d.ts, None, d.load, d.torque, source=d.source, channels=fitted,
                     sensors=tuple(s for s, _ in d.outputs()))
        est = angle_estimate(model, req.scene.mech, direction(st), float(a[0]))
        out.append(a if est is None or not np.all(np.isfinite(est)) else est)
    return out


def residual_levels(ss: Problem, r: np.ndarray) -> dict[str, float]:
    """Each channel's rms residual (SI) in the single-shooting residuals `r` of `ss`."""
    r = np.asarray(r)
    return {name: float(np.sqrt(np.mean((r[rows] / w) ** 2)))
            for name, (rows, _, w) in channel_rows(ss).items()}


def reweighted(problem: Problem, sigmas: dict[str, float]) -> Problem:
    """`problem` with each channel weighted by the first channel's level over its own
    (`sigmas`, SI); the weights are array leaves, so nothing recompiles."""
    first = sigmas[problem.exps[0].channels[0]]
    new = tuple(device_array(channel_weights(e.channels, sigmas, first), float)
                for e in problem.exps)
    return eqx.tree_at(lambda p: tuple(e.weight for e in p.exps), problem, new)


def new_levels(req: FitRequest, ss: Problem, z: np.ndarray) -> dict[str, float] | None:
    """The channels' noise levels from the residuals at `z` (the unknown ones only; degrees
    of freedom shared out by sample count), or None when none moves by more than
    [`REWEIGHT_TOLERANCE`][] (or the solve fails)."""
    unknown = req.estimated
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
        period = motion_period(d.ts, a)
        ps, dps, _ = smooth_derivatives(d.ts, a, half_window(d.ts, period), first)
        for p_, dp in zip(ps, dps):
            out += [p_ / float(e.ref_phi), dp / float(e.ref_dphi)]
    return np.asarray(out, dtype=float)
