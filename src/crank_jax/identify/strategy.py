"""The fit's strategy: single or multiple shooting, the ODE step budget, multistart and
when to try them.

Phase drift decides the shooting. A model whose frequency is off by a fraction `e` drifts
`2 pi e N` rad in phase over `N` periods, and single shooting loses the basin of attraction
once that nears `pi/2`. Both `e` and `N` are judged from the record itself: `N` from its
zero crossings, `e` from the crossings of the start model's angle against the record's
(the linearised period of the start scene would be 20% off at large amplitude). The
segment count then comes from the record alone (see `record_segments`).
"""

from __future__ import annotations

import math

import numpy as np

from .fit_options import ShootingMode

__all__ = ["AUTO_PERIODS", "SEGMENT_PERIODS", "MAX_DRIFT", "BLIND_DRIFT", "MAX_ODE_STEPS",
           "SMALL_ODE_BUDGET",
           "STEPS_PER_PERIOD", "FAR_FROM_NOISE", "FREQUENCY_RATIO", "n_segments", "ode_budget",
           "absurd_start", "absurd_frequency", "refusal", "segment_count", "record_segments",
           "MAX_SEGMENTS", "MIN_MOTION", "no_motion", "aliased",
           "perturb", "AT_ZERO", "far_from_noise", "stall_rms", "noise_unit"]

#: `shooting="auto"` uses multiple shooting above this many observed periods, whatever
#: the start's drift (a record that long has many chances to slip a cycle).
AUTO_PERIODS = 25.0
#: Multiple-shooting segment length, in observed periods of the record: a record of `N`
#: periods is cut into about `N / SEGMENT_PERIODS` segments (see [`record_segments`][]).
SEGMENT_PERIODS = 2.0
#: Most segments per record (longer records get longer segments): the LM's host-side
#: linear algebra grows with the square of the coordinates (two per segment).
MAX_SEGMENTS = 48
#: Largest predicted phase drift (rad) over a record that `"auto"` fits by single shooting.
MAX_DRIFT = 1.0
#: Largest predicted drift (rad) of one multiple-shooting segment of a record that no
#: channel measures the angle of (see [`n_segments`][]).
BLIND_DRIFT = math.pi / 2
#: The ODE step budget of a fit's solves when the start solve is cheap, and otherwise.
SMALL_ODE_BUDGET = 32_768
MAX_ODE_STEPS = 200_000
#: A start solve that takes more steps than this per observed period or turn of the
#: record (or per record, if it holds less than one) is absurd: the start values make the dynamics
#: orders of magnitude faster or stiffer than the record shows.
STEPS_PER_PERIOD = 4000
#: A start model whose linearised frequency is this many times above (or below) the
#: record's observed frequency is rejected before any solve.
FREQUENCY_RATIO = 30.0
#: A record whose motion (rms, noise taken out) is below this many noise levels is
#: noise about a constant (see [`no_motion`][]); the bound is higher where pure noise
#: could reach it ([`NO_MOTION_FALSE_ALARM`][]): 0.77 noise levels at 1001 samples, so a
#: sinusoid of amplitude 1.1 noise levels or less is refused there.
MIN_MOTION = 0.2
#: The probability that a record of pure noise is taken for a motion (see [`no_motion`][]).
NO_MOTION_FALSE_ALARM = 1e-4
#: A global coordinate whose magnitude is below this (in its unit, `ref`) sits at 0 for
#: [`perturb`][]: it is moved by an added step, not a factor.
AT_ZERO = 1e-3
#: A fit whose rms residual ends above this multiple of the record's noise level (and
#: of `sigma`, when given) is stalled far from the noise: try another strategy.
FAR_FROM_NOISE = 3.0


