"""Time-dependent loads: the slider force P(t) (N, along -x) and the crank torque tau(t)
(N*m, about +z), and the ONE table of load kinds and their parameter names.

Each load is an `eqx.Module` with `__call__(t) -> value`; its kind (its class, and a
sampled load's interpolation) is static structure, its numbers are dynamic arrays, so
amplitudes can be fitted and vmapped without recompiling.

**The table.** Scenes (TOML), fits (`free=`) and sweeps (`samples=`) name load parameters
the same way, through [`LOAD_KINDS`][] and [`LOAD_PARAMS`][]. A *side* is `"load"` (the
slider force, prefix `P`) or `"torque"` (prefix `tau`); a *role* is one of [`ROLES`][]:

| role      | parameter name     | TOML key (in `[load]`/`[torque]`) |
|-----------|--------------------|-----------------------------------|
| `mean`    | `P0`, `tau0`       | `P0`, `tau0`                      |
| `amp`     | `P1`, `tau1`       | `P1`, `tau1`                      |
| `freq_hz` | `P_freq_hz`, ...   | `freq_hz`                         |
| `phase`   | `P_phase`, ...     | `phase`                           |
| `gain`    | `P_gain`, `tau_gain` | `gain`                          |

An [`InputLoad`][] is driven by a measured input `u(t)` (a record's column, e.g. a motor
voltage) through a gain: `X(t) = X0 + X1 sin(2 pi f t + phase) + gain u(t)`; its TOML
table names the column, `input = "volts"`.

Each kind declares which roles it has (a [`MultiSineLoad`][] has only `mean`; a
[`SampledLoad`][] none), so asking a kind for a role it lacks is refused by name.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from . import trig
from .angle_load import AngleLoad
from .load_base import AbstractLoad, Nonsmooth, check_load_values
from .params import as_float_array
from .sampled import INTERPOLATIONS, InputLoad, SampledLoad, is_sampled
from .trig import Trig, form_field

__all__ = ["AbstractLoad", "NoLoad", "ConstantLoad", "HarmonicLoad", "MultiSineLoad",
           "SampledLoad", "InputLoad", "AngleLoad", "is_sampled", "as_load",
           "INTERPOLATIONS", "Nonsmooth",
           "nonsmooth_times",
           "ROLES", "SIDES", "LoadKind", "LOAD_KINDS", "LOAD_PARAMS", "load_kind",
           "param_name", "toml_key", "get_param", "set_param", "promote", "toml_keys",
           "load_from_table", "load_to_table", "OWN_LOADS", "only_own_loads"]



class NoLoad(AbstractLoad):
    """No load at all. The dynamics skip every term it would multiply."""

    def __call__(self, t: ArrayLike) -> Array:
        return jnp.zeros_like(jnp.asarray(t, dtype=float))

    def mean(self) -> Array:
        return jnp.asarray(0.0)


class ConstantLoad(AbstractLoad):
    """`X(t) = value` (N or N*m)."""

    value: Float[Array, ""] = eqx.field(converter=as_float_array)

    def __check_init__(self):
        check_load_values(self, ("value",))

    def __call__(self, t: ArrayLike) -> Array:
        return self.value + jnp.zeros_like(jnp.asarray(t, dtype=float))

    def mean(self) -> Array:
        return self.value


class HarmonicLoad(AbstractLoad):
    """`X(t) = X0 + X1 sin(2 pi freq_hz t + phase)`.

    **Arguments:** `X0` mean and `X1` amplitude (N or N*m), `freq_hz` (Hz), `phase` (rad).
    """

    X0: Float[Array, ""] = eqx.field(converter=as_float_array)
    X1: Float[Array, ""] = eqx.field(converter=as_float_array)
    freq_hz: Float[Array, ""] = eqx.field(converter=as_float_array)
    phase: Float[Array, ""] = eqx.field(converter=as_float_array, default=0.0)
    trig: Trig = form_field()  # how sin is traced (trig.py): a solver's choice

    def __check_init__(self):
        check_load_values(self, ("X0", "X1", "freq_hz", "phase"), frequencies=("freq_hz",))

    def __call__(self, t: ArrayLike) -> Array:
        return self.X0 + self.X1 * trig.sin(2 * jnp.pi * self.freq_hz * t + self.phase,
                                            self.trig)

    def mean(self) -> Array:
        return self.X0


class MultiSineLoad(AbstractLoad):
    """An identification excitation: `X(t) = X0 + sum_j a_j sin(2 pi f_j t + p_j)`.

    A sum of sines at several frequencies excites the mechanism's nonlinear terms with
    different shapes, which separates masses and inertias that a single tone cannot.

    **Arguments:** `amplitudes` (k,), N or N*m; `freqs_hz` (k,), Hz; `phases` (k,), rad;
    `X0`, the mean.
    """

    amplitudes: Float[Array, " k"] = eqx.field(converter=as_float_array)
    freqs_hz: Float[Array, " k"] = eqx.field(converter=as_float_array)
    phases: Float[Array, " k"] = eqx.field(converter=as_float_array)
    X0: Float[Array, ""] = eqx.field(converter=as_float_array, default=0.0)
    trig: Trig = form_field()  # how sin is traced (trig.py): a solver's choice

    def __check_init__(self):
        arrays = (self.amplitudes, self.freqs_hz, self.phases)
        shapes = [np.shape(a) for a in arrays]
        if len(set(shapes)) > 1 or 0 in shapes[0]:
            raise ValueError(f"MultiSineLoad needs amplitudes, freqs_hz and phases of one "
                             f"length >= 1 (one entry per sine), got shapes {shapes}")
        check_load_values(self, ("amplitudes", "freqs_hz", "phases", "X0"),
                          frequencies=("freqs_hz",))

    def __call__(self, t: ArrayLike) -> Array:
        t = jnp.asarray(t, dtype=float)[..., None]
        arg = 2 * jnp.pi * self.freqs_hz * t + self.phases
        return self.X0 + jnp.sum(self.amplitudes * trig.sin(arg, self.trig), axis=-1)

    def mean(self) -> Array:
        return self.X0


def as_load(x: AbstractLoad | ArrayLike | None) -> AbstractLoad:
    """`None` -> [`NoLoad`][]; a number -> [`ConstantLoad`][]; a load -> itself."""
    if x is None:
        return NoLoad()
    if isinstance(x, AbstractLoad):
        return x
    return ConstantLoad(x)


def nonsmooth_times(*loads: AbstractLoad) -> Nonsmooth:
    """The sorted union of the loads' [`Nonsmooth`][] times (`None` where there are none),
    for a step-size controller's `step_ts` and `jump_ts`."""
    parts = [x.nonsmooth() for x in loads]
    step = [p.step_ts for p in parts if p.step_ts is not None]
    jump = [p.jump_ts for p in parts if p.jump_ts is not None]
    return Nonsmooth(jnp.sort(jnp.concatenate(step)) if step else None,
                     jnp.sort(jnp.concatenate(jump)) if jump else None)


