"""Start values from the data: smoothed states and derivatives, and the linear regressor.

Both work on the record alone, in memory proportional to the record (not to the record
times the smoothing window): a long record at a high rate (10^6 samples at 100 kHz) is
smoothed at the few samples that need it, and the regressor uses a thinned record.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..model.dynamics import equation_residual
from ..model.loads import AbstractLoad
from ..model.params import SCALE_GROUP, SliderCrank
from ..records.data import Data
from ..runtime.arrays import device_array
from .segments import row_bucket

__all__ = ["smooth_derivatives", "half_window", "regressor_start", "regressor_samples",
           "padded_rows", "observed_period", "noise_level", "channel_level", "MAX_WINDOW",
           "MAX_REGRESSOR_ROWS", "MIN_RELATIVE_NOISE"]

#: At most this many samples enter one local fit: a wider window is thinned evenly
#: (enough to average the noise out of a start value, and bounded work per sample).
MAX_WINDOW = 129
#: The regressor start uses at most this many rows (evenly thinned samples).
MAX_REGRESSOR_ROWS = 20_000
_CHUNK = 4096


def smooth_derivatives(ts: np.ndarray, phi: np.ndarray, half: int, at=None):
    """Local quartic least-squares fits (a Savitzky-Golay filter for irregular samples).

    **Arguments:** `ts`, `phi` (n,); `half`, the half-width of the window in samples (the
    window is shifted inwards at the ends, and thinned to at most [`MAX_WINDOW`][]
    samples); `at`: indices (k,) at which to evaluate (default: every sample).

    **Returns:** `(phi, dphi, ddphi)`, each (k,), in rad, rad/s, rad/s^2. Memory is
    O(k * MAX_WINDOW), computed in chunks.
    """
    ts = np.asarray(ts, dtype=float)
    phi = np.asarray(phi, dtype=float)
    n = ts.shape[0]
    at = np.arange(n) if at is None else np.asarray(at, dtype=int)
    w = min(max(2 * half + 1, 7), n)
    stride = max(1, -(-w // MAX_WINDOW))
    offs = np.arange(0, w, stride)
    outs = [_local_fit(ts, phi, at[i:i + _CHUNK], half, w, offs)
            for i in range(0, at.shape[0], _CHUNK)]
    if not outs:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    return tuple(np.concatenate([o[j] for o in outs]) for j in range(3))


def _local_fit(ts, phi, at, half, w, offs):
    n = ts.shape[0]
    start = np.clip(at - half, 0, n - w)
    idx = start[:, None] + offs[None, :]
    dt = ts[idx] - ts[at][:, None]
    h = np.maximum(np.abs(dt).max(axis=1, keepdims=True), 1e-12)
    x = dt / h  # scaled for conditioning
    # Quartic: a cubic's error in phi'' is ~25x larger over the same window.
    V = x[..., None] ** np.arange(5)
    A = np.einsum("nwi,nwj->nij", V, V)
    bvec = np.einsum("nwi,nw->ni", V, phi[idx])
    c = np.linalg.solve(A + 1e-12 * np.eye(5), bvec[..., None])[..., 0]
    hh = h[:, 0]
    return c[:, 0], c[:, 1] / hh, 2 * c[:, 2] / hh**2


def observed_period(ts: np.ndarray, phi: np.ndarray) -> float | None:
    """The mean period of the record's oscillation, s, from the upward zero crossings of
    the detrended angle, or None when the record holds less than one full period.

    Judged from the record itself, not from a model: at large amplitude the period is far
    from the linearised one (about 20% at 135 degrees for a pendulum). A crossing counts
    only once the angle has gone from below -h to above +h (h: a tenth of its spread),
    so noise and encoder steps near zero do not add crossings. The angle's mean is taken
    out; a linear drift too once the record holds three periods (over less, a line would
    take part of the swing itself).
    """
    ts = np.asarray(ts, dtype=float)
    x = np.asarray(phi, dtype=float)
    if ts.shape[0] < 8:
        return None
    found = _crossings(ts, x - np.mean(x))
    if found is not None and found[1] >= 4:
        trend = np.polyval(np.polyfit(ts - ts[0], x, 1), ts - ts[0])
        found = _crossings(ts, x - trend) or found
    return found[0] if found is not None else None


def _crossings(ts, x) -> tuple[float, int] | None:
    """(mean period, number of upward crossings) of a zero-mean signal, or None."""
    h = 0.1 * float(np.std(x))
    if not h > 0:
        return None
    level = np.where(x > h, 1, np.where(x < -h, -1, 0))
    idx = np.flatnonzero(level)
    if idx.size < 2:
        return None
    lv = level[idx]
    ups = idx[1:][(lv[1:] == 1) & (lv[:-1] == -1)]
    if ups.size < 2:
        return None
    # The crossing itself: between the last sample <= 0 before each rise above +h and the
    # next one (the time to climb to +h grows as the swing decays, so it would bias).
    last = np.maximum.accumulate(np.where(x <= 0, np.arange(x.shape[0]), 0))[ups]
    x0, x1 = x[last], x[last + 1]
    tc = ts[last] + (ts[last + 1] - ts[last]) * (-x0) / np.where(x1 > x0, x1 - x0, 1.0)
    return float((tc[-1] - tc[0]) / (ups.size - 1)), int(ups.size)


#: Samples in each pseudo-residual of [`noise_level`][]: the combination of this many
#: consecutive samples that annihilates every polynomial of degree one less.
NOISE_STENCIL = 9


def noise_level(ts: np.ndarray, y: np.ndarray) -> float:
    """A channel's noise standard deviation (its unit), estimated from the record alone:
    the rms of normalised divided differences over [`NOISE_STENCIL`][] consecutive samples
    at their recorded times (each sample's weight `1 / prod_j (t_i - t_j)`, scaled to unit
    noise gain, so each is an unbiased estimate of the noise variance for white noise and
    is blind to any polynomial of degree `NOISE_STENCIL - 2`).

    Local quartic fits over a fixed fraction of a period, used before, followed the motion
    poorly where a record has few samples per turn (a fast crank at 50 Hz, 12 per turn): the
    estimate was up to 6x the noise, and every channel's weight and stall test with it.
    **Arguments:** `ts` (n,), s; `y` (n,). **Returns:** the level; 0 for under 3 samples."""
    n = ts.shape[0]
    k = min(NOISE_STENCIL, n)
    if k < 3:
        return 0.0
    idx = np.arange(n - k + 1)[:, None] + np.arange(k)[None]
    t = ts[idx] - ts[idx][:, :1]
    t = t / t[:, -1:]  # each window's times on [0, 1]: the weights stay well scaled
    diff = t[:, :, None] - t[:, None, :]
    diff[:, np.arange(k), np.arange(k)] = 1.0
    c = 1.0 / np.prod(diff, axis=2)
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    return float(np.sqrt(np.mean(np.sum(c * y[idx], axis=1) ** 2)))


#: A channel's noise level is at least this fraction of its data's spread (a noiseless
#: synthetic channel would otherwise get an infinite weight).
MIN_RELATIVE_NOISE = 1e-9


def channel_level(ts: np.ndarray, y: np.ndarray) -> float:
    """A channel's noise level for weighting (its unit): [`noise_level`][], at least
    [`MIN_RELATIVE_NOISE`][] of the data's spread and never 0. `ts` (n,), s; `y` (n,)."""
    return max(noise_level(ts, y), MIN_RELATIVE_NOISE * float(np.std(y)), 1e-300)


