"""The fit's compiled programs, and the residual views the optimisers see.

Every program is traced under [`checks_without_callbacks`][], so that none holds a host
callback and JAX's persistent cache can keep it between processes.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..persistent import PersistentProgram, checks_without_callbacks
from .problem import Problem

__all__ = ["checks_without_callbacks", "Program", "residuals_at", "jacobian_at", "Subspace",
           "Pinned"]


def Program(fn, name: str) -> PersistentProgram:
    """A compiled function of the fit, traced under [`checks_without_callbacks`][] and
    kept between processes (see [`PersistentProgram`][]). Call it, or `.lower(...)` it
    (for inspection)."""
    return PersistentProgram(fn, name, checks_without_callbacks)


def _residuals(problem, z):
    return problem.residuals(z)


def _jacobian(problem, z):
    def f(x):
        r, failed, steps = problem.residuals(x)
        return r, (r, failed, steps)

    J, (r, failed, steps) = jax.jacfwd(f, has_aux=True)(z)
    return r, failed, steps, J


#: `residuals_at(problem, z) -> (r, n_failed, steps)`, compiled.
residuals_at = Program(_residuals, "residuals")
#: `jacobian_at(problem, z) -> (r, n_failed, steps, J)`: the residuals with their
#: sensitivities `J = dr/dz` (N, p), by forward mode through the ODE solves (one program
#: for both: the fit needs both at its start and at its estimate).
jacobian_at = Program(_jacobian, "jacobian")


class Subspace(eqx.Module):
    """The residuals on the affine subspace `z = z0 + B w` (B: orthonormal columns), used
    to hold exactly flat directions (a common scale) fixed during the optimisation."""

    problem: Problem
    z0: Array
    B: Array

    def residuals(self, w):
        return self.problem.residuals(self.z0 + self.B @ w)

    def lift(self, w: np.ndarray) -> np.ndarray:
        """On the host: the problem's coordinates `z` (p,) of the point `w` (q,)."""
        return np.asarray(self.z0) + np.asarray(self.B) @ w

    def restrict(self, J: np.ndarray) -> np.ndarray:
        """On the host: the sensitivities `dr/dw` (N, q) from `dr/dz` (N, p)."""
        return J @ np.asarray(self.B)


class Pinned(eqx.Module):
    """The residuals with coordinate `j` held at `zj` (for profile likelihoods)."""

    problem: Problem
    zj: Array
    j: int = eqx.field(static=True)

    def full(self, zr):
        return jnp.concatenate([zr[:self.j], self.zj[None], zr[self.j:]])

    def residuals(self, zr):
        return self.problem.residuals(self.full(zr))

    def lift(self, zr: np.ndarray) -> np.ndarray:
        """On the host: the problem's coordinates (p,) of the free ones `zr` (p - 1,)."""
        return np.insert(np.asarray(zr, float), self.j, float(self.zj))

    def restrict(self, J: np.ndarray) -> np.ndarray:
        """On the host: the sensitivities to the free coordinates (N, p - 1)."""
        return np.delete(J, self.j, axis=1)
