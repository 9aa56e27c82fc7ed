"""The parameter combinations of the equation of motion: the one place they are formed,
and their packing into one array for a solver's step loop.

M, K and q are sums of products of a parameter part (`m_p r b`, `g m_s`, `1/w_c`, ...)
and a crank-angle part (the [`geometry`][]). [`coefficients`][] forms every parameter
part once; the term builders in `dynamics.py` multiply them by the geometry.

Why a solver packs them ([`pack`][], [`unpack`][]): inside a step loop every parameter
part is loop-invariant. With traced parameters (every compiled solve: a value change must
not recompile) XLA hoists each one out of the loop as a scalar of its own, and every
kernel of the loop body that reads one takes it as a separate operand. Packed in one array
behind an `optimization_barrier`, the coefficients are one loop-carried buffer that the
kernels slice (XLA does not hoist a bare slice), and a traced solve compiles to the same
loop as one with the parameters as constants (experiments/bench_fusion.py counts the
loop-carried values and kernel operands per step: the fusion table of
docs/benchmarks/performance.md).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array

from .params import SliderCrank
from .structure import Structure

__all__ = ["Coefficients", "coefficients", "pack", "unpack"]

_FULL = Structure()


class Coefficients(NamedTuple):
    """Parameter parts of the equation of motion (SI units; each field has the parameters'
    broadcast shape). Terms a [`Structure`][] leaves out are still formed (and unused)."""

    lam: Array
    """r / L."""
    lam2: Array
    """(r / L)^2."""
    eL: Array
    """e / L."""
    eL2: Array
    """(e / L)^2: with `a1`, `cos(delta)^2 = 1 - (eL2 + sin(phi) (lam2 sin(phi) - a1))`."""
    a1: Array
    """2 r e / L^2."""
    r: Array
    L: Array
    e: Array
    s: Array
    b: Array
    cM0: Array
    """m_c s^2 + I_c (+ m_p r^2 with a coupler): M at delta' = 0 and no slider, kg*m^2."""
    c2: Array
    """2 m_p r b, kg*m^2."""
    c2h: Array
    """m_p r b, kg*m^2."""
    c3: Array
    """m_p b^2 + I_p, kg*m^2."""
    m_s: Array
    gA: Array
    """g (m_c s + m_p r) cos(gamma), N*m: the weight torque's sin(phi) part (m_p r with a
    coupler; gamma = gravity_angle, its factor formed only with `structure.tilt`)."""
    gB: Array
    """g m_p b cos(gamma), N*m."""
    gC: Array
    """g m_s cos(gamma), N."""
    gAy: Array
    """g (m_c s + m_p r) sin(gamma), N*m: gravity's y-part, the weight torque's -cos(phi)
    part (zero without `structure.tilt`)."""
    gBy: Array
    """g m_p b sin(gamma), N*m (zero without `structure.tilt`)."""
    k: Array
    c: Array
    T_c: Array
    inv_wc: Array
    """1 / w_c, s/rad."""
    c_s: Array
    F_s: Array
    inv_ws: Array
    """1 / w_s, s/m."""


def coefficients(mech: SliderCrank, structure: Structure = _FULL) -> Coefficients:
    """The [`Coefficients`][] of `mech`; `structure.coupler` says whether the coupler's
    terms join `cM0` and `gA`, `structure.tilt` whether gravity's direction is formed
    (without it gravity is the paper's -x, with the paper's arithmetic)."""
    r, L, e, s, b = mech.r, mech.L, mech.e, mech.s, mech.b
    m_c, m_p, g = mech.m_c, mech.m_p, mech.g
    inv_L = 1.0 / L
    lam, eL = r * inv_L, e * inv_L
    cM0, gA = m_c * s * s + mech.I_c, m_c * s
    if structure.coupler:
        cM0, gA = cM0 + m_p * r * r, gA + m_p * r
    gA, gB, gC = g * gA, g * m_p * b, g * mech.m_s
    if structure.tilt:
        # Gravity along (-cos gamma, -sin gamma): the x-parts scale by cos, the y-parts by sin.
        cg, sg = jnp.cos(mech.gravity_angle), jnp.sin(mech.gravity_angle)
        gAy, gBy = gA * sg, gB * sg
        gA, gB, gC = gA * cg, gB * cg, gC * cg
    else:
        gAy = gBy = jnp.zeros_like(gA)
    c2h = m_p * r * b
    return Coefficients(
        lam=lam, lam2=lam * lam, eL=eL, eL2=eL * eL, a1=2.0 * lam * eL, r=r, L=L, e=e,
        s=s, b=b, cM0=cM0, c2=2.0 * c2h, c2h=c2h, c3=m_p * b * b + mech.I_p, m_s=mech.m_s,
        gA=gA, gB=gB, gC=gC, gAy=gAy, gBy=gBy, k=mech.k, c=mech.c, T_c=mech.T_c,
        inv_wc=1.0 / mech.w_c, c_s=mech.c_s, F_s=mech.F_s, inv_ws=1.0 / mech.w_s)


def pack(coefs: Coefficients) -> Array:
    """The coefficients as one array, shape (len(Coefficients._fields),) + the parameters'
    shape, behind an `optimization_barrier` so that XLA keeps it one buffer (see the
    module docstring). Differentiable; forms its inputs' graph outside any loop."""
    leaves = jnp.broadcast_arrays(*coefs)
    return jax.lax.optimization_barrier(jnp.stack(leaves))


def unpack(packed: Array) -> Coefficients:
    """[`pack`][]'s inverse: each coefficient a slice of `packed` (inside a loop body, a
    slice the kernels read, not a hoisted scalar)."""
    return Coefficients(*_slices(packed))


@jax.custom_jvp
def _slices(packed):
    """The coefficients as slices of `packed`. Its tangent is one `unstack`, so a reverse
    pass gathers their cotangents with one `stack`: the slices' own transpose pads each
    cotangent to the full array and adds the pads (one per coefficient, 25 then), which
    made a reverse pass of the field dearer (docs/benchmarks/design-figures.md). The
    primal stays slices (see `unpack`)."""
    # `lax.slice` and `lax.squeeze`, the primitives `packed[i]` binds, called directly:
    # jnp's indexing costs ~0.6 ms of tracing per slice, ~0.1 s per field traced.
    rest = packed.shape[1:]
    return tuple(jax.lax.squeeze(jax.lax.slice(packed, (i,) + (0,) * len(rest),
                                               (i + 1,) + rest), (0,))
                 for i in range(len(Coefficients._fields)))


@_slices.defjvp
def _slices_jvp(primals, tangents):
    (packed,), (dpacked,) = primals, tangents
    return _slices(packed), tuple(jnp.unstack(dpacked))