def half_window(ts: np.ndarray, period: float | None) -> int:
    """Half-width (samples) of the smoothing window: an eighth of `period` (s), or of a
    tenth of the record when no period is known."""
    # A quartic fitted over a quarter period follows a sinusoid closely while averaging
    # out the noise of the samples in it.
    dt = float(np.median(np.diff(ts)))
    span = (period if period is not None else (ts[-1] - ts[0]) / 10) / 8
    return int(np.clip(round(span / dt), 2, max(2, (ts.shape[0] - 1) // 2)))


@eqx.filter_jit
def _regressor(mech, phi, dphi, ddphi, ts, load, torque):
    """Rows Y (n, 7) and offsets e0 (n,) with `M phi'' + K phi'^2 - q = Y theta + e0`,
    theta = (m_c, m_p, m_s, I_c, I_p, k, c): the equation is linear in theta."""
    theta0 = jnp.stack([getattr(mech, n) for n in SCALE_GROUP])

    def eom(theta, p, dp, ddp, t):
        m = mech.replace(**dict(zip(SCALE_GROUP, theta)))
        return equation_residual(m, p, dp, ddp, t, load, torque)

    def row(p, dp, ddp, t):
        e = eom(theta0, p, dp, ddp, t)
        Yrow = jax.jacfwd(lambda th: eom(th, p, dp, ddp, t))(theta0)
        return Yrow, e - Yrow @ theta0

    return jax.vmap(row)(phi, dphi, ddphi, ts)


def regressor_samples(ts: np.ndarray, phi: np.ndarray, period: float | None):
    """The samples a regressor uses: `(phi, dphi, ddphi, t)`, each (m,) as jax arrays,
    smoothed (`smooth_derivatives`, window from `period`, s) at the record's samples
    away from its ends (where the window would be one-sided), thinned evenly to at most
    [`MAX_REGRESSOR_ROWS`][]."""
    ts = np.asarray(ts, dtype=float)
    n = ts.shape[0]
    half = half_window(ts, period)
    lo, hi = (half, n - half) if n > 2 * half + 2 else (0, n)
    step = max(1, -(-(hi - lo) // MAX_REGRESSOR_ROWS))
    at = np.arange(lo, hi, step)
    p, dp, ddp = smooth_derivatives(ts, phi, half, at)
    return tuple(device_array(x) for x in (p, dp, ddp, ts[at]))


def padded_rows(rows, lengths=None) -> tuple[tuple, np.ndarray]:
    """Each record's [`regressor_samples`][] `(phi, dphi, ddphi, t)` padded to a
    [`row_bucket`][crank_jax.identify.segments.row_bucket] length by repeating their last
    sample (so that records of other lengths reuse the programs that take them), and the
    mask (sum of the padded lengths,) of the rows that are the records' own.

    `lengths`: each record's sample count; the rows then take the ladder size of the
    record's (at most [`MAX_REGRESSOR_ROWS`][]) rather than of their own count, so that
    a record and its single-shooting row (the same ladder of its sample count) cross a
    ladder edge together: the rows lack the record's ends and would cross it elsewhere."""
    out, keep = [], []
    lengths = [None] * len(rows) if lengths is None else list(lengths)
    for row, length in zip(rows, lengths):
        n = len(row[0])
        size = row_bucket(n if length is None else max(n, min(length, MAX_REGRESSOR_ROWS)))
        extra = size - n
        out.append(tuple(np.pad(np.asarray(x, float), (0, extra), mode="edge") for x in row))
        keep.append(np.arange(n + extra) < n)
    return tuple(out), np.concatenate(keep)


def _rows(data: Data, load, torque, mech, period):
    (rows,), keep = padded_rows([regressor_samples(data.ts, data.phi, period)],
                                [len(data.ts)])
    Y, e0 = _regressor(mech, *rows, load, torque)
    return np.asarray(Y)[keep], np.asarray(e0)[keep]


def regressor_start(
    mech: SliderCrank,
    records: Sequence[tuple[Data, AbstractLoad, AbstractLoad]],
    free: Sequence[str],
    periods: Sequence[float | None] | None = None,
) -> tuple[dict[str, float], list[str]]:
    """Start values of the free masses, inertias, k and c from the linear regressor form.

    The equation of motion is linear in theta = (m_c, m_p, m_s, I_c, I_p, k, c):
    `Y(phi, phi', phi'', t) theta = tau(t) + P(t) lever(phi)`, with phi' and phi'' from
    local quartic fits to the data. The fixed members of theta and the known loads fix the
    scale; the free ones follow by linear least squares.

    **Arguments:** `mech`, the fixed values; `records`, `(data, load, torque)` per record;
    `free`, the free names; `periods`, each record's oscillation period, s (sets the
    smoothing window; default from the record's zero crossings).

    **Returns:** `(start values of the free members of theta, warnings)`; a member whose
    estimate is not positive (or a scale nothing fixes) keeps the scene's value, with a
    warning.
    """
    free_g = [n for n in SCALE_GROUP if n in free]
    if not free_g:
        return {}, []
    if periods is None:
        periods = [observed_period(d.ts, d.phi) for d, _, _ in records]
    rows = [_rows(d, lo, to, mech, per) for (d, lo, to), per in zip(records, periods)]
    Y, e0 = np.concatenate([r[0] for r in rows]), np.concatenate([r[1] for r in rows])
    theta = np.array([float(getattr(mech, n)) for n in SCALE_GROUP])
    fi = [SCALE_GROUP.index(n) for n in free_g]
    xi = [i for i in range(len(SCALE_GROUP)) if i not in fi]
    b = -(e0 + Y[:, xi] @ theta[xi])
    Yf = Y[:, fi]
    # Column scaling by the scene's values makes the least squares well posed in units.
    scale = np.where(theta[fi] > 0, theta[fi], 1.0)
    if np.linalg.norm(b) <= 1e-9 * np.linalg.norm(Yf @ scale):
        return {}, ["regressor start: nothing fixes the common scale (no known load and no "
                    "fixed mass, inertia, k or c), so the scene's values are used"]
    sol, *_ = np.linalg.lstsq(Yf * scale, b, rcond=1e-10)
    sol = sol * scale
    out, notes = {}, []
    for n, v in zip(free_g, sol):
        if np.isfinite(v) and v > 0:
            out[n] = float(v)
        else:
            notes.append(f"regressor start for {n} is {v:.3g} (not positive); the scene's "
                         "value is used instead")
    return out, notes
