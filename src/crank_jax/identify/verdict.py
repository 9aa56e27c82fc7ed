"""Identifiability verdicts checked against the profile likelihood.

The sensitivities flag a unit direction `u` of z as weakly determined when its standard
error `sigma / |J u|` is large (`uncertainty.analyze`): a quadratic guess, in coordinates
whose scale can be arbitrary, so only a candidate. The verdict is the likelihood's: the
profile along `u` (every other direction re-fitted) is traced outwards on each side until
its deviance `n ln(RSS(t) / RSS_min)` passes the 95% threshold of chi-squared(1) or the
offset reaches a wide range: **a decade** of the parameter `u` moves most, in its own
scale, **or a bound** 0 of a parameter that cannot be negative (then the interval's end
is that bound, `[0, hi]`, not an open end).

A direction is **not determined** only when a side stays below the threshold over the
whole range (a re-fit that stops before converging still bounds the profile from above:
below the threshold it counts, above it leaves the profile untraced). Otherwise it is
determined, and a Hessian half-width `1.96 se` more than 2x off the profile's is said in
a note. A profile that cannot be traced leaves the candidate flagged and says so.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from ..runtime.arrays import device_array
from .coordinates import own_scale

__all__ = ["DirectionProfile", "Checked", "profile_direction", "check", "wide_offset",
           "bound_offsets", "CHI2_95", "Z95", "DISAGREE"]

#: 95% quantile of chi-squared with 1 degree of freedom.
CHI2_95 = 3.841458820694124
#: Two-sided 95% quantile of the standard normal distribution.
Z95 = 1.959963984540054
#: A profile half-width more than this factor away from the Hessian's is said in a note.
DISAGREE = 2.0
_MAX_POINTS = 6  # re-fits per side


class DirectionProfile(NamedTuple):
    """The profile likelihood along a unit direction `u` of z.

    `open`: a side stayed below the threshold over the wide range (not determined).
    `traced`: every re-fit converged (False: nothing can be said). `lo`, `hi`: the offsets
    along `u` (z units, `lo` <= 0 <= `hi`) where the deviance crosses the threshold, or
    reaches a bound (`at_bound`); NaN on an open side. `t`, `deviance`: the points traced.
    """

    open: bool
    traced: bool
    lo: float
    hi: float
    at_bound: tuple[bool, bool]
    t: np.ndarray
    deviance: np.ndarray


def wide_offset(u, values, log, ref) -> float:
    """The offset along `u` (z units) that moves its most-moved parameter by a decade in
    its own scale (see the module's docstring)."""
    return math.log(10.0) / float(np.max(np.abs(u) / own_scale(values, log, ref)))


def bound_offsets(u, z_hat, folded) -> tuple[float, float]:
    """How far along `-u` and `+u` (z units, inf: none) a folded coordinate (a parameter
    `>= 0`, value `ref |z|`) reaches its bound 0."""
    lo = hi = math.inf
    for i in np.flatnonzero(np.asarray(folded, dtype=bool)):
        if u[i] == 0 or z_hat[i] == 0:  # at the bound, a move either way grows |z|
            continue
        t = -z_hat[i] / u[i]
        if t > 0:
            hi = min(hi, t)
        else:
            lo = min(lo, -t)
    return lo, hi


def profile_direction(problem, z_hat, u, se: float, n: int, rss_min: float, wide: float,
                      bounds: tuple[float, float], max_steps: int = 50, tol: float = 1e-8,
                      hold=None) -> DirectionProfile:
    """Trace the profile likelihood along `u` (p,) from `z_hat` (p,), each side from
    1.5 Hessian half-widths (`1.96 se`) outwards, at least doubling, to `wide` or the
    side's bound, then one interpolated re-fit near the crossing (linear in
    `sqrt(deviance)`). `problem`: the fit's single-shooting problem; `n`: the number of
    residuals; `rss_min`: `|r|^2` at `z_hat`; `hold` (p, h): the exactly flat directions,
    held in the re-fits as the fit holds them (LM crawls along them)."""
    trace = _Trace(problem, z_hat, u, hold, n, rss_min, max_steps, tol)
    ends, at_bound = [math.nan, math.nan], [False, False]
    traced, is_open = True, False
    for side, sign in ((1, 1.0), (0, -1.0)):
        limit = min(wide, bounds[side])
        first = min(1.5 * Z95 * se, limit) if math.isfinite(se) and se > 0 else limit
        outcome, walk = trace.walk(sign, first, limit)
        if outcome == "untraced":
            traced = False
            break
        if outcome == "below":
            if walk[2] >= bounds[side] and bounds[side] <= wide:
                ends[side], at_bound[side] = sign * bounds[side], True
                continue
            is_open = True
            break  # one open side is enough: not determined
        ends[side] = sign * trace.crossing(sign, *walk)
    if n * math.log(trace.best / rss_min) < -0.1:
        # A re-fit found a lower cost than the estimate: the fit did not reach its
        # minimum along u, and nothing here is a profile around the estimate.
        traced = False
    order = np.argsort(trace.ts)
    return DirectionProfile(is_open, traced, ends[0], ends[1], tuple(at_bound),
                            np.asarray(trace.ts)[order], np.asarray(trace.devs)[order])


class _Trace:
    """The re-fits of one direction's profile: the points `ts`, `devs` traced so far (the
    estimate's first), each point's re-fitted coordinates, and the lowest `|r|^2` seen."""

    def __init__(self, problem, z_hat, u, hold, n: int, rss_min: float, max_steps: int,
                 tol: float):
        self.problem, self.n, self.rss_min = problem, n, rss_min
        self.max_steps, self.tol = max_steps, tol
        self.u = np.asarray(u, dtype=float)
        self.z_hat = np.asarray(z_hat, dtype=float)
        # An orthonormal basis of the complement of u and `hold`: every other direction
        # is re-fitted.
        held = np.column_stack([self.u] + ([] if hold is None else [np.asarray(hold, float)]))
        basis, sv, _ = np.linalg.svd(held, full_matrices=True)
        self.B = basis[:, int(np.sum(sv > 1e-12 * sv[0])):]
        self.ts, self.devs, self.runs, self.best = [0.0], [0.0], {}, rss_min

    def refit(self, t: float, w0: np.ndarray):
        """The re-fit at offset `t` from `w0` and its deviance (inf where it failed)."""

        from .optimize import least_squares
        from .programs import Subspace

        run = least_squares(Subspace(self.problem, device_array(self.z_hat + t * self.u),
                                     device_array(self.B)), w0, self.max_steps, self.tol,
                            "", False)
        d = (self.n * math.log(2.0 * run.cost / self.rss_min) if math.isfinite(run.cost)
             else math.inf)
        return run, d

    def walk(self, sign: float, t: float, limit: float):
        """Outwards on one side from offset `t`, at least doubling, to `limit`, until the
        deviance passes the threshold. **Returns:** `(outcome, (prev_t, prev_d, t, d))`:
        `"crossed"` between the last two points, `"below"` (below it up to the last
        point `t`) or `"untraced"` (a re-fit that did not converge above it)."""
        # At least doubling, and fast enough to reach the limit within the points allowed.
        grow = max(2.0, (limit / t) ** (1.0 / (_MAX_POINTS - 1)))
        w = np.zeros(self.B.shape[1])
        prev_t, prev_d, d = 0.0, 0.0, 0.0
        for _ in range(_MAX_POINTS):
            run, d = self.refit(sign * t, w)
            # A re-fit that did not converge is an upper bound on the profile there:
            # below the threshold it still shows the profile below it; above, nothing.
            if not (run.converged or d <= CHI2_95):
                return "untraced", (prev_t, prev_d, t, d)
            w = np.asarray(run.z)
            self._keep(sign * t, d, run)
            if d > CHI2_95:
                return "crossed", (prev_t, prev_d, t, d)
            prev_t, prev_d = t, d
            if t >= limit:
                break
            t = min(grow * t, limit)
        return "below", (prev_t, prev_d, t, d)

    def crossing(self, sign: float, prev_t: float, prev_d: float, t: float,
                 d: float) -> float:
        """The offset (> 0) where the deviance crosses the threshold between `prev_t` and
        `t`: one re-fit where `sqrt(deviance)` interpolates to the threshold's root."""
        t_c = _root(prev_t, prev_d, t, d)
        run, d_c = self.refit(sign * t_c, self.runs.get(sign * prev_t,
                                                         np.zeros(self.B.shape[1])))
        if run.converged or d_c <= CHI2_95:
            self.ts.append(sign * t_c)
            self.devs.append(d_c)
            t_c = (_root(prev_t, prev_d, t_c, d_c) if d_c > CHI2_95
                   else _root(t_c, d_c, t, d))
        return t_c

    def _keep(self, t: float, d: float, run) -> None:
        self.best = min(self.best, 2.0 * run.cost)
        self.ts.append(t)
        self.devs.append(d)
        self.runs[t] = np.asarray(run.z)


def _root(t0, d0, t1, d1) -> float:
    """Where `sqrt(deviance)`, linear between (t0, d0) and (t1, d1), meets the threshold."""
    s0, s1, s = math.sqrt(max(d0, 0.0)), math.sqrt(max(d1, 0.0)), math.sqrt(CHI2_95)
    if s1 == s0:
        return t1
    return t0 + (s - s0) / (s1 - s0) * (t1 - t0)


class Checked(NamedTuple):
    """Output of [`check`][]: the candidate directions the profile closes (unit vectors
    of z, for `analyze(closed=...)`), and the notes to add to the fit's warnings."""

    closed: list
    notes: list


def check(problem, z_hat, candidates: Sequence, values, log, ref, folded, names, n: int,
          rss_min: float, max_steps: int = 50, tol: float = 1e-8, hold=None) -> Checked:
    """Check each candidate direction `(u, se)` (see `Uncertainty.candidates`) against its
    profile likelihood; `hold` (p, h): exactly flat directions, held fixed in the re-fits.
    **Returns:** a [`Checked`][]."""
    z_hat = np.asarray(z_hat, dtype=float)
    values = np.asarray(values, dtype=float)
    closed, notes = [], []
    for u, se in candidates:
        u = np.asarray(u, dtype=float)
        prof = profile_direction(problem, z_hat, u, se, n, rss_min,
                                 wide_offset(u, values, log, ref),
                                 bound_offsets(u, z_hat, folded), max_steps, tol, hold)
        what = _combination(u, names, log)
        if not prof.traced:
            notes.append(f"the profile likelihood along {what} could not be traced (a re-fit "
                         "did not converge, or found a lower cost than the estimate), so its "
                         "verdict rests on the sensitivities alone")
            continue
        if prof.open:
            continue
        closed.append(u)
        half = Z95 * se
        wide = [abs(prof.lo), abs(prof.hi)]
        off = [not b and (w > DISAGREE * half or w < half / DISAGREE)
               for w, b in zip(wide, prof.at_bound)]
        if any(off):
            notes.append(
                f"the Hessian interval and the profile likelihood disagree by more than "
                f"{DISAGREE:g}x along {what}: the profile's 95% range is {prof.lo:+.3g} to "
                f"{prof.hi:+.3g} (in its coordinates) against the Hessian's +-{half:.3g}; "
                "the intervals reported are the Hessian's, so read them as rough (fit with "
                "`profile=` that parameter for its interval)")
    return Checked(closed, notes)


def _combination(u, names, log) -> str:
    """`u` in words: its parameter when one dominates, else its leading terms."""
    order = [i for i in np.argsort(-np.abs(u)) if abs(u[i]) > 0.05]
    if abs(u[order[0]]) > 0.99:
        return names[order[0]]
    terms = [f"{u[i]:+.2f} {'ln ' if log[i] else ''}{names[i]}" for i in order[:4]]
    return "the combination " + " ".join(terms).lstrip("+")
