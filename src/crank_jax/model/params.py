"""Physical parameters of the slider-crank: geometry, inertia, crank-axis shaft, gravity
(strength and in-plane direction), slider offset and joint friction; their validation (one
rule list, used for concrete values at construction and for traced values inside `jit`)."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

__all__ = ["SliderCrank", "FIELDS", "PAPER_FIELDS", "SIGNED_FIELDS", "WIDTH_FIELDS",
           "SCALE_GROUP", "FRICTION_SCALED", "check_shapes", "UNITS", "as_float_array",
           "validation_rules"]

#: The paper's twelve mechanism fields, in the order of its symbol table.
PAPER_FIELDS: tuple[str, ...] = ("r", "L", "b", "s", "m_c", "m_p", "m_s", "I_c", "I_p", "k",
                                 "c", "g")
#: Every field: the paper's, then the slider offset and the friction terms (DESIGN.md §1
#: "Beyond the paper"), each zero by default except the two smoothing widths, then the
#: direction of gravity (§1 "Beyond the paper, second step"; 0 is the paper's -x).
FIELDS: tuple[str, ...] = PAPER_FIELDS + ("e", "T_c", "w_c", "c_s", "F_s", "w_s",
                                          "gravity_angle")
#: Fields that may be negative (log coordinates do not apply to them).
SIGNED_FIELDS: tuple[str, ...] = ("e", "gravity_angle")
#: Smoothing widths of the Coulomb terms: numerical choices, not physical parameters.
WIDTH_FIELDS: tuple[str, ...] = ("w_c", "w_s")
#: Fields that enter the equation of motion linearly: scaling all of them (and every
#: load) by one factor leaves the motion unchanged (DESIGN.md section 3).
SCALE_GROUP: tuple[str, ...] = ("m_c", "m_p", "m_s", "I_c", "I_p", "k", "c")
#: Friction coefficients: they scale with that group too (every term of the equation of
#: motion is then multiplied by the same factor); their true value is often 0.
FRICTION_SCALED: tuple[str, ...] = ("c_s", "T_c", "F_s")

UNITS: dict[str, str] = {
    "r": "m", "L": "m", "b": "m", "s": "m", "m_c": "kg", "m_p": "kg", "m_s": "kg",
    "I_c": "kg*m^2", "I_p": "kg*m^2", "k": "N*m/rad", "c": "N*m*s/rad", "g": "m/s^2",
    "e": "m", "T_c": "N*m", "w_c": "rad/s", "c_s": "N*s/m", "F_s": "N", "w_s": "m/s",
    "gravity_angle": "rad",
}
_DEFAULTS = {"g": 9.81, "e": 0.0, "T_c": 0.0, "w_c": 0.01, "c_s": 0.0, "F_s": 0.0,
             "w_s": 0.001, "gravity_angle": 0.0}


def as_float_array(x: ArrayLike) -> Array:
    """`x` as a strongly typed float array (float64 under x64); tracers pass through.

    A Python int too large for a float (e.g. 400 digits) becomes +-inf, so validation
    reports "must be finite" rather than an `OverflowError`.
    """
    if isinstance(x, int) and not isinstance(x, bool):
        try:
            x = float(x)
        except OverflowError:
            x = math.inf if x > 0 else -math.inf
    # Python floats would become weakly-typed; an explicit float array keeps the pytree's
    # dtype stable (float64 under x64) so a new value never means a new compilation.
    if isinstance(x, jax.core.Tracer):
        return x
    is_array = isinstance(x, (jax.Array, np.ndarray, np.generic))
    if is_array and jnp.issubdtype(x.dtype, jnp.floating):
        return jnp.asarray(x)
    # Strongly typed: a weakly-typed Python float would compile a different program than
    # a float64 array of the same value.
    return jnp.asarray(x, dtype=jax.dtypes.canonicalize_dtype(jnp.float64))


def validation_rules(v: dict[str, np.ndarray]) -> list[tuple[str, np.ndarray, str]]:
    """Every validation rule, the one place they are written.

    **Arguments:** `v`, field name -> value (numpy arrays for concrete values, jax arrays
    or tracers for traced ones); fields missing from `v` take their defaults.

    **Returns:** a list of `(field, violated-mask, rule and fix)`.
    """
    v = {**_DEFAULTS, **v}
    xp = jnp if any(isinstance(a, jax.Array) for a in v.values()) else np
    rules = [(name, ~xp.isfinite(v[name]), f"{name} must be finite (got NaN or inf)")
             for name in FIELDS]
    rules += [
        ("r", v["r"] <= 0, "r must be > 0 (crank radius O->A, meters)"),
        ("L", v["L"] <= v["r"] + xp.abs(v["e"]),
         "L must be > r + |e| (coupler longer than crank plus offset), else the crank locks"),
        ("s", v["s"] < 0, "s must be >= 0 (distance O->crank center of mass, meters)"),
        ("b", (v["b"] < 0) | (v["b"] > v["L"]), "b must satisfy 0 <= b <= L (A->coupler CoM)"),
    ]
    for name in ("m_c", "m_p", "m_s", "I_c", "I_p"):
        rules.append((name, v[name] < 0,
                      f"{name} must be >= 0 ({UNITS[name]}); use 0 for an absent body"))
    rules += [
        ("I_c", v["m_c"] * v["s"] ** 2 + v["I_c"] <= 0,
         "m_c*s^2 + I_c must be > 0 so that M(phi) > 0: give the crank an inertia I_c"),
        ("k", v["k"] < 0, "k must be >= 0 (torsional stiffness, N*m/rad)"),
        ("g", v["g"] < 0, "g must be >= 0 (m/s^2; 0 for a horizontal table): give its "
         "direction with gravity_angle, e.g. pi for gravity along +x"),
        ("c", v["c"] < 0, "c must be >= 0 (torsional damping, N*m*s/rad)"),
    ]
    for name in ("T_c", "c_s", "F_s"):
        rules.append((name, v[name] < 0, f"{name} must be >= 0 ({UNITS[name]}); use 0 for "
                      "no friction"))
    for name in WIDTH_FIELDS:
        rules.append((name, v[name] <= 0, f"{name} must be > 0 ({UNITS[name]}; smoothing "
                      f"width of the Coulomb term, default {_DEFAULTS[name]})"))
    return rules


def check_shapes(shapes: dict[str, tuple[int, ...]]) -> None:
    """Raise a `ValueError` naming the fields whose shapes do not broadcast together."""
    try:
        np.broadcast_shapes(*shapes.values())
    except ValueError:
        shown = ", ".join(f"{n} {s}" for n, s in shapes.items() if s != ())
        raise ValueError(f"SliderCrank fields have shapes that do not broadcast together: "
                         f"{shown}; give every batched field one shape (or a scalar)") from None


class SliderCrank(eqx.Module):
    """Parameters of a slider-crank with a flexible crank axis, all in SI units.

    Every field is a floating-point array (a scalar, or a batch under `jax.vmap`), so one
    compiled function serves every value and the object can be differentiated and vmapped.

    **Arguments:**

    - `r`: crank radius O->A, m. `L`: coupler length A->B, m (`L > r`).
    - `b`: distance A->coupler centre of mass along the coupler, m (`0 <= b <= L`).
    - `s`: distance O->crank centre of mass, m (`s >= 0`).
    - `m_c`, `m_p`, `m_s`: masses of crank, coupler and slider, kg (`>= 0`).
    - `I_c`, `I_p`: moments of inertia of crank and coupler about z at their centres of
      mass, kg*m^2 (`>= 0`, and `m_c*s^2 + I_c > 0`).
    - `k`: torsional stiffness of the crank axis, N*m/rad. `c`: its damping, N*m*s/rad.
    - `g`: gravitational acceleration, m/s^2 (`>= 0`; 0 switches gravity off: a horizontal
      table), along `(-cos(gravity_angle), -sin(gravity_angle))`.
    - `e`: offset of the slider's line from O, m (the slider runs along `y = e`; signed;
      `L > r + |e|`).
    - `T_c`: Coulomb friction torque of the crank bearing, N*m (`>= 0`), smoothed as
      `T_c tanh(phi'/w_c)`; `w_c`: its width, rad/s (`> 0`, default 0.01).
    - `c_s`: viscous friction of the slider guide, N*s/m (`>= 0`). `F_s`: its Coulomb
      friction force, N (`>= 0`), smoothed as `F_s tanh(v_s/w_s)`; `w_s`: its width, m/s
      (`> 0`, default 0.001).
    - `gravity_angle`: direction of gravity in the mechanism's plane, rad (any finite
      value, default 0): gravity pulls along `(-cos, -sin)` of it, x along the slider's
      line, y perpendicular to it. 0 is the paper's -x, pi/2 pulls along -y.

    Every field but the paper's twelve defaults to zero (the widths to the values above); a
    zero term is compiled out (see `Structure`). Field shapes must broadcast together.

    Concrete values are validated at construction (a `ValueError` naming the field and the
    rule). Traced values are checked inside `jit` by [`SliderCrank.checked`][] with
    `eqx.error_if`, which every simulation calls.
    """

    r: Float[Array, ...] = eqx.field(converter=as_float_array)
    L: Float[Array, ...] = eqx.field(converter=as_float_array)
    b: Float[Array, ...] = eqx.field(converter=as_float_array)
    s: Float[Array, ...] = eqx.field(converter=as_float_array)
    m_c: Float[Array, ...] = eqx.field(converter=as_float_array)
    m_p: Float[Array, ...] = eqx.field(converter=as_float_array)
    m_s: Float[Array, ...] = eqx.field(converter=as_float_array)
    I_c: Float[Array, ...] = eqx.field(converter=as_float_array)
    I_p: Float[Array, ...] = eqx.field(converter=as_float_array)
    k: Float[Array, ...] = eqx.field(converter=as_float_array)
    c: Float[Array, ...] = eqx.field(converter=as_float_array)
    g: Float[Array, ...] = eqx.field(converter=as_float_array, default=_DEFAULTS["g"])
    e: Float[Array, ...] = eqx.field(converter=as_float_array, default=_DEFAULTS["e"])
    T_c: Float[Array, ...] = eqx.field(converter=as_float_array, default=_DEFAULTS["T_c"])
    w_c: Float[Array, ...] = eqx.field(converter=as_float_array, default=_DEFAULTS["w_c"])
    c_s: Float[Array, ...] = eqx.field(converter=as_float_array, default=_DEFAULTS["c_s"])
    F_s: Float[Array, ...] = eqx.field(converter=as_float_array, default=_DEFAULTS["F_s"])
    w_s: Float[Array, ...] = eqx.field(converter=as_float_array, default=_DEFAULTS["w_s"])
    gravity_angle: Float[Array, ...] = eqx.field(converter=as_float_array,
                                                 default=_DEFAULTS["gravity_angle"])

    def __check_init__(self):
        values = {name: getattr(self, name) for name in FIELDS}
        # Shapes are known even for tracers: a batch that cannot broadcast is refused here.
        if all(hasattr(v, "shape") for v in values.values()):
            check_shapes({n: tuple(v.shape) for n, v in values.items()})
        # Values that are traced (inside jit/vmap/grad) cannot be inspected here; they are
        # checked where they are used, by `checked()`.
        if any(isinstance(v, jax.core.Tracer) for v in values.values()):
            return
        # Arrays placed by JAX transformations (e.g. object() sentinels in tree_map) are skipped.
        if not all(isinstance(v, (jax.Array, np.ndarray, np.generic)) for v in values.values()):
            return
        concrete = {n: np.asarray(v) for n, v in values.items()}
        for name, bad, rule in validation_rules(concrete):
            if np.any(bad):
                raise ValueError(
                    f"SliderCrank.{name} = {_show(concrete[name])} is invalid: {rule}."
                )

    def checked(self) -> SliderCrank:
        """Return `self` with every validation rule enforced by `eqx.error_if`.

        Use this on parameters that may be traced (built inside `jit`/`vmap` from data):
        an invalid value raises at run time with the field and the rule in the message.
        """
        values = {name: getattr(self, name) for name in FIELDS}
        out = dict(values)
        for name, bad, rule in validation_rules(values):
            out[name] = eqx.error_if(out[name], bad, f"SliderCrank.{name} is invalid: {rule}.")
        return SliderCrank(**out)

    def replace(self, **changes: ArrayLike) -> SliderCrank:
        """A copy with some fields changed, e.g. `mech.replace(k=3.0)`."""
        unknown = set(changes) - set(FIELDS)
        if unknown:
            raise ValueError(
                f"unknown SliderCrank field(s) {sorted(unknown)}; valid fields are {list(FIELDS)}"
            )
        return SliderCrank(**{n: changes.get(n, getattr(self, n)) for n in FIELDS})

    def as_dict(self) -> dict[str, float]:
        """The concrete values as Python floats (for reports and TOML)."""
        return {n: float(np.asarray(getattr(self, n))) for n in FIELDS}


def _show(x: np.ndarray) -> str:
    if x.ndim == 0:
        return repr(float(x)) if math.isfinite(float(x)) else str(float(x))
    return f"array(shape={x.shape})"
