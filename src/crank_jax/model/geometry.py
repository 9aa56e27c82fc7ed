"""Kinematics of the slider-crank (paper eq. 1-15), planar.

The coupler angle delta is measured so that the wrist pin B stays on the x axis:
`sin(delta) = (r/L) sin(phi)`. Primes are derivatives with respect to phi; dots with
respect to time. Every function works on scalars and broadcasts over arrays of phi.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .params import SliderCrank

__all__ = ["CouplerAngle", "coupler_angle", "Kinematics", "kinematics"]


class CouplerAngle(NamedTuple):
    """The coupler angle and its derivatives with respect to phi (all dimensionless/rad)."""

    delta: Array
    """delta, rad."""
    sin: Array
    """sin(delta) = (r/L) sin(phi)."""
    cos: Array
    """cos(delta) = sqrt(1 - (r/L)^2 sin^2(phi)) > 0 because L > r."""
    d1: Array
    """delta' = d delta / d phi = (r/L) cos(phi) / cos(delta)."""
    d2: Array
    """delta'' = (r/L) (delta' cos(phi) sin(delta) - sin(phi) cos(delta)) / cos(delta)^2."""


def coupler_angle(mech: SliderCrank, phi: ArrayLike) -> CouplerAngle:
    """Coupler angle delta(phi) and its first two phi-derivatives (paper eq. 1).

    **Arguments:** `mech`, the parameters; `phi`, crank angle in rad, any shape.

    **Returns:** a [`CouplerAngle`][] whose fields have the shape of `phi`.
    """
    lam = mech.r / mech.L
    sphi, cphi = jnp.sin(phi), jnp.cos(phi)
    sd = lam * sphi
    # Written with sqrt rather than cos(arcsin(.)): the argument 1 - sd^2 >= 1 - lam^2 > 0
    # is bounded away from zero whenever L > r, so this is smooth for every phi.
    cd = jnp.sqrt(1.0 - sd * sd)
    d1 = lam * cphi / cd
    d2 = lam * (d1 * cphi * sd - sphi * cd) / (cd * cd)
    return CouplerAngle(jnp.arcsin(sd), sd, cd, d1, d2)


class Kinematics(NamedTuple):
    """Positions, velocities and accelerations of the three bodies in the x-y plane.

    Vectors have a trailing axis of size 2 (x, y); everything else has phi's shape.
    Units: m, m/s, m/s^2; rad, rad/s, rad/s^2.
    """

    delta: Array
    ddelta: Array
    dddelta: Array
    r_c: Array
    v_c: Array
    a_c: Array
    r_p: Array
    v_p: Array
    a_p: Array
    x_s: Array
    v_s: Array
    a_s: Array


def _vec(xy: list[Array]) -> Array:
    return jnp.stack(jnp.broadcast_arrays(*xy), -1)


def kinematics(mech: SliderCrank, phi: ArrayLike, dphi: ArrayLike, ddphi: ArrayLike) -> Kinematics:
    """Body kinematics from the crank's motion (paper eq. 2-4, 9-15, with erratum 2).

    **Arguments:** `phi` (rad), `dphi` (rad/s), `ddphi` (rad/s^2), broadcastable arrays.

    **Returns:** a [`Kinematics`][]. Centre of mass of the crank `r_c`, of the coupler
    `r_p`, slider position `x_s` (scalar, along x) and their time derivatives; the coupler
    angle `delta` and its time derivatives.
    """
    r, L, b, s = mech.r, mech.L, mech.b, mech.s
    phi, dphi, ddphi = jnp.broadcast_arrays(*(jnp.asarray(x) for x in (phi, dphi, ddphi)))
    ca = coupler_angle(mech, phi)
    sphi, cphi = jnp.sin(phi), jnp.cos(phi)
    sd, cd, d1, d2 = ca.sin, ca.cos, ca.d1, ca.d2
    w2 = dphi * dphi

    r_c = _vec([s * cphi, s * sphi])
    v_c = _vec([-s * sphi, s * cphi]) * dphi[..., None]
    a_c = (_vec([-s * sphi, s * cphi]) * ddphi[..., None]
           + _vec([-s * cphi, -s * sphi]) * w2[..., None])

    J_p = _vec([-r * sphi - b * d1 * sd, r * cphi - b * d1 * cd])
    # Erratum 2: the y-component's b*delta'^2*sin(delta) term takes a + sign.
    abar_p = _vec([-r * cphi - b * d2 * sd - b * d1 * d1 * cd,
                        -r * sphi - b * d2 * cd + b * d1 * d1 * sd])
    r_p = _vec([r * cphi + b * cd, r * sphi - b * sd])
    v_p = J_p * dphi[..., None]
    a_p = J_p * ddphi[..., None] + abar_p * w2[..., None]

    J_s = -r * sphi - L * d1 * sd
    abar_s = -r * cphi - L * d2 * sd - L * d1 * d1 * cd
    x_s = r * cphi + L * cd
    return Kinematics(
        delta=ca.delta, ddelta=d1 * dphi, dddelta=d1 * ddphi + d2 * w2,
        r_c=r_c, v_c=v_c, a_c=a_c, r_p=r_p, v_p=v_p, a_p=a_p,
        x_s=x_s, v_s=J_s * dphi, a_s=J_s * ddphi + abar_s * w2,
    )
