"""The step-size controller of the fused adaptive solver ([`PIDController`][]), held by
`AdaptiveDopri8` as diffrax's solvers are given theirs.

Why not diffrax's `PIDController`? The fused solver's step loop runs a lockstep batch in
which every member has its own step size and decisions, on packed (..., N) states, and its
tolerances come with each solve (per member in a batch: `solve(rtol=, atol=)`), not with
the solver object. diffrax's controller steps one unbatched solution through
`adapt_step_size`, with its tolerances, its jump and clip handling and its error norm on
the solution's pytree. This one holds only the step-size law: the same formula as
diffrax's (`beta1 = (pcoeff + icoeff + dcoeff) / order`, `beta2 = -(pcoeff + 2 dcoeff) /
order`, `beta3 = dcoeff / order` on the last three scaled errors), with the fused solver's
habits kept (no growth right after a rejection, as scipy's DOP853; a non-finite error
shrinks by `factormin`). The default, an integral controller (`pcoeff = dcoeff = 0`,
`icoeff = 1`), is diffrax's default and what the solver always used.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

__all__ = ["PIDController"]


def _check(name: str, value, ok, want: str) -> None:
    # Python numbers are checked here; arrays (traced values) are the caller's to keep sane.
    if isinstance(value, (int, float)) and not ok(float(value)):
        raise ValueError(f"PIDController: {name} must be {want}, got {value!r}")


class PIDController(eqx.Module):
    """How an adaptive step's size follows its scaled error estimate `err` (accepted when
    `err <= 1`): the next step is `h * factor`,

        factor = clip(safety * err^-beta1 * err_prev^-beta2 * err_prev2^-beta3,
                      factormin, factormax),

    with `err_prev`, `err_prev2` the errors of the last two accepted steps (1 at the
    start), `beta1 = (pcoeff + icoeff + dcoeff) / order`, `beta2 = -(pcoeff + 2 dcoeff) /
    order`, `beta3 = dcoeff / order` (diffrax's `PIDController`, with `order` the method's);
    `err = 0` gives `factormax`, a non-finite `err` `factormin`, and right after a rejection
    an accepted step does not grow (`factor <= 1`).

    **Fields:** `pcoeff`, `dcoeff` (static: nonzero, the loop carries the earlier errors,
    another program), default 0; `icoeff`, default 1; `factormin`, `factormax`, default
    0.2 and 10; `safety`, default 0.9. The values may be Python numbers (constants of the
    program, as the defaults) or arrays (values of it, like any parameter).
    """

    pcoeff: float = eqx.field(static=True, default=0.0)
    icoeff: float | Array = 1.0
    dcoeff: float = eqx.field(static=True, default=0.0)
    factormin: float | Array = 0.2
    factormax: float | Array = 10.0
    safety: float | Array = 0.9

    def __check_init__(self):
        for name in ("pcoeff", "dcoeff"):
            if not isinstance(getattr(self, name), (int, float)):
                raise TypeError(f"PIDController: {name} must be a Python number (it is "
                                f"static), got {getattr(self, name)!r}")
        _check("icoeff", self.icoeff, lambda v: v > 0, "> 0")
        _check("factormin", self.factormin, lambda v: 0 < v <= 1, "in (0, 1]")
        _check("factormax", self.factormax, lambda v: v >= 1, ">= 1")
        _check("safety", self.safety, lambda v: 0 < v <= 1, "in (0, 1]")

    @property
    def _remembers(self) -> bool:
        """Whether the law reads earlier steps' errors (a proportional or derivative term)."""
        return self.pcoeff != 0 or self.dcoeff != 0

    def init(self, shape: tuple, dtype) -> tuple[Array, Array] | None:
        """The controller's state at the start, one per member (`shape`, e.g. (B, 1)): the
        last two accepted steps' errors (1), or None for an integral controller."""
        if not self._remembers:
            return None
        one = jnp.ones(shape, dtype)
        return one, one

    def factor(self, err: ArrayLike, ok, rejected, order: int, state):
        """`(factor, state)`: the step-size factor from the scaled error `err` (..., 1) of
        an attempt (`ok`: accepted; `rejected`: the attempt before it was), and the state
        after it. Values only: the caller stops the gradient of `err`."""
        beta1 = (self.pcoeff + self.icoeff + self.dcoeff) / order
        fac = self.safety * err ** -beta1
        if self._remembers:
            prev, prev2 = state
            beta2 = -(self.pcoeff + 2 * self.dcoeff) / order
            beta3 = self.dcoeff / order
            fac = fac * prev ** -beta2 * prev2 ** -beta3
            good = ok & jnp.isfinite(err) & (err > 0)
            state = (jnp.where(good, err, prev), jnp.where(good, prev, prev2))
        fac = jnp.where(err == 0, self.factormax, fac)
        # No growth right after a rejection (as scipy's DOP853).
        fac = jnp.where(ok & rejected, jnp.minimum(fac, 1.0), fac)
        fac = jnp.where(jnp.isfinite(err), jnp.clip(fac, self.factormin, self.factormax),
                        self.factormin)
        return fac, state

