"""Linearisation about the static equilibrium phi_eq (paper eq. 33, corrected by errata 1
and 3, generalised as in DESIGN.md §1 "Beyond the paper"):

    mu (phi - phi_eq)'' + chi (phi - phi_eq)' + xi (phi - phi_eq) = tau(t) - mean(tau)

    phi_eq: the root of q(phi, 0) = 0 (loads at their means) nearest phi = 0
    mu  = M(phi_eq)
    chi = c + c_s lever(phi_eq)^2
    xi  = -dq/dphi (phi_eq, 0) = k - k_crit,
    k_crit = g cos(gamma) (m_c s cos(phi) + m_p (r cos(phi) + b (delta'' sin(delta)
                                                                 + delta'^2 cos(delta)))
                           + m_s lever')
           + g sin(gamma) (m_c s sin(phi) + m_p (r sin(phi) + b (delta'' cos(delta)
                                                                 - delta'^2 sin(delta))))
           + P lever'        (at phi_eq; lever' = d lever / d phi; gamma = gravity_angle)

With `e = 0`, `gamma = 0` and no constant loads, `phi_eq = 0` and these are the paper's

    mu  = m_c s^2 + I_c + m_p r^2 (1 - b/L)^2 + I_p r^2/L^2
    chi = c
    xi  = k - g (m_c s + m_p r (1 + r b/L^2) + m_s r (1 + r/L)) - P r (1 + r/L)

The paper's coupler term `m_p g r (1 + b/L)` is wrong (erratum 1), and its "excitation"
`M_e = P r (1 + r/L) phi` is a stiffness, not a forcing (erratum 3): a constant P enters
xi, a harmonic P(t) pumps the stiffness parametrically. Coulomb friction (T_c, F_s) has no
linearisation (its slope at rest, `T_c / w_c`, is an artefact of the smoothing): it is left
out, and [`coulomb_note`][] says so. `xi` is written by hand here, not differentiated, so
that it stays an independent check of q (tested against `jax.jacfwd`).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .dynamics import force_terms, formed_at, mass_terms
from .geometry import Geometry
from .loads import AbstractLoad, ConstantLoad, NoLoad, as_load
from .params import SliderCrank

__all__ = ["Linearization", "linearize", "equilibrium", "coulomb_note", "mean_loads",
           "linearize_tuple"]

# Damped Newton from phi = 0: steps are clipped so that the search creeps towards the
# nearest root instead of jumping over it; 40 steps of at most 0.25 rad reach 10 rad.
_NEWTON_STEPS = 40
_MAX_STEP = 0.25
_STEP_TOL = 1e-10


class Linearization(NamedTuple):
    """Coefficients of the linearised equation and derived quantities (SI units)."""

    mu: Array
    """Inertia M(phi_eq), kg*m^2."""
    chi: Array
    """Damping c + c_s lever(phi_eq)^2, N*m*s/rad (Coulomb friction left out)."""
    xi: Array
    """Effective stiffness at phi_eq (shaft minus gravity and slider-force softening), N*m/rad."""
    omega_n: Array
    """Undamped natural frequency sqrt(xi/mu), rad/s (NaN when xi <= 0: no oscillation)."""
    zeta: Array
    """Damping ratio chi / (2 sqrt(xi mu)) (NaN when xi <= 0)."""
    stable: Array
    """Static stability of phi_eq: xi > 0 (False where no equilibrium was found)."""
    k_crit: Array
    """Stiffness k at which xi = 0 (with phi_eq held), N*m/rad: below it the crank falls."""
    phi_eq: Array
    """The static equilibrium, rad: the root of q(phi, 0) = 0 nearest 0. NaN where the
    search found none (e.g. a constant torque that no spring holds); the coefficients are
    then those at phi = 0, a rate scale rather than an equilibrium's."""


