"""sin, cos and 1/sqrt as plain arithmetic, so that XLA:CPU vectorises a batch's step.

Why not `jnp.sin` and `jnp.cos` in a batch: on XLA:CPU a float64 `sin` or `cos` is a
scalar call into the math library per element, many times the cost of a multiply or an
add over a batch (SIMD), and one such call in a fused kernel keeps LLVM from vectorising
the whole kernel. Every field
evaluation needs both, a Dormand-Prince 8 step has 12 of them. [`sincos`][] computes the
pair from one range reduction and two short polynomials (fdlibm's `__kernel_sin` /
`__kernel_cos` coefficients, as in glibc and musl), all multiplies, adds and selects that
XLA fuses into the step's kernels (experiments/bench_fusion.py times both forms; the
figures on docs/benchmarks/design-figures.md).

[`rsqrt`][] is the same story for `1/sqrt(u)` (the geometry's `1/cos(delta)`): XLA:CPU's
float64 `rsqrt`, which is also what it makes of `1/sqrt`, is a scalar call, and with it
in a kernel of ten cheap ops the kernel costs several times what it does with this one.
`sqrt` and a division vectorise but are two "expensive"
ops that XLA will not duplicate into consumers, so each became a kernel of its own per
stage (68 kernels per step instead of 29). The seed is the bit-level estimate of
`1/sqrt` (the "fast inverse square root" with the float64 constant; relative error
<= 3.5%), refined by four Newton steps (quadratic convergence: 3.5e-2, 1.8e-3, 5e-6,
4e-11, then rounding): within 2 ulp of `1/np.sqrt` over positive normal floats.

Which form is an explicit, static choice (numerics are arguments or fields, not
context state): each function takes `form`, a [`Trig`][], and a module that traces them
(the crank's fields, the harmonic loads) holds it in a static field made by
[`form_field`][], default `Trig.LIBRARY` (its name, `"library"` or `"arithmetic"`, is
converted when the module is made). A solver that wants the arithmetic form asks for
the field in it with [`traced_as`][]: the lockstep batch (solve/lockstep.py) and the
discrete adjoint's vectorised blocks (solve/adjoint.py) do. A user's own field offers no
choice and is stepped as it is. A single trajectory has nothing to vectorise (the same
run time either way), and the polynomials made its programs slower to compile, which
every command-line fit and the test suite would pay (docs/benchmarks/design-figures.md).
The two forms agree to 1-2 ulp; the form is part
of the field's static structure, so a compiled program's key says which one it holds.

Accuracy of [`sincos`][] (tests/test_trig.py checks it against NumPy): within 1 ulp of
the correctly rounded value for |x| <= 1e3 rad, 2 ulp to 1e6 rad. The reduction
subtracts n*pi/2 in three parts (Cody-Waite; each part has 33 bits, so `n * part` is
exact for |n| < 2^20, |x| < 1.6e6 rad). Beyond that the absolute error grows like
ulp(x): the error of the angle itself in float64, so a crank that has turned 10^6 times
has lost those digits already in `phi`. Derivatives are the exact identities
(`custom_jvp`: d sin = cos dx, d cos = -sin dx, d u^-1/2 = -u^-3/2 du / 2), not those of
the polynomials.

GPU: the same arithmetic runs there (CUDA's own sin is a polynomial of this kind).
"""

from __future__ import annotations

import copy
import dataclasses
import enum

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

__all__ = ["Trig", "LIBRARY", "ARITHMETIC", "FORMS", "form_field", "as_form",
           "traced_as", "sincos", "sin", "rsqrt"]


class Trig(enum.StrEnum):
    """How sin, cos and 1/sqrt are traced (equal to its name, so a key or a comparison
    that met the name meets the same value)."""

    LIBRARY = "library"  # JAX's own `sin`, `cos` and `rsqrt` (cheaper to compile)
    ARITHMETIC = "arithmetic"  # this module's arithmetic, for float64 (others: JAX's own)


#: The default form, and the one a lockstep batch steps.
LIBRARY, ARITHMETIC = Trig.LIBRARY, Trig.ARITHMETIC
#: The names a `form` argument or a [`form_field`][] takes.
FORMS: tuple[str, ...] = tuple(f.value for f in Trig)

# Marks the field that [`traced_as`][] sets (a name alone could be a user's own field's).
_MARK = "crank_jax_trig_form"


def form_field():
    """A module's static field `trig`, a [`Trig`][] (default `Trig.LIBRARY`; a name of
    [`FORMS`][] is converted, anything else refused by [`as_form`][]): how the module
    traces sin, cos and 1/sqrt. [`traced_as`][] sets it."""
    return eqx.field(static=True, default=LIBRARY, converter=as_form,
                     metadata={_MARK: True})


def as_form(form) -> Trig:
    """`form` (a [`Trig`][] or its name) as a [`Trig`][]; `ValueError` naming the field
    otherwise."""
    if not isinstance(form, str) or form not in FORMS:
        raise ValueError(f"trig must be one of {FORMS}, got {form!r}")
    return Trig(form)


def _chooses(x) -> bool:
    return isinstance(x, eqx.Module) and any(
        f.metadata.get(_MARK) for f in dataclasses.fields(x))


def _set_form(module, form: Trig):
    if not _chooses(module):
        return module
    # A copy with the static field changed, set as JAX's unflattening sets fields (no
    # __init__): a partitioned module (None for its arrays, `eqx.partition`) cannot pass
    # its converters. Its other fields may hold such modules too (a field's loads).
    new = copy.copy(module)
    for f in dataclasses.fields(module):
        if f.metadata.get(_MARK):
            object.__setattr__(new, f.name, form)
        elif not f.metadata.get("static"):
            object.__setattr__(new, f.name, traced_as(getattr(module, f.name), form))
    return new


