"""Records as shooting segments, in rows padded to a few lengths (so that records of other
lengths reuse the compiled programs; the padding has weight 0), and a record as the fit's
problem holds it ([`Experiment`][])."""

from __future__ import annotations

import equinox as eqx
import numpy as np
from jaxtyping import Array

from ..model.loads import AbstractLoad, AngleLoad, InputLoad, SampledLoad
from ..runtime.arrays import device_array

__all__ = ["bucket", "row_bucket", "Segments", "Experiment", "segment_layout", "make_segments",
           "padded_load"]


def bucket(m: int) -> int:
    """The next of 72, 108, 144, 216, 288, ..., 1152, 1728, 2304, ... at or above `m`
    (9 * 2^k and 27 * 2^k: two sizes per doubling). A value, not a shape: the length that
    weighs a segment's continuity defects (`Segments.size`; the ladder the rows were once
    padded to, kept so that the weights, and the fits' results, stay as they were). The
    shapes take [`row_bucket`][]'s coarser ladder."""
    size = 72
    while size < m:
        # 9 * 2^k -> 27 * 2^(k-1) (x 3/2) -> 9 * 2^(k+1) (x 4/3)
        size = size * 3 // 2 if (size // 9) & (size // 9 - 1) == 0 else size * 4 // 3
    return size


class Segments(eqx.Module):
    """One record cut into shooting segments, in `S` rows of `m` save times each (padded;
    the rows after the record's segments inactive, see [`segment_layout`][]).

    Segment `s` covers samples `starts[s] .. starts[s+1]` inclusive: the shared sample is
    fitted by segment `s+1` (weight 0 in segment `s`) and is where continuity is imposed.
    """

    ts: Array  # (S, m) save times, strictly increasing in each row
    ys: Array  # (C, S, m) data, one row block per channel (SI)
    w: Array  # (S, m) 1 for a fitted sample, 0 for padding and the shared end sample
    end: Array  # (S,) int: index of the continuity sample in each row
    first: Array  # (S,) int: index in the record of each row's first sample
    # (S,) 1 for a segment of the record, 0 for an inactive row (padding: see
    # `segment_layout`); its state is held, its samples and continuity weigh nothing.
    on: Array
    # () the row length that weighs a continuity defect as a segment's worth of data
    # (`Problem.residuals`): the length a row of these segments alone would be padded to
    size: Array


class Experiment(eqx.Module):
    """One record in the problem: its segments, loads and fixed initial state, and its
    channels: each one's calibration (`scale`, fixed `offset`, SI) and `weight` (C,), the
    first channel's noise level over its own (so the residuals are in the first channel's
    unit, and every channel counts by its noise)."""

    seg: Segments
    load: AbstractLoad
    torque: AbstractLoad
    phi0: Array  # used when phi0 is not free
    dphi0: Array
    # Arrays, not static floats: a static value that depends on the data would recompile
    # every fit.
    ref_phi: Array
    ref_dphi: Array
    scale: Array  # (C,)
    offset: Array  # (C,)
    weight: Array  # (C,)
    per_radian: Array  # the first channel's typical reading change per radian of crank
    channels: tuple[str, ...] = eqx.field(static=True, default=("phi",))

    @property
    def n(self) -> int:
        """Number of fitted samples (host side)."""
        return int(np.asarray(self.seg.w).sum())




def row_bucket(m: int) -> int:
    """The padded length of a row that holds `m` samples: the next of 6, 12, 24, 48, 96,
    ..., 1536, 3072, 6144, ... (3 * 2^k: one size per doubling, coarser than [`bucket`][]).

    The rows of the fit's solves (a single-shooting record, a multiple-shooting segment)
    and of the motion start's equation of motion take this ladder, so that records of
    neighbouring lengths share one program. At 200 Hz: 769-1536 samples (3.8-7.7 s) give
    one single-shooting row, 1537-3072 (to 15.4 s) the next; a lab-rig segment (two
    periods, 62-93 samples whatever the record's length) one row of 96. The price: a
    padded save time repeats the row's last and costs a Jacobian row (weight 0), but no
    solver step (the adaptive solver stops at the first of them, see
    `solve.adaptive.solve_adaptive`)."""
    size = 6
    while size < m:
        size *= 2
    return size


