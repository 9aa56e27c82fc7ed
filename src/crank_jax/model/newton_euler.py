"""The global Newton-Euler form (paper eq. 16-29) in the plane, and the joint reactions.

The paper writes each body in 3-D (15 rows). The motion is planar, so here each body has
its in-plane rows only; the eight global coordinates are

    [x_c, y_c, x_p, y_p, x_s, y_s, theta_c, theta_p]

(centres of mass of crank and coupler, the slider, the two body rotations). The global
equations read

    Mbar J phi'' + qbar_c = qbar_e + Qbar g_r                      (eq. 24)

and D'Alembert's projection with J^T removes the reactions because `J^T Qbar = 0`:
`J^T Mbar J = M`, `J^T qbar_c = K phi'^2`, `J^T qbar_e = q`.

The seven reactions `g_r` (the planar counterpart of the paper's 14) are:

- `O` (2,): force of the frame on the crank at the crank bearing O, N.
- `A` (2,): force of the coupler on the crank at the crank pin A, N (the crank pushes
  back with -A on the coupler).
- `B` (2,): force of the slider on the coupler at the wrist pin B, N.
- `N` (): normal force of the guide on the slider, along +y, N.
- `F` (): friction force of the guide on the slider, along +x, N (the applied
  `-c_s v_s - F_s tanh(v_s/w_s)`; zero without slider friction).

With an offset `e` the slider runs along `y = e`; the positions and moment arms come from
the same geometry, and the crank bearing's friction torque `-T_c tanh(phi'/w_c)` joins the
crank's moment row. Each weight is `m g (-cos(gamma), -sin(gamma))` (gamma =
`gravity_angle`): the slider's y-part is carried by the guide's normal force N.

All functions here take a scalar state; `jax.vmap` them for time series.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .geometry import CouplerAngle, coupler_angle
from .loads import AbstractLoad, as_load
from .params import SliderCrank

__all__ = ["GlobalForm", "global_form", "guide_friction", "distribution_matrix", "Reactions",
           "reactions"]


class GlobalForm(NamedTuple):
    """The global Newton-Euler quantities at one state (eq. 25-29), planar."""

    Mbar: Array
    """(8, 8) block-diagonal mass matrix diag(m_c, m_c, m_p, m_p, m_s, m_s, I_c, I_p)."""
    J: Array
    """(8,) global Jacobian d(coordinates)/d(phi)."""
    qbar_c: Array
    """(8,) Coriolis/centripetal forces Mbar (dJ/dphi) phi'^2 (gyroscopic terms vanish)."""
    qbar_e: Array
    """(8,) applied forces and torques (weights along g (-cos(gamma), -sin(gamma)), P, guide
    friction, spring-damper, bearing friction, tau)."""


def global_form(
    mech: SliderCrank, phi: ArrayLike, dphi: ArrayLike, t: ArrayLike = 0.0,
    load: AbstractLoad | None = None, torque: AbstractLoad | None = None,
) -> GlobalForm:
    """Build Mbar, J, qbar_c and qbar_e at a scalar state (phi rad, dphi rad/s, t s)."""
    return _global_form(mech, coupler_angle(mech, phi), phi, dphi, t, load, torque)


def _global_form(mech: SliderCrank, ca: CouplerAngle, phi, dphi, t, load, torque
                 ) -> GlobalForm:
    """[`global_form`][] at the coupler angle `ca` of `phi`."""
    load, torque = as_load(load), as_load(torque)
    r, L, b, s, g = mech.r, mech.L, mech.b, mech.s, mech.g
    sd, cd, d1, d2 = ca.sin, ca.cos, ca.d1, ca.d2
    sp, cp = jnp.sin(phi), jnp.cos(phi)
    J = jnp.stack([
        -s * sp, s * cp,
        -r * sp - b * d1 * sd, r * cp - b * d1 * cd,
        -r * sp - L * d1 * sd, jnp.zeros_like(sp),
        jnp.ones_like(sp), -d1,
    ])
    dJ = jnp.stack([  # dJ/dphi, the velocity-product accelerations per phi'^2 (eq. 13-15)
        -s * cp, -s * sp,
        -r * cp - b * d2 * sd - b * d1 * d1 * cd, -r * sp - b * d2 * cd + b * d1 * d1 * sd,
        -r * cp - L * d2 * sd - L * d1 * d1 * cd, jnp.zeros_like(sp),
        jnp.zeros_like(sp), -d2,
    ])
    m = jnp.stack([mech.m_c, mech.m_c, mech.m_p, mech.m_p, mech.m_s, mech.m_s, mech.I_c, mech.I_p])
    zero = jnp.zeros_like(sp)
    # Gravity's vector, m/s^2: g (-cos(gamma), -sin(gamma)), gamma = gravity_angle.
    gx, gy = -g * jnp.cos(mech.gravity_angle), -g * jnp.sin(mech.gravity_angle)
    crank_torque = (-mech.k * phi - mech.c * dphi + torque.at(t, phi)
                    - mech.T_c * jnp.tanh(dphi / mech.w_c))
    qbar_e = jnp.stack([
        mech.m_c * gx + zero, mech.m_c * gy + zero,
        mech.m_p * gx + zero, mech.m_p * gy + zero,
        -load.at(t, phi) + mech.m_s * gx + guide_friction(mech, J[4] * dphi) + zero,
        mech.m_s * gy + zero,
        crank_torque + zero, zero,
    ])
    return GlobalForm(jnp.diag(m), J, m * dJ * dphi**2, qbar_e)