def n_segments(span: float, period_data: float | None, period_model: float | None,
               shooting: str, segments: int | None, turns_data: float = 0.0,
               turns_model: float = 0.0, blind: bool = False) -> tuple[int, str]:
    """Shooting segments for one record and the reason, in words. The start values
    decide only *whether* to shoot multiply (`"auto"`: when their predicted phase drift is
    large); the count, a shape of the compiled programs, comes from the record alone
    ([`record_segments`][]).

    **Arguments:** `span`, the record's length, s; `period_data`, its observed period, s
    (None: less than one period); `period_model`, the start model's over the same
    samples; `shooting`, `"auto"`, `"single"` or `"multiple"`; `segments`, a fixed count
    or None; `turns_data`, `turns_model`: the net turns of the record and of the start
    model (a turning crank with no period is judged by its turns' shortfall, its segments
    cut per two turns); `blind`: no channel measures the angle (a slide reading repeats
    every turn and has two angles per position, so a segment that may drift more than
    [`BLIND_DRIFT`][] can slip a turn or half-turn: at least one segment per
    `BLIND_DRIFT` of predicted drift, at most [`MAX_SEGMENTS`][]).
    """
    shooting = ShootingMode(shooting)
    if shooting is ShootingMode.SINGLE:
        return 1, "single shooting (requested)"
    if segments is not None:
        return int(segments), f"{segments} segments (requested)"
    if period_data is None and turns_data >= 1:
        drift = 2 * math.pi * abs(turns_model - turns_data)
        why = (f"the crank turns {turns_data:.3g} times in the record (mean speed "
               f"{2 * math.pi * turns_data / span:.3g} rad/s), the start model "
               f"{turns_model:.3g} times (predicted drift {drift:.1f} rad)")
        if shooting is ShootingMode.AUTO and drift <= MAX_DRIFT and turns_data <= AUTO_PERIODS:
            return 1, why
        return _blind(record_segments(span, span / turns_data), drift, blind), why
    if period_data is None:
        n = 1 if shooting is ShootingMode.AUTO else 2
        return n, "the record holds less than one period and less than one turn"
    periods = span / period_data
    if period_model is None:
        err = 0.5  # the start model does not even oscillate like the record
    else:
        err = abs(period_data / period_model - 1.0)
    drift = 2 * math.pi * err * periods
    why = (f"{periods:.1f} periods in the record, start period "
           + (f"{100 * err:.0f}% off" if period_model is not None else "not observed")
           + f" (predicted drift {drift:.1f} rad)")
    if shooting is ShootingMode.AUTO and drift <= MAX_DRIFT and periods <= AUTO_PERIODS:
        return 1, why
    return _blind(record_segments(span, period_data), drift, blind), why


def _blind(n: int, drift: float, blind: bool) -> int:
    """`n` segments, or more for a record no channel of which measures the angle: at
    most [`BLIND_DRIFT`][] of predicted drift each (see [`n_segments`][])."""
    if not blind or not math.isfinite(drift):
        return n
    return segment_count(min(max(n, math.ceil(drift / BLIND_DRIFT)), MAX_SEGMENTS))


def record_segments(span: float, period_data: float | None) -> int:
    """The multiple-shooting segment count of a record `span` s long with observed period
    `period_data` s (None: less than one period): one segment per [`SEGMENT_PERIODS`][]
    periods, at most [`MAX_SEGMENTS`][], rounded up by [`segment_count`][].
    From the record alone, not from the start's predicted drift (segment states start
    from the record, so the count matters little; a drift-dependent one compiled new
    programs for each start)."""
    if not period_data:
        return 2
    return segment_count(min(math.ceil(span / period_data / SEGMENT_PERIODS), MAX_SEGMENTS))


def segment_count(n: int) -> int:
    """At least `n` (and 2) segments, rounded up to the next of 2, 3, 4, 6, 8, 12, 16, 24,
    ... (two counts per doubling): the count is a shape of the compiled programs, so
    records a few periods longer or shorter share them. Shorter segments than needed cost
    little and make the fit no less robust."""
    size = 2
    while size < n:
        size = size * 3 // 2 if (size & (size - 1)) == 0 else size * 4 // 3
    return size


