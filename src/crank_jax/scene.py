"""Scenes: a mechanism, its loads, an initial state, solver settings and wanted outputs.

A scene's *structure* (which bodies have mass, gravity on/off, the kinds of load, the
solver, the outputs, the number of samples) is static; its *values* are arrays. Scenes
load from TOML (see the README for the format) and ship as presets.
"""

from __future__ import annotations

import importlib.resources
import math
import os
import tomllib
from pathlib import Path
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .model.dynamics import Structure
from .model.loads import (
    AbstractLoad,
    NoLoad,
    load_from_table,
    load_to_table,
    toml_keys,
)
from .model.params import PAPER_FIELDS, SliderCrank, as_float_array
from .records.column_checks import scene_columns_problem
from .records.sensors import (
    Sensor,
    SensorError,
    sensors_from_table,
    sensors_to_table,
)
from .runtime.io import atomic_write
from .simulation import simulate
from .solve.inputs import check_scene_values, check_tolerances  # simulate's own rules
from .solve.policy import SOLVERS
from .solve.trajectory import OUTPUTS, Trajectory

__all__ = ["Scene", "SceneError", "load_scene", "scene_to_toml", "save_scene", "presets",
           "PRESETS", "read_scene_doc"]

#: Preset scene names; `load_scene(name)` loads one.
PRESETS: tuple[str, ...] = ("lab-rig", "torsional", "near-buckling", "pendulum")
DEFAULT_PRESET = "lab-rig"


class SceneError(ValueError):
    """A scene file or value is malformed; the message names the place and the fix."""


class Scene(eqx.Module):
    """Everything one simulation needs.

    **Fields:**

    - `mech`: [`SliderCrank`][] parameters.
    - `load`, `torque`: slider force P(t) (N, along -x) and crank torque tau(t) (N*m).
    - `phi0`, `dphi0`: initial state at t = 0 (rad, rad/s).
    - `rtol`, `atol`: solver tolerances (arrays: changing them never recompiles).
    - `t1`: default end time, s. `samples`: default number of uniform samples on [0, t1].
    - `solver`: a name from [`SOLVERS`][] (static). `outputs`: derived outputs (static).
    - `name`, `description`: labels (static).
    - `sensors`: what a record of this rig measures ([`Sensor`][crank_jax.records.sensors.Sensor]s,
      static; the `[sensors]` table): `synth` writes these channels, `fit` reads them.
    """

    mech: SliderCrank
    load: AbstractLoad = NoLoad()
    torque: AbstractLoad = NoLoad()
    phi0: Array = eqx.field(converter=as_float_array, default=1.0)
    dphi0: Array = eqx.field(converter=as_float_array, default=0.0)
    rtol: Array = eqx.field(converter=as_float_array, default=1e-8)
    atol: Array = eqx.field(converter=as_float_array, default=1e-10)
    t1: float = eqx.field(static=True, default=10.0)
    samples: int = eqx.field(static=True, default=1001)
    solver: str = eqx.field(static=True, default="auto")
    outputs: tuple[str, ...] = eqx.field(static=True, default=())
    name: str = eqx.field(static=True, default="custom")
    description: str = eqx.field(static=True, default="")
    sensors: tuple[Sensor, ...] = eqx.field(static=True, default=())

    def __check_init__(self):
        for side in ("load", "torque"):
            if not isinstance(getattr(self, side), AbstractLoad):
                raise SceneError(f"Scene.{side} must be a load (NoLoad() for none, or "
                                 f"HarmonicLoad, ...), got {getattr(self, side)!r:.60}")
        problem = scene_columns_problem(self.sensors, self.load, self.torque)
        if problem:
            raise SceneError(problem)
        if self.solver not in SOLVERS:
            raise SceneError(f"solver {self.solver!r} is unknown; choose from {list(SOLVERS)}")
        if bad := [o for o in self.outputs if o not in OUTPUTS]:
            raise SceneError(f"output {bad[0]!r} is unknown; choose from {sorted(OUTPUTS)}")
        if not (isinstance(self.samples, int) and self.samples >= 2):
            raise SceneError(f"samples must be an integer >= 2, got {self.samples!r}")
        if not (math.isfinite(self.t1) and self.t1 > 0):
            raise SceneError(f"t1 must be a finite time > 0 s, got {self.t1!r}")
        try:  # analyses check again: `eqx.tree_at` builds a scene without this
            check_scene_values(self.phi0, self.dphi0, self.rtol, self.atol)
        except ValueError as e:
            raise SceneError(f"Scene {e}") from None

    @property
    def structure(self) -> Structure:
        """The static set of equation terms this scene uses."""
        return Structure.of(self.mech)

    def ts(self, t1: float | None = None, samples: int | None = None) -> Array:
        """Uniform save times on [0, t1] inclusive, shape (samples,)."""
        return jnp.linspace(0.0, self.t1 if t1 is None else t1,
                            self.samples if samples is None else samples)

    def simulate(self, ts: Array | None = None, **kwargs: Any) -> Trajectory:
        """Run [`simulate`][] with this scene's settings; keyword arguments override them."""
        opts = dict(load=self.load, torque=self.torque, solver=self.solver, rtol=self.rtol,
                    atol=self.atol, outputs=self.outputs)
        opts.update(kwargs)
        phi0 = opts.pop("phi0", self.phi0)
        dphi0 = opts.pop("dphi0", self.dphi0)
        return simulate(self.mech, phi0, dphi0, self.ts() if ts is None else ts, **opts)