def _softening(mech: SliderCrank, g: Geometry, P: Array, has_P: bool) -> Array:
    """k_crit(phi) = dq/dphi + k at rest (q without its spring term, differentiated),
    N*m/rad, written by hand; `g`, the [`Geometry`][] at phi."""
    # Gravity's x-part, d/dphi of q's g cos(gamma) (...), and its y-part, d/dphi of
    # -g sin(gamma) ((m_c s + m_p r) cos(phi) - m_p b delta' cos(delta)).
    coupler = mech.r * g.cphi + mech.b * (g.d2 * g.sin + g.d1 * g.d1 * g.cos)
    soft_x = mech.m_c * mech.s * g.cphi + mech.m_p * coupler + mech.m_s * g.dlever
    coupler_y = mech.r * g.sphi + mech.b * (g.d2 * g.cos - g.d1 * g.d1 * g.sin)
    soft_y = mech.m_c * mech.s * g.sphi + mech.m_p * coupler_y
    gamma = mech.gravity_angle
    # At gamma = 0 this is the paper's g * soft_x exactly (cos 0 = 1, sin 0 = 0).
    soft = mech.g * (jnp.cos(gamma) * soft_x + jnp.sin(gamma) * soft_y)
    return soft + P * g.dlever if has_P else soft


def equilibrium(mech: SliderCrank, load: AbstractLoad | None = None,
                torque: AbstractLoad | None = None) -> Array:
    """The static equilibrium phi_eq, rad: the root of `q(phi, 0) = 0` with the loads at
    their means, found by damped Newton steps from phi = 0 (the root nearest 0).

    Works on concrete and traced parameters and on batches (one root per member); its
    derivative with respect to the parameters is the implicit one.

    **Returns:** an array of the parameters' broadcast shape; NaN where no root was found.
    """
    return _equilibrium(mech, mean_loads(load, torque))


def _at_rest(mech: SliderCrank, loads, phi: Array) -> tuple[Array, Array, Array, Array]:
    """The equation at crank angle `phi` and rest, loads at their means: q(phi, 0) (N*m),
    k_crit (N*m/rad), mu = M(phi) (kg*m^2) and chi = c + c_s lever^2 (N*m*s/rad). Its
    callers run under `jit`, which leaves out what they do not read."""
    p, g = formed_at(mech, phi)
    q = force_terms(p, g, phi, 0.0, 0.0, *loads)
    mu = mass_terms(p, g)
    chi = mech.c + mech.c_s * g.lever * g.lever
    has_P = not isinstance(loads[0], NoLoad)
    return q, _softening(mech, g, loads[0].mean(), has_P), mu, chi


def _q_xi(mech: SliderCrank, loads, phi: Array) -> tuple[Array, Array]:
    """q(phi, 0) (N*m) and xi = -dq/dphi (N*m/rad), loads at their means."""
    q, k_crit, _, _ = _at_rest(mech, loads, phi)
    return q, mech.k - k_crit


def _newton_step(mech: SliderCrank, loads, phi: Array) -> Array:
    q, xi = _q_xi(mech, loads, phi)
    return jnp.where(xi != 0, q / jnp.where(xi != 0, xi, 1.0), 0.0)


def _search_step(mech: SliderCrank, loads, phi: Array) -> Array:
    """A clipped Newton step; on a flat point (xi zero to rounding, e.g. phi = 0 of a crank
    without spring under gravity along -y, where cos(pi/2) leaves ~1e-17 of the x-part) a
    full clipped step downhill, along q = -dV/dphi: Newton would stop there and call the
    flat point a root (xi = 0), or take a direction from rounding alone."""
    q, xi = _q_xi(mech, loads, phi)
    m = mech
    # A bound on the stiffness terms' size, N*m/rad: xi below 1e-12 of it is rounding.
    size = (jnp.abs(m.k) + jnp.abs(m.g) * (m.m_c * m.s + m.m_p * (m.r + m.b)
                                             + m.m_s * (m.r + m.L))
            + jnp.abs(loads[0].mean()) * (m.r + m.L))
    flat = jnp.abs(xi) <= 1e-12 * size
    step = jnp.where(flat, jnp.sign(q) * _MAX_STEP, q / jnp.where(flat, 1.0, xi))
    return jnp.clip(step, -_MAX_STEP, _MAX_STEP)


