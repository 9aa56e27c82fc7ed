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

__all__ = ["profile_likelihood", "hessian_disagreement", "CHI2_95"]

#: 95% quantile of chi-squared with 1 degree of freedom.
CHI2_95 = 3.841458820694124


def profile_likelihood(problem: Problem, z_hat, j: int, se_z: float, n: int, max_steps: int,
                       tol: float, progress: bool) -> Profile:
    """Profile likelihood of coordinate `j` on a grid of +-4.5 standard errors (or +-ln 2 /
    +-50% of `ref` if none), warm-started outwards from the estimate `z_hat` (p,). (4.5:
    past twice the Hessian's 95% half-width, so a profile 2x wider than it shows as one,
    see [`hessian_disagreement`][].)

    **Returns:** a [`Profile`][] with `n ln(RSS / RSS_min)` per grid point.
    """
    half = 4.5 * se_z if math.isfinite(se_z) and se_z > 0 else (
        math.log(2) if problem.log[j] else 0.5)
    z_hat = np.array(z_hat, dtype=float)
    fold = problem.folded[j]
    if fold:
        # A parameter >= 0 fitted as ref |z|: its profile stops at its bound, 0.
        z_hat[j] = abs(z_hat[j])
        grid = np.linspace(max(-half, -z_hat[j]), half, 9)
    else:
        grid = np.linspace(-half, half, 9)
    rss_min = 2 * evaluate(problem, z_hat)[0]
    rss = np.full(grid.shape, np.nan)
    centre = int(np.argmin(np.abs(grid)))
    zr_hat = np.delete(z_hat, j)
    with progress_bar(len(grid), f"profile {problem.names[j]}", progress) as bar:
        for direction in (range(centre, len(grid)), range(centre - 1, -1, -1)):
            zr = zr_hat.copy()
            for k in direction:
                pinned = Pinned(problem, jnp.asarray(z_hat[j] + grid[k]), j)
                run = least_squares(pinned, zr, max_steps, tol, "", False)
                if np.isfinite(run.cost):
                    rss[k] = 2 * run.cost
                    zr = run.z  # warm start the next grid point
                bar.update(1)
    rss_min = min(rss_min, float(np.nanmin(rss))) if np.any(np.isfinite(rss)) else rss_min
    dev = n * np.log(rss / rss_min)
    zs = z_hat[j] + grid
    values = np.exp(zs) if problem.log[j] else np.abs(zs) * float(problem.ref[j])
    lo, hi = _crossings(values, dev, centre)
    if fold and lo is None and values[0] == 0.0 and np.all(np.isfinite(dev[:centre + 1])):
        lo = 0.0  # the deviance stays below the threshold down to the bound
    return Profile(problem.names[j], values, dev, (lo, hi))


def _crossings(values, dev, centre) -> tuple[float | None, float | None]:
    def cross(rng):
        prev = centre
        for k in rng:
            if not np.isfinite(dev[k]):
                return None
            if dev[k] > CHI2_95:
                # Linear in sqrt(deviance): exact where the cost is quadratic.
                d0, d1 = math.sqrt(max(dev[prev], 0.0)), math.sqrt(dev[k])
                f = (math.sqrt(CHI2_95) - d0) / (d1 - d0) if d1 != d0 else 0.0
                return float(values[prev] + f * (values[k] - values[prev]))
            prev = k
        return None

    return cross(range(centre - 1, -1, -1)), cross(range(centre + 1, len(values)))


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
