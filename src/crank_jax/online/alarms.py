"""Alarms of the filter's change test, named: when, which parameters moved, from what to
what, and the test's statistic.

The CUSUM says *that* the record stopped agreeing with the model; the parameters that
moved are read from the filter's own path: each alarm restores the parameters'
covariance, so a few seconds later (`settle`) the estimate stands at the new values. A
parameter moved when its estimate after differs from its estimate before the change
point (where the statistic last left 0) by more than [`MOVED`][] combined standard errors.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["name_alarms", "MOVED"]

#: A parameter moved at an alarm when its change exceeds this many combined standard
#: errors (before and after, in its coordinate).
MOVED = 3.0


def _value(z: float, log: bool) -> float:
    return math.exp(z) if log else z


def name_alarms(steps, events, free, log, settle: float, every: int, dt: float,
                n: int) -> list[dict]:
    """Each alarm of `events` (`(sample index, change point's index, time s, change
    point's time s, statistic)`, full resolution, from
    [`run_chunks`][crank_jax.online.runner.run_chunks]) as a dict: `t` (s), `t_change`
    (the change point's time, s), `parameters` (the names that moved, largest change
    first), `before` and `after` ({name: value}), `z` ({name: change over its combined
    standard error}), `statistic` (the CUSUM's largest value) and `tests` (the test's
    alarms merged into this one: those within `settle` s of the one before).
    `steps` holds every `every`-th sample of the filter's output; `dt` is the sample
    interval (s) and `n` the record's samples."""
    n_kept = steps.x.shape[0]
    wait = int(round(settle / dt)) if dt > 0 else 0
    groups = _grouped(events, wait)
    out = []
    for k, group in enumerate(groups):
        i, change, t, t_change, _ = group[0]
        last = group[-1][0]
        stat = max(e[-1] for e in group)
        nxt = groups[k + 1][0][0] - 1 if k + 1 < len(groups) else n - 1
        b = min(max(change - 1, 0) // every, n_kept - 1)
        a = min(min(last + wait, nxt) // every, n_kept - 1)
        zb, za = steps.x[b, 2:], steps.x[a, 2:]
        sd = np.sqrt(steps.se[b, 2:] ** 2 + steps.se[a, 2:] ** 2)
        score = np.abs(za - zb) / np.where(sd > 0, sd, np.inf)
        order = np.argsort(-score)
        moved = [free[j] for j in order if score[j] > MOVED] or [free[order[0]]]
        out.append({
            "t": t, "t_change": t_change, "parameters": moved,
            "before": {m: _value(float(zb[j]), log[j]) for j, m in enumerate(free)},
            "after": {m: _value(float(za[j]), log[j]) for j, m in enumerate(free)},
            "z": {m: float(score[j]) for j, m in enumerate(free)},
            "statistic": float(stat), "tests": len(group)})
    return out


def _grouped(events, wait: int) -> list[list]:
    """`events` in groups: an alarm within `wait` samples of the one before belongs to
    the same change (the filter is still taking it in: its restored covariance lets the
    estimate swing past the new value, and the test fires again)."""
    groups = []
    for e in events:
        if groups and e[0] - groups[-1][-1][0] <= wait:
            groups[-1].append(e)
        else:
            groups.append([e])
    return groups
