"""k-step-ahead prediction for [`validate`][crank_jax.validate.validate]`(..., horizon=T)`.

After the initial-state window the record is cut into consecutive windows of `T` s (a
window holds the samples `a < t <= a + T`). Every window, the first included, estimates
its own state `(phi0, dphi0)` at its first sample from its head, its first
`max(MIN_SAMPLES samples, T / 10)`, and the model predicts the rest of the window open
loop. Only those predicted samples are scored. So a `T` at least the rest of the record
is one window: an open-loop prediction from the state its own head gives, not the
open-loop validation's (whose state is the initial-state window's).

The head's state fit is a small Levenberg-Marquardt (MINPACK's, through scipy) on the
head's samples, every channel weighted by its noise level
(`identify.start.noise_level`), started from the
state the previous window's prediction reaches at this window's first sample (for the
first window, the prediction from the initial-state window's state). It evaluates
the window predictions' compiled program, so one program serves every head and every
window: they are padded to one length (padded samples carry weight 0 and lie
microseconds after the last real one).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import least_squares

from .data import MIN_SAMPLES
from .model.outputs import output
from .solve.simulate import simulate

__all__ = ["HEAD_FRACTION", "Window", "cut", "Predictor", "estimate_state", "predict"]

#: The fraction of a window whose samples estimate its state (at least [`MIN_SAMPLES`][]).
HEAD_FRACTION = 0.1


class Window(NamedTuple):
    """One window: samples `start` to `stop - 1` of the record; the first `head` of them
    estimate its state."""

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
        k += 1
        if hi <= lo:
            continue  # a gap in the record longer than the horizon
        head = max(MIN_SAMPLES, int(np.searchsorted(
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


def estimate_state(pred: Predictor, y0: np.ndarray, ts: np.ndarray, mask: np.ndarray,
                   ys: np.ndarray):
    """The state at `ts[0]` that best explains the head's channels `ys` (C, m) at `ts`
    (m,) (`mask` (m,): 1 for a real sample, 0 for padding), from `y0` (2,).

    MINPACK's Levenberg-Marquardt (scipy, on the host, as the fit's) over the compiled
    [`predict`][] with a forward-difference Jacobian: the window predictions' own
    program, so the state fit compiles nothing of its own (a program differentiated
    through the solve took longer to compile than the rest of a validation). The
    difference step, 1e-5 relative, stays well above the solver's tolerance, whose step
    choices would make a smaller one noisy. **Returns:** the state (2,) and whether LM
    converged with every solve successful."""
    ts_j = jnp.asarray(ts)
    weight = np.asarray(pred.weight)[:, None] * np.asarray(mask)[None]
    ys = np.asarray(ys)
    failed = np.full(ys.size, 1e50)  # a failed solve: far worse than any state

    def residuals(y):
        out, _, ok = predict(pred, jnp.asarray(y), ts_j)
        return ((np.asarray(out) - ys) * weight).ravel() if bool(ok) else failed

    sol = least_squares(residuals, np.asarray(y0, float), method="lm", x_scale="jac",
                        diff_step=1e-5, ftol=1e-12, xtol=1e-12, gtol=1e-12, max_nfev=200)
    _, _, ok = predict(pred, jnp.asarray(sol.x), ts_j)
    return sol.x, bool(sol.status > 0) and bool(ok)


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