# TOML ----------------------------------------------------------------------------------

#: Optional [mechanism] keys beyond the paper's (default 0), and the [friction] table's
#: keys with the SliderCrank field each sets (default: the field's default).
_OPTIONAL_MECH = ("e", "T_c", "c_s", "F_s", "gravity_angle")
_FRICTION = {"crank_width": "w_c", "slider_width": "w_s"}
_DEFAULT_MECH = {n: float(SliderCrank.__dataclass_fields__[n].default)
                 for n in ("g", *_OPTIONAL_MECH, *_FRICTION.values())}

_TABLES: dict[str, tuple[str, ...]] = {
    "mechanism": PAPER_FIELDS + _OPTIONAL_MECH,
    "friction": tuple(_FRICTION),
    "load": toml_keys("load"),
    "torque": toml_keys("torque"),
    "initial": ("phi0", "dphi0"),
    "solver": ("name", "rtol", "atol"),
    "output": ("t1", "samples", "extras"),
}
# [priors] belongs to the posterior (bayes/posterior.py reads and checks it); [fit]
# marks a fitted scene from a fit that did not converge (identify/fitted.py).
_TOP_KEYS = ("description", "sensors", "priors", "fit")


def _number(where: str, key: str, v: Any) -> float:
    table, name = key.split(".")
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SceneError(f"{where}: [{table}] {name} must be a number, got {_short(v)}")
    try:
        x = float(v)  # an integer beyond float64's range raises OverflowError
    except OverflowError:
        x = math.inf
    if not math.isfinite(x):
        raise SceneError(f"{where}: [{table}] {name} must be finite, got {_short(v)}")
    # Products of a few parameters (m s^2, k / mu, ...) must stay inside float64: beyond
    # this range (far beyond any SI value of a mechanism) they overflow or lose all digits.
    if x != 0 and not _NUMBER_RANGE[0] <= abs(x) <= _NUMBER_RANGE[1]:
        raise SceneError(f"{where}: [{table}] {name} = {x:g} is out of range: use 0 or a "
                         f"magnitude from {_NUMBER_RANGE[0]:g} to {_NUMBER_RANGE[1]:g} (SI "
                         "units)")
    return x


#: Magnitudes a scene number may have, besides 0.
_NUMBER_RANGE = (1e-30, 1e30)


def _short(v: Any, limit: int = 60) -> str:
    """`repr(v)`, cut to `limit` characters: a message stays one readable line."""
    text = repr(v)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _load(where: str, doc: dict, side: str) -> AbstractLoad:
    try:
        return load_from_table(doc.get(side, {}), side)
    except ValueError as e:
        raise SceneError(f"{where}: {e}") from None


def scene_from_dict(doc: dict, where: str = "<scene>", name: str = "custom") -> Scene:
    """Build a [`Scene`][] from a parsed TOML document, rejecting unknown tables and keys."""
    _check_tables(doc, where)
    mech = _mechanism(doc, where)
    load = _load(where, doc, "load")
    torque = _load(where, doc, "torque")
    init = doc.get("initial", {})
    phi0 = _number(where, "initial.phi0", init.get("phi0", 1.0))
    dphi0 = _number(where, "initial.dphi0", init.get("dphi0", 0.0))
    solver, rtol, atol = _solver(doc.get("solver", {}), where)
    t1, samples, extras = _output(doc.get("output", {}), where)
    description = doc.get("description", "")
    if not isinstance(description, str):
        raise SceneError(f"{where}: description must be a string")
    try:
        sensors = sensors_from_table(doc.get("sensors", {}), f"{where}: [sensors]")
    except SensorError as e:
        raise SceneError(str(e)) from None
    try:
        return Scene(mech, load, torque, phi0, dphi0, rtol, atol, t1=t1, samples=samples,
                     solver=solver, outputs=tuple(extras), name=name,
                     description=description, sensors=sensors)
    except SceneError as e:
        raise SceneError(f"{where}: {e}") from None


