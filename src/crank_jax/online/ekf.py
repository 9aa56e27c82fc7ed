"""An extended Kalman filter on the mechanism's state augmented with its free parameters,
with a CUSUM change test on the innovations: one `lax.scan` over a record's samples, so
that `jax.jit` compiles it once per structure and `jax.vmap` runs a fleet of records in
one program.

The augmented state is `x = (phi, dphi, z_1 .. z_p)`: the crank angle (rad) and speed
(rad/s) and the free parameters' coordinates (`z = ln value` for a field that cannot be
negative, else the value itself). Between two samples the state follows the equation of
motion (classical Runge-Kutta in `substeps` equal steps: a fixed cost per sample, and its
Jacobian by forward mode), the parameters a random walk (`q_param`, per sqrt(s), in their
coordinates: relative for the log ones). A channel reads `scale h(x) + offset`
([`output`][crank_jax.model.outputs.output]), with the channel's noise variance.

Why a Kalman filter rather than a sliding-window refit of the fit's problem: it costs a
few microseconds a sample with no optimiser in the loop, runs as one compiled program
whatever the record's length (chunks of a fixed shape), and its innovations are the
natural input of a change test. The sliding window's advantage, robustness to a
nonlinear start, is taken care of by the batch fit that starts it.

The change test is Page's CUSUM on the log-likelihood ratio of the normalised innovations
`e` (m channels) under "their variance grew by `lam`" against "white, unit variance":
`l = (1 - 1/lam) |e|^2 / 2 - m ln(lam) / 2`, `g = max(0, g + l)`, an alarm when `g > h`.
Lorden's bound makes the mean time between false alarms at least `exp(h)` samples, so
`h = ln(1 / alpha)` bounds the false-alarm probability per sample by `alpha`. At an alarm
the parameters' covariance gets its initial value back (the filter follows the new values
at once) and `g` restarts from 0.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from ..model.dynamics import acceleration
from ..model.load_base import AbstractLoad
from ..model.outputs import output
from ..model.params import SliderCrank

__all__ = ["TrackModel", "FilterSettings", "FilterState", "Steps", "run_filter",
           "init_state"]


class TrackModel(eqx.Module):
    """What the filter propagates and measures: the mechanism with its fixed values, the
    record's loads, the free names (static) and the channels' calibration.

    `names`: free mechanism fields; `log`: each in log coordinates; `channels`: output
    names (`phi`, `x_s`, ...); `scale`, `offset` (C,): each channel's calibration, SI;
    `substeps`: Runge-Kutta steps per sample interval."""

    mech: SliderCrank
    load: AbstractLoad
    torque: AbstractLoad
    scale: Array
    offset: Array
    names: tuple[str, ...] = eqx.field(static=True)
    log: tuple[bool, ...] = eqx.field(static=True)
    channels: tuple[str, ...] = eqx.field(static=True)
    substeps: int = eqx.field(static=True)

    def mech_at(self, z: Array) -> SliderCrank:
        """The mechanism with the free parameters at coordinates `z` (p,)."""
        return self.mech.replace(**{n: jnp.exp(z[i]) if lg else z[i]
                                    for i, (n, lg) in enumerate(zip(self.names, self.log))})

    def propagate(self, x: Array, t: Array, dt: Array) -> Array:
        """The augmented state `dt` s after `x` at time `t` (parameters unchanged)."""
        mech = self.mech_at(x[2:])
        h = dt / self.substeps

        def f(s, y):
            return jnp.stack([y[1], acceleration(mech, y[0], y[1], s, self.load, self.torque)])

        def rk4(k, y):
            s = t + k * h
            k1 = f(s, y)
            k2 = f(s + h / 2, y + h / 2 * k1)
            k3 = f(s + h / 2, y + h / 2 * k2)
            k4 = f(s + h, y + h * k3)
            return y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)

        y = jax.lax.fori_loop(0, self.substeps, rk4, x[:2])
        return jnp.concatenate([y, x[2:]])

    def measure(self, x: Array, t: Array) -> Array:
        """Each channel's reading (C,) of the augmented state `x` at time `t`, SI."""
        mech = self.mech_at(x[2:])
        return jnp.stack([self.scale[c] * output(n, mech, t, x[0], x[1], self.load,
                                                 self.torque) + self.offset[c]
                          for c, n in enumerate(self.channels)])


