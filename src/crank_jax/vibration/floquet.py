"""Floquet multipliers: the eigenvalues of an orbit's monodromy matrix.

The monodromy matrix `Phi = d flow_T(y0) / d y0` (2 x 2: the state is `(phi, dphi)`) maps
a small perturbation of the orbit's start to its value one period later, so a
perturbation grows by `|lambda|` per period along each eigenvector: the orbit is stable
when every multiplier lies inside the unit circle. For a damped single-degree-of-freedom
system `det Phi = exp(-int chi/M dt) < 1`, so instability always comes from one real
multiplier leaving through +1 (a fold) or -1 (a period doubling, a parametric tongue).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array

from .flow import flow

__all__ = ["monodromy", "multipliers", "STABLE_MARGIN"]

#: A multiplier counts as outside the unit circle when its modulus exceeds 1 by this
#: much: the solver's rounding puts a neutral multiplier (an undamped orbit's) at 1 +- ~1e-9.
STABLE_MARGIN = 1e-6


def monodromy(field, y0: Array, period: Array, *, rtol, atol, t0: Array = 0.0) -> Array:
    """The monodromy matrix (2, 2) of the orbit starting at `y0` (2,) at `t0`, over
    `period` (s): forward mode through the solve (the variational equation)."""
    return jax.jacfwd(lambda y: flow(field, y, period, rtol=rtol, atol=atol, t0=t0))(y0)


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
