"""The filter over a record chunk by chunk: one compiled program of `CHUNK` samples
whatever the record's length, the samples coming from memory or from a file, a thinned
path kept in memory, the full-resolution alarms, and an optional sink that writes the
path to disk as it goes (a long record's memory is bounded by the chunk and the kept
path, not by the record)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator

import jax.numpy as jnp
import numpy as np

from ..runtime.progress import progress_bar
from .ekf import FilterSettings, FilterState, Steps, TrackModel, run_filter

__all__ = ["CHUNK", "Run", "run_chunks", "array_chunks"]

#: Samples per compiled chunk: the filter's program has this shape whatever the record.
CHUNK = 4096


class Run:
    """What [`run_chunks`][] keeps: `steps` ([`Steps`][crank_jax.online.ekf.Steps] of every
    `every`-th sample, host arrays), `t` (the kept samples' times, s), `events` (each
    alarm at full resolution: `(sample index, the change point's index, time s, the
    change point's time s, statistic)`; the change point is where the statistic last
    left 0), `n` (samples filtered) and `dt` (the median sample interval of the
    first chunk, s)."""

    def __init__(self, steps: Steps, t: np.ndarray, events: list, n: int, dt: float):
        self.steps, self.t, self.events, self.n, self.dt = steps, t, events, n, dt


def array_chunks(ts: np.ndarray, ys: np.ndarray) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """A record in memory, `ts` (n,), `ys` (n, C), as chunks of at most `CHUNK` samples."""
    for lo in range(0, ts.shape[0], CHUNK):
        yield ts[lo:lo + CHUNK], ys[lo:lo + CHUNK]


def _padded(t: np.ndarray, y: np.ndarray):
    """A chunk padded to `CHUNK` samples (the last sample repeated) and its mask."""
    k = t.shape[0]
    pad = CHUNK - k
    tp = np.concatenate([t, np.full(pad, t[-1])])
    yp = np.concatenate([y, np.repeat(y[-1:], pad, axis=0)])
    return jnp.asarray(tp), jnp.asarray(yp), jnp.asarray(np.arange(CHUNK) < k)


def run_chunks(model: TrackModel, settings: FilterSettings, state: FilterState,
               chunks: Iterable[tuple[np.ndarray, np.ndarray]], every: int = 1,
               progress: bool = False, total: int | None = None,
               sink: Callable[[np.ndarray, Steps], None] | None = None) -> Run:
    """Filter `chunks` (`(t (k,), y (k, C))`, k <= `CHUNK`, in time order) from `state`.

    Keeps every `every`-th sample (indices that are multiples of `every`) in memory;
    `sink(t, steps)`, when given, receives every chunk's full-resolution output as it is
    made (to write it to disk); `total` (samples, or None) sizes the progress display.

    **Returns:** a [`Run`][]."""
    kept, kept_t, events = [], [], []
    lo, dt, out = 0, 0.0, None
    with progress_bar(total, "track", progress, unit="sample") as bar:
        for t, y in chunks:
            k = t.shape[0]
            if lo == 0 and k > 1:
                dt = float(np.median(np.diff(t)))
            state, out = run_filter(model, settings, state, *_padded(t, y))
            host = Steps(*(np.asarray(a)[:k] for a in out))
            first = (-lo) % every  # the kept samples' indices are multiples of `every`
            # (Copies: a slice would keep the whole chunk's buffers alive.)
            kept.append(Steps(*(a[first::every].copy() for a in host)))
            kept_t.append(t[first::every].copy())
            for i in np.flatnonzero(host.alarm):
                change = lo + int(i) - int(host.run[i])
                events.append((lo + int(i), max(change, 0), float(t[i]),
                               _time_of(change, lo, t, kept_t, every), float(host.g[i])))
            if sink is not None:
                sink(t, host)
            lo += k
            bar.update(k)
    if out is None:
        raise ValueError("the record has no samples to track")
    steps = Steps(*(np.concatenate([s[i] for s in kept]) for i in range(len(Steps._fields))))
    return Run(steps, np.concatenate(kept_t), events, lo, dt)


def _time_of(index: int, lo: int, t: np.ndarray, kept_t: list, every: int) -> float:
    """The time of sample `index` (s): exact in the chunk that starts at sample `lo` (times
    `t`), else the nearest kept sample at or before it (`every` samples at most early)."""
    index = max(index, 0)
    if index >= lo:
        return float(t[index - lo])
    j = index // every
    for part in kept_t:
        if j < part.shape[0]:
            return float(part[j])
        j -= part.shape[0]
    return float(kept_t[-1][-1])
