"""Pseudo-arclength continuation of the roots of `G(u) = 0`, `G: R^(n+1) -> R^n`.

The curve is followed by arclength `s`, not by its last coordinate (the parameter), so it
passes through folds, where the parameter turns back. Each step predicts along the unit
tangent `t` (the null vector of `dG/du`) and corrects with Newton's method on

    G(u) = 0,   t . (u - u_pred) = 0,

the hyperplane through the prediction orthogonal to the tangent. The step length adapts:
halved when Newton fails or the tangent turns by more than `MAX_TURN`, lengthened after
an easy step. A fold is where the tangent's parameter component changes sign.

The driver is a host loop (its length is not known in advance); each corrector is one
compiled program, passed in as `correct(u_pred, t) -> Point`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

__all__ = ["Point", "Curve", "continue_curve", "null_vector", "MAX_TURN"]

#: Largest angle (rad) between consecutive tangents before a step is retried shorter: a
#: sharper turn means the step jumped across a tight fold or onto another branch.
MAX_TURN = 0.35


class Point(NamedTuple):
    """A corrector's answer: `u` (n+1,), the tangent `t` (n+1,) at it (unoriented), `ok`,
    Newton's iteration count `steps`, and `extra`, whatever the caller records per point."""

    u: Any
    t: Any
    ok: Any
    steps: Any
    extra: Any


class Curve(NamedTuple):
    """The continued curve: `u` (m, n+1), oriented tangents `t` (m, n+1), `extra` (a
    list of m records), `folds` (indices i: a fold lies between points i and i+1),
    `stopped`, why the continuation ended, in words (in `u`'s units), and `reason`, the
    same as one of `"range"` (the parameter left `[lo, hi]`: the only complete end),
    `"max_points"` or `"corrector"` (Newton failed at the smallest step)."""

    u: np.ndarray
    t: np.ndarray
    extra: list
    folds: list[int]
    stopped: str
    reason: str


def null_vector(jac: np.ndarray) -> np.ndarray:
    """The unit null vector of an (n, n+1) Jacobian (the last right singular vector)."""
    _, _, vt = np.linalg.svd(np.asarray(jac))
    return vt[-1]


def continue_curve(correct: Callable[[np.ndarray, np.ndarray], Point], start: Point, *,
                   direction: float, lo: float, hi: float, ds: float, ds_max: float,
                   ds_min: float, max_points: int) -> Curve:
    """Follow the curve from `start` until its parameter (`u[-1]`) leaves `[lo, hi]`.

    **Arguments:** `correct`, the corrector; `start`, a converged point; `direction`, +1
    or -1: the parameter's initial direction; `ds`, `ds_max`, `ds_min`, the first,
    largest and smallest step (in `u`'s units); `max_points`, the most points to keep.
    """
    u = np.asarray(start.u, float)
    t = np.asarray(start.t, float)
    t = t * (np.sign(t[-1] * direction) or 1.0)
    us, ts, extras = [u], [t], [start.extra]
    stopped, reason = f"reached max_points = {max_points}", "max_points"
    while len(us) < max_points:
        if not lo <= u[-1] <= hi:
            stopped, reason = "left the parameter range", "range"
            break
        p = correct(u + ds * t, t)
        t_new = np.asarray(p.t, float)
        t_new = t_new * (np.sign(t_new @ t) or 1.0)
        turn = np.arccos(np.clip(t_new @ t, -1.0, 1.0))
        if not bool(p.ok) or not np.all(np.isfinite(np.asarray(p.u))) or turn > MAX_TURN:
            ds /= 2
            if ds < ds_min:
                stopped = (f"the corrector failed at parameter {u[-1]:.6g} with the smallest "
                           f"step {ds_min:.3g}")
                reason = "corrector"
                break
            continue
        u, t = np.asarray(p.u, float), t_new
        us.append(u)
        ts.append(t)
        extras.append(p.extra)
        if int(p.steps) <= 3 and turn < MAX_TURN / 3:
            ds = min(ds * 1.5, ds_max)
    if reason == "max_points" and not lo <= u[-1] <= hi:  # its last point left the range
        stopped, reason = "left the parameter range", "range"
    us_a, ts_a = np.array(us), np.array(ts)
    folds = [i for i in range(len(us) - 1) if ts_a[i, -1] * ts_a[i + 1, -1] < 0]
    return Curve(us_a, ts_a, extras, folds, stopped, reason)