def traced_as(tree, form: Trig | str):
    """`tree` (a vector field, a load, any pytree) with every module in it that holds a
    [`form_field`][] set to `form`: what a solver steps to have the field's sin, cos and
    1/sqrt traced in that form. Parts that offer no choice (a user's own field or load)
    are left as they are. Static fields are not searched."""
    form = as_form(form)
    return jax.tree_util.tree_map(lambda x: _set_form(x, form), tree, is_leaf=_chooses)


def _use_arithmetic(x, form: Trig) -> bool:
    return form == ARITHMETIC and x.dtype == jnp.float64

# pi/2 = _PIO2_1 + _PIO2_2 + _PIO2_3 (fdlibm's pio2_1, pio2_2, pio2_2t): 33 + 33 + 53 bits.
_PIO2_1 = 1.57079632673412561417e+00
_PIO2_2 = 6.07710050630396597660e-11
_PIO2_3 = 2.02226624879595063154e-21
_TWO_OVER_PI = 6.36619772367581382433e-01

# fdlibm k_sin.c / k_cos.c: minimax polynomials on |r| <= pi/4.
_S = (-1.66666666666666324348e-01, 8.33333333332248946124e-03,
      -1.98412698298579493134e-04, 2.75573137070700676789e-06,
      -2.50507602534068634195e-08, 1.58969099521155010221e-10)
_C = (4.16666666666666019037e-02, -1.38888888888741095749e-03,
      2.48015872894767294178e-05, -2.75573143513906633035e-07,
      2.08757232129817482790e-09, -1.13596475577881948265e-11)


def _horner(z, coefs):
    acc = coefs[-1]
    for c in coefs[-2::-1]:
        acc = c + z * acc
    return acc


@jax.custom_jvp
def _sincos(x):
    n = jnp.round(x * _TWO_OVER_PI)
    r = ((x - n * _PIO2_1) - n * _PIO2_2) - n * _PIO2_3  # |r| <= pi/4
    z = r * r
    s = r + r * z * _horner(z, _S)
    # cos(r) = 1 - z/2 + z^2 C(z), summed as fdlibm does to keep the last bit.
    hz = 0.5 * z
    w = 1.0 - hz
    c = w + (((1.0 - w) - hz) + z * (z * _horner(z, _C)))
    # The quadrant n mod 4, exactly in floating point (n is an integer-valued float).
    q = n - 4.0 * jnp.floor(0.25 * n)
    sin_x = jnp.where(q == 0.0, s, jnp.where(q == 1.0, c, jnp.where(q == 2.0, -s, -c)))
    cos_x = jnp.where(q == 0.0, c, jnp.where(q == 1.0, -s, jnp.where(q == 2.0, -c, s)))
    return sin_x, cos_x


def sincos(x: ArrayLike, form: Trig = LIBRARY) -> tuple[Array, Array]:
    """`(sin(x), cos(x))` of an angle `x` in rad, any shape.

    With `form="arithmetic"` and for float64 the polynomial form: within 1 ulp of
    `jnp.sin`/`jnp.cos` for |x| <= 1e3 (see the module docstring) and much cheaper per
    element in a batch on XLA:CPU (docs/benchmarks/design-figures.md). Otherwise
    `jnp.sin`/`jnp.cos`.
    """
    x = jnp.asarray(x)
    if not _use_arithmetic(x, form):
        return jnp.sin(x), jnp.cos(x)
    return _sincos(x)


@_sincos.defjvp
def _sincos_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    s, c = _sincos(x)
    return (s, c), (c * dx, -s * dx)


def sin(x: ArrayLike, form: Trig = LIBRARY) -> Array:
    """`sin(x)` through [`sincos`][] (the unused cosine is removed by XLA)."""
    return sincos(x, form)[0]


_RSQRT_MAGIC = 0x5FE6EB50C7B537A9  # the float64 constant of the bit-level 1/sqrt estimate


@jax.custom_jvp
def _rsqrt(u):
    bits = jax.lax.bitcast_convert_type(u, jnp.int64)
    w = jax.lax.bitcast_convert_type(jnp.int64(_RSQRT_MAGIC) - (bits >> 1), jnp.float64)
    h = 0.5 * u
    for _ in range(3):
        w = w * (1.5 - h * w * w)
    # The last step as a correction to w (one rounding less: within 2 ulp, not 3).
    w = w + w * (0.5 - h * w * w)
    # u <= 0 (a mechanism that cannot close) gives NaN, as jax.lax.rsqrt's would for u < 0,
    # so that the solver's finiteness checks see it.
    return jnp.where(u > 0.0, w, jnp.nan)


def rsqrt(u: ArrayLike, form: Trig = LIBRARY) -> Array:
    """`1/sqrt(u)`, any shape. With `form="arithmetic"` and for float64 the Newton form:
    within 2 ulp for positive normal `u`, NaN for `u <= 0`. Otherwise `jax.lax.rsqrt`."""
    u = jnp.asarray(u)
    if not _use_arithmetic(u, form):
        return jax.lax.rsqrt(u)
    return _rsqrt(u)


@_rsqrt.defjvp
def _rsqrt_jvp(primals, tangents):
    (u,), (du,) = primals, tangents
    w = _rsqrt(u)
    return w, -0.5 * (w * w * w) * du
