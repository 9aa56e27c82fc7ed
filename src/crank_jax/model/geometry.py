"""Geometry and kinematics of the slider-crank (paper eq. 1-15, with an offset slider line).

[`geometry_terms`][] is the one place the coupler angle, its phi-derivatives, the slider's
lever and the body positions are computed, from the parameters' [`Coefficients`][]; M, K,
q, the energy, the kinematics and the Newton-Euler form all read it. The slider runs along
the line `y = e` (the paper has `e = 0`); the loop closure `r sin(phi) - L sin(delta) = e`
gives `sin(delta)`. Primes are derivatives with respect to phi; dots with respect to time.
Every function works on scalars and broadcasts over arrays of phi and of the parameters.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .coefficients import Coefficients, coefficients
from .params import SliderCrank
from .structure import Structure
from .trig import LIBRARY, Trig, rsqrt, sincos

__all__ = ["Geometry", "geometry", "geometry_terms", "CouplerAngle", "coupler_angle",
           "Kinematics", "kinematics"]

_FULL = Structure()


class Geometry(NamedTuple):
    """Everything position-dependent, at one crank angle (each field has phi's shape,
    broadcast with the parameters'). Lengths in m, angles in rad."""

    sphi: Array
    """sin(phi)."""
    cphi: Array
    """cos(phi)."""
    sin: Array
    """sin(delta) = (r sin(phi) - e) / L."""
    cos: Array
    """cos(delta) = sqrt(1 - sin(delta)^2) > 0 because L > r + |e|."""
    d1: Array
    """delta' = r cos(phi) / (L cos(delta))."""
    d2: Array
    """delta'' = (L sin(delta) delta'^2 - r sin(phi)) / (L cos(delta))."""
    spd: Array
    """sin(phi + delta)."""
    cpd: Array
    """cos(phi + delta)."""
    lever: Array
    """-dx_s/dphi = r sin(phi) + L delta' sin(delta), m: the slider's lever arm."""
    dlever: Array
    """d lever / d phi = r cos(phi) + L (delta'' sin(delta) + delta'^2 cos(delta)), m."""
    x_c: Array
    """Crank centre of mass, x = s cos(phi); y = s sin(phi) is `y_c`."""
    y_c: Array
    x_p: Array
    """Coupler centre of mass, x = r cos(phi) + b cos(delta); y = r sin(phi) - b sin(delta)."""
    y_p: Array
    x_s: Array
    """Slider (wrist pin B) along x, r cos(phi) + L cos(delta); it sits at y = e."""

    @property
    def delta(self) -> Array:
        """The coupler angle, rad, in (-pi/2, pi/2)."""
        return jnp.arcsin(self.sin)


def geometry(mech: SliderCrank | Coefficients, phi: ArrayLike,
             structure: Structure = _FULL, trig: Trig = LIBRARY) -> Geometry:
    """The geometry at crank angle `phi` ([`geometry_terms`][] of the coefficients).

    **Arguments:** `mech`, the parameters or their [`Coefficients`][]; `phi`, crank angle
    in rad, any shape; `structure`: with `offset=False` the offset `e` is left out (it must
    then be 0); `trig`, a `trig.Trig`: how sin, cos and 1/sqrt are traced.

    **Returns:** a [`Geometry`][].
    """
    p = mech if isinstance(mech, Coefficients) else coefficients(mech, structure)
    return geometry_terms(p, phi, structure, trig)


def geometry_terms(p: Coefficients, phi: ArrayLike, structure: Structure = _FULL,
                   trig: Trig = LIBRARY) -> Geometry:
    """The geometry at crank angle `phi` from [`Coefficients`][], written for XLA's CPU
    fusion: the one place it is computed.

    `w = 1/cos(delta)` is a single `rsqrt` and every other quantity is a product of it:
    XLA does not duplicate "expensive" ops (sqrt, division) into several consumers, so
    each extra one becomes its own kernel in a solver's stage. sin, cos and rsqrt come
    from [`trig`][], in the form `trig` says: `"arithmetic"` (what a lockstep batch steps)
    vectorises over the members on XLA:CPU, `"library"` is JAX's own. The parameters enter only
    through [`Coefficients`][] (products of parameters alone, formed outside any step
    loop), and `cos(delta)^2` is `1 -` a polynomial in `sin(phi)` rather than
    `1 - sin(delta)^2`: with traced parameters the latter left `sin(delta) = (r/L) sin(phi)`
    as a kernel of its own in every stage, and `(1 - (e/L)^2) + ...` did the same to u
    (XLA duplicates an op of a constant and one value into several consumers, not an op
    of two values, so such a value read by both a cheap and an expensive op is a kernel).
    The whole right-hand side then fuses into ~2 kernels per Runge-Kutta stage, traced
    parameters or not. Unused fields cost nothing under `jit` (dead-code elimination).

    **Arguments:** `p`, the parameters' [`Coefficients`][]; `phi`, `structure` and `trig`
    as [`geometry`][]'s.
    """
    r, L, b, s = p.r, p.L, p.b, p.s
    phi = jnp.asarray(phi)
    sphi, cphi = sincos(phi, trig)
    if structure.offset:
        sd = p.lam * sphi - p.eL
        u = 1.0 - (p.eL2 + sphi * (p.lam2 * sphi - p.a1))
    else:
        sd = p.lam * sphi
        u = 1.0 - p.lam2 * (sphi * sphi)
    # u = cos(delta)^2 >= 1 - ((r + |e|)/L)^2 > 0: bounded away from zero, smooth.
    w = rsqrt(u, trig)
    cd = u * w
    d1 = p.lam * (cphi * w)
    # delta'' = (sin(delta) delta'^2 - (r/L) sin(phi)) / cos(delta), and
    # (r/L) sin(phi) = sin(delta) + e/L.
    d2 = sd * (d1 * d1 - 1.0)
    d2 = (d2 - p.eL if structure.offset else d2) * w
    # lever = r sin(phi) + L delta' sin(delta), and L sin(delta) = r sin(phi) - e.
    rs = r * sphi
    lever = rs * (1.0 + d1)
    if structure.offset:
        lever = lever - p.e * d1
    dlever = r * cphi + L * (d2 * sd + d1 * d1 * cd)
    spd = sphi * cd + cphi * sd
    cpd = cphi * cd - sphi * sd
    return Geometry(sphi, cphi, sd, cd, d1, d2, spd, cpd, lever, dlever,
                    s * cphi, s * sphi, r * cphi + b * cd, r * sphi - b * sd, r * cphi + L * cd)


class CouplerAngle(NamedTuple):
    """The coupler angle and its derivatives with respect to phi (all dimensionless/rad)."""

    delta: Array
    """delta, rad."""
    sin: Array
    """sin(delta) = (r sin(phi) - e) / L."""
    cos: Array
    """cos(delta) > 0 because L > r + |e|."""
    d1: Array
    """delta' = d delta / d phi = r cos(phi) / (L cos(delta))."""
    d2: Array
    """delta'' = (L sin(delta) delta'^2 - r sin(phi)) / (L cos(delta))."""


def coupler_angle(mech: SliderCrank, phi: ArrayLike) -> CouplerAngle:
    """Coupler angle delta(phi) and its first two phi-derivatives (paper eq. 1).

    **Arguments:** `mech`, the parameters; `phi`, crank angle in rad, any shape.

    **Returns:** a [`CouplerAngle`][] whose fields have the shape of `phi`.
    """
    g = geometry(mech, phi)
    return CouplerAngle(g.delta, g.sin, g.cos, g.d1, g.d2)


class Kinematics(NamedTuple):
    """Positions, velocities and accelerations of the three bodies in the x-y plane.

    Vectors have a trailing axis of size 2 (x, y); everything else has phi's shape. The
    slider moves along x only (at y = e). Units: m, m/s, m/s^2; rad, rad/s, rad/s^2.
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
    r, b, s = mech.r, mech.b, mech.s
    phi, dphi, ddphi = jnp.broadcast_arrays(*(jnp.asarray(x) for x in (phi, dphi, ddphi)))
    g = geometry(mech, phi)
    sphi, cphi, sd, cd, d1, d2 = g.sphi, g.cphi, g.sin, g.cos, g.d1, g.d2
    w2 = dphi * dphi

    r_c = _vec([g.x_c, g.y_c])
    v_c = _vec([-s * sphi, s * cphi]) * dphi[..., None]
    a_c = (_vec([-s * sphi, s * cphi]) * ddphi[..., None]
           + _vec([-s * cphi, -s * sphi]) * w2[..., None])

    J_p = _vec([-r * sphi - b * d1 * sd, r * cphi - b * d1 * cd])
    # Erratum 2: the y-component's b*delta'^2*sin(delta) term takes a + sign.
    abar_p = _vec([-r * cphi - b * d2 * sd - b * d1 * d1 * cd,
                   -r * sphi - b * d2 * cd + b * d1 * d1 * sd])
    r_p = _vec([g.x_p, g.y_p])
    v_p = J_p * dphi[..., None]
    a_p = J_p * ddphi[..., None] + abar_p * w2[..., None]

    return Kinematics(
        delta=g.delta, ddelta=d1 * dphi, dddelta=d1 * ddphi + d2 * w2,
        r_c=r_c, v_c=v_c, a_c=a_c, r_p=r_p, v_p=v_p, a_p=a_p,
        x_s=g.x_s, v_s=-g.lever * dphi, a_s=-g.lever * ddphi - g.dlever * w2,
    )
