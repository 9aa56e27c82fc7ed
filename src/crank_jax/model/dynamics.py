"""The minimal form of the equation of motion (paper eq. 30, corrected):

    M(phi) phi'' + K(phi) phi'^2 = q(phi, phi', t)

`M`, `K` and `q` are hand-written from the paper. The tests check them against autodiff
(`K = M'/2`), the global Newton-Euler form (`M = J^T Mbar J`) and a potential
(`q_conservative = -dV/dphi`).

A [`Structure`][] says which terms a scene has. It is static (a hashable dataclass of
bools), so the compiled program contains only the terms that are used: a crank-only
pendulum traces no coupler or slider arithmetic, a scene without loads no load calls.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from .geometry import coupler_angle
from .loads import AbstractLoad, NoLoad, as_load
from .params import SliderCrank

__all__ = [
    "Structure", "mass", "coriolis", "generalized_force", "acceleration", "energy",
    "kinetic_energy", "potential_energy", "power_in", "CrankField", "fused_acceleration",
]


@dataclasses.dataclass(frozen=True)
class Structure:
    """Which terms of the equation of motion are present (static, hashable).

    `Structure.of(mech)` reads it from concrete parameters: a body whose masses and inertia
    are all zero is a body the scene does not have. `Structure()` keeps every term, which is
    always correct and is the default everywhere.
    """

    crank: bool = True
    """m_c s^2 + I_c and m_c s (the crank's inertia and weight)."""
    coupler: bool = True
    """m_p or I_p nonzero."""
    slider: bool = True
    """m_s nonzero."""
    gravity: bool = True
    """g nonzero."""
    spring: bool = True
    """k nonzero."""
    damper: bool = True
    """c nonzero."""

    @classmethod
    def of(cls, mech: SliderCrank) -> Structure:
        """The structure of concrete (non-traced) parameters. Batched fields count a term
        as present if any member of the batch has it."""
        names = ("m_c", "s", "m_p", "I_p", "m_s", "g", "k", "c")
        v = {n: np.asarray(getattr(mech, n)) for n in names}
        nz = lambda x: bool(np.any(x != 0))  # noqa: E731
        return cls(
            crank=True,  # M > 0 requires crank inertia; it is always present.
            coupler=nz(v["m_p"]) or nz(v["I_p"]),
            slider=nz(v["m_s"]),
            gravity=nz(v["g"]),
            spring=nz(v["k"]),
            damper=nz(v["c"]),
        )

    def union(self, other: Structure) -> Structure:
        """A structure with every term that either has."""
        return Structure(*(a or b for a, b in zip(dataclasses.astuple(self),
                                                  dataclasses.astuple(other))))


_FULL = Structure()


def _slider_lever(mech: SliderCrank, phi, ca):
    """`r sin(phi) + L delta' sin(delta) = -dx_s/dphi`: the slider's lever arm, m."""
    return mech.r * jnp.sin(phi) + mech.L * ca.d1 * ca.sin


def mass(mech: SliderCrank, phi: ArrayLike, structure: Structure = _FULL) -> Array:
    """Generalised mass M(phi), kg*m^2 (paper eq. 30):

        M = m_c s^2 + I_c + m_p (r^2 - 2 r b delta' cos(phi+delta) + b^2 delta'^2)
            + I_p delta'^2 + m_s (r sin(phi) + L delta' sin(delta))^2

    **Arguments:** `mech`; `phi`, crank angle (rad), any shape; `structure`, the static
    set of terms to include. **Returns:** an array of `phi`'s shape, always > 0.
    """
    phi = jnp.asarray(phi)
    ca = coupler_angle(mech, phi)
    M = mech.m_c * mech.s**2 + mech.I_c + jnp.zeros_like(phi)
    if structure.coupler:
        r, b, d1 = mech.r, mech.b, ca.d1
        # cos(phi + delta), expanded so delta itself (an arcsin) is never needed.
        cpd = jnp.cos(phi) * ca.cos - jnp.sin(phi) * ca.sin
        M = M + mech.m_p * (r * r - 2 * r * b * d1 * cpd + b * b * d1 * d1) + mech.I_p * d1 * d1
    if structure.slider:
        M = M + mech.m_s * _slider_lever(mech, phi, ca) ** 2
    return M


def coriolis(mech: SliderCrank, phi: ArrayLike, structure: Structure = _FULL) -> Array:
    """Velocity-squared coefficient K(phi) = M'(phi)/2, kg*m^2/rad (paper eq. 30):

        K = m_p (r b (delta'(1+delta') sin(phi+delta) - delta'' cos(phi+delta))
                 + b^2 delta' delta'')
            + m_s (r sin(phi) + L delta' sin(delta))
                  (r cos(phi) + L (delta'' sin(delta) + delta'^2 cos(delta)))
            + I_p delta' delta''

    **Returns:** an array of `phi`'s shape.
    """
    phi = jnp.asarray(phi)
    K = jnp.zeros_like(phi) * mech.r
    if not (structure.coupler or structure.slider):
        return K
    ca = coupler_angle(mech, phi)
    d1, d2 = ca.d1, ca.d2
    if structure.coupler:
        r, b = mech.r, mech.b
        sphi, cphi = jnp.sin(phi), jnp.cos(phi)
        spd = sphi * ca.cos + cphi * ca.sin
        cpd = cphi * ca.cos - sphi * ca.sin
        K = K + mech.m_p * (r * b * (d1 * (1 + d1) * spd - d2 * cpd) + b * b * d1 * d2)
        K = K + mech.I_p * d1 * d2
    if structure.slider:
        L = mech.L
        lever = _slider_lever(mech, phi, ca)
        K = K + mech.m_s * lever * (mech.r * jnp.cos(phi) + L * (d2 * ca.sin + d1 * d1 * ca.cos))
    return K


def generalized_force(
    mech: SliderCrank,
    phi: ArrayLike,
    dphi: ArrayLike,
    t: ArrayLike = 0.0,
    load: AbstractLoad | None = None,
    torque: AbstractLoad | None = None,
    structure: Structure = _FULL,
) -> Array:
    """Generalised force q(phi, phi', t), N*m (paper eq. 30 plus the crank torque tau):

        q = g (m_c s sin(phi) + m_p (r sin(phi) + b delta' sin(delta))
               + m_s (r sin(phi) + L delta' sin(delta)))
            + P(t) (r sin(phi) + L delta' sin(delta)) - k phi - c phi' + tau(t)

    **Arguments:** `phi` (rad), `dphi` (rad/s), `t` (s), broadcastable; `load`, the
    slider force P(t) in N along -x; `torque`, the crank torque tau(t) in N*m about +z;
    `None` means none. **Returns:** an array of the broadcast shape.
    """
    load, torque = as_load(load), as_load(torque)
    phi, dphi = jnp.asarray(phi), jnp.asarray(dphi)
    sphi = jnp.sin(phi)
    q = jnp.zeros(jnp.broadcast_shapes(phi.shape, dphi.shape, jnp.shape(t))) * mech.r
    has_P = not isinstance(load, NoLoad)
    d1 = sd = lever = None
    if structure.gravity or has_P:
        ca = coupler_angle(mech, phi)
        d1, sd = ca.d1, ca.sin
        lever = _slider_lever(mech, phi, ca)
    return q + generalized_force_terms(mech, phi, dphi, t, load, torque, structure,
                                       sphi, d1, sd, lever)


def generalized_force_terms(mech, phi, dphi, t, load, torque, structure, sphi, d1, sd, lever):
    """The terms of q from precomputed geometry: `sphi = sin(phi)`, `d1 = delta'`,
    `sd = sin(delta)` and `lever = r sin(phi) + L delta' sin(delta)` (the last three may be
    None when the structure has no term that needs them). Shared by `generalized_force` and
    the fused right-hand side of the uniform solver, so q is written once."""
    q = 0.0
    if structure.gravity:
        weight_arm = mech.m_c * mech.s * sphi
        if structure.coupler:
            weight_arm = weight_arm + mech.m_p * (mech.r * sphi + mech.b * d1 * sd)
        if structure.slider:
            weight_arm = weight_arm + mech.m_s * lever
        q = q + mech.g * weight_arm
    if not isinstance(load, NoLoad):
        q = q + load(t) * lever
    if structure.spring:
        q = q - mech.k * phi
    if structure.damper:
        q = q - mech.c * dphi
    if not isinstance(torque, NoLoad):
        q = q + torque(t)
    return q


def acceleration(
    mech: SliderCrank,
    phi: ArrayLike,
    dphi: ArrayLike,
    t: ArrayLike = 0.0,
    load: AbstractLoad | None = None,
    torque: AbstractLoad | None = None,
    structure: Structure = _FULL,
) -> Array:
    """Crank angular acceleration phi'' = (q - K phi'^2) / M, rad/s^2."""
    M = mass(mech, phi, structure)
    K = coriolis(mech, phi, structure)
    q = generalized_force(mech, phi, dphi, t, load, torque, structure)
    return (q - K * jnp.square(dphi)) / M


def kinetic_energy(mech: SliderCrank, phi: ArrayLike, dphi: ArrayLike) -> Array:
    """T = M(phi) phi'^2 / 2, J."""
    return 0.5 * mass(mech, phi) * jnp.square(dphi)


def potential_energy(mech: SliderCrank, phi: ArrayLike) -> Array:
    """V = g (m_c x_c + m_p x_p + m_s x_s) + k phi^2 / 2, J (gravity along -x)."""
    phi = jnp.asarray(phi)
    ca = coupler_angle(mech, phi)
    cphi = jnp.cos(phi)
    x_c = mech.s * cphi
    x_p = mech.r * cphi + mech.b * ca.cos
    x_s = mech.r * cphi + mech.L * ca.cos
    return mech.g * (mech.m_c * x_c + mech.m_p * x_p + mech.m_s * x_s) + 0.5 * mech.k * phi**2


def energy(mech: SliderCrank, phi: ArrayLike, dphi: ArrayLike) -> Array:
    """Mechanical energy T + V, J. Constant when c = P = tau = 0."""
    return kinetic_energy(mech, phi, dphi) + potential_energy(mech, phi)


def power_in(
    mech: SliderCrank, phi: ArrayLike, dphi: ArrayLike, t: ArrayLike = 0.0,
    load: AbstractLoad | None = None, torque: AbstractLoad | None = None,
) -> Array:
    """Power of the non-conservative forces, W: `d(T+V)/dt = power_in`.

    `(P(t) (r sin(phi) + L delta' sin(delta)) - c phi' + tau(t)) phi'`.
    """
    load, torque = as_load(load), as_load(torque)
    ca = coupler_angle(mech, phi)
    gen = load(t) * _slider_lever(mech, phi, ca) - mech.c * dphi + torque(t)
    return gen * dphi


def fused_acceleration(mech: SliderCrank, phi, dphi, t, load, torque,
                       structure: Structure):
    """phi'' = (q - K phi'^2) / M, rad/s^2: the same function as `acceleration`, written
    for XLA's CPU fusion.

    `acceleration` computes cos(delta) with a `sqrt` and delta', delta'' and phi'' with
    three divisions. XLA does not duplicate such "expensive" ops into several consumers, so
    each becomes its own kernel: ~4 kernels per evaluation, ~9 per Runge-Kutta stage once the
    stage sums are counted. Here `w = 1/cos(delta)` is one `rsqrt`, everything else is a
    product of it, and the only division is the last one, so a stage is ~3 kernels.
    Equal to `acceleration` to rounding (tested); `structure` skips terms as there.
    """
    has_P = not isinstance(load, NoLoad)
    sphi, cphi = jnp.sin(phi), jnp.cos(phi)
    M = mech.m_c * mech.s**2 + mech.I_c
    K = jnp.zeros_like(phi)
    q = jnp.zeros_like(phi)
    d1 = sd = lever = None
    if structure.coupler or structure.slider or has_P:
        r, L = mech.r, mech.L
        lam = r / L  # loop-invariant: XLA hoists it
        sd = lam * sphi
        u = 1.0 - sd * sd
        w = jax.lax.rsqrt(u)
        cd = u * w
        d1 = lam * cphi * w
        d2 = lam * (d1 * cphi * sd - sphi * cd) * (w * w)
        lever = r * sphi + L * d1 * sd
    if structure.coupler:
        b = mech.b
        cpd = cphi * cd - sphi * sd
        spd = sphi * cd + cphi * sd
        M = M + mech.m_p * (r * r - 2 * r * b * d1 * cpd + b * b * d1 * d1) + mech.I_p * d1 * d1
        K = K + mech.m_p * (r * b * (d1 * (1 + d1) * spd - d2 * cpd) + b * b * d1 * d2)
        K = K + mech.I_p * d1 * d2
    if structure.slider:
        M = M + mech.m_s * lever * lever
        K = K + mech.m_s * lever * (r * cphi + L * (d2 * sd + d1 * d1 * cd))
    q = q + generalized_force_terms(mech, phi, dphi, t, load, torque, structure, sphi,
                                    d1, sd, lever)
    return (q - K * dphi * dphi) / M


class CrankField(eqx.Module):
    """The slider-crank's equation of motion as a first-order vector field.

    `field(t, y, args=None)` with `y = (phi, dphi)` (a tuple of arrays of one shape, rad and
    rad/s) returns `(dphi, ddphi)` (rad/s, rad/s^2). It is a pytree: the parameters and
    loads are its (differentiable, vmappable) leaves, the `structure` is static. Every solver
    takes it as an opaque vector field, the way diffrax takes an `ODETerm`: no solver
    module imports the mechanism.

    **Fields:** `mech`, the [`SliderCrank`][]; `load`, the slider force P(t) (N, along -x);
    `torque`, the crank torque tau(t) (N*m); `structure`, the static set of terms.
    """

    mech: SliderCrank
    load: AbstractLoad
    torque: AbstractLoad
    structure: Structure = eqx.field(static=True, default=_FULL)

    def acceleration(self, t, phi, dphi):
        """phi'' = (q - K phi'^2) / M, rad/s^2, at time `t` (s)."""
        return fused_acceleration(self.mech, phi, dphi, t, self.load, self.torque,
                                  self.structure)

    def __call__(self, t, y, args=None):
        phi, dphi = y
        return dphi, self.acceleration(t, phi, dphi)
