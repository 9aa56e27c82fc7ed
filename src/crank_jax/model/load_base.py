"""The base of every load: [`AbstractLoad`][] and the [`Nonsmooth`][] times a solver's
steps must end at (see `loads.py` for the kinds and their table)."""

from __future__ import annotations

import abc
from typing import NamedTuple

import equinox as eqx
from jaxtyping import Array, ArrayLike

__all__ = ["AbstractLoad", "Nonsmooth"]


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