def _check_tables(doc: dict, where: str) -> None:
    """`SceneError` for an unknown table or key, or a table that is not one."""
    for key in doc:
        if key not in _TABLES and key not in _TOP_KEYS:
            raise SceneError(f"{where}: unknown table or key {key!r}; valid tables are "
                             f"{['[' + t + ']' for t in _TABLES]}")
    for table, keys in _TABLES.items():
        if table in doc:
            if not isinstance(doc[table], dict):
                raise SceneError(f"{where}: {table!r} must be a table [{table}]")
            for key in doc[table]:
                if key not in keys:
                    raise SceneError(f"{where}: unknown key {key!r} in [{table}]; valid keys "
                                     f"are {list(keys)}")


def _mechanism(doc: dict, where: str) -> SliderCrank:
    """The [mechanism] and [friction] tables' mechanism."""
    if "mechanism" not in doc:
        raise SceneError(f"{where}: the [mechanism] table is required")
    mt = doc["mechanism"]
    missing = [f for f in PAPER_FIELDS if f not in mt and f != "g"]
    if missing:
        raise SceneError(f"{where}: [mechanism] is missing {missing}; every field but g "
                         f"(default 9.81) and {list(_OPTIONAL_MECH)} (default 0) is required")
    values = {f: _number(where, f"mechanism.{f}", mt.get(f, _DEFAULT_MECH.get(f)))
              for f in PAPER_FIELDS + _OPTIONAL_MECH}
    ft = doc.get("friction", {})
    values.update({f: _number(where, f"friction.{key}", ft.get(key, _DEFAULT_MECH[f]))
                   for key, f in _FRICTION.items()})
    try:
        return SliderCrank(**values)
    except ValueError as e:
        raise SceneError(f"{where}: [mechanism] {e}") from None


def _solver(st: dict, where: str) -> tuple[str, float, float]:
    """The [solver] table's name, rtol and atol."""
    solver = st.get("name", "auto")
    if solver not in SOLVERS:
        raise SceneError(f"{where}: [solver] name {solver!r} is unknown; choose from "
                         f"{list(SOLVERS)}")
    rtol = _number(where, "solver.rtol", st.get("rtol", 1e-8))
    atol = _number(where, "solver.atol", st.get("atol", 1e-10))
    try:
        check_tolerances(rtol, atol)
    except ValueError as e:
        raise SceneError(f"{where}: [solver] {e}") from None
    return solver, rtol, atol


def _output(out: dict, where: str) -> tuple[float, int, list]:
    """The [output] table's t1 (s), number of samples and extra outputs."""
    t1 = _number(where, "output.t1", out.get("t1", 10.0))
    samples = out.get("samples", 1001)
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 2:
        raise SceneError(f"{where}: [output] samples must be an integer >= 2, got {samples!r}")
    extras = out.get("extras", [])
    if not isinstance(extras, list) or not all(isinstance(e, str) and e in OUTPUTS
                                               for e in extras):
        raise SceneError(f"{where}: [output] extras must be a list drawn from "
                         f"{sorted(OUTPUTS)}, got {_short(extras)}")
    return t1, samples, extras


def presets() -> dict[str, str]:
    """Preset name -> one-line description."""
    return {n: load_scene(n).description for n in PRESETS}


#: Scene files are a few kB; a larger file is a mistake (a record given as the scene),
#: refused before it is read.
MAX_SCENE_BYTES = 1 << 20


def load_scene(source: str | os.PathLike) -> Scene:
    """Load a scene from a preset name (see [`PRESETS`][]) or a TOML file path.

    Raises [`SceneError`][] naming the file, table and key on any mistake, including
    unknown tables or keys (a typo never falls back to a default silently).
    """
    src = str(source)
    if src in PRESETS:
        text = importlib.resources.files("crank_jax").joinpath(f"scenes/{src}.toml").read_text()
        return scene_from_dict(tomllib.loads(text), where=f"preset {src}", name=src)
    return scene_from_dict(read_scene_doc(src), where=src, name=Path(src).stem)


