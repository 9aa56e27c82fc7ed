"""k-step-ahead prediction for [`validate`][crank_jax.validate.validate]`(..., horizon=T)`.

After the initial-state window the record is cut into consecutive windows of `T` s (a
window holds the samples `a < t <= a + T`). The first window's state is the one estimated
on the initial-state window (that window is its head), so with `T` at least the rest of
the record this is the open-loop validation. Every later window estimates its own state
`(phi0, dphi0)` at its first sample from its head, its first `max(MIN_SAMPLES samples,
T / 10)`, and the model predicts the rest of the window open loop. Only those predicted
samples are scored.

The head's state fit is a small Levenberg-Marquardt (optimistix) on the head's samples,
every channel weighted by its noise level (`identify.start.noise_level`), started from the
state the previous window's prediction reaches at this window's first sample. It is one
compiled program for every window: heads and windows are padded to fixed lengths (padded
samples carry weight 0 and lie microseconds after the last real one).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .data import MIN_SAMPLES
from .model.outputs import output
from .solve.simulate import simulate

__all__ = ["HEAD_FRACTION", "Window", "cut", "Predictor", "estimate_state", "predict"]

#: The fraction of a window whose samples estimate its state (at least [`MIN_SAMPLES`][]).
HEAD_FRACTION = 0.1


class Window(NamedTuple):
    """One window: samples `start` to `stop - 1` of the record; the first `head` of them
    estimate its state (0 for the first window: the initial-state window is its head)."""

    start: int
    stop: int
    head: int
    t_start: float  # the window's left end a, s (its samples have a < t <= a + T)


def cut(ts: np.ndarray, t_init: float, horizon: float) -> list[Window]:
    """The windows of a record with sample times `ts` (n,), s, after `t_init`, each
    `horizon` s long. A last window with no sample left to predict after its head is
    dropped. Raises `ValueError` (naming `horizon`) when a full window has no sample to
    predict."""
    out = []
    k = 0
    while True:
        a = t_init + k * horizon
        if a >= ts[-1]:
            break
        lo = int(np.searchsorted(ts, a, side="right"))
        # Both ends from the same products, so that consecutive windows share a boundary.
        hi = int(np.searchsorted(ts, t_init + (k + 1) * horizon, side="right"))
        first = not out  # the first window with samples: the initial-state window is its head
        k += 1
        if hi <= lo:
            continue  # a gap in the record longer than the horizon
        head = 0 if first else max(MIN_SAMPLES, int(np.searchsorted(
            ts, a + HEAD_FRACTION * horizon, side="right")) - lo)
        if hi - lo <= head:
            if a + horizon < ts[-1]:
                raise ValueError(
                    f"horizon (--horizon) = {horizon:g} s holds {hi - lo} samples from t = "
                    f"{a:g} s, and the state is estimated from the first {head} of a window "
                    f"(at least {MIN_SAMPLES}): none is left to predict; lengthen the "
                    "horizon")
            continue
        out.append(Window(lo, hi, head, float(a)))
    return out


class Predictor(eqx.Module):
    """The model's channels along a solve from a state: the (fitted) mechanism and loads,
    the scene's solver, and each channel's sensor (`scale h + offset`, SI) and weight."""

    mech: eqx.Module
    load: eqx.Module
    torque: eqx.Module
    rtol: jax.Array
    atol: jax.Array
    scale: jax.Array  # (C,)
    offset: jax.Array  # (C,)
    weight: jax.Array  # (C,) 1 / noise level, relative to the first channel's
    names: tuple[str, ...] = eqx.field(static=True)
    solver: object = eqx.field(static=True)

    def __call__(self, y0: jax.Array, ts: jax.Array):
        """Channels (C, n) at `ts` (n,) from the state `y0 = (phi, dphi)` at `ts[0]`, the
        state (2, n), and whether the solve succeeded."""
        traj = simulate(self.mech, y0[0], y0[1], ts, load=self.load, torque=self.torque,
                        solver=self.solver, rtol=self.rtol, atol=self.atol, adjoint="forward",
                        throw=False, checks=False)
        h = jnp.stack([output(n, self.mech, ts, traj.phi, traj.dphi, self.load, self.torque)
                       for n in self.names])
        return (self.scale[:, None] * h + self.offset[:, None],
                jnp.stack([traj.phi, traj.dphi]), traj.ok)


@eqx.filter_jit
def estimate_state(pred: Predictor, y0: jax.Array, ts: jax.Array, mask: jax.Array,
                   ys: jax.Array):
    """The state at `ts[0]` that best explains the head's channels `ys` (C, m) at `ts`
    (m,) (`mask` (m,): 1 for a real sample, 0 for padding), from `y0` (2,). **Returns:**
    the state (2,) and whether LM converged with every solve successful."""
    def residuals(y, _):
        out, _, _ = pred(y, ts)
        return ((out - ys) * pred.weight[:, None] * mask[None]).ravel()

    sol = optx.least_squares(residuals, optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12), y0,
                             max_steps=256, throw=False)
    _, _, ok = pred(sol.value, ts)
    return sol.value, (sol.result == optx.RESULTS.successful) & ok


@eqx.filter_jit
def predict(pred: Predictor, y0: jax.Array, ts: jax.Array):
    """[`Predictor`][]`(y0, ts)`, compiled."""
    return pred(y0, ts)


def padded(ts: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """`ts` (m,) extended to `n` strictly increasing times (the extra ones microseconds
    after the last: sampled loads hold their last value there) and its mask (n,)."""
    m = ts.shape[0]
    step = 1e-6 * max(1.0, abs(float(ts[-1])))
    extra = float(ts[-1]) + step * np.arange(1, n - m + 1)
    return np.concatenate([ts, extra]), np.concatenate([np.ones(m), np.zeros(n - m)])


def pad_rows(ys: np.ndarray, n: int) -> np.ndarray:
    """Channels (C, m) padded with their last value to (C, n)."""
    return np.concatenate([ys, np.repeat(ys[:, -1:], n - ys.shape[1], axis=1)], axis=1)


def bucket(n: int) -> int:
    """`n` rounded up to a power of two (at least 8): the compiled programs' lengths, so
    windows a sample longer or shorter share them."""
    return max(8, 1 << math.ceil(math.log2(max(n, 1))))
