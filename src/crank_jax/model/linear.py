"""Linearisation about phi = 0 (paper eq. 33, corrected by erratum 1 and 3):

    mu phi'' + chi phi' + xi phi = tau(t)

    mu  = m_c s^2 + I_c + m_p r^2 (1 - b/L)^2 + I_p r^2/L^2
    chi = c
    xi  = k - g (m_c s + m_p r (1 + r b/L^2) + m_s r (1 + r/L)) - P r (1 + r/L)

The paper's coupler term `m_p g r (1 + b/L)` is wrong (erratum 1), and its "excitation"
`M_e = P r (1 + r/L) phi` is a stiffness, not a forcing (erratum 3): a constant P enters
xi, a harmonic P(t) pumps the stiffness parametrically. Here P is the load's mean.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jaxtyping import Array

from .loads import AbstractLoad, as_load
from .params import SliderCrank

__all__ = ["Linearization", "linearize"]


class Linearization(NamedTuple):
    """Coefficients of the linearised equation and derived quantities (SI units)."""

    mu: Array
    """Inertia at phi = 0, kg*m^2."""
    chi: Array
    """Damping, N*m*s/rad."""
    xi: Array
    """Effective stiffness at phi = 0 (shaft minus gravity and slider-force softening), N*m/rad."""
    omega_n: Array
    """Undamped natural frequency sqrt(xi/mu), rad/s (NaN when xi <= 0: no oscillation)."""
    zeta: Array
    """Damping ratio chi / (2 sqrt(xi mu)) (NaN when xi <= 0)."""
    stable: Array
    """Static stability of phi = 0: xi > 0."""
    k_crit: Array
    """Stiffness k at which xi = 0, N*m/rad: below it the crank falls over."""


def linearize(mech: SliderCrank, load: AbstractLoad | None = None) -> Linearization:
    """Linearise the equation of motion about phi = 0 with the slider force's mean.

    **Arguments:** `mech`; `load`, the slider force P (its `mean()` enters xi).

    **Returns:** a [`Linearization`][]; every field has the shape of the parameters.
    """
    P = as_load(load).mean()
    r, L, b, s, g = mech.r, mech.L, mech.b, mech.s, mech.g
    mu = mech.m_c * s**2 + mech.I_c + mech.m_p * r**2 * (1 - b / L) ** 2 + mech.I_p * r**2 / L**2
    weight = mech.m_c * s + mech.m_p * r * (1 + r * b / L**2) + mech.m_s * r * (1 + r / L)
    softening = g * weight + P * r * (1 + r / L)
    xi = mech.k - softening
    chi = mech.c + jnp.zeros_like(xi)
    # Only defined for a statically stable equilibrium; NaN says "no oscillation" honestly
    # rather than a silently clipped number.
    pos = jnp.where(xi > 0, xi, jnp.nan)
    omega_n = jnp.sqrt(pos / mu)
    zeta = chi / (2 * jnp.sqrt(pos * mu))
    return Linearization(mu, chi, xi, omega_n, zeta, xi > 0, softening + jnp.zeros_like(xi))