# ---------------------------------------------------------------------------------------
# The table of load kinds and parameter names

#: Parameter roles a load kind may have (see the module docstring).
ROLES: tuple[str, ...] = ("mean", "amp", "freq_hz", "phase", "gain")
#: Side -> the prefix of its parameter names.
SIDES: dict[str, str] = {"load": "P", "torque": "tau"}


class LoadKind(NamedTuple):
    """One kind of load in the table.

    **Fields:** `name`, its TOML `kind`; `cls`, its class; `fields`, role -> the class's
    field holding that (scalar) parameter; `arrays`, further array fields (written as TOML
    lists); `toml`, whether a scene file can hold it.
    """

    name: str
    cls: type
    fields: dict[str, str]
    arrays: tuple[str, ...] = ()
    toml: bool = True


#: Every kind of load, from the simplest. A scene's load promotes along the first three
#: (none -> constant -> harmonic) when a sweep varies a role the scene's kind lacks.
LOAD_KINDS: tuple[LoadKind, ...] = (
    LoadKind("none", NoLoad, {}),
    LoadKind("constant", ConstantLoad, {"mean": "value"}),
    LoadKind("harmonic", HarmonicLoad,
             {"mean": "X0", "amp": "X1", "freq_hz": "freq_hz", "phase": "phase"}),
    LoadKind("multisine", MultiSineLoad, {"mean": "X0"},
             ("amplitudes", "freqs_hz", "phases")),
    LoadKind("sampled", SampledLoad, {}, toml=False),
    LoadKind("angle", AngleLoad, {}, toml=False),
    LoadKind("input", InputLoad,
             {"mean": "X0", "amp": "X1", "freq_hz": "freq_hz", "phase": "phase",
              "gain": "gain"}),
)
_PROMOTABLE = LOAD_KINDS[:3]

