"""The crank angle as far as a record's channels tell it, for start values and planning.

The fit itself compares every channel with the model; but its start state, its scales and
its shooting plan are judged from the crank's motion, so a record without an angle
channel needs one estimated from what it has:

- `phi`: the calibration undone, `(data - offset) / scale`;
- `dphi`: integrated from the start angle;
- `x_s`: `x_s(phi)` inverted. Each slider position has two crank angles, one on each
  half-turn between the slider's ends. A crank that turns (the record spans most of the
  stroke) takes the half-turn its direction and the slider's motion imply, and the angle
  is unwrapped; near the dead centres, where the slider hardly moves with the crank and
  its noise makes a large angle error, the angle is bridged in time from either side; a
  crank that swings about an end takes the side that flips each time the
  slider passes that end (the start angle's side first). Which side is a guess that the
  dynamics and the start values then decide (DESIGN.md section 1);
- only `v_s` or `a_s`: nothing to invert (returns None; the caller simulates the start
  model instead).
"""

from __future__ import annotations

import math

import numpy as np

from ..model.coefficients import coefficients
from ..model.geometry import geometry_terms
from ..model.params import SliderCrank
from ..records.data import Data
from .start import noise_level, observed_period

__all__ = ["angle_estimate", "slide_angle", "motion_period", "ROTATING_STROKE"]

#: A slide record spanning more than this fraction of the full stroke is a turning crank.
ROTATING_STROKE = 0.8
_GRID = 4096


def angle_estimate(data: Data, mech: SliderCrank, direction: float = 1.0,
                   phi_start: float = 0.0) -> np.ndarray | None:
    """The crank angle (n,) at the record's samples, rad, or None when its channels do not
    tell it (only `v_s`/`a_s`). `direction`: the sign of the crank's rotation when it
    turns (+1: increasing phi); `phi_start`: the angle near the first sample, rad (which
    turn an unwrapped angle starts on, and which side a swing starts on)."""
    outs = {s.name: (s, y) for s, y in data.outputs()}
    if "phi" in outs:
        s, y = outs["phi"]
        return np.asarray(s.model(y), dtype=float)
    if "dphi" in outs:
        s, y = outs["dphi"]
        w = np.asarray(s.model(y), dtype=float)
        steps = 0.5 * (w[1:] + w[:-1]) * np.diff(data.ts)
        return phi_start + np.concatenate([[0.0], np.cumsum(steps)])
    if "x_s" in outs:
        s, y = outs["x_s"]
        return slide_angle(mech, data.ts, np.asarray(s.model(y), dtype=float), direction,
                           phi_start)
    return None


def _arcs(mech: SliderCrank):
    """The two half-turns between the slider's ends: (x ascending, phi) for the half-turn
    on which x falls as phi grows (a), and for the one on which it rises (b); the ends'
    positions and the top's angle; and x at `_GRID` angles over a turn."""
    p = coefficients(mech)  # formed once for the three grids
    grid = np.linspace(0.0, 2 * math.pi, _GRID, endpoint=False)
    xg = np.asarray(geometry_terms(p, grid).x_s, dtype=float)
    top, bot = grid[np.argmax(xg)], grid[np.argmin(xg)]
    down = np.linspace(0.0, (bot - top) % (2 * math.pi), _GRID) + top
    up = np.linspace(0.0, (top - bot) % (2 * math.pi), _GRID) + bot
    xa = np.asarray(geometry_terms(p, down).x_s, dtype=float)
    xb = np.asarray(geometry_terms(p, up).x_s, dtype=float)
    return (xa[::-1], down[::-1]), (xb, up), float(xg.min()), float(xg.max()), top, xg


def _smooth(x: np.ndarray, k: int) -> np.ndarray:
    if k <= 1 or x.shape[0] < 3 * k:
        return x
    pad = np.pad(x, (k, k), mode="edge")
    return np.convolve(pad, np.ones(2 * k + 1) / (2 * k + 1), mode="same")[k:-k]


