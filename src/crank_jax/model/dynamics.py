"""The minimal form of the equation of motion (paper eq. 30, corrected, plus the offset and
the friction terms of DESIGN.md §1 "Beyond the paper"):

    M(phi) phi'' + K(phi) phi'^2 = q(phi, phi', t)

`M`, `K` and `q` are written once, here, on the [`geometry`][] of the crank angle; the
mass, Coriolis and force functions, the acceleration, the energy and [`CrankField`][] all
call the same term builders. The tests check them against autodiff (`K = M'/2`), the
global Newton-Euler form (`M = J^T Mbar J`), a potential (`q_conservative = -dV/dphi`) and
the power balance (`d(T+V)/dt = power_in`).

A [`Structure`][] says which terms a scene has. It is static (a hashable dataclass of
bools), so the compiled program contains only the terms that are used: a crank-only
pendulum traces no coupler or slider arithmetic, a scene without loads no load calls, a
scene without friction no `tanh`.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .geometry import Geometry, geometry
from .loads import AbstractLoad, NoLoad, as_load
from .params import SliderCrank
from .structure import Structure

__all__ = [
    "Structure", "mass", "coriolis", "generalized_force", "acceleration", "energy",
    "kinetic_energy", "potential_energy", "power_in", "CrankField", "mass_terms",
    "coriolis_terms", "force_terms", "dissipative_terms",
]

_FULL = Structure()


def mass_terms(mech: SliderCrank, g: Geometry, structure: Structure = _FULL) -> Array:
    """M from a [`Geometry`][] (see [`mass`][]); the one place M is written."""
    M = mech.m_c * mech.s**2 + mech.I_c + jnp.zeros_like(g.sphi)
    if structure.coupler:
        r, b, d1 = mech.r, mech.b, g.d1
        M = M + mech.m_p * (r * r - 2 * r * b * d1 * g.cpd + b * b * d1 * d1) + mech.I_p * d1 * d1
    if structure.slider:
        M = M + mech.m_s * g.lever * g.lever
    return M


def coriolis_terms(mech: SliderCrank, g: Geometry, structure: Structure = _FULL) -> Array:
    """K from a [`Geometry`][] (see [`coriolis`][]); the one place K is written."""
    K = jnp.zeros_like(g.sphi) * mech.r
    if structure.coupler:
        r, b, d1, d2 = mech.r, mech.b, g.d1, g.d2
        K = K + mech.m_p * (r * b * (d1 * (1 + d1) * g.spd - d2 * g.cpd) + b * b * d1 * d2)
        K = K + mech.I_p * d1 * d2
    if structure.slider:
        K = K + mech.m_s * g.lever * g.dlever
    return K


def force_terms(mech: SliderCrank, g: Geometry, phi, dphi, t, load: AbstractLoad,
                torque: AbstractLoad, structure: Structure = _FULL) -> Array:
    """q from a [`Geometry`][] (see [`generalized_force`][]); the one place q is written.
    `load` and `torque` must be loads (not None)."""
    q = 0.0
    if structure.gravity:
        weight_arm = mech.m_c * mech.s * g.sphi
        if structure.coupler:
            weight_arm = weight_arm + mech.m_p * (mech.r * g.sphi + mech.b * g.d1 * g.sin)
        if structure.slider:
            weight_arm = weight_arm + mech.m_s * g.lever
        q = q + mech.g * weight_arm
    if not isinstance(load, NoLoad):
        q = q + load(t) * g.lever
    if structure.spring:
        q = q - mech.k * phi
    return q + dissipative_terms(mech, g, dphi, structure) + (
        0.0 if isinstance(torque, NoLoad) else torque(t))


def dissipative_terms(mech: SliderCrank, g: Geometry, dphi, structure: Structure = _FULL):
    """The damping and friction part of q, N*m:
    `-c phi' - T_c tanh(phi'/w_c) - c_s lever^2 phi' - F_s lever tanh(lever phi'/w_s)`."""
    q = 0.0
    if structure.damper:
        q = q - mech.c * dphi
    if structure.crank_coulomb:
        # 1/w_c is loop-invariant (hoisted), so the stage keeps a single division.
        q = q - mech.T_c * jnp.tanh(dphi * (1.0 / mech.w_c))
    if structure.slider_damper:
        q = q - mech.c_s * g.lever * g.lever * dphi
    if structure.slider_coulomb:
        q = q - mech.F_s * g.lever * jnp.tanh(g.lever * dphi * (1.0 / mech.w_s))
    return q


def mass(mech: SliderCrank, phi: ArrayLike, structure: Structure = _FULL) -> Array:
    """Generalised mass M(phi), kg*m^2 (paper eq. 30):

        M = m_c s^2 + I_c + m_p (r^2 - 2 r b delta' cos(phi+delta) + b^2 delta'^2)
            + I_p delta'^2 + m_s (r sin(phi) + L delta' sin(delta))^2

    **Arguments:** `mech`; `phi`, crank angle (rad), any shape; `structure`, the static
    set of terms to include. **Returns:** an array of `phi`'s shape, always > 0.
    """
    return mass_terms(mech, geometry(mech, phi, structure), structure)


def coriolis(mech: SliderCrank, phi: ArrayLike, structure: Structure = _FULL) -> Array:
    """Velocity-squared coefficient K(phi) = M'(phi)/2, kg*m^2/rad (paper eq. 30):

        K = m_p (r b (delta'(1+delta') sin(phi+delta) - delta'' cos(phi+delta))
                 + b^2 delta' delta'')
            + m_s (r sin(phi) + L delta' sin(delta))
                  (r cos(phi) + L (delta'' sin(delta) + delta'^2 cos(delta)))
            + I_p delta' delta''

    **Returns:** an array of `phi`'s shape.
    """
    return coriolis_terms(mech, geometry(mech, phi, structure), structure)


def generalized_force(
    mech: SliderCrank,
    phi: ArrayLike,
    dphi: ArrayLike,
    t: ArrayLike = 0.0,
    load: AbstractLoad | None = None,
    torque: AbstractLoad | None = None,
    structure: Structure = _FULL,
) -> Array:
    """Generalised force q(phi, phi', t), N*m (paper eq. 30 plus tau, offset, friction):

        q = g (m_c s sin(phi) + m_p (r sin(phi) + b delta' sin(delta)) + m_s lever)
            + P(t) lever - k phi - c phi' + tau(t)
            - T_c tanh(phi'/w_c) - c_s lever^2 phi' - F_s lever tanh(lever phi'/w_s)

    with `lever = r sin(phi) + L delta' sin(delta)`.

    **Arguments:** `phi` (rad), `dphi` (rad/s), `t` (s), broadcastable; `load`, the
    slider force P(t) in N along -x; `torque`, the crank torque tau(t) in N*m about +z;
    `None` means none. **Returns:** an array of the broadcast shape.
    """
    load, torque = as_load(load), as_load(torque)
    phi, dphi = jnp.asarray(phi), jnp.asarray(dphi)
    zero = jnp.zeros(jnp.broadcast_shapes(phi.shape, dphi.shape, jnp.shape(t))) * mech.r
    return zero + force_terms(mech, geometry(mech, phi, structure), phi, dphi, t, load,
                              torque, structure)


def acceleration(
    mech: SliderCrank,
    phi: ArrayLike,
    dphi: ArrayLike,
    t: ArrayLike = 0.0,
    load: AbstractLoad | None = None,
    torque: AbstractLoad | None = None,
    structure: Structure = _FULL,
    force: Callable | None = None,
) -> Array:
    """Crank angular acceleration phi'' = (q - K phi'^2) / M, rad/s^2.

    `force`, if given, is a user's generalised force `force(t, phi, dphi) -> N*m` added to
    q (any pytree callable, e.g. an `equinox` MLP: a learned friction law, a controller).

    One geometry evaluation (a single `rsqrt`) and a single division: this is the form
    the fast solvers step (see [`geometry`][]).
    """
    load, torque = as_load(load), as_load(torque)
    phi, dphi = jnp.asarray(phi), jnp.asarray(dphi)
    g = geometry(mech, phi, structure)
    q = force_terms(mech, g, phi, dphi, t, load, torque, structure)
    if force is not None:
        q = q + force(t, phi, dphi)
    return (q - coriolis_terms(mech, g, structure) * dphi * dphi) / mass_terms(mech, g, structure)


def kinetic_energy(mech: SliderCrank, phi: ArrayLike, dphi: ArrayLike) -> Array:
    """T = M(phi) phi'^2 / 2, J."""
    return 0.5 * mass(mech, phi) * jnp.square(dphi)


def potential_energy(mech: SliderCrank, phi: ArrayLike) -> Array:
    """V = g (m_c x_c + m_p x_p + m_s x_s) + k phi^2 / 2, J (gravity along -x)."""
    phi = jnp.asarray(phi)
    g = geometry(mech, phi)
    weight = mech.m_c * g.x_c + mech.m_p * g.x_p + mech.m_s * g.x_s
    return mech.g * weight + 0.5 * mech.k * phi**2


def energy(mech: SliderCrank, phi: ArrayLike, dphi: ArrayLike) -> Array:
    """Mechanical energy T + V, J. Constant when c = P = tau = 0 and there is no friction."""
    return kinetic_energy(mech, phi, dphi) + potential_energy(mech, phi)


def power_in(
    mech: SliderCrank, phi: ArrayLike, dphi: ArrayLike, t: ArrayLike = 0.0,
    load: AbstractLoad | None = None, torque: AbstractLoad | None = None,
) -> Array:
    """Power of the non-conservative forces, W: `d(T+V)/dt = power_in`.

    `(P(t) lever - c phi' + tau(t) - T_c tanh(phi'/w_c) - c_s lever^2 phi'
    - F_s lever tanh(lever phi'/w_s)) phi'`; every friction term is <= 0.
    """
    load, torque = as_load(load), as_load(torque)
    phi, dphi = jnp.asarray(phi), jnp.asarray(dphi)
    g = geometry(mech, phi)
    gen = load(t) * g.lever + torque(t) + dissipative_terms(mech, g, dphi)
    return gen * dphi


class CrankField(eqx.Module):
    """The slider-crank's equation of motion as a first-order vector field.

    `field(t, y, args=None)` with `y = (phi, dphi)` (a tuple of arrays of one shape, rad and
    rad/s) returns `(dphi, ddphi)` (rad/s, rad/s^2). It is a pytree: the parameters and
    loads are its (differentiable, vmappable) leaves, the `structure` is static. Every solver
    takes it as an opaque vector field, the way diffrax takes an `ODETerm`: no solver
    module imports the mechanism.

    **Fields:** `mech`, the [`SliderCrank`][]; `load`, the slider force P(t) (N, along -x);
    `torque`, the crank torque tau(t) (N*m); `structure`, the static set of terms;
    `force`, an optional user term `force(t, phi, dphi) -> N*m` added to q: any pytree
    callable, so an `equinox` MLP's weights are leaves of the field and train through the
    solver (a universal differential equation; experiments/ude_friction.py).
    """

    mech: SliderCrank
    load: AbstractLoad
    torque: AbstractLoad
    structure: Structure = eqx.field(static=True, default=_FULL)
    force: Callable | None = None

    def acceleration(self, t, phi, dphi):
        """phi'' = (q - K phi'^2) / M, rad/s^2, at time `t` (s)."""
        return acceleration(self.mech, phi, dphi, t, self.load, self.torque, self.structure,
                            self.force)

    def __call__(self, t, y, args=None):
        phi, dphi = y
        return dphi, self.acceleration(t, phi, dphi)
