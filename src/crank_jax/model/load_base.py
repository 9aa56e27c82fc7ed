"""The base of every load: [`AbstractLoad`][] and the [`Nonsmooth`][] times a solver's
steps must end at (see `loads.py` for the kinds and their table)."""

from __future__ import annotations

import abc
from typing import NamedTuple

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, ArrayLike

__all__ = ["AbstractLoad", "Nonsmooth", "check_load_values"]


class Nonsmooth(NamedTuple):
    """Where a load is not smooth, as a step-size controller takes it (each (k,) times in
    s, or `None`): `step_ts`, where the load or one of its first three derivatives jumps
    (steps end exactly there); `jump_ts`, where the load itself jumps (steps end just
    before and restart just after)."""

    step_ts: Array | None = None
    jump_ts: Array | None = None


class AbstractLoad(eqx.Module):
    """A scalar function of time. Subclasses are final."""

    @abc.abstractmethod
    def __call__(self, t: ArrayLike) -> Array:
        """The load at time `t` (s); returns an array of `t`'s shape."""

    @abc.abstractmethod
    def mean(self) -> Array:
        """The time-average, used by the linearisation (a constant load shifts xi)."""

    def at(self, t: ArrayLike, phi: ArrayLike) -> Array:
        """The load at time `t` (s) with the crank at `phi` (rad): what the equation of
        motion uses. A load of time (every kind but an angle table) ignores `phi`."""
        return self(t)

    def nonsmooth(self) -> Nonsmooth:
        """Times where the load is not smooth enough for a high-order step (none here)."""
        return Nonsmooth()


def check_load_values(load: eqx.Module, fields: tuple[str, ...],
                      frequencies: tuple[str, ...] = ()) -> None:
    """`ValueError` naming `Class.field` if a concrete value of `fields` is not finite, or
    one of `frequencies` (Hz) is negative: what a scene file's `[load]` table refuses.

    Traced values (a sweep builds loads inside `jax.vmap`) and placeholders that JAX puts
    in a pytree are skipped: only concrete arrays can be read here."""
    for name in fields:
        v = getattr(load, name)
        if isinstance(v, jax.core.Tracer) or not isinstance(v, (jax.Array, np.ndarray,
                                                                 np.generic)):
            continue
        a = np.asarray(v)
        where = f"{type(load).__name__}.{name}"
        shown = a.item() if a.size == 1 else np.array2string(a, threshold=6)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{where} must be finite, got {shown}")
        if name in frequencies and np.any(a < 0):
            raise ValueError(f"{where} must be >= 0 Hz, got {shown} (for a sine of the "
                             "opposite sign add pi to the phase)")
