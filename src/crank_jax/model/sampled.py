"""Loads made of samples: a measured load ([`SampledLoad`][]) and a load driven by a
measured input through a gain ([`InputLoad`][]), with the interpolations they share."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from . import trig
from .load_base import AbstractLoad, Nonsmooth, check_load_values
from .params import as_float_array
from .trig import Trig, form_field

__all__ = ["SampledLoad", "InputLoad", "is_sampled", "bind_input", "INTERPOLATIONS"]

#: Interpolations of a [`SampledLoad`][] (and of the `P`/`tau` columns of a data file).
INTERPOLATIONS: tuple[str, ...] = ("cubic", "linear", "zoh")


def _spline_second_derivatives(ts: Array, ys: Array) -> Array:
    """Second derivatives (n,) at the knots of the not-a-knot cubic spline through
    `(ts, ys)`: C2, and exact for cubic polynomials (so its error is O(h^4))."""
    n = ts.shape[0]
    h = jnp.diff(ts)
    delta = jnp.diff(ys) / h
    if n == 2:
        return jnp.zeros_like(ys)
    if n == 3:  # not-a-knot on three points: the parabola through them
        return jnp.full_like(ys, 2 * (delta[1] - delta[0]) / (h[0] + h[1]))
    # Rows for knots 1..n-2: h[i-1] M[i-1] + 2 (h[i-1] + h[i]) M[i] + h[i] M[i+1]
    # = 6 (delta[i] - delta[i-1]); M[0] and M[n-1] are eliminated with the not-a-knot
    # conditions (the third derivative is continuous at knots 1 and n-2).
    lo, hi = h[:-1], h[1:]
    diag = 2 * (lo + hi)
    dl = lo.at[0].set(0.0)
    du = hi.at[-1].set(0.0)
    diag = diag.at[0].add(h[0] * (1 + h[0] / h[1]))
    du = du.at[0].add(-h[0] ** 2 / h[1])
    diag = diag.at[-1].add(h[-1] * (1 + h[-1] / h[-2]))
    dl = dl.at[-1].add(-h[-1] ** 2 / h[-2])
    rhs = 6 * jnp.diff(delta)
    inner = jax.lax.linalg.tridiagonal_solve(dl, diag, du, rhs[:, None])[:, 0]
    first = inner[0] * (1 + h[0] / h[1]) - inner[1] * h[0] / h[1]
    last = inner[-1] * (1 + h[-1] / h[-2]) - inner[-2] * h[-1] / h[-2]
    return jnp.concatenate([first[None], inner, last[None]])


def _spline_coeffs(ts: Array, ys: Array) -> tuple[Array, Array, Array, Array]:
    """`(d, c, b, a)`, each (n-1,), as `diffrax.CubicInterpolation` takes them:
    `y = a + b u + c u^2 + d u^3` with `u = t - ts[i]` on interval i."""
    M = _spline_second_derivatives(ts, ys)
    h = jnp.diff(ts)
    b = jnp.diff(ys) / h - h * (2 * M[:-1] + M[1:]) / 6
    return (jnp.diff(M) / (6 * h), M[:-1] / 2, b, ys[:-1])


def _check_samples(ts: Array, vs: Array, interp: str) -> None:
    if interp not in INTERPOLATIONS:
        raise ValueError(f"SampledLoad interp {interp!r} is unknown; choose from "
                         f"{list(INTERPOLATIONS)}")
    if ts.ndim != 1 or vs.shape != ts.shape or ts.shape[0] < 2:
        raise ValueError(f"SampledLoad needs 1-D ts and values of equal length >= 2, got "
                         f"shapes {ts.shape} and {vs.shape}")
    for name, v in (("ts", ts), ("values", vs)):
        if not isinstance(v, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(v))):
            bad = int(np.argmin(np.isfinite(np.asarray(v))))
            raise ValueError(f"SampledLoad.{name} must be finite; sample {bad} is "
                             f"{float(np.asarray(v)[bad])} (fill or drop the gap)")
    if not isinstance(ts, jax.core.Tracer):
        d = np.diff(np.asarray(ts))
        if not np.all(d > 0):
            raise ValueError(f"SampledLoad.ts must increase strictly (sample "
                             f"{int(np.argmin(d)) + 1})")


class SampledLoad(AbstractLoad):
    """A measured load: samples `(ts, values)` joined by an interpolation, and held at
    the first and last value outside `[ts[0], ts[-1]]`.

    **Arguments:**

    - `ts`: sample times, s, shape `(n,)`, strictly increasing, `n >= 2`.
    - `values`: the samples (N or N*m), shape `(n,)`.
    - `interp` (static): `"cubic"` (default; the not-a-knot cubic spline, C2, exact for
      cubics, for measured smooth signals), `"linear"` (C0: its slope jumps at every
      sample) or `"zoh"` (zero-order hold, `X(t) = values[i]` on `[ts[i], ts[i+1])`:
      exact for a command that a digital controller holds between samples).

    The spline coefficients are computed once here (a tridiagonal solve, differentiable
    in `values`), not at every evaluation: build a new `SampledLoad` rather than
    replacing `values` with `eqx.tree_at`.
    """

    ts: Float[Array, " n"]
    values: Float[Array, " n"]
    coeffs: tuple[Array, Array, Array, Array] | None
    interp: str = eqx.field(static=True)

    def __init__(self, ts: ArrayLike, values: ArrayLike, interp: str = "cubic"):
        ts, values = as_float_array(ts), as_float_array(values)
        _check_samples(ts, values, interp)
        self.ts, self.values, self.interp = ts, values, interp
        self.coeffs = _spline_coeffs(ts, values) if interp == "cubic" else None

    def __call__(self, t: ArrayLike) -> Array:
        import diffrax

        t = jnp.asarray(t, dtype=self.ts.dtype)
        if self.interp == "linear":
            return jnp.interp(t, self.ts, self.values)
        if self.interp == "zoh":
            i = jnp.clip(jnp.searchsorted(self.ts, t, side="right") - 1, 0,
                         self.ts.shape[0] - 1)
            return self.values[i]
        spline = diffrax.CubicInterpolation(self.ts, self.coeffs)
        # Clamping holds the end values outside the samples (the polynomial would run off).
        return jnp.vectorize(spline.evaluate)(jnp.clip(t, self.ts[0], self.ts[-1]))

    def mean(self) -> Array:
        span = self.ts[-1] - self.ts[0]
        h = jnp.diff(self.ts)
        if self.interp == "linear":
            return jnp.trapezoid(self.values, self.ts) / span
        if self.interp == "zoh":
            return jnp.sum(self.values[:-1] * h) / span
        d, c, b, a = self.coeffs
        return jnp.sum(h * (a + h * (b / 2 + h * (c / 3 + h * d / 4)))) / span

    def nonsmooth(self) -> Nonsmooth:
        # zoh: the value jumps at every sample; linear: the slope does. The cubic spline
        # is C2, but its third derivative jumps at every knot, which a Dopri8 step across
        # a knot sees. Measured (experiments/sampled_load_bias.py, 250 Hz multisine):
        # ending steps at the knots gives Dopri8 a 220x smaller error with 9% fewer steps
        # at rtol 1e-8 (2.9x fewer at 1e-10), and Tsit5 a 2-3x smaller error for 1-16%
        # more steps.
        if self.interp == "zoh":
            return Nonsmooth(jump_ts=self.ts)
        return Nonsmooth(step_ts=self.ts)


class InputLoad(AbstractLoad):
    """A load driven by a measured input through a gain (a DC motor's torque from its
    voltage): `X(t) = X0 + X1 sin(2 pi freq_hz t + phase) + gain u(t)`.

    **Arguments:** `column` (static), the record's column holding `u`; `gain` (N or N*m
    per unit of `u`); `X0`, `X1`, `freq_hz`, `phase` as [`HarmonicLoad`][]'s; `signal`,
    the input's samples as a [`SampledLoad`][] (interpolated as a sampled load is), or
    `None` until a record supplies them ([`InputLoad.bind`][]). Calling it without a signal
    raises `ValueError` naming the column.
    """

    gain: Float[Array, ""] = eqx.field(converter=as_float_array)
    column: str = eqx.field(static=True)
    X0: Float[Array, ""] = eqx.field(converter=as_float_array, default=0.0)
    X1: Float[Array, ""] = eqx.field(converter=as_float_array, default=0.0)
    freq_hz: Float[Array, ""] = eqx.field(converter=as_float_array, default=0.0)
    phase: Float[Array, ""] = eqx.field(converter=as_float_array, default=0.0)
    signal: SampledLoad | None = None
    trig: Trig = form_field()  # how sin is traced (trig.py): a solver's choice

    def __check_init__(self):
        check_load_values(self, ("gain", "X0", "X1", "freq_hz", "phase"),
                          frequencies=("freq_hz",))

    def _u(self, t):
        if self.signal is None:
            raise ValueError(f"the input {self.column!r} has no samples: read the record with "
                             f"its {self.column!r} column (a record's inputs), or give "
                             "InputLoad a signal")
        return self.signal(t)

    def __call__(self, t: ArrayLike) -> Array:
        harmonic = self.X0 + self.X1 * trig.sin(2 * jnp.pi * self.freq_hz * t + self.phase,
                                                self.trig)
        return harmonic + self.gain * self._u(t)

    def mean(self) -> Array:
        u = self.signal.mean() if self.signal is not None else 0.0
        return self.X0 + self.gain * u

    def nonsmooth(self) -> Nonsmooth:
        return self.signal.nonsmooth() if self.signal is not None else Nonsmooth()

    def bind(self, ts: ArrayLike, values: ArrayLike, interp: str = "cubic") -> InputLoad:
        """This load with the input's samples `(ts, values)` (a record's column)."""
        return eqx.tree_at(lambda x: x.signal, self, SampledLoad(ts, values, interp),
                           is_leaf=lambda x: x is None)


def bind_input(load: AbstractLoad, inputs: dict, where: str, side: str = "load"
               ) -> AbstractLoad:
    """`load` with its measured input's samples from a record's `inputs` (column ->
    [`SampledLoad`][]), when it is an [`InputLoad`][] without them; `ValueError` naming
    the record (`where`) and the column when it lacks it."""
    if not isinstance(load, InputLoad) or load.signal is not None:
        return load
    if load.column not in inputs:
        raise ValueError(f"{where}: the {side} is driven by the input {load.column!r}, which "
                         f"the record does not carry; read it with load_data(..., "
                         f"inputs=[{load.column!r}])")
    return eqx.tree_at(lambda x: x.signal, load, inputs[load.column],
                       is_leaf=lambda x: x is None)


def is_sampled(load: AbstractLoad) -> bool:
    """True for a load made of samples (a [`SampledLoad`][], or an [`InputLoad`][] with
    its input's): its interpolation has kinks that solver steps must end at."""
    return isinstance(load, SampledLoad) or (isinstance(load, InputLoad)
                                             and load.signal is not None)
