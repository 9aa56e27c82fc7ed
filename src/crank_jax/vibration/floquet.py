"""Floquet multipliers: the eigenvalues of an orbit's monodromy matrix.

The monodromy matrix `Phi = d flow_T(y0) / d y0` (2 x 2: the state is `(phi, dphi)`) maps
a small perturbation of the orbit's start to its value one period later, so a
perturbation grows by `|lambda|` per period along each eigenvector: the orbit is stable
when every multiplier lies inside the unit circle. For a damped single-degree-of-freedom
system `det Phi = exp(-int chi/M dt) < 1`, so instability always comes from one real
multiplier leaving through +1 (a fold) or -1 (a period doubling, a parametric tongue).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from ..runtime.lazy import lazy_import
from ..solve.adjoints import ForwardSensitivities
from ..solve.solvers import solve
from .flow import MAX_STEPS, Scaled, adaptive_solver, flow, packed_scaled

diffrax = lazy_import("diffrax")

__all__ = ["monodromy", "monodromy_at_rest", "multipliers", "STABLE_MARGIN"]

#: A multiplier counts as outside the unit circle when its modulus exceeds 1 by this
#: much: the solver's rounding puts a neutral multiplier (an undamped orbit's) at 1 +- ~1e-9.
STABLE_MARGIN = 1e-6


def monodromy(field, y0: Array, period: Array, *, rtol, atol, t0: Array = 0.0) -> Array:
    """The monodromy matrix (2, 2) of the orbit starting at `y0` (2,) at `t0`, over
    `period` (s): forward mode through the solve (the variational equation)."""
    return jax.jacfwd(lambda y: flow(field, y, period, rtol=rtol, atol=atol, t0=t0))(y0)


class _Tangent(eqx.Module):
    """The variational equation about a rest state: `dX/ds = A(s) X` for the 2 x 2 matrix
    X (as four scalars, column by column), `A` the scaled field's Jacobian at `y_eq`."""

    inner: Scaled
    y_eq: Array

    def __call__(self, s, x, args=None):
        def f(z):
            return jnp.stack(self.inner(s, (z[0], z[1])))

        cols = (jnp.stack(x[:2]), jnp.stack(x[2:]))
        d = [jax.jvp(f, (self.y_eq,), (c,))[1] for c in cols]
        return (d[0][0], d[0][1], d[1][0], d[1][1])


def monodromy_at_rest(field, y_eq: Array, period: Array, *, rtol, atol) -> Array:
    """The monodromy matrix (2, 2) of a rest state `y_eq` (2,) (an equilibrium for all t)
    over `period` (s): the variational equation solved as the state itself.

    Why not [`monodromy`][] at `y_eq`? There the solution stays at rest, so the step
    control, which sees only the solution, takes one step over the whole period and the
    sensitivities (the perturbations) are not resolved at all. Here the step control sees
    the perturbations themselves."""
    tg = _Tangent(Scaled(field, jnp.asarray(period, float), jnp.asarray(0.0)), y_eq)
    one, zero = jnp.ones_like(y_eq[0]), jnp.zeros_like(y_eq[0])
    x, result, _ = solve(tg, adaptive_solver(), jnp.array([0.0, 1.0]), (one, zero, zero, one),
                         rtol=rtol, atol=atol, max_steps=MAX_STEPS, adjoint=ForwardSensitivities(),
                         throw=False, prepare=lambda t: _Tangent(packed_scaled(t.inner), t.y_eq),
                         checks=False)
    mat = jnp.stack([jnp.stack([x[0][-1], x[2][-1]]), jnp.stack([x[1][-1], x[3][-1]])])
    return jnp.where(result == diffrax.RESULTS.successful, mat, jnp.nan)


def multipliers(phi_mat: Array) -> Array:
    """The two eigenvalues of a real 2 x 2 matrix, complex (2,), largest modulus first:
    closed form from the trace and determinant (no general eigen-solver, so it
    differentiates and runs on any backend)."""
    tr = phi_mat[0, 0] + phi_mat[1, 1]
    det = phi_mat[0, 0] * phi_mat[1, 1] - phi_mat[0, 1] * phi_mat[1, 0]
    disc = jnp.sqrt((tr * tr / 4 - det).astype(complex))
    lam = jnp.stack([tr / 2 + disc, tr / 2 - disc])
    order = jnp.argsort(-jnp.abs(lam))
    return lam[order]
