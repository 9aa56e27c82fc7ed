"""Checks of a record's time scale and of synthetic-record options: what float64 and the
solver can resolve (a leaf module: [`crank_jax.records.data`][] raises its `DataError` with these
messages)."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["MAX_TIME_SPAN", "MIN_TIME_STEP", "MIN_STEP_ULPS", "MAX_SYNTH_ANGLE",
           "time_scale_problem", "series_problem", "check_synth_options"]


#: The longest span a record's times may cover, s (about 32 years): a longer one is a
#: time column in other units, or garbage; beyond float64's range it cannot be subtracted.
MAX_TIME_SPAN = 1e9
#: The closest two samples may be, s (a 1 GHz logger): closer ones are a time column in
#: other units; spacings near 1e-300 s overflow every rate (1/dt) the solver computes.
MIN_TIME_STEP = 1e-9
#: Two samples must be at least this many float64 spacings (ulps) of the largest |t| apart,
#: so that the solver can place steps between them (times near 1e8 s resolve only 1.5e-8 s).
MIN_STEP_ULPS = 64


def time_scale_problem(ts: np.ndarray, d: np.ndarray, where: str, label) -> str | None:
    """The message for times a solver cannot resolve in float64 (a span beyond
    [`MAX_TIME_SPAN`][], or two samples closer than [`MIN_TIME_STEP`][] or than
    [`MIN_STEP_ULPS`][] float64 spacings of the largest |t|), else None.

    `ts` (n,) the times, s; `d` (n-1,) `diff(ts)`, all > 0; `where` the record's label;
    `label(i)` names sample `i` (a line of the file, or "sample i")."""
    with np.errstate(over="ignore"):
        span = d.sum()
    if not span <= MAX_TIME_SPAN:  # also +inf: the span overflowed
        return (f"{where}: column 't' runs from {float(ts[0]):g} s ({label(0)}) to "
                        f"{float(ts[-1]):g} s ({label(len(ts) - 1)}); a record may span at "
                        f"most {MAX_TIME_SPAN:g} s: is the time column in seconds? (choose it "
                        "with `t_col=`)")
    ulp = float(np.spacing(max(abs(float(ts[0])), abs(float(ts[-1])))))
    # (1 - 1e-9): a 1 GHz grid computed in float64 has spacings a few ulps under 1e-9 s.
    close = d < max(MIN_TIME_STEP * (1 - 1e-9), MIN_STEP_ULPS * ulp)
    if not close.any():
        return None
    i = int(np.argmax(close))  # the first such sample
    if d[i] < MIN_TIME_STEP * (1 - 1e-9):
        return (f"{where}: {label(i + 1)}: t = {float(ts[i + 1])!r} s is only "
                        f"{float(d[i]):.3g} s after the previous sample; samples closer than "
                        f"{MIN_TIME_STEP:g} s (a {1 / MIN_TIME_STEP:g} Hz logger) are not "
                        "resolved: is the time column in seconds?")
    return (f"{where}: {label(i + 1)}: t = {float(ts[i + 1])!r} s is only "
                    f"{float(d[i]):.3g} s after the previous sample, but at times near "
                    f"{max(abs(float(ts[0])), abs(float(ts[-1]))):g} s float64 resolves only "
                    f"{ulp:.3g} s and the solver needs {MIN_STEP_ULPS} times that: subtract "
                    "the start time from the t column so that it starts near 0")


#: The largest start-up transient amplitude and noise standard deviation `synthesize`
#: adds, rad (about 160,000 turns): the angle stays a finite float64 that a fit can read.
MAX_SYNTH_ANGLE = 1e6


def check_synth_options(t1, rate, noise_std, jitter_std, drop, t_start, seed, transient,
                         transient_time, transient_hz, quantization) -> None:
    """Raise `ValueError` naming the argument (as `` `name=` ``) and its valid range for
    any value [`synthesize`][] cannot turn into a valid record."""
    for name, v, ok, valid in (
            ("rate", rate, rate > 0, "> 0 Hz"),
            ("noise_std", noise_std, 0 <= noise_std <= MAX_SYNTH_ANGLE,
             f"from 0 to {MAX_SYNTH_ANGLE:g} rad"),
            ("jitter_std", jitter_std, jitter_std >= 0, ">= 0 s"),
            ("drop", drop, 0 <= drop < 1, "a probability in [0, 1)"),
            ("t1", t1, t1 > 0, "> 0 s"),
            ("t_start", t_start, 0 <= t_start < t1, f"in [0, t1 = {t1:g}) s"),
            ("transient", transient, abs(transient) <= MAX_SYNTH_ANGLE,
             f"from -{MAX_SYNTH_ANGLE:g} to {MAX_SYNTH_ANGLE:g} rad"),
            ("transient_time", transient_time, transient_time > 0, "> 0 s"),
            ("transient_hz", transient_hz, transient_hz >= 0, ">= 0 Hz")):
        if not (math.isfinite(v) and ok):
            raise ValueError(f"synthesize: `{name}=` {v!r} is out of range: use a "
                             f"finite value {valid}")
    if quantization is not None and not (int(quantization) == quantization and quantization > 0):
        raise ValueError(f"synthesize: `quantization=` must be a positive "
                         f"integer count per revolution, got {quantization!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"synthesize: `seed=` must be an integer >= 0, got {seed!r}")
    # The samples' spacing must be one that a record may have (see Data): float64 resolves
    # times near t1 only to spacing(t1), so a high rate far from t = 0 collapses samples.
    # Each sample time t_start + i / rate is off by up to one spacing: two in hand.
    dt, ulp = 1.0 / rate, float(np.spacing(t1))
    need = max(MIN_TIME_STEP, MIN_STEP_ULPS * ulp) + 2 * ulp
    if dt < need:
        raise ValueError(
            f"synthesize: `rate=` {rate:g} Hz samples every {dt:.3g} s, but a record's "
            f"samples must be at least {MIN_TIME_STEP:g} s and {MIN_STEP_ULPS} float64 "
            f"spacings apart, and near t1 = {t1:g} s one spacing is {ulp:.3g} s: lower `rate=`"
            f" to at most {1 / need:.3g} Hz or start"
            " nearer t = 0 (`t_start=`, `t1=`)")


def series_problem(ts: np.ndarray, phi: np.ndarray, where: str, rows, name: str,
                   min_samples: int) -> str | None:
    """The message naming the first bad row of a record's times `ts` (n,) and one column
    `phi` (n,) (named `name`), or None; `rows[i]` labels sample `i` (None: "sample i")."""
    label = (lambda i: rows[i]) if rows is not None else (lambda i: f"sample {i}")
    if ts.ndim != 1 or phi.shape != ts.shape:
        return (f"{where}: t and {name} must be 1-D of equal length, got shapes "
                f"{ts.shape} and {phi.shape}")
    if ts.shape[0] < min_samples:
        return (f"{where}: too few samples ({ts.shape[0]}); a record needs at least "
                f"{min_samples}")
    for name, x in (("t", ts), (name, phi)):
        bad = ~np.isfinite(x)
        if bad.any():
            i = int(np.argmax(bad))
            return (f"{where}: {label(i)}: column {name!r} is {float(x[i])} (NaN or inf); "
                    "remove or repair that row")
    with np.errstate(over="ignore", invalid="ignore"):  # +-1.7e308: the span overflows
        d = np.diff(ts)
    if not np.all(d > 0):
        i = int(np.argmax(d <= 0)) + 1
        return (f"{where}: {label(i)}: time t = {float(ts[i])!r} does not increase "
                f"(previous t = {float(ts[i - 1])!r}); sort the record and remove "
                "duplicate times")
    return time_scale_problem(ts, d, where, label)