def ode_budget(steps0: int) -> int:
    """The step budget of the fit's solves from the steps of the start solve: generous
    next to it, so that a trial point in a stiff corner fails fast; two levels only (the
    budget is static in the compiled program: a finer ladder would recompile from one
    noisy record to the next)."""
    return SMALL_ODE_BUDGET if 20 * int(steps0) <= SMALL_ODE_BUDGET else MAX_ODE_STEPS


def absurd_start(steps0: int, span: float, period_data: float | None,
                 budget: int | None = None, turns: float = 0.0) -> str | None:
    """A message when the start solve took absurdly many steps for what the record shows
    (see [`STEPS_PER_PERIOD`][]), else None. `budget`: the step budget of that solve (a
    solve that reached it took at least that many); `turns`: the record's net turns
    (said in the message: a crank that turns many times is no oscillation)."""
    # A crank that turns has a turn for its cycle (it has no period): the budget counts
    # whichever the record holds more of.
    periods = max(1.0, span / period_data if period_data else 0.0, turns)
    if steps0 <= STEPS_PER_PERIOD * periods:
        return None
    took = (f"more than {budget}" if budget is not None and steps0 >= budget
            else f"{steps0}")
    shows = (f"{span / period_data:.0f} observed periods" if period_data
             else "less than one observed period")
    if turns >= 1:
        shows += f" and {turns:.3g} turns"
    return (f"the start values make the model far faster or stiffer than the record: its "
            f"solve takes {took} steps for a record of {shows}; choose start values nearer "
            "the truth (e.g. `init='regressor'`, or the stiffness from the observed period)")


def absurd_frequency(omega_start: float | None, period_data: float | None) -> str | None:
    """A message when the start model's linearised natural frequency (rad/s) is more than
    [`FREQUENCY_RATIO`][] times off the record's observed one, else None (such a start
    would spend minutes in stiff solves that cannot converge)."""
    if not omega_start or not period_data or not math.isfinite(omega_start):
        return None
    ratio = omega_start * period_data / (2 * math.pi)
    if 1 / FREQUENCY_RATIO <= ratio <= FREQUENCY_RATIO:
        return None
    return (f"the start values put the model's natural frequency at "
            f"{omega_start / (2 * math.pi):.3g} Hz, {ratio:.3g} times the record's "
            f"{1 / period_data:.3g} Hz: choose start values nearer the truth (e.g. "
            "`init='regressor'`, or a stiffness from the observed period)")


def refusal(records, messages) -> str | None:
    """The fit's refusal from its records' judgements: the first of `messages` (one per
    record, None: fine), naming its record (`source`) if there are several."""
    multi = len(records) > 1
    return next(((f"record {d.source}: {a}" if multi else a)
                 for a, d in zip(messages, records) if a), None)


def _pure_noise_ratio(n: int) -> float:
    """The variance-to-noise ratio that pure noise of `n` samples exceeds with probability
    [`NO_MOTION_FALSE_ALARM`][] (see [`no_motion`][])."""
    # The F distribution's quantile from scipy.special (`fdtri`, what `scipy.stats.f.ppf`
    # calls): importing scipy.stats took 1.0 s of a 2.2 s warm `crank-jax fit`.
    from scipy.special import fdtri

    from .start import NOISE_STENCIL

    dof = max((n - NOISE_STENCIL + 1) / 6.0, 1.0)
    return max(1.0 + MIN_MOTION**2, float(fdtri(n - 1, dof, 1.0 - NO_MOTION_FALSE_ALARM)))