def slide_angle(mech: SliderCrank, ts: np.ndarray, x: np.ndarray, direction: float = 1.0,
                phi_start: float = 0.0, noise: float | None = None) -> np.ndarray:
    """The crank angle (n,), rad, whose slider position is `x` (n,), m (see the module);
    `noise`, the positions' noise level, m (default: estimated from `x`), sets where a
    turning crank's angle is bridged across a dead centre."""
    (xa, pa), (xb, pb), lo, hi, top, xg = _arcs(mech)
    xc = np.clip(x, lo, hi)
    phi_a, phi_b = np.interp(xc, *(xa, pa)), np.interp(xc, *(xb, pb))
    xs = _smooth(x, max(1, x.shape[0] // 200))
    dx = np.gradient(xs, ts)
    lo_q, hi_q = np.quantile(x, [0.02, 0.98])
    if hi_q - lo_q > ROTATING_STROKE * (hi - lo):
        # x falls on half-turn a while phi grows: turning forwards, falling x means a.
        phi = np.where(dx * np.sign(direction or 1.0) < 0, phi_a, phi_b)
        noise = noise_level(ts, x) if noise is None else noise
        phi = _bridge(ts, np.unwrap(phi), _steep(xg, phi, noise))
        return phi + 2 * math.pi * round((phi_start - phi[0]) / (2 * math.pi))
    # A swing about one end of the stroke: the side flips each time x passes that end.
    near_top = abs(float(np.median(x)) - hi) < abs(float(np.median(x)) - lo)
    a_side = np.angle(np.exp(1j * (phi_a - top)))  # signed distance from the top, rad
    b_side = np.angle(np.exp(1j * (phi_b - top)))
    dist = np.minimum(np.abs(a_side), np.abs(b_side))
    ends = _passes(dx, want_max=near_top)
    side = np.cumsum(np.isin(np.arange(x.shape[0]), ends)) % 2
    start_side = 1.0 if np.angle(np.exp(1j * (phi_start - top))) >= 0 else -1.0
    sign = start_side * np.where(side == 0, 1.0, -1.0)
    if near_top:
        return top + sign * dist
    return top + math.pi - sign * (math.pi - dist)


#: A slider position's noise `s` makes an angle error of `s / |dx_s/dphi|`, unbounded at
#: the dead centres (dx_s/dphi = 0). Where that exceeds this (rad), the angle is bridged
#: in time instead (see `_bridge`); a noiseless record is inverted everywhere.
ANGLE_ERROR = 5e-3


def _steep(xg: np.ndarray, phi: np.ndarray, noise: float) -> np.ndarray:
    """Whether each angle (n,) lies where the slider moves fast enough with the crank for
    a position of noise level `noise` (m) to tell it within [`ANGLE_ERROR`][]; `xg`, the
    slider position at `_GRID` angles over a turn (`_arcs`)."""
    grid = np.linspace(0.0, 2 * math.pi, _GRID, endpoint=False)
    slope = np.gradient(xg, grid)
    at = np.interp(np.mod(phi, 2 * math.pi), grid, np.abs(slope), period=2 * math.pi)
    return at * ANGLE_ERROR > noise


#: Each side of a bridged run of samples contributes up to this many samples to its fit.
_BRIDGE_SIDE = 4


def _bridge(ts: np.ndarray, phi: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """`phi` (n,) with each run of samples not `ok` replaced by a quadratic in time fitted
    (least squares) to the nearest `ok` samples on either side: a turning crank crosses a
    dead centre in a small part of a turn, smoothly, and a quadratic follows its speeding
    up or slowing down there while averaging the neighbours' noise. At the record's ends,
    the straight line through the two nearest `ok` samples (a one-sided quadratic
    extrapolates their noise). Unchanged when fewer than 4 samples are `ok`."""
    good = np.flatnonzero(ok)
    if good.size < 4 or good.size == phi.shape[0]:
        return phi
    out = phi.copy()
    bad = np.flatnonzero(~ok)
    for run in np.split(bad, np.flatnonzero(np.diff(bad) > 1) + 1):
        before = good[good < run[0]][-_BRIDGE_SIDE:]
        after = good[good > run[-1]][:_BRIDGE_SIDE]
        if before.size == 0 or after.size == 0:  # an end
            near, degree = (after[:2] if before.size == 0 else before[-2:]), 1
        else:
            near, degree = np.concatenate([before, after]), 2
        t0 = ts[run[0]]
        out[run] = np.polyval(np.polyfit(ts[near] - t0, phi[near], degree), ts[run] - t0)
    return out


def _passes(dx: np.ndarray, want_max: bool) -> np.ndarray:
    """Indices where x has a local maximum (`want_max`) or minimum: where its slope
    changes sign."""
    s = np.sign(dx if want_max else -dx)
    return np.flatnonzero((s[:-1] > 0) & (s[1:] <= 0)) + 1


def motion_period(ts: np.ndarray, angle: np.ndarray) -> float | None:
    """The record's natural time scale, s: the mean time per revolution of a crank that
    turns at least one full revolution over the record (its angle, unwrapped, has no zero
    crossings), else the observed period of its oscillation (`observed_period`), or None.
    """
    turned = abs(float(angle[-1] - angle[0]))
    if turned >= 2 * math.pi:
        return 2 * math.pi * float(ts[-1] - ts[0]) / turned
    return observed_period(ts, angle)