#: The load classes whose code is crank-jax's own: every kind of the table, matched by
#: exact type (a subclass, which may override any method, is a user's class).
OWN_LOADS: frozenset[type] = frozenset(kind.cls for kind in LOAD_KINDS)

# Static values equal exactly when their values are (what JAX's trace cache compares);
# the model's own enum of the trigonometry's form (`trig.Trig`) is one.
_PLAIN = (type(None), bool, int, float, complex, str, trig.Trig)
_MAX_DEPTH = 8  # the table's kinds nest three deep (AngleLoad -> SampledLoad -> coeffs)


def only_own_loads(*loads) -> bool:
    """Whether `loads` hold crank-jax's own code only, at any depth: each is exactly one
    of [`OWN_LOADS`][], and each of its fields is an array, a plain value (None, bool,
    int, float, complex, str, [`Trig`][crank_jax.model.trig.Trig]), a tuple of these or
    again such a load. A closed test on the objects alone: a user's class or subclass
    anywhere, a function or any other object in a field (static or not) makes it False."""
    return all(_own(x, 0) for x in loads)


def _own(x, depth: int) -> bool:
    if depth > _MAX_DEPTH:
        return False
    if type(x) in _PLAIN:
        return True
    if isinstance(x, np.ndarray):
        return x.dtype != object  # an object array holds anything
    if isinstance(x, (jax.Array, np.generic)):
        return True
    if type(x) is tuple:
        return all(_own(v, depth + 1) for v in x)
    if type(x) in OWN_LOADS:
        return all(_own(getattr(x, f.name), depth + 1) for f in dataclasses.fields(x))
    return False


def param_name(side: str, role: str) -> str:
    """The public name of a parameter: `("load", "mean") -> "P0"`, `("torque",
    "freq_hz") -> "tau_freq_hz"`."""
    p = SIDES[side]
    return {"mean": f"{p}0", "amp": f"{p}1"}.get(role, f"{p}_{role}")


def toml_key(side: str, role: str) -> str:
    """The key of a parameter in a scene's `[load]`/`[torque]` table."""
    return param_name(side, role) if role in ("mean", "amp") else role


#: Every load parameter name -> `(side, role)`: `P0`, `P1`, `P_freq_hz`, `P_phase`,
#: `tau0`, `tau1`, `tau_freq_hz`, `tau_phase`.
LOAD_PARAMS: dict[str, tuple[str, str]] = {
    param_name(side, role): (side, role) for side in SIDES for role in ROLES}


def load_kind(load: AbstractLoad | str) -> LoadKind:
    """The table entry of a load (or of a kind name); `ValueError` for an unknown one."""
    for kind in LOAD_KINDS:
        if kind.name == load or isinstance(load, kind.cls):
            return kind
    known = [k.name for k in LOAD_KINDS]
    what = load if isinstance(load, str) else type(load).__name__
    raise ValueError(f"unknown load kind {what!r}; the kinds are {known}")


def _lacks(load: AbstractLoad, side: str, role: str) -> ValueError:
    kind = load_kind(load)
    has = [param_name(side, r) for r in kind.fields] or "none"
    return ValueError(f"the {side} is a {type(load).__name__} ({kind.name}), which has no "
                      f"{param_name(side, role)}; its parameters are {has}")


def get_param(load: AbstractLoad, role: str) -> Array | None:
    """The value of `role` (see [`ROLES`][]) of a load, or `None` if its kind lacks it."""
    field = load_kind(load).fields.get(role)
    return None if field is None else getattr(load, field)


def set_param(load: AbstractLoad, role: str, value, side: str = "load") -> AbstractLoad:
    """A copy of `load` with `role` set to `value` (an array: traced values are fine).
    `ValueError` naming the kind's parameters if it lacks the role."""
    field = load_kind(load).fields.get(role)
    if field is None:
        raise _lacks(load, side, role)
    return eqx.tree_at(lambda x: getattr(x, field), load, value)


def promote(load: AbstractLoad, roles, side: str = "load") -> AbstractLoad:
    """The simplest load equal to `load` whose kind has every role in `roles`: a
    [`NoLoad`][] or [`ConstantLoad`][] becomes constant or harmonic as needed. Other kinds
    are returned as they are, or refused (`ValueError`) if they lack a role."""
    roles = set(roles)
    kind = load_kind(load)
    if roles <= set(kind.fields):
        return load
    if kind not in _PROMOTABLE:
        raise _lacks(load, side, sorted(roles - set(kind.fields))[0])
    mean = get_param(load, "mean")
    mean = 0.0 if mean is None else mean
    if roles <= {"mean"}:
        return ConstantLoad(mean)
    return HarmonicLoad(mean, 0.0, 0.0, 0.0)


