"""k-step-ahead prediction for
[`validate`][crank_jax.validation.kstep.validate]`(..., horizon=T)`.

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

from ..identify.start import channel_level
from ..model.outputs import output
from ..records.data import MIN_SAMPLES, Data
from ..simulation import simulate
from ..solve.adjoints import ForwardSensitivities

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
    _check_horizon(ts, horizon)
    out = []
    k, last = 0, -math.inf
    while True:
        a = t_init + k * horizon
        if a >= ts[-1]:
            break
        if not a > last:  # never true after _check_horizon; a guard against a hang
            raise ValueError(f"`horizon=` {horizon:g} s is below the float spacing of the "
                             f"record's times near t = {a:g} s; lengthen `horizon=`")
        last = a
        lo = int(np.searchsorted(ts, a, side="right"))
        # Both ends from the same products, so that consecutive windows share a boundary.
        hi = int(np.searchsorted(ts, t_init + (k + 1) * horizon, side="right"))
        k += 1
        if hi <= lo:
            # A gap in the record longer than the horizon: on to a window or two before
            # the one that holds the next sample (rounding never skips it), so a long gap
            # costs a few empty windows, not one per horizon.
            if lo < ts.size:
                k = max(k, math.ceil((ts[lo] - t_init) / horizon) - 2)
            continue
        head = max(MIN_SAMPLES, int(np.searchsorted(
            ts, a + HEAD_FRACTION * horizon, side="right")) - lo)
        if hi - lo <= head:
            if a + horizon < ts[-1]:
                raise ValueError(
                    f"`horizon=` {horizon:g} s holds {hi - lo} samples from t = "
                    f"{a:g} s, and the state is estimated from the first {head} of a window "
                    f"(at least {MIN_SAMPLES}): none is left to predict; lengthen "
                    "`horizon=`")
            continue
        out.append(Window(lo, hi, head, float(a)))
    return out


def _check_horizon(ts: np.ndarray, horizon: float) -> None:
    """Raise `ValueError` naming `horizon` when it is shorter than two of the record's
    shortest sample intervals: no window could then hold more than two samples, never
    enough for a state fit and a prediction, and a horizon below the float spacing of
    the times would never move the window loop on."""
    steps = np.diff(np.asarray(ts, dtype=float))
    shortest = float(np.min(steps)) if steps.size else math.inf
    if not horizon >= 2 * shortest:
        raise ValueError(
            f"`horizon=` {horizon:g} s is shorter than two sample intervals of "
            f"the record (its shortest is {shortest:g} s); a window needs at least "
            f"{MIN_SAMPLES + 1} samples: give `horizon=` at least "
            f"{(MIN_SAMPLES + 1) * shortest:g} s")


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
                        solver=self.solver, rtol=self.rtol, atol=self.atol,
                        adjoint=ForwardSensitivities(),
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

    # (Imported here: scipy.optimize costs ~0.45 s, a fifth of `import crank_jax`, which
    # `simulate` alone never needs; the fit's LM imports it where it runs too.)
    from scipy.optimize import least_squares

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


def scored_windows(ts: np.ndarray, t_init: float, horizon: float
                   ) -> tuple[list[Window], np.ndarray]:
    """The windows of [`cut`][crank_jax.validation.horizon.cut] and the mask (n,) of the
    samples they predict (each window's after its head); `ValueError` naming `horizon` if
    fewer than `MIN_SAMPLES` are left to predict."""
    windows = cut(ts, t_init, horizon)
    scored = np.zeros(ts.shape[0], bool)
    for w in windows:
        scored[w.start + w.head:w.stop] = True
    if int(scored.sum()) < MIN_SAMPLES:
        raise ValueError(f"`horizon=` {horizon:g} s leaves {int(scored.sum())} "
                         f"samples to predict; at least {MIN_SAMPLES} are needed: "
                         "lengthen `horizon=` or the record")
    return windows, scored


def predict_windows(scene, mech, load, torque, sensors, win: Data, windows, state0, predicted,
             warnings) -> list[dict]:
    """Predict every window (see [`crank_jax.validation.horizon`][]) into `predicted`, and the
    initial-state window from `state0` (its fitted state at the record's first sample);
    **returns** each window's row of `Validation.windows`."""
    ts = np.asarray(win.ts)
    ys = np.stack([np.asarray(y) for _, y in win.outputs()])  # (C, n)
    sigma = [channel_level(ts, y) for y in ys]
    pred = Predictor(mech, load, torque, jnp.asarray(scene.rtol, float),
                        jnp.asarray(scene.atol, float),
                        jnp.asarray([s.scale for s in sensors], float),
                        jnp.asarray([s.offset for s in sensors], float),
                        jnp.asarray([1.0 / s for s in sigma]),
                        tuple(s.name for s in sensors), scene.solver)
    # One compiled program serves every head's state fit and every window's prediction:
    # all are padded to one length (a window's prediction runs one sample into the next
    # window, whose state fit starts from the state it reaches there).
    n_win = bucket(max(w.stop - w.start for w in windows) + 1)
    # The initial-state window's fit, carried to the first window's first sample (the
    # first window's state fit starts there), in pieces of that length: no other program.
    stop0, guess = windows[0].start + 1, np.asarray(state0, float)
    for i in range(0, stop0 - 1, n_win - 1):
        j = min(i + n_win, stop0)
        t_piece, _ = padded(ts[i:j], n_win)
        out, state, solved = predict(pred, jnp.asarray(guess), jnp.asarray(t_piece))
        if not bool(solved):
            raise RuntimeError("the prediction's solve failed on the initial-state window; "
                               "check the scene's solver settings")
        out, state = np.asarray(out), np.asarray(state)
        for c, s in enumerate(sensors):
            predicted[s.name][i:j] = out[c, :j - i]
        guess = state[:, j - 1 - i]
    first = sensors[0].name
    rows, bad = [], []
    for j, w in enumerate(windows):
        t_head, mask = padded(ts[w.start:w.start + w.head], n_win)
        y_head = pad_rows(ys[:, w.start:w.start + w.head], n_win)
        y0, ok = estimate_state(pred, guess, t_head, mask, y_head)
        stop = min(windows[j + 1].start + 1 if j + 1 < len(windows) else w.stop, win.n)
        t_win, _ = padded(ts[w.start:stop], n_win)
        out, state, solved = predict(pred, jnp.asarray(y0), jnp.asarray(t_win))
        if not bool(solved):
            raise RuntimeError(f"the prediction's solve failed in the window from t = "
                               f"{w.t_start:g} s; check the scene's solver settings")
        out, state = np.asarray(out), np.asarray(state)
        for c, s in enumerate(sensors):
            predicted[s.name][w.start:w.stop] = out[c, :w.stop - w.start]
        if not bool(ok):
            bad.append(f"{w.t_start:g} s")
        rows.append(_row(w, float(y0[0]), float(y0[1]), bool(ok), ys[0], predicted[first],
                         win.ts))
        guess = state[:, stop - 1 - w.start]
    if bad:
        warnings.append(f"the state fit did not converge in {len(bad)} of {len(windows)} "
                        f"windows (from {', '.join(bad[:5])}{', ...' if len(bad) > 5 else ''}"
                        "); their predictions start from its last iterate")
    return rows


def _row(w, phi0: float, dphi0: float, ok: bool, y: np.ndarray, yhat: np.ndarray, ts
         ) -> dict:
    e = (y - yhat)[w.start + w.head:w.stop]
    return {"t_start": w.t_start, "t_end": float(ts[w.stop - 1]), "n_head": int(w.head),
            "n_predicted": int(w.stop - w.start - w.head), "phi0": phi0, "dphi0": dphi0,
            "rms": float(np.sqrt(np.mean(e**2))), "converged": ok}