def segment_layout(n: int, S: int, pad: bool = True) -> tuple[int, int]:
    """The shape `(rows, m)` that holds a record of `n` samples cut into `S` segments:
    with `pad`, a function of `S`'s class and of the longest segment's [`row_bucket`][]
    alone (for single shooting, of the record's), not of the record's length: the
    segment count follows the motion (about two periods a segment), so records of one
    scene and rate, short or long, have segments of about one length and share their
    multiple-shooting programs within a class.

    The classes are the powers of two: `S` segments take `rows` = the next power of two
    (the rows beyond `S` inactive, weight 0), so the ladder's 12 and 16 segments (or 3 and
    4, 6 and 8, 24 and 32) give one shape."""
    if S == 1:
        return 1, row_bucket(n) if pad else n
    bounds = np.linspace(0, n - 1, S + 1).round().astype(int)
    own = int(np.max(np.diff(bounds))) + 1
    if not pad:
        return S, own
    return 1 << (S - 1).bit_length(), row_bucket(own)


def make_segments(ts: np.ndarray, ys: np.ndarray, n_segments: int, pad: bool = True
                  ) -> Segments:
    """Split a record into `n_segments` segments of nearly equal sample counts, in the
    rows of [`segment_layout`][] (padded when `pad`: each row to its length, and inactive
    rows after the segments). `ys`: (n,) or (C, n), the channels' data at `ts` (n,)."""
    ys = np.atleast_2d(np.asarray(ys, dtype=float))
    n = ts.shape[0]
    S = max(1, min(int(n_segments), n // 4))
    bounds = np.linspace(0, n - 1, S + 1).round().astype(int)
    rows, m = segment_layout(n, S, pad)
    own = int(np.max(np.diff(bounds))) + 1 if S > 1 else n
    T, P, W = np.zeros((rows, m)), np.zeros((ys.shape[0], rows, m)), np.zeros((rows, m))
    E, F = np.zeros(rows, dtype=np.int32), np.full(rows, n - 1, dtype=np.int32)
    on = np.zeros(rows)
    for s in range(rows):
        a, b = (bounds[s], bounds[s + 1]) if s < S else (n - 1, n - 1)
        k = b - a + 1 if S > 1 else n
        seg_t = ts[a:a + k]
        # Padding times repeat the row's last: the solve stops at the first and the
        # repeats take its value, so padding costs no step. An inactive row is such
        # padding of the record's last sample: a solve of no step from the state there
        # (its start, see `channel_noise.segment_states`).
        pad_t = np.full(m - k, seg_t[-1])
        T[s] = np.concatenate([seg_t, pad_t])
        if s >= S:
            continue
        P[:, s, :k] = ys[:, a:a + k]
        W[s, :k] = 1.0
        if S > 1 and s < S - 1:
            W[s, k - 1] = 0.0  # the shared sample belongs to the next segment
        E[s], F[s], on[s] = k - 1, a, 1.0
    size = float(bucket(own) if pad else own)
    return Segments(*(device_array(x) for x in (T, P, W, E, F, on, size)))


def padded_load(load: AbstractLoad) -> AbstractLoad:
    # A sampled load's length is a shape: pad it (holding its last value, as it is held
    # outside its samples anyway) so records of other lengths reuse the programs.
    if isinstance(load, InputLoad) and load.signal is not None:
        return eqx.tree_at(lambda x: x.signal, load, padded_load(load.signal))
    if isinstance(load, AngleLoad):  # its table's knots are angles: held past the last
        return eqx.tree_at(lambda x: x.table, load, padded_load(load.table))
    if not isinstance(load, SampledLoad):
        return load
    ts, vs = np.asarray(load.ts), np.asarray(load.values)
    m = row_bucket(ts.shape[0])
    extra = ts[-1] + np.arange(1, m - ts.shape[0] + 1) * max(1.0, abs(ts[-1] - ts[0]))
    return SampledLoad(np.concatenate([ts, extra]),
                       np.concatenate([vs, np.full(extra.shape, vs[-1])]), interp=load.interp)


