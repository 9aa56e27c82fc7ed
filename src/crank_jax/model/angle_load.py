"""A measured load that follows the crank angle, not the clock ([`AngleLoad`][]): a gas
force from a pressure trace, a cam's follower force, anything a machine's own motion
times. Tabled by the angle it was measured at, it meets the model's crank at the right
angle even where the model's phase slips from the record's.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from .load_base import AbstractLoad, Nonsmooth
from .sampled import SampledLoad

__all__ = ["AngleLoad", "angle_problem"]


def angle_problem(angle: np.ndarray) -> tuple[int, str] | None:
    """Why `angle` (n,), rad, cannot index a load table, as `(sample, reason)`, or None:
    it must be finite and strictly monotone (a crank turning one way; an unwrapped
    angle)."""
    angle = np.asarray(angle, dtype=float)
    if angle.ndim != 1 or angle.shape[0] < 2 or not np.all(np.isfinite(angle)):
        return 0, f"needs a finite 1-D angle of >= 2 samples, got shape {angle.shape}"
    d = np.diff(angle)
    if np.all(d > 0) or np.all(d < 0):
        return None
    turn = 1.0 if np.sum(d) >= 0 else -1.0  # the record's overall direction
    i = int(np.argmax(turn * d <= 0)) + 1
    how = "stops" if d[i - 1] == 0 else "turns back"
    return i, (f"the angle is not strictly monotone: it {how} at sample {i} "
               f"({angle[i - 1]:.6g} -> {angle[i]:.6g} rad; a wrapped angle jumps back by a "
               "turn: unwrap it)")


class AngleLoad(AbstractLoad):
    """A load tabled by crank angle: `X(t, phi) = table(phi)`, N or N*m.

    **Fields:**

    - `table`: a [`SampledLoad`][] whose knots are crank angles, rad (the model's phi,
      increasing; a record taken turning backwards is reversed), and whose values are the
      load there. Beyond the knots the table holds its end values (a prediction that runs
      past the record's last angle sees the last measured load, not an extrapolation),
      unless `period` wraps it.
    - `record`: the load as recorded, a [`SampledLoad`][] in time, or None: what
      `load(t)` returns (a record's column written back, a plot); the equation of motion
      calls [`AngleLoad.at`][] instead.
    - `period` (static): None, or the period in rad (`2 pi`, `4 pi` for a four-stroke
      cycle) of a periodic load: the angle is taken modulo it, from the first knot, and
      the table must span at least one period.

    Differentiable in `phi` (the fit's Jacobians pass through it) and in the values; the
    table's length and interpolation are its only structure.
    """

    table: SampledLoad
    record: SampledLoad | None = None
    period: float | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if self.table.interp == "zoh":
            raise ValueError("AngleLoad's table cannot hold its values (interp='zoh'): a "
                             "jump at an angle has no time a solver's step can end at; use "
                             "'cubic' or 'linear'")
        if self.period is not None:
            if not (np.isfinite(self.period) and self.period > 0):
                raise ValueError(f"AngleLoad period must be > 0 rad, got {self.period}")
            ts = self.table.ts
            if not isinstance(ts, jax.core.Tracer) and float(ts[-1] - ts[0]) < self.period:
                raise ValueError(f"AngleLoad period = {self.period:g} rad is longer than "
                                 f"its table's {float(ts[-1] - ts[0]):g} rad: a record that "
                                 "covers one period is needed to wrap it")

    @classmethod
    def from_samples(cls, angle: ArrayLike, values: ArrayLike, ts: ArrayLike | None = None,
                     interp: str = "cubic", period: float | None = None) -> AngleLoad:
        """The load measured at crank angles `angle` (n,), rad, strictly monotone, with
        `values` (n,); `ts` (n,), s, the sample times (for `record`). `ValueError` naming
        the first sample where `angle` is not monotone."""
        angle = np.asarray(angle, dtype=float)
        values = np.asarray(values, dtype=float)
        problem = angle_problem(angle)
        if problem:
            raise ValueError(f"AngleLoad angle: {problem[1]}")
        record = None if ts is None else SampledLoad(ts, values, interp)
        order = slice(None) if angle[-1] > angle[0] else slice(None, None, -1)
        return cls(SampledLoad(angle[order], values[order], interp), record, period)

    def at(self, t: ArrayLike, phi: ArrayLike) -> Array:
        """The load with the crank at `phi` (rad), at any time `t` (s): the table at
        `phi` (wrapped by `period` when given), of the broadcast shape of both."""
        phi = jnp.asarray(phi, dtype=self.table.ts.dtype)
        if self.period is not None:
            lo = self.table.ts[0]
            phi = lo + jnp.mod(phi - lo, self.period)
        return self.table(phi) + jnp.zeros_like(jnp.asarray(t, dtype=phi.dtype))

    def __call__(self, t: ArrayLike) -> Array:
        if self.record is None:
            raise ValueError("this AngleLoad has no record in time: call load.at(t, phi), "
                             "the load at the crank angle phi")
        return self.record(t)

    def mean(self) -> Array:
        """The average over the table's angles (over a turn at a steady speed, the
        time-average), N or N*m."""
        return self.table.mean()

    def nonsmooth(self) -> Nonsmooth:
        # The kinks are at angles, which have no times before the solve.
        return Nonsmooth()