class FilterSettings(NamedTuple):
    """The filter's noise model and change test (arrays: a `vmap` may batch them).

    `R` (C,): each channel's noise variance, SI^2; `q_accel`: the state's acceleration
    noise, (rad/s^2)^2 per Hz (what the model misses between samples); `q_param` (p,):
    each parameter's random-walk variance per second, in its coordinate; `P_param` (p, p):
    the parameters' covariance restored at an alarm; `threshold`: the CUSUM's `h`;
    `lam`: the variance ratio the test looks for."""

    R: Array
    q_accel: Array
    q_param: Array
    P_param: Array
    threshold: Array
    lam: Array


class FilterState(NamedTuple):
    """The filter's carry: augmented state `x` (2 + p,) and covariance `P`, the time of
    the last sample `t`, the CUSUM statistic `g` and the samples since it last left 0."""

    x: Array
    P: Array
    t: Array
    g: Array
    run: Array


class Steps(NamedTuple):
    """Per sample: the filtered state (n, 2 + p) and its standard errors, the normalised
    innovations (n, C), the CUSUM statistic and the alarms (n,), and the samples since
    the statistic last left 0 (an alarm's change point is that many samples back)."""

    x: Array
    se: Array
    innovation: Array
    g: Array
    alarm: Array
    run: Array


def init_state(x0: Array, P0: Array, t0: Array) -> FilterState:
    """The carry at the first sample (time `t0`, no prediction before it)."""
    return FilterState(jnp.asarray(x0, float), jnp.asarray(P0, float),
                       jnp.asarray(t0, float), jnp.zeros(()), jnp.zeros((), jnp.int32))


def _step(model: TrackModel, s: FilterSettings, state: FilterState, sample):
    t, y, valid = sample
    dt = jnp.where(valid, t - state.t, 0.0)
    # (The value rides along as the Jacobian's aux: one propagation, not two.)
    F, x = jax.jacfwd(lambda v: (model.propagate(v, state.t, dt),) * 2, has_aux=True)(state.x)
    Q = jnp.diag(jnp.concatenate([jnp.stack([0.0, s.q_accel]), s.q_param])) * dt
    P = F @ state.P @ F.T + Q
    H, yhat = jax.jacfwd(lambda v: (model.measure(v, t),) * 2, has_aux=True)(x)
    nu = y - yhat
    S = H @ P @ H.T + jnp.diag(s.R)
    L = jnp.linalg.cholesky(S)
    e = jax.scipy.linalg.solve_triangular(L, nu, lower=True)
    K = jax.scipy.linalg.cho_solve((L, True), H @ P).T
    IKH = jnp.eye(x.shape[0]) - K @ H
    P_new = IKH @ P @ IKH.T + K @ jnp.diag(s.R) @ K.T  # Joseph's form: stays symmetric
    x_new = x + K @ nu
    m = y.shape[0]
    llr = 0.5 * (1 - 1 / s.lam) * jnp.sum(e**2) - 0.5 * m * jnp.log(s.lam)
    g = jnp.maximum(0.0, state.g + llr)
    run = jnp.where(g > 0, state.run + 1, 0)
    alarm = valid & (g > s.threshold)
    reset = jnp.zeros_like(P_new).at[2:, 2:].set(s.P_param)
    P_new = jnp.where(alarm, P_new + reset, P_new)
    new = FilterState(x_new, 0.5 * (P_new + P_new.T), t, jnp.where(alarm, 0.0, g),
                      jnp.where(alarm, 0, run))
    new = jax.tree.map(lambda a, b: jnp.where(valid, a, b), new, state)
    # At an alarm the statistic and its run as they stood, before the restart.
    out = Steps(new.x, jnp.sqrt(jnp.clip(jnp.diag(new.P), 0.0)), jnp.where(valid, e, 0.0),
                jnp.where(alarm, g, new.g), alarm, jnp.where(alarm, run, new.run))
    return new, out


@eqx.filter_jit
def run_filter(model: TrackModel, settings: FilterSettings, state: FilterState, ts: Array,
               ys: Array, valid: Array) -> tuple[FilterState, Steps]:
    """Filter the samples `ts` (n,), s, `ys` (n, C), SI, from `state`; samples where
    `valid` (n,) is False (a chunk's padding) leave the carry as it was.

    **Returns:** the carry after the last sample and the per-sample [`Steps`][]."""
    # (Not unrolled: 4 or 8 samples per iteration measured 1.4-1.5x slower on the CPU.)
    return jax.lax.scan(lambda c, smp: _step(model, settings, c, smp), state,
                        (ts, ys, valid))
