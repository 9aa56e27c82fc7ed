"""Time-dependent loads: the slider force P(t) (N, along -x) and the crank torque tau(t)
(N*m, about +z). Each load is an `eqx.Module` with `__call__(t) -> value`; its kind (its
class) is static structure, its numbers are dynamic arrays, so amplitudes can be fitted
and vmapped without recompiling.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .params import as_float_array

__all__ = ["AbstractLoad", "NoLoad", "ConstantLoad", "HarmonicLoad", "SampledLoad", "as_load"]


class AbstractLoad(eqx.Module):
    """A scalar function of time. Subclasses are final."""

    @abc.abstractmethod
    def __call__(self, t: ArrayLike) -> Array:
        """The load at time `t` (s); returns an array of `t`'s shape."""

    @abc.abstractmethod
    def mean(self) -> Array:
        """The time-average, used by the linearisation (a constant load shifts xi)."""


class NoLoad(AbstractLoad):
    """No load at all. The dynamics skip every term it would multiply."""

    def __call__(self, t: ArrayLike) -> Array:
        return jnp.zeros_like(jnp.asarray(t, dtype=float))

    def mean(self) -> Array:
        return jnp.asarray(0.0)


class ConstantLoad(AbstractLoad):
    """`X(t) = value` (N or N*m)."""

    value: Float[Array, ""] = eqx.field(converter=as_float_array)

    def __call__(self, t: ArrayLike) -> Array:
        return self.value + jnp.zeros_like(jnp.asarray(t, dtype=float))

    def mean(self) -> Array:
        return self.value


class HarmonicLoad(AbstractLoad):
    """`X(t) = X0 + X1 sin(2 pi freq_hz t + phase)`.

    **Arguments:** `X0` mean and `X1` amplitude (N or N*m), `freq_hz` (Hz), `phase` (rad).
    """

    X0: Float[Array, ""] = eqx.field(converter=as_float_array)
    X1: Float[Array, ""] = eqx.field(converter=as_float_array)
    freq_hz: Float[Array, ""] = eqx.field(converter=as_float_array)
    phase: Float[Array, ""] = eqx.field(converter=as_float_array, default=0.0)

    def __call__(self, t: ArrayLike) -> Array:
        return self.X0 + self.X1 * jnp.sin(2 * jnp.pi * self.freq_hz * t + self.phase)

    def mean(self) -> Array:
        return self.X0


class SampledLoad(AbstractLoad):
    """A measured load, linearly interpolated between samples and held constant outside.

    **Arguments:** `ts`, sample times (s), shape `(n,)`, strictly increasing; `values`,
    shape `(n,)`.
    """

    ts: Float[Array, " n"] = eqx.field(converter=as_float_array)
    values: Float[Array, " n"] = eqx.field(converter=as_float_array)

    def __check_init__(self):
        ts, vs = self.ts, self.values
        if ts.ndim != 1 or vs.shape != ts.shape or ts.shape[0] < 2:
            raise ValueError(
                f"SampledLoad needs 1-D ts and values of equal length >= 2, got shapes "
                f"{ts.shape} and {vs.shape}"
            )
        if not isinstance(ts, jax.core.Tracer):
            t = np.asarray(ts)
            if not np.all(np.diff(t) > 0):
                i = int(np.argmin(np.diff(t)))
                raise ValueError(f"SampledLoad.ts must increase strictly (sample {i + 1})")

    def __call__(self, t: ArrayLike) -> Array:
        # jnp.interp is piecewise linear with a well-defined derivative almost everywhere,
        # which is what an adaptive solver and a gradient need from measured data.
        return jnp.interp(t, self.ts, self.values)

    def mean(self) -> Array:
        return jnp.trapezoid(self.values, self.ts) / (self.ts[-1] - self.ts[0])


def as_load(x: AbstractLoad | ArrayLike | None) -> AbstractLoad:
    """`None` -> [`NoLoad`][]; a number -> [`ConstantLoad`][]; a load -> itself."""
    if x is None:
        return NoLoad()
    if isinstance(x, AbstractLoad):
        return x
    return ConstantLoad(x)