# Jitted at module level so that eager calls (every concrete `simulate` asks the solver
# policy for a linearisation) reuse one compiled loop instead of re-tracing a closure.
@eqx.filter_jit
def _equilibrium(mech: SliderCrank, loads) -> Array:
    shape = jnp.broadcast_shapes(*(jnp.shape(x) for x in jax.tree_util.tree_leaves(mech)))
    frozen = jax.lax.stop_gradient((mech, loads))

    def body(_, carry):
        phi, _ = carry
        step = _search_step(*frozen, phi)
        return phi + step, step

    zero = jnp.zeros(shape, jnp.result_type(float))
    phi, last = jax.lax.fori_loop(0, _NEWTON_STEPS, body, (zero, zero + 1.0))
    phi = jax.lax.stop_gradient(phi)
    found = jnp.isfinite(phi) & (jnp.abs(last) <= _STEP_TOL)
    # One more (unclipped) Newton step with live parameters: the value is unchanged to
    # rounding, and its derivative is the implicit function theorem's -(dq/dp)/(dq/dphi).
    phi = phi + _newton_step(mech, loads, phi)
    return jnp.where(found, phi, jnp.nan)


def linearize(mech: SliderCrank, load: AbstractLoad | None = None,
              torque: AbstractLoad | None = None) -> Linearization:
    """Linearise the equation of motion about its static equilibrium (loads at their means).

    **Arguments:** `mech`; `load`, the slider force P; `torque`, the crank torque tau
    (their `mean()`s set the equilibrium; P's also enters xi).

    **Returns:** a [`Linearization`][]; every field has the shape of the parameters.
    Concrete inputs give concrete outputs even inside a caller's `jit` (the solver policy
    reads them on the host to choose a solver).
    """
    loads = mean_loads(load, torque)
    leaves = jax.tree_util.tree_leaves((mech, loads))
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        return _linearize(mech, loads)
    # Concrete values inside a caller's `jit`: computed now, for the host to read.
    with jax.ensure_compile_time_eval():
        return _linearize(mech, loads)


def mean_loads(load, torque) -> tuple[AbstractLoad, AbstractLoad]:
    """The loads at their means; an absent load stays `NoLoad` (its terms are left out)."""
    load, torque = as_load(load), as_load(torque)
    return (NoLoad() if isinstance(load, NoLoad) else ConstantLoad(load.mean()),
            NoLoad() if isinstance(torque, NoLoad) else ConstantLoad(torque.mean()))


# One compiled program for eager calls too (the solver policy linearises before every
# concrete solve); inside an outer jit it is simply inlined.
@eqx.filter_jit
def _linearize(mech: SliderCrank, loads) -> Linearization:
    phi_eq = _equilibrium(mech, loads)
    _, k_crit, mu, chi = _at_rest(mech, loads, jnp.where(jnp.isnan(phi_eq), 0.0, phi_eq))
    k_crit = k_crit + jnp.zeros_like(mu)
    xi = mech.k - k_crit
    # Only defined for a statically stable equilibrium; NaN says "no oscillation" honestly
    # rather than a silently clipped number.
    pos = jnp.where(xi > 0, xi, jnp.nan)
    omega_n = jnp.sqrt(pos / mu)
    zeta = chi / (2 * jnp.sqrt(pos * mu))
    stable = (xi > 0) & ~jnp.isnan(phi_eq)
    return Linearization(mu, chi, xi, omega_n, zeta, stable, k_crit, phi_eq)


def linearize_tuple(mech: SliderCrank, loads) -> tuple:
    """[`linearize`][] of `mech` and `loads` (from [`mean_loads`][]) as a tuple of arrays:
    the form a stored program returns (the front door's `crank_jax.linearize` keeps it in
    the program store)."""
    return tuple(_linearize(mech, loads))


def coulomb_note(mech: SliderCrank) -> str | None:
    """A one-line note when the (concrete) parameters have Coulomb friction, which the
    linearisation leaves out; `None` otherwise."""
    names = [n for n in ("T_c", "F_s") if np.any(np.asarray(getattr(mech, n)) != 0)]
    if not names:
        return None
    return (f"note: Coulomb friction ({', '.join(names)}) is left out of the linearization "
            "(it has none at rest); the real decay is partly linear, not exponential")
