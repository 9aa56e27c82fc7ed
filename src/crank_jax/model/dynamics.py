"""The minimal form of the equation of motion (paper eq. 30, corrected, plus the offset,
the friction terms and gravity's direction of DESIGN.md §1 "Beyond the paper"):

    M(phi) phi'' + K(phi) phi'^2 = q(phi, phi', t)

`M`, `K` and `q` are written once, here, as the [`Coefficients`][] (the parameter parts,
formed in `coefficients.py`) times the [`geometry`][] of the crank angle; the mass,
Coriolis and force functions, the acceleration, the energy and [`CrankField`][] all call
the same term builders. The tests check them against autodiff (`K = M'/2`), the
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

from .coefficients import Coefficients, coefficients, pack, unpack
from .geometry import Geometry, geometry_terms
from .loads import AbstractLoad, NoLoad, as_load, only_own_loads
from .params import SliderCrank
from .structure import Structure
from .trig import Trig, form_field

__all__ = [
    "Structure", "mass", "coriolis", "generalized_force", "acceleration", "energy",
    "kinetic_energy", "potential_energy", "power_in", "CrankField", "formed_at", "mass_terms",
    "coriolis_terms", "force_terms", "dissipative_terms", "acceleration_terms",
    "PackedCrankField", "equation_residual",
]

_FULL = Structure()


def formed_at(mech: SliderCrank, phi: ArrayLike, structure: Structure = _FULL
              ) -> tuple[Coefficients, Geometry]:
    """The [`Coefficients`][] of `mech` and its [`Geometry`][] at `phi`, formed once: the
    pair that the term builders below take."""
    p = coefficients(mech, structure)
    return p, geometry_terms(p, phi, structure)


def mass_terms(p: Coefficients, g: Geometry, structure: Structure = _FULL) -> Array:
    """M from [`Coefficients`][] and a [`Geometry`][] (see [`mass`][]); the one place M is
    written: `cM0 - c2 delta' cos(phi+delta) + c3 delta'^2 + m_s lever^2`."""
    M = p.cM0 + jnp.zeros_like(g.sphi)
    if structure.coupler:
        d1 = g.d1
        M = M - p.c2 * d1 * g.cpd + p.c3 * d1 * d1
    if structure.slider:
        M = M + p.m_s * g.lever * g.lever
    return M


def coriolis_terms(p: Coefficients, g: Geometry, structure: Structure = _FULL) -> Array:
    """K from [`Coefficients`][] and a [`Geometry`][] (see [`coriolis`][]); the one place K
    is written."""
    K = jnp.zeros_like(g.sphi) * p.r
    if structure.coupler:
        d1, d2 = g.d1, g.d2
        K = K + p.c2h * (d1 * (1 + d1) * g.spd - d2 * g.cpd) + p.c3 * d1 * d2
    if structure.slider:
        K = K + p.m_s * g.lever * g.dlever
    return K


def force_terms(p: Coefficients, g: Geometry, phi, dphi, t, load: AbstractLoad,
                torque: AbstractLoad, structure: Structure = _FULL) -> Array:
    """q from [`Coefficients`][] and a [`Geometry`][] (see [`generalized_force`][]); the one
    place q is written. `load` and `torque` must be loads (not None)."""
    q = 0.0
    if structure.gravity:
        # -dV/dphi of V = g sum m_i (x_i cos(gamma) + y_i sin(gamma)); x-part:
        # g cos(gamma) (m_c s sin(phi) + m_p (r sin(phi) + b delta' sin(delta)) + m_s lever)
        q = p.gA * g.sphi
        if structure.coupler:
            q = q + p.gB * g.d1 * g.sin
        if structure.slider:
            q = q + p.gC * g.lever
        if structure.tilt:
            # y-part: g sin(gamma) (-(m_c s + m_p r) cos(phi) + m_p b delta' cos(delta)); the
            # slider's y = e is constant, so its weight does no work along y.
            q = q - p.gAy * g.cphi
            if structure.coupler:
                q = q + p.gBy * g.d1 * g.cos
    if not isinstance(load, NoLoad):
        q = q + load.at(t, phi) * g.lever
    if structure.spring:
        q = q - p.k * phi
    return q + dissipative_terms(p, g, dphi, structure) + (
        0.0 if isinstance(torque, NoLoad) else torque.at(t, phi))


def dissipative_terms(p: Coefficients, g: Geometry, dphi, structure: Structure = _FULL):
    """The damping and friction part of q, N*m:
    `-c phi' - T_c tanh(phi'/w_c) - c_s lever^2 phi' - F_s lever tanh(lever phi'/w_s)`."""
    q = 0.0
    if structure.damper:
        q = q - p.c * dphi
    if structure.crank_coulomb:
        q = q - p.T_c * jnp.tanh(dphi * p.inv_wc)
    if structure.slider_damper:
        q = q - p.c_s * g.lever * g.lever * dphi
    if structure.slider_coulomb:
        q = q - p.F_s * g.lever * jnp.tanh(g.lever * dphi * p.inv_ws)
    return q


def mass(mech: SliderCrank, phi: ArrayLike, structure: Structure = _FULL) -> Array:
    """Generalised mass M(phi), kg*m^2 (paper eq. 30):

        M = m_c s^2 + I_c + m_p (r^2 - 2 r b delta' cos(phi+delta) + b^2 delta'^2)
            + I_p delta'^2 + m_s (r sin(phi) + L delta' sin(delta))^2

    **Arguments:** `mech`; `phi`, crank angle (rad), any shape; `structure`, the static
    set of terms to include. **Returns:** an array of `phi`'s shape, always > 0.
    """
    p, g = formed_at(mech, phi, structure)
    return mass_terms(p, g, structure)


def coriolis(mech: SliderCrank, phi: ArrayLike, structure: Structure = _FULL) -> Array:
    """Velocity-squared coefficient K(phi) = M'(phi)/2, kg*m^2/rad (paper eq. 30):

        K = m_p (r b (delta'(1+delta') sin(phi+delta) - delta'' cos(phi+delta))
                 + b^2 delta' delta'')
            + m_s (r sin(phi) + L delta' sin(delta))
                  (r cos(phi) + L (delta'' sin(delta) + delta'^2 cos(delta)))
            + I_p delta' delta''

    **Returns:** an array of `phi`'s shape.
    """
    p, g = formed_at(mech, phi, structure)
    return coriolis_terms(p, g, structure)


def generalized_force(
    mech: SliderCrank,
    phi: ArrayLike,
    dphi: ArrayLike,
    t: ArrayLike = 0.0,
    load: AbstractLoad | None = None,
    torque: AbstractLoad | None = None,
    structure: Structure = _FULL,
) -> Array:
    """Generalised force q(phi, phi', t), N*m (paper eq. 30 plus tau, offset, friction,
    gravity's direction gamma = `gravity_angle`):

        q = g cos(gamma) (m_c s sin(phi) + m_p (r sin(phi) + b delta' sin(delta)) + m_s lever)
            - g sin(gamma) ((m_c s + m_p r) cos(phi) - m_p b delta' cos(delta))
            + P(t) lever - k phi - c phi' + tau(t)
            - T_c tanh(phi'/w_c) - c_s lever^2 phi' - F_s lever tanh(lever phi'/w_s)

    with `lever = r sin(phi) + L delta' sin(delta)` (gamma = 0: the paper's q).

    **Arguments:** `phi` (rad), `dphi` (rad/s), `t` (s), broadcastable; `load`, the
    slider force P(t) in N along -x; `torque`, the crank torque tau(t) in N*m about +z;
    `None` means none. **Returns:** an array of the broadcast shape.
    """
    load, torque = as_load(load), as_load(torque)
    phi, dphi = jnp.asarray(phi), jnp.asarray(dphi)
    zero = jnp.zeros(jnp.broadcast_shapes(phi.shape, dphi.shape, jnp.shape(t))) * mech.r
    p, g = formed_at(mech, phi, structure)
    return zero + force_terms(p, g, phi, dphi, t, load, torque, structure)


def equation_residual(mech: SliderCrank, phi, dphi, ddphi, t, load: AbstractLoad,
                      torque: AbstractLoad, structure: Structure = _FULL) -> Array:
    """`M phi'' + K phi'^2 - q`, N*m: zero on a motion of the model. `phi` (rad), `dphi`
    (rad/s), `ddphi` (rad/s^2), `t` (s) of one shape; `load`, `torque` loads (not None).
    The coefficients and the geometry are formed once for M, K and q (what a regressor
    differentiates with respect to the parameters)."""
    p, g = formed_at(mech, phi, structure)
    return (mass_terms(p, g, structure) * ddphi + coriolis_terms(p, g, structure) * dphi**2
            - force_terms(p, g, phi, dphi, t, load, torque, structure))


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
    the fast solvers step (see [`geometry_terms`][]).
    """
    load, torque = as_load(load), as_load(torque)
    phi = jnp.asarray(phi)
    p, g = formed_at(mech, phi, structure)
    return acceleration_terms(p, g, phi, jnp.asarray(dphi), t, load, torque, structure, force)


def _acceleration(p: Coefficients, phi, dphi, t, load, torque, structure, force,
                  trig: Trig = Trig.LIBRARY) -> Array:
    """[`acceleration`][] from [`Coefficients`][] (loads already loads), the geometry's
    sin, cos and 1/sqrt traced in the form `trig` (`trig.FORMS`): what a solver steps."""
    g = geometry_terms(p, phi, structure, trig)
    return acceleration_terms(p, g, phi, dphi, t, load, torque, structure, force)


def acceleration_terms(p: Coefficients, g: Geometry, phi, dphi, t, load: AbstractLoad,
                       torque: AbstractLoad, structure: Structure = _FULL,
                       force: Callable | None = None) -> Array:
    """phi'' from [`Coefficients`][] and a [`Geometry`][] (see [`acceleration`][]); the one
    place it is written. `load` and `torque` must be loads (not None)."""
    q = force_terms(p, g, phi, dphi, t, load, torque, structure)
    if force is not None:
        q = q + force(t, phi, dphi)
    return (q - coriolis_terms(p, g, structure) * dphi * dphi) / mass_terms(p, g, structure)


def kinetic_energy(mech: SliderCrank, phi: ArrayLike, dphi: ArrayLike) -> Array:
    """T = M(phi) phi'^2 / 2, J."""
    phi = jnp.asarray(phi)
    return _kinetic(*formed_at(mech, phi), dphi)


def _kinetic(p: Coefficients, g: Geometry, dphi) -> Array:
    """[`kinetic_energy`][] from [`Coefficients`][] and the [`Geometry`][] of phi."""
    return 0.5 * mass_terms(p, g) * jnp.square(dphi)


def potential_energy(mech: SliderCrank, phi: ArrayLike) -> Array:
    """V = g sum m_i (x_i cos(gamma) + y_i sin(gamma)) + k phi^2 / 2 over the crank, coupler
    and slider centres of mass (the slider at y = e), J; gravity along
    (-cos(gamma), -sin(gamma)), gamma = `gravity_angle` (0: the paper's -x)."""
    phi = jnp.asarray(phi)
    return _potential(mech, formed_at(mech, phi)[1], phi)


def _potential(mech: SliderCrank, g: Geometry, phi: Array) -> Array:
    """[`potential_energy`][] at the [`Geometry`][] `g` of `phi`."""
    weight_x = mech.m_c * g.x_c + mech.m_p * g.x_p + mech.m_s * g.x_s
    weight_y = mech.m_c * g.y_c + mech.m_p * g.y_p + mech.m_s * mech.e
    gamma = mech.gravity_angle
    # At gamma = 0 this is the paper's g * weight_x exactly (cos 0 = 1, sin 0 = 0).
    return (mech.g * (jnp.cos(gamma) * weight_x + jnp.sin(gamma) * weight_y)
            + 0.5 * mech.k * phi**2)


def energy(mech: SliderCrank, phi: ArrayLike, dphi: ArrayLike) -> Array:
    """Mechanical energy T + V, J. Constant when c = P = tau = 0 and there is no friction.
    The coefficients and the geometry are formed once for both."""
    phi = jnp.asarray(phi)
    p, g = formed_at(mech, phi)
    return _kinetic(p, g, dphi) + _potential(mech, g, phi)


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
    p, g = formed_at(mech, phi)
    gen = load.at(t, phi) * g.lever + torque.at(t, phi) + dissipative_terms(p, g, dphi)
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
    solver (a universal differential equation; experiments/ude_friction.py); `trig`
    (static, one of `trig.FORMS`, default `"library"`): how the geometry traces sin, cos
    and 1/sqrt. A solver that wants the arithmetic form (the lockstep batch) steps
    `trig.traced_as(field, "arithmetic")`, which sets it here and in the loads.
    """

    mech: SliderCrank
    load: AbstractLoad
    torque: AbstractLoad
    structure: Structure = eqx.field(static=True, default=_FULL)
    force: Callable | None = None
    trig: Trig = form_field()

    def acceleration(self, t, phi, dphi):
        """phi'' = (q - K phi'^2) / M, rad/s^2, at time `t` (s)."""
        return _acceleration(coefficients(self.mech, self.structure), jnp.asarray(phi),
                             jnp.asarray(dphi), t, as_load(self.load), as_load(self.torque),
                             self.structure, self.force, self.trig)

    def __call__(self, t, y, args=None):
        phi, dphi = y
        return dphi, self.acceleration(t, phi, dphi)

    def packed(self) -> PackedCrankField:
        """The same field with its [`Coefficients`][] formed once and packed in one array:
        what a solver should step (see `coefficients.py` for why). Call it outside the
        step loop."""
        return PackedCrankField(pack(coefficients(self.mech, self.structure)), self.load,
                                self.torque, self.structure, self.force, self.trig)


class PackedCrankField(eqx.Module):
    """[`CrankField`][] with the parameters as packed [`Coefficients`][]
    (`CrankField.packed()`): the same `field(t, y, args=None) -> (dphi, ddphi)`, the same
    values; the leaf `coefficients` (shape (n,) + batch) is differentiable; `trig` as
    [`CrankField`][]'s."""

    coefficients: Array
    load: AbstractLoad
    torque: AbstractLoad
    structure: Structure = eqx.field(static=True, default=_FULL)
    force: Callable | None = None
    trig: Trig = form_field()

    def __call__(self, t, y, args=None):
        phi, dphi = y
        accel = _traced_once if _own_code(self.load, self.torque, self.force) else _acceleration
        return dphi, accel(unpack(self.coefficients), phi, dphi, t, self.load, self.torque,
                           self.structure, self.force, self.trig)


# A solver evaluates the field at several places in one program (the first stage, the
# initial step's two, the stage loop, the variational equation's reverse passes, the
# adjoint's blocks), each a fresh trace of the same arithmetic: jnp's operators cost
# ~0.25 ms each to trace, ~50 ms per acceleration. Under `jit`, the acceleration is
# traced once per input shape and its jaxpr reused (JAX caches a jitted function's trace,
# and its JVP and transpose). XLA inlines the call before optimising, so the compiled
# programs are the same (tested: test_field_trace.py); a fit's first Jacobian traced in
# 1.3-1.6 s instead of 2.0-2.2 s (experiments/results/trace_once.json).
_traced_once = eqx.filter_jit(_acceleration)


def _own_code(load, torque, force) -> bool:
    """Whether the field's loads are crank-jax's own code only, at any depth, and it has
    no user force: only then is the acceleration's cached trace used. A user's class
    may read a module global or a closure cell that JAX's trace cache does not see, so
    such a field is traced afresh wherever its caller's program is (the same numbers,
    traced more slowly). Decided on the objects alone ([`only_own_loads`][]: exact types
    of the table of load kinds, plain static values), never on where code lies."""
    return force is None and only_own_loads(load, torque)