# ---------------------------------------------------------------------------------------
# Scene files: a load as a `[load]` / `[torque]` TOML table


def toml_keys(side: str) -> tuple[str, ...]:
    """Every key a scene's `[load]`/`[torque]` table may hold."""
    keys = ["kind"] + [toml_key(side, r) for r in ROLES]
    return tuple(keys + [a for k in LOAD_KINDS for a in k.arrays] + ["input"])


def _toml_number(side: str, key: str, v) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise ValueError(f"[{side}] {key} must be a finite number, got {v!r}")
    return float(v)


def load_from_table(table: dict, side: str) -> AbstractLoad:
    """Build a load from a scene's `[load]`/`[torque]` table (see [`load_to_table`][]).

    Without `kind`, the table is a harmonic load whose zero terms are dropped: no
    amplitude gives a constant load, nothing at all gives [`NoLoad`][] (whose terms the
    compiled program then skips). Raises `ValueError` naming the table and key.
    """
    name = table.get("kind", "input" if "input" in table else None)
    kind = next((k for k in LOAD_KINDS if k.name == ("harmonic" if name is None else name)),
                None)
    if kind is None or not kind.toml:
        ok = [k.name for k in LOAD_KINDS if k.toml]
        why = {"sampled": " (sampled loads come from a data file's P/tau columns)",
               "angle": " (angle tables come from a record's P/tau columns with "
                        "`load_by='angle'`)"}.get(name, "")
        raise ValueError(f"[{side}] kind {name!r} cannot be used in a scene{why}; choose "
                         f"from {ok}")
    allowed = ({toml_key(side, r) for r in kind.fields} | set(kind.arrays) | {"kind"}
               | ({"input"} if kind.cls is InputLoad else set()))
    for key in table:
        if key not in allowed:
            raise ValueError(f"[{side}] key {key!r} does not apply to kind {kind.name!r}; "
                             f"its keys are {sorted(allowed)}")
    vals = {r: _toml_number(side, toml_key(side, r), table.get(toml_key(side, r), 0.0))
            for r in kind.fields}
    if vals.get("freq_hz", 0.0) < 0:
        raise ValueError(f"[{side}] freq_hz must be >= 0, got {vals['freq_hz']}")
    if name is None and not vals["amp"]:
        kind = LOAD_KINDS[1] if vals["mean"] else LOAD_KINDS[0]
    arrays = {}
    for a in kind.arrays:
        v = table.get(a)
        if not isinstance(v, list) or not v:
            raise ValueError(f"[{side}] kind {kind.name!r} needs {a} = a list of numbers")
        arrays[a] = [_toml_number(side, a, x) for x in v]
    if len({len(v) for v in arrays.values()}) > 1:
        raise ValueError(f"[{side}] {', '.join(kind.arrays)} must have equal lengths")
    if kind.name == "multisine" and min(arrays["freqs_hz"]) < 0:
        raise ValueError(f"[{side}] freqs_hz must be >= 0")
    fields = {kind.fields[r]: v for r, v in vals.items() if r in kind.fields}
    if kind.cls is InputLoad:
        column = table.get("input")
        if not (isinstance(column, str) and column):
            raise ValueError(f"[{side}] kind 'input' needs input = the record's column of the "
                             "input (e.g. input = \"volts\")")
        return InputLoad(column=column, **fields)
    return kind.cls(**fields, **arrays)


def load_to_table(load: AbstractLoad, side: str) -> dict | None:
    """The `[load]`/`[torque]` table of a load (`None` for [`NoLoad`][]), which
    [`load_from_table`][] reads back; `ValueError` for a kind a scene cannot hold."""
    kind = load_kind(load)
    if not kind.toml:
        raise ValueError(f"a {type(load).__name__} cannot be written to a scene file; keep "
                         "it as data (a record's P/tau columns)")
    if kind.name == "none":
        return None
    out: dict = {"kind": kind.name}
    out.update({toml_key(side, r): float(np.asarray(getattr(load, f)))
                for r, f in kind.fields.items()})
    out.update({a: [float(x) for x in np.asarray(getattr(load, a))] for a in kind.arrays})
    if isinstance(load, InputLoad):
        out["input"] = load.column
    return out
