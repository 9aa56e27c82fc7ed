"""Sensors: which model output a record's column measures, in what unit, through what
calibration (DESIGN.md section 1, "Sensors are a measurement model, not the state").

A [`Sensor`][] maps one model output (a *channel*: `phi`, `dphi`, `x_s`, `v_s`, `a_s`,
see [`model.outputs`][crank_jax.model.outputs]) to a column of a record:

    column * unit_factor = data_SI = scale * h(x) + offset

`scale` is fixed (1, or -1 for a sensor that counts the other way; never 0); `offset` (in
the channel's SI unit) is fixed unless the fit frees `<channel>_offset`. Scenes hold
sensors in a `[sensors]` table, one inline table per channel:

    [sensors]
    phi = { column = "wheel_deg", unit = "deg", scale = -1.0, offset = -3.083 }
    x_s = { column = "slide_mm", unit = "mm", scale = -1.0, offset = 0.2948 }
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import equinox as eqx
import numpy as np

from ..model.outputs import OUTPUT_NAMES, SI_UNITS
from .columns import RESERVED, column_problem, role_conflict

__all__ = ["Sensor", "SensorError", "CHANNELS", "UNITS", "OFFSET_NAMES", "sensors_from_table",
           "sensors_to_table", "parse_channel", "select_sensors", "DEFAULT_SENSOR",
           "sensor_columns_conflict"]

#: The channel names a sensor may measure.
CHANNELS: tuple[str, ...] = OUTPUT_NAMES
#: Per channel, each accepted unit and its factor to the SI unit (value_SI = value * f).
UNITS: dict[str, dict[str, float]] = {
    "phi": {"rad": 1.0, "deg": math.pi / 180, "rev": 2 * math.pi},
    "dphi": {"rad/s": 1.0, "deg/s": math.pi / 180, "rpm": 2 * math.pi / 60},
    "x_s": {"m": 1.0, "mm": 1e-3},
    "v_s": {"m/s": 1.0, "mm/s": 1e-3},
    "a_s": {"m/s^2": 1.0, "g": 9.80665},  # standard gravity, as accelerometers use
}
#: The free names of the channels' offsets: `phi_offset`, `dphi_offset`, ...
OFFSET_NAMES: dict[str, str] = {f"{c}_offset": c for c in CHANNELS}
_KEYS = ("column", "unit", "scale", "offset")


class SensorError(ValueError):
    """A sensor specification is malformed; the message names the field and the fix."""


def _finite(where: str, key: str, v) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise SensorError(f"{where}: {key} must be a finite number, got {v!r}")
    return float(v)


class Sensor(eqx.Module):
    """One channel of a record: `column * UNITS[name][unit] = scale * h_name + offset`.

    **Fields:** `name`, a channel of [`CHANNELS`][]; `column`, the record's column (default:
    the channel's name); `unit`, one of `UNITS[name]` (default: the SI unit); `scale`
    (fixed, non-zero, default 1); `offset` (SI unit, default 0). All static: a sensor is a
    description, not a fitted value (a free offset is the fit's `<name>_offset`).
    """

    name: str = eqx.field(static=True)
    column: str = eqx.field(static=True, default="")
    unit: str = eqx.field(static=True, default="")
    scale: float = eqx.field(static=True, default=1.0)
    offset: float = eqx.field(static=True, default=0.0)

    def __post_init__(self):
        # Defaults that depend on the name (a frozen dataclass: set through object).
        if self.column is None or self.column == "":
            object.__setattr__(self, "column", self.name)
        if not self.unit and self.name in SI_UNITS:
            object.__setattr__(self, "unit", SI_UNITS[self.name])

    def __check_init__(self):
        where = f"sensor {self.name!r}"
        if not isinstance(self.name, str) or self.name not in CHANNELS:
            raise SensorError(f"channel {self.name!r} is unknown; choose from {list(CHANNELS)}")
        problem = column_problem(self.column)
        if problem:
            raise SensorError(f"{where}: column {problem}")
        if not isinstance(self.unit, str) or self.unit not in UNITS[self.name]:
            raise SensorError(f"{where}: unit {self.unit!r} is unknown for {self.name}; choose "
                              f"from {list(UNITS[self.name])}")
        scale = _finite(where, "scale", self.scale)
        if scale == 0:
            raise SensorError(f"{where}: scale = 0 would make the channel blind to the "
                              "model; use 1, or -1 for a sensor that counts the other way")
        _finite(where, "offset", self.offset)

    @property
    def factor(self) -> float:
        """The column's unit in SI (value_SI = column * factor)."""
        return UNITS[self.name][self.unit]

    @property
    def si_unit(self) -> str:
        return SI_UNITS[self.name]

    def to_si(self, column: np.ndarray) -> np.ndarray:
        """Column values -> data in the channel's SI unit."""
        return np.asarray(column, dtype=np.float64) * self.factor

    def from_si(self, values: np.ndarray) -> np.ndarray:
        """Data in SI -> column values in the sensor's unit."""
        return np.asarray(values, dtype=np.float64) / self.factor

    def measure(self, h):
        """What the sensor reads in SI for the model output `h` (SI): `scale h + offset`."""
        return self.scale * h + self.offset

    def model(self, data_si):
        """The model output that explains `data_si`: `(data - offset) / scale`."""
        return (data_si - self.offset) / self.scale


#: The implicit channel of a record without sensors: the angle in rad, as measured.
DEFAULT_SENSOR = Sensor("phi")


def sensors_from_table(table, where: str = "[sensors]") -> tuple[Sensor, ...]:
    """Sensors from a scene's `[sensors]` table (channel -> inline table of `column`,
    `unit`, `scale`, `offset`). Raises [`SensorError`][] naming the key."""
    if not isinstance(table, Mapping):
        raise SensorError(f"{where} must be a table of channels, e.g. phi = {{ column = "
                          "\"phi\", unit = \"rad\" }}")
    out = []
    for name, spec in table.items():
        if name not in CHANNELS:
            raise SensorError(f"{where}: channel {name!r} is unknown; choose from "
                              f"{list(CHANNELS)}")
        if not isinstance(spec, Mapping):
            raise SensorError(f"{where} {name} must be an inline table, e.g. {name} = "
                              f"{{ column = \"{name}\", unit = \"{SI_UNITS[name]}\" }}")
        bad = [k for k in spec if k not in _KEYS]
        if bad:
            raise SensorError(f"{where} {name}: unknown key {bad[0]!r}; valid keys are "
                              f"{list(_KEYS)}")
        for k in ("column", "unit"):
            if k in spec and not (isinstance(spec[k], str) and spec[k]):
                raise SensorError(f"{where} {name}: {k} must be a non-empty string, got "
                                  f"{spec[k]!r}")
        try:
            out.append(Sensor(name, spec.get("column", ""), spec.get("unit", ""),
                              spec.get("scale", 1.0), spec.get("offset", 0.0)))
        except SensorError as e:
            raise SensorError(f"{where} {name}: {e}") from None
    problem = sensor_columns_conflict(out, where)
    if problem:
        raise SensorError(problem)
    return tuple(out)


def sensor_columns_conflict(sensors: Sequence[Sensor], where: str = "[sensors]"
                            ) -> str | None:
    """Why `sensors` cannot be a rig's channels, or None: a column that is another
    channel's, or one of the names records keep for the time and the loads
    ([`RESERVED`][crank_jax.records.columns.RESERVED]: `synth` writes them, `fit` reads them)."""
    for s in sensors:
        if s.column in RESERVED:
            return (f"{where} {s.name}: column {s.column!r} is {RESERVED[s.column]}, which "
                    "records keep for it; name the sensor's column otherwise")
    problem = role_conflict((s.column, f"channel {s.name}") for s in sensors)
    return f"{where}: {problem}" if problem else None


def sensors_to_table(sensors: Sequence[Sensor]) -> dict[str, dict]:
    """The `[sensors]` table of [`sensors_from_table`][] (channel -> its four keys)."""
    return {s.name: {"column": s.column, "unit": s.unit, "scale": float(s.scale),
                     "offset": float(s.offset)} for s in sensors}


def parse_channel(text: str) -> tuple[str, str | None, str | None]:
    """`NAME[=COLUMN[:UNIT]]` (the CLI's `--channel`) -> `(name, column, unit)`, the
    missing parts None. Raises [`SensorError`][] for an unknown name or unit."""
    name, _, rest = text.partition("=")
    name = name.strip()
    column, _, unit = rest.partition(":")
    column, unit = column.strip() or None, unit.strip() or None
    if name not in CHANNELS:
        raise SensorError(f"`channels=` entry {text!r}: channel {name!r} is unknown; choose "
                          "from "
                          f"{list(CHANNELS)}")
    if unit is not None and unit not in UNITS[name]:
        raise SensorError(f"`channels=` entry {text!r}: unit {unit!r} is unknown for {name}; "
                          f"choose from {list(UNITS[name])}")
    return name, column, unit


def select_sensors(channels: Sequence[str] | None, scene_sensors: Sequence[Sensor],
                   header: Sequence[str] | None = None) -> tuple[Sensor, ...]:
    """The channels a fit uses (the CLI's rules):

    - `channels` given (`--channel` texts): exactly those, each taking the calibration of
      the scene's sensor of the same name when there is one, and the column and unit the
      text names (else the scene sensor's, else the channel's name and SI unit);
    - else every scene sensor whose column is in the record's `header` (all of them when
      `header` is None);
    - with neither, the `phi` column in rad ([`DEFAULT_SENSOR`][]).
    """
    scene = {s.name: s for s in scene_sensors}
    if channels:
        out = {}
        for text in channels:
            name, column, unit = parse_channel(text)
            if name in out:
                raise SensorError(f"`channels=`: channel {name} is given twice; give each "
                                  "channel once")
            base = scene.get(name, Sensor(name))
            out[name] = Sensor(name, column or base.column, unit or base.unit, base.scale,
                               base.offset)
        return tuple(out.values())
    found = tuple(s for s in scene_sensors if header is None or s.column in header)
    return found or (DEFAULT_SENSOR,)