def no_motion(phi: np.ndarray, noise: float) -> str | None:
    """A message when a record's angle shows no motion above its noise, else None.

    The record's variance over the noise level's square (`start.noise_level`) is near 1
    for pure noise (a crank at rest), which no model can explain. Both are estimates, so
    that ratio scatters, widely on a short record: the record is refused while it stays
    below what pure noise exceeds with probability [`NO_MOTION_FALSE_ALARM`][] (an F
    quantile, the noise level's overlapping stencil windows counted as a sixth of their
    number of degrees of freedom), and at least `1 + MIN_MOTION^2`."""
    x = np.asarray(phi, dtype=float)
    spread = float(np.std(x))
    # A spread of float rounding (or none) is no motion either, whatever the noise says.
    rounding = spread <= 1e-12 * float(np.max(np.abs(x)))
    limit = _pure_noise_ratio(x.size)
    if not (rounding or noise > 0 and spread**2 < noise**2 * limit):
        return None
    if rounding:
        return (f"the angle shows no motion above its noise: it is constant (spread "
                f"{spread:.3g} rad, float rounding); check the angle column and its unit, or "
                "record a motion")
    # The words give the test's numbers: a spread far above the noise level, refused on a
    # short record whose pure noise can reach as far, must not read as a contradiction.
    return (f"the angle shows no motion above its noise that {x.size} samples can tell: its "
            f"spread ({spread:.3g} rad) is {spread / noise:.3g} times its noise level "
            f"({noise:.3g} rad), but pure noise of {x.size} samples reaches "
            f"{math.sqrt(limit):.3g} times one time in {1 / NO_MOTION_FALSE_ALARM:.0f}; check "
            "the angle column and its unit, or give more samples (a longer record or window)")


def aliased(phi: np.ndarray) -> str | None:
    """A message when a record's angle moves more than pi between most samples, else
    None: sampled that coarsely (or with an angle column in the wrong unit), the record
    cannot resolve the motion, whatever model and start values. Decided before any
    solve."""
    step = np.abs(np.diff(np.asarray(phi, dtype=float)))
    if step.size == 0 or not float(np.median(step)) > math.pi:
        return None
    return (f"the angle moves {float(np.median(step)):.3g} rad between samples (median), "
            "more than pi: the record cannot resolve the motion (a crank that turns faster "
            "than half a turn per sample); sample it faster, or check the angle column's "
            "unit")


def perturb(z0: np.ndarray, names, log, rng: np.random.Generator, folded=None) -> np.ndarray:
    """A multistart point: the log-coordinates of `names` (the first entries of `z0`) plus
    N(0, 0.5^2), their other global coordinates times `1 + N(0, 0.3^2)`; initial and
    segment states stay. A global coordinate at 0 (below [`AT_ZERO`][]), which a factor
    cannot move, gets N(0, 0.5^2) added in its unit `ref` instead (`|.|` where `folded`):
    else every extra start from a bound at 0 stays there (experiments/misfit_rig.py,
    case `friction`)."""
    z = np.array(z0, dtype=float)
    for i, n in enumerate(names):
        if log[i]:
            z[i] += rng.normal(0.0, 0.5)
        elif not (n.startswith("phi0") or n.startswith("dphi0")):
            if abs(z[i]) < AT_ZERO:
                step = rng.normal(0.0, 0.5)
                z[i] = abs(step) if folded is not None and folded[i] else step
            else:
                z[i] *= 1 + rng.normal(0.0, 0.3)
    return z


def far_from_noise(rms: float, noise: float) -> bool:
    """True when a fit's rms residual is far above `noise`, the records' noise level
    (`FitRequest.noise`, the first channel's unit)."""
    return not (math.isfinite(rms) and rms <= stall_rms(noise))


def noise_unit(noise: float) -> float:
    """The noise level (residual unit) that LM's termination is judged in: the records'
    level `noise` (`FitRequest.noise`: given by `sigma=` or estimated), kept above 0."""
    return max(noise, 1e-12)


def stall_rms(noise: float) -> float:
    """The rms residual above which a fit is far from the records' noise level `noise`:
    [`FAR_FROM_NOISE`][] times it."""
    return FAR_FROM_NOISE * noise_unit(noise)