def guide_friction(mech: SliderCrank, v_s: ArrayLike) -> Array:
    """Friction force of the guide on the slider along +x, N, at slider velocity `v_s`
    (m/s): `-c_s v_s - F_s tanh(v_s / w_s)`."""
    return -mech.c_s * v_s - mech.F_s * jnp.tanh(v_s / mech.w_s)


def distribution_matrix(mech: SliderCrank, phi: ArrayLike) -> Array:
    """Qbar (8, 7): how the reactions [O_x, O_y, A_x, A_y, B_x, B_y, N] enter each global
    equation (eq. 29). Moments are taken about each body's centre of mass."""
    r, L, b, s = mech.r, mech.L, mech.b, mech.s
    ca = coupler_angle(mech, phi)
    sd, cd = ca.sin, ca.cos
    sp, cp = jnp.sin(phi), jnp.cos(phi)
    z, o = jnp.zeros_like(sp), jnp.ones_like(sp)
    # Moment of a force F at offset u from the centre of mass: u_x F_y - u_y F_x.
    # Crank: O at u = -s(cos, sin), A at u = (r-s)(cos, sin).
    # Coupler: A (force -A) at u = b(-cos d, sin d), B at u = (L-b)(cos d, -sin d).
    rows = [
        [o, z, o, z, z, z, z],
        [z, o, z, o, z, z, z],
        [z, z, -o, z, o, z, z],
        [z, z, z, -o, z, o, z],
        [z, z, z, z, -o, z, z],
        [z, z, z, z, z, -o, o],
        [s * sp, -s * cp, -(r - s) * sp, (r - s) * cp, z, z, z],
        [z, z, b * sd, b * cd, (L - b) * sd, (L - b) * cd, z],
    ]
    return jnp.stack([jnp.stack(row) for row in rows])


class Reactions(NamedTuple):
    """Joint reaction forces at one state (N). See the module docstring for conventions."""

    O: Array  # noqa: E741 (the paper's name for the crank bearing)
    A: Array
    B: Array
    N: Array
    F: Array


def reactions(
    mech: SliderCrank, phi: ArrayLike, dphi: ArrayLike, ddphi: ArrayLike,
    t: ArrayLike = 0.0, load: AbstractLoad | None = None, torque: AbstractLoad | None = None,
) -> Reactions:
    """Joint reactions from the crank's motion (phi, phi', phi'') and the loads.

    Solves the seven translational and coupler-rotation rows of eq. 24 for g_r. The
    eighth row, the crank's moment balance, is then satisfied exactly when phi'' obeys the
    equation of motion: it is the projection D'Alembert's principle keeps.
    """
    ca = coupler_angle(mech, phi)
    gf = _global_form(mech, ca, phi, dphi, t, load, torque)
    h = gf.Mbar @ gf.J * ddphi + gf.qbar_c - gf.qbar_e
    # The kept rows of `distribution_matrix` are triangular once ordered from the slider
    # inwards, so they are solved by substitution, not by an LU: a batched LAPACK kernel
    # waits on XLA:CPU's intra-op threads, and with a program on every CPU device (a
    # sweep's shard_map) each device's kernel holds a thread the others wait for, a
    # deadlock (jax 0.10). Rows: 4 -> B_x, 2 -> A_x, 0 -> O_x; 7 (the coupler's moment,
    # with A_y = B_y - h3 from row 3) -> B_y; then 3, 1 and 5. cos(delta) > 0 (L > r+|e|).
    b, L = mech.b, mech.L
    B_x = -h[4]
    A_x = B_x - h[2]
    B_y = (h[7] - b * ca.sin * A_x - (L - b) * ca.sin * B_x + b * ca.cos * h[3]) / (L * ca.cos)
    A_y = B_y - h[3]
    return Reactions(O=jnp.stack([h[0] - A_x, h[1] - A_y]), A=jnp.stack([A_x, A_y]),
                     B=jnp.stack([B_x, B_y]), N=h[5] + B_y,
                     F=guide_friction(mech, gf.J[4] * dphi))