def read_scene_doc(source: str | os.PathLike) -> dict:
    """The TOML document of a scene file, as every reader of scene files gets it (the
    scene itself, its `[priors]`): a regular file of at most [`MAX_SCENE_BYTES`][], UTF-8
    with or without a byte-order mark. Raises [`SceneError`][] naming the file."""
    src = str(source)
    path = Path(src)
    if not path.is_file():  # a FIFO or device too: opening it could wait forever
        kind = "a TOML file" if not path.exists() else "a regular file"
        raise SceneError(f"{src!r} is neither a preset ({', '.join(PRESETS)}) nor {kind}")
    if path.stat().st_size > MAX_SCENE_BYTES:
        raise SceneError(f"{src}: {path.stat().st_size} bytes is not a scene file (scenes are "
                         f"a few kB; the limit is {MAX_SCENE_BYTES} bytes); a record goes "
                         "after the command as DATA, a scene second")
    try:
        # utf-8-sig: a byte-order mark (as Windows editors write) is dropped, as in CSV.
        doc = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"{src}: malformed TOML: {e}") from None
    except UnicodeDecodeError:
        raise SceneError(f"{src}: not a UTF-8 text file") from None
    return doc


def _load_table(load: AbstractLoad, side: str) -> dict[str, Any] | None:
    try:
        return load_to_table(load, side)
    except ValueError as e:
        raise SceneError(str(e)) from None


#: TOML's short escapes; every other control character is written as `\\uXXXX`.
_TOML_ESCAPES = {"\\": "\\\\", '"': '\\"', "\b": "\\b", "\t": "\\t", "\n": "\\n",
                 "\f": "\\f", "\r": "\\r"}


def _toml_string(text: str) -> str:
    """`text` as a TOML basic string that reads back equal: quotes, backslashes and every
    control character (U+0000 to U+001F and U+007F, which TOML forbids raw) are escaped.
    Raises [`SceneError`][] for a lone surrogate, which no UTF-8 file can hold."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise SceneError(f"the string {_short(text)} holds a lone surrogate (not Unicode "
                         "text), which a scene file cannot hold; remove it") from None
    out = [_TOML_ESCAPES.get(c) or (f"\\u{ord(c):04X}" if ord(c) < 0x20 or c == "\x7f" else c)
           for c in text]
    return '"' + "".join(out) + '"'


def scene_to_toml(scene: Scene) -> str:
    """Serialise a scene to the TOML format that [`load_scene`][] reads."""
    def fmt(v: Any) -> str:
        if isinstance(v, str):
            return _toml_string(v)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(fmt(x) for x in v) + "]"
        return repr(v)

    lines = []
    if scene.description:
        lines.append(f"description = {fmt(scene.description)}\n")
    mech = scene.mech.as_dict()
    # Keys beyond the paper's are written only when they differ from their defaults, so a
    # scene without offset or friction reads exactly as before.
    mech_table = {k: v for k, v in mech.items()
                  if k in PAPER_FIELDS or (k in _OPTIONAL_MECH and v != _DEFAULT_MECH[k])}
    friction = {key: mech[f] for key, f in _FRICTION.items() if mech[f] != _DEFAULT_MECH[f]}
    tables: dict[str, dict[str, Any] | None] = {
        "mechanism": mech_table,
        "friction": friction or None,
        "load": _load_table(scene.load, "load"),
        "torque": _load_table(scene.torque, "torque"),
        "initial": {"phi0": float(np.asarray(scene.phi0)),
                    "dphi0": float(np.asarray(scene.dphi0))},
        "solver": {"name": scene.solver, "rtol": float(np.asarray(scene.rtol)),
                   "atol": float(np.asarray(scene.atol))},
        "output": {"t1": float(scene.t1), "samples": int(scene.samples),
                   "extras": list(scene.outputs)},
    }
    for table, body in tables.items():
        if body is None:
            continue
        lines.append(f"[{table}]")
        lines += [f"{k} = {fmt(v)}" for k, v in body.items()]
        lines.append("")
    if scene.sensors:
        lines.append("[sensors]")
        lines += [f"{name} = {{ " + ", ".join(f"{k} = {fmt(v)}" for k, v in spec.items())
                  + " }" for name, spec in sensors_to_table(scene.sensors).items()]
        lines.append("")
    return "\n".join(lines)


def save_scene(scene: Scene, path: str | os.PathLike) -> None:
    """Write a scene as TOML, atomically."""
    text = scene_to_toml(scene)  # before the file is opened: a failure leaves no file
    # UTF-8 whatever the locale: load_scene reads UTF-8.
    with atomic_write(path, "wb") as f:
        f.write(text.encode("utf-8"))

