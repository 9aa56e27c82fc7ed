"""Profile likelihood of one parameter: every other free parameter re-fitted on a grid."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ..runtime.progress import progress_bar
from .fit_result import Profile
from .optimize import evaluate, least_squares
from .problem import Problem
from .programs import Pinned
from .verdict import CHI2_95

__all__ = ["profile_likelihood", "hessian_disagreement", "CHI2_95"]

#: Grid points on each side of the estimate before the walk outwards.
_GRID_SIDE = 4
#: Largest number of re-fits on one side (the grid's and the walk's).
_MAX_SIDE = 14


def profile_likelihood(problem: Problem, z_hat, j: int, se_z: float, n: int, max_steps: int,
                       tol: float, progress: bool) -> Profile:
    """Profile likelihood of coordinate `j`, warm-started outwards from the estimate
    `z_hat` (p,) on each side: a grid of 4 steps to 4.5 standard errors `se_z` (past twice
    the Hessian's 95% half-width, see [`hessian_disagreement`][]; without one, a first step
    of 1% of the parameter's own magnitude), then doubling steps until the deviance passes
    [`CHI2_95`][], the parameter has moved by a decade, or one that cannot be negative
    reaches 0. The crossing is refined by one re-fit where the deviance interpolates to
    the threshold (as `sqrt(RSS / RSS_min - 1)`, linear in the offset for a quadratic
    cost). **Returns:** a [`Profile`][] with `n ln(RSS / RSS_min)` per point traced.
    """
    z_hat = np.array(z_hat, dtype=float)
    fold = bool(problem.folded[j])
    if fold:
        z_hat[j] = abs(z_hat[j])  # a parameter >= 0 fitted as ref |z|: its bound is z = 0
    ref = float(problem.ref[j])
    # z units per unit of the parameter's own magnitude (1 in log coordinates).
    per = 1.0 if problem.log[j] else max(abs(z_hat[j]), 1.0)
    hessian = math.isfinite(se_z) and se_z > 0
    step, grid = (4.5 * se_z / _GRID_SIDE, _GRID_SIDE) if hessian else (0.01 * per, 1)
    wide = math.log(10.0) * per
    rss_min = 2 * evaluate(problem, z_hat)[0]
    points = {0.0: rss_min}
    with progress_bar(2 * _GRID_SIDE, f"profile {problem.names[j]}", progress) as bar:
        for sign in (1.0, -1.0):
            limit = z_hat[j] if fold and sign < 0 else math.inf
            if limit > 0:  # (an estimate at its bound 0 has nothing below it)
                _walk(problem, z_hat, j, sign, step, grid, min(wide, limit), limit, rss_min,
                      n, max_steps, tol, points, bar)
    ts = np.array(sorted(points))
    rss = np.array([points[t] for t in ts])
    rss_min = min(rss_min, float(np.nanmin(rss)))
    dev = n * np.log(rss / rss_min)

    def value(t):  # the parameter at offset t: its sign kept where it has one
        z = z_hat[j] + t
        return np.exp(z) if problem.log[j] else np.abs(z) * ref if fold else z * ref

    values = value(ts)
    centre = int(np.flatnonzero(ts == 0.0)[0])
    lo, hi = (None if c is None else float(value(c))
              for c in _crossings(ts, dev, centre, n))
    if fold and lo is None and values[0] == 0.0 and np.all(np.isfinite(dev[:centre + 1])):
        lo = 0.0  # the deviance stays below the threshold down to the bound
    return Profile(problem.names[j], values, dev, (lo, hi))


def _walk(problem, z_hat, j, sign, step, grid, wide, bound, rss_min, n, max_steps, tol,
          points, bar) -> None:
    """One side of the profile: re-fits at `sign` times the offsets `step`, 2 `step`, ...
    (`grid` of them), then doubling while the deviance stays below the threshold
    and the offset below `wide`; never past `bound` (a parameter's 0). The first crossing
    is refined by one re-fit. Adds each point's `|r|^2` (NaN where the re-fit failed) to
    `points` (offset -> `|r|^2`)."""
    zr = np.delete(z_hat, j)
    below, crossed, t = (0.0, 0.0, zr), False, 0.0
    for k in range(_MAX_SIDE):
        if k >= grid and (crossed or below[0] >= min(wide, bound)):
            return
        t = min(step * (k + 1) if k < grid else 2.0 * t, bound)
        run, d = _refit(problem, z_hat, j, sign * t, zr, rss_min, n, max_steps, tol, points)
        bar.update(1)
        if not math.isfinite(d):
            return  # a failed re-fit: nothing beyond it is traced on this side
        zr = run.z  # warm start the next point
        if d <= CHI2_95 and not crossed:
            below = (t, d, zr)
        elif not crossed:
            crossed = True
            # One re-fit where the deviance, interpolated between the bracket's ends,
            # meets the threshold: exact for a quadratic cost, and the interval's end.
            _refit(problem, z_hat, j, sign * _root(below[0], below[1], t, d, n), below[2],
                   rss_min, n, max_steps, tol, points)
        if t >= bound:
            return


def _refit(problem, z_hat, j, t, zr, rss_min, n, max_steps, tol, points):
    """The re-fit with coordinate `j` pinned at `z_hat[j] + t`, from `zr`; its `|r|^2` goes
    into `points[t]`. **Returns:** `(run, deviance)` (deviance inf where it failed)."""
    run = least_squares(Pinned(problem, jnp.asarray(z_hat[j] + t), j), zr, max_steps, tol,
                        "", False)
    ok = np.isfinite(run.cost)
    points[float(t)] = 2 * run.cost if ok else np.nan
    return run, (n * math.log(2 * run.cost / rss_min) if ok else math.inf)


def _q(d: float, n: int) -> float:
    """`sqrt(RSS / RSS_min - 1)` of a deviance `d = n ln(RSS / RSS_min)`: linear in the
    offset where the cost is quadratic, however far out (`sqrt(d)` is not: the log
    flattens it)."""
    return math.sqrt(math.expm1(max(d, 0.0) / n))


def _root(t0, d0, t1, d1, n: int) -> float:
    """Where the deviance, with `_q` linear between (t0, d0) and (t1, d1), meets the
    threshold: exact for a quadratic cost."""
    q0, q1 = _q(d0, n), _q(d1, n)
    if q1 == q0:
        return t1
    return t0 + (_q(CHI2_95, n) - q0) / (q1 - q0) * (t1 - t0)


def _crossings(ts, dev, centre, n: int) -> tuple[float | None, float | None]:
    """The offsets below and above `ts[centre]` where the deviance first passes the
    threshold (None: not within the points traced, or past a failed re-fit)."""
    def cross(rng):
        prev = centre
        for k in rng:
            if not np.isfinite(dev[k]):
                return None
            if dev[k] > CHI2_95:
                return float(_root(ts[prev], dev[prev], ts[k], dev[k], n))
            prev = k
        return None

    return cross(range(centre - 1, -1, -1)), cross(range(centre + 1, len(ts)))


def hessian_disagreement(prof: Profile, value: float, ci_hessian, factor: float = 2.0
                         ) -> str | None:
    """The note for a profile whose 95% interval and the Hessian's (`ci_hessian`, `(lo,
    hi)` or None) differ by more than `factor` on a side, measured from the estimate
    `value`; None when they agree (or either is missing). A side where the profile stays
    below the threshold to the end of its grid (4.5 standard errors) is over 2.3x the
    Hessian's: it counts as wider."""
    if ci_hessian is None or not all(map(math.isfinite, ci_hessian)):
        return None
    grid_end = (prof.values[0], prof.values[-1])
    out = []
    for side, (p_end, h_end) in enumerate(zip(prof.ci95, ci_hessian)):
        h = abs(h_end - value)
        if h == 0:
            continue
        w = abs((grid_end[side] if p_end is None else p_end) - value)
        if p_end is None and grid_end[side] == 0.0:
            continue  # the profile reaches the bound 0: a one-sided interval, no width
        if w > factor * h or w < h / factor:
            out.append(f"{'lower' if side == 0 else 'upper'} end "
                       f"{'beyond ' if p_end is None else ''}{value + (w if side else -w):.4g}"
                       f" against {h_end:.4g}")
    if not out:
        return None
    return (f"the profile likelihood of {prof.name} and its Hessian interval disagree by "
            f"more than {factor:g}x ({'; '.join(out)}): the reported interval is the "
            "Hessian's; the profile's (`profile` in fit.json) is the better one")
