"""The flow map of the crank over a time span T, the building block of shooting.

The span is a variable of the map, not of the solve: the field is rescaled to unit time,
`dy/ds = T f(T s, y)` on `s` in [0, 1], so T (a period, a half swing) is a parameter of
the field that forward mode, `jax.grad` and a root find differentiate like any other. The
integration is the library's own ([`solve`][crank_jax.solve.solvers.solve] with
`"dopri8-adaptive"`); its forward mode steps the variational equation beside the solution
(`solve/variational.py`), which gives the monodromy matrix of an orbit (`jax.jacfwd` of the
map) at the cost of a few solves.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from ..model.dynamics import CrankField
from ..runtime.lazy import lazy_import
from ..solve.adjoints import AbstractAdjoint, ForwardSensitivities
from ..solve.names import solver_named
from ..solve.solvers import solve

diffrax = lazy_import("diffrax")  # imported on first use (see lazy.py)

__all__ = ["Scaled", "flow", "flow_samples", "MAX_STEPS", "adaptive_solver", "packed_scaled"]

#: Step budget of one span (a forcing period or a half swing: ~100 steps at rtol 1e-10).
MAX_STEPS = 20_000


def adaptive_solver():
    """The solver of every flow here: `"dopri8-adaptive"` with rolled variational stages."""
    # Rolled stages in the variational solve: monodromy matrices and the implicit rule's
    # Jacobians are forward mode, whose unrolled program compiles ~2x longer.
    return solver_named("dopri8-adaptive").with_loop_stages()


class Scaled(eqx.Module):
    """`field` in unit time: `(s, y) -> T field(t0 + T s, y)` (rad/s -> rad per unit s)."""

    field: CrankField
    span: Array
    t0: Array

    def __call__(self, s, y, args=None):
        dy = self.field(self.t0 + self.span * s, y)
        return jax.tree_util.tree_map(lambda d: self.span * d, dy)


def packed_scaled(sc: Scaled) -> Scaled:
    """`sc` with its crank field packed: the form a solver steps (`prepare=`)."""
    # The crank's coefficients formed once, outside the step loop (CrankField.packed).
    return Scaled(sc.field.packed(), sc.span, sc.t0)


def flow_samples(field: CrankField, y0: Array, span: Array, s: Array, *, rtol, atol,
                 adjoint: AbstractAdjoint = ForwardSensitivities(),
                 t0: Array = 0.0) -> tuple[Array, Array]:
    """States at times `t0 + span * s` from `y0` at `t0`.

    **Arguments:** `field`, the crank's vector field; `y0` (2,), `(phi, dphi)` (rad,
    rad/s); `span`, T (s); `s` (n,), increasing fractions of T from 0; `rtol`, `atol`,
    the solver's tolerances; `adjoint`, an adjoint object: `ForwardSensitivities()`
    (jacfwd, root finds) or a `DiscreteAdjoint` (`jax.grad`).

    **Returns:** `(ys, ok)`: ys (n, 2), ok a bool scalar (the solve succeeded). A failed
    solve's samples are NaN, so a root find on them fails rather than converging on them.
    """
    sc = Scaled(field, jnp.asarray(span, float), jnp.asarray(t0, float))
    (phi, dphi), result, _ = solve(sc, adaptive_solver(), s, (y0[0], y0[1]),
                                   rtol=rtol, atol=atol, max_steps=MAX_STEPS, adjoint=adjoint,
                                   throw=False, prepare=packed_scaled, checks=False)
    ok = result == diffrax.RESULTS.successful
    ys = jnp.stack([phi, dphi], axis=-1)
    return jnp.where(ok, ys, jnp.nan), ok


def flow(field: CrankField, y0: Array, span: Array, *, rtol, atol, t0: Array = 0.0) -> Array:
    """The state (2,) at `t0 + span` from `y0` (2,) at `t0` (NaN if the solve failed)."""
    ys, _ = flow_samples(field, y0, span, jnp.array([0.0, 1.0]), rtol=rtol, atol=atol,
                         t0=t0)
    return ys[-1]
