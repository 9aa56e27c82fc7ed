"""Measured or synthetic crank-angle records: the [`Data`][] record, CSV in and out, and
validation ([`synthesize`][crank_jax.records.synth.synthesize], in `synth.py`, makes synthetic
records with a documented noise model).

A record is a [`Data`][]: sample times `ts` (s), crank angles `phi` (rad) or other sensor
channels (see [`sensors`][crank_jax.records.sensors]), and optionally the loads that acted during
it (slider force P, N; crank torque tau, N*m). Loads that come from a file are
[`SampledLoad`][]s and replace the scene's loads when fitting.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import equinox as eqx
import numpy as np

from ..model.loads import INTERPOLATIONS, AbstractLoad, NoLoad, SampledLoad
from ..runtime.io import atomic_write
from .checks import MAX_TIME_SPAN, MIN_STEP_ULPS, MIN_TIME_STEP, series_problem
from .column_checks import data_fields_problem, data_roles
from .columns import TIME_ROLE, load_roles
from .fields import LineLabels
from .sensors import DEFAULT_SENSOR, Sensor
from .table import MAX_RECORD_SAMPLES, DataError, header_columns, read_table

__all__ = ["Data", "load_data", "save_data", "DataError", "MIN_SAMPLES",
           "MAX_RECORD_SAMPLES", "header_columns", "MAX_TIME_SPAN", "MIN_TIME_STEP",
           "MIN_STEP_ULPS"]

#: The fewest samples a record may have.
MIN_SAMPLES = 5


def _check_series(ts: np.ndarray, phi: np.ndarray, where: str, rows: Sequence[str] | None,
                  name: str = "phi") -> None:
    """Raise [`DataError`][] naming the first bad row; `rows[i]` labels sample `i`; `name`
    is the column of `phi` (a channel's)."""
    problem = series_problem(ts, phi, where, rows, name, MIN_SAMPLES)
    if problem:
        raise DataError(problem)


def _real(x, field: str) -> np.ndarray:
    """`x` as a float64 array; a complex one is refused (numpy would drop its imaginary
    part with only a warning)."""
    a = np.asarray(x)
    if np.iscomplexobj(a):
        raise DataError(f"Data.{field} is complex; a record holds real numbers: give its "
                        "real part (np.real) if that is what was measured")
    return np.asarray(a, dtype=np.float64)


def _optional_array(x):
    return None if x is None else _real(x, "phi")


def _channel_arrays(x) -> dict:
    return {str(k): _real(v, f"channels[{str(k)!r}]") for k, v in dict(x or {}).items()}


class Data(eqx.Module):
    """One record: sample times and what the sensors read, with the loads known to have
    acted during it.

    **Fields:**

    - `ts`: (n,) sample times, s, strictly increasing, n >= [`MIN_SAMPLES`][]. They may
      start anywhere and be irregular, but must span at most [`MAX_TIME_SPAN`][] and be
      at least [`MIN_TIME_STEP`][] and [`MIN_STEP_ULPS`][] float64 spacings of the largest
      |t| apart (what a solver can resolve).
    - `phi`: (n,) measured crank angle, rad (the `phi` channel with no calibration), or
      `None` when the record has no angle (its channels are in `channels`).
    - `load`: the slider force P(t), N, or `None` to use the scene's when fitting.
    - `torque`: the crank torque tau(t), N*m, or `None` to use the scene's.
    - `source`: a label (file name or "synthetic"), used in messages.
    - `channels`: more channels, name (see [`CHANNELS`][crank_jax.records.sensors.CHANNELS]) ->
      (n,) data in the channel's SI unit, e.g. `{"x_s": slide_m}`.
    - `sensors`: the calibration of each channel ([`Sensor`][crank_jax.records.sensors.Sensor]:
      `data = scale * model + offset`); a channel without one is read as the model output
      itself (scale 1, offset 0).
    - `inputs`: measured inputs that drive loads through gains (an
      [`InputLoad`][crank_jax.model.loads.InputLoad]'s column, e.g. a motor voltage):
      column name -> [`SampledLoad`][] of its samples.

    Construction validates the arrays and raises [`DataError`][] naming the bad sample.
    """

    ts: np.ndarray = eqx.field(converter=lambda x: _real(x, "ts"))
    phi: np.ndarray | None = eqx.field(converter=_optional_array, default=None)
    load: AbstractLoad | None = None
    torque: AbstractLoad | None = None
    source: str = eqx.field(static=True, default="<array>")
    channels: dict = eqx.field(converter=_channel_arrays, default=None)
    sensors: tuple[Sensor, ...] = eqx.field(static=True, default=())
    inputs: dict = eqx.field(default=None, converter=lambda x: dict(x or {}))

    def __check_init__(self):
        if self.phi is None and not self.channels:
            raise DataError(f"{self.source}: a record needs at least one channel: give phi "
                            "or channels={name: values}")
        problem = data_fields_problem(self)
        if problem:
            raise DataError(f"{self.source}: {problem}")
        for name, y in self.outputs_items():
            _check_series(self.ts, y, self.source, None, name)
        names = [s.name for s in self.sensors]
        for s in self.sensors:
            if names.count(s.name) > 1:
                raise DataError(f"{self.source}: channel {s.name!r} has two sensors; give one")
            if s.name not in self._names():
                raise DataError(f"{self.source}: sensor {s.name!r} has no channel data")

    def column_roles(self) -> list[tuple[str, str]]:
        """(column, role) of every column [`save_data`][] writes for this record."""
        return data_roles(self)

    def _names(self) -> list[str]:
        return ([] if self.phi is None or "phi" in self.channels else ["phi"]) + list(
            self.channels)

    def outputs_items(self) -> list[tuple[str, np.ndarray]]:
        """(channel name, data in SI) for every channel, `phi` first when present."""
        return [(n, self.phi if n == "phi" and "phi" not in self.channels
                 else self.channels[n]) for n in self._names()]

    def outputs(self) -> list[tuple[Sensor, np.ndarray]]:
        """([`Sensor`][crank_jax.records.sensors.Sensor], (n,) data in SI) for every channel, in
        order (the first is the one a fit reports its overall rms in)."""
        cal = {s.name: s for s in self.sensors}
        return [(cal.get(n, DEFAULT_SENSOR if n == "phi" else Sensor(n)), y)
                for n, y in self.outputs_items()]

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.ts.shape[0])

    def window(self, t_start: float | None = None, t_end: float | None = None) -> Data:
        """The samples with `t_start <= t <= t_end`, as a new record with the same loads
        (they are functions of absolute time, so nothing shifts).

        **Arguments:** `t_start`, `t_end`: the window, s; `None` leaves that end open.

        **Returns:** a [`Data`][]. Raises [`DataError`][] naming the window when it is
        empty or reversed or holds fewer than [`MIN_SAMPLES`][] samples.
        """
        lo = -math.inf if t_start is None else float(t_start)
        hi = math.inf if t_end is None else float(t_end)
        if math.isnan(lo) or math.isnan(hi) or not lo < hi:
            raise DataError(f"{self.source}: window t_start = {t_start}, t_end = {t_end} s is "
                            "empty: t_start must be below t_end")
        keep = (self.ts >= lo) & (self.ts <= hi)
        if int(keep.sum()) < MIN_SAMPLES:
            raise DataError(f"{self.source}: the window [{t_start}, {t_end}] s holds "
                            f"{int(keep.sum())} samples of the record's {self.n} (t from "
                            f"{self.ts[0]:g} to {self.ts[-1]:g} s); a record needs at least "
                            f"{MIN_SAMPLES}: widen the window (`t_start=`, `t_end=`)")
        return self.select(keep)

    def select(self, keep: np.ndarray) -> Data:
        """The samples where `keep` (n,) bool is true, every channel with them; the same
        loads and sensors."""
        return Data(self.ts[keep], None if self.phi is None else self.phi[keep], self.load,
                    self.torque, source=self.source,
                    channels={n: y[keep] for n, y in self.channels.items()},
                    sensors=self.sensors, inputs=self.inputs)

    def columns(self) -> dict[str, np.ndarray]:
        """`t`, the channels (`phi` in rad; a channel with a sensor in its column and
        unit) and the known loads sampled at `ts` (`P`, `tau`), as numpy arrays."""
        cols = {"t": self.ts}
        cal = {s.name: s for s in self.sensors}
        for n, y in self.outputs_items():
            s = cal.get(n)
            cols[n if s is None else s.column] = y if s is None else s.from_si(y)
        if self.load is not None and not isinstance(self.load, NoLoad):
            cols["P"] = np.asarray(self.load(self.ts))
        if self.torque is not None and not isinstance(self.torque, NoLoad):
            cols["tau"] = np.asarray(self.torque(self.ts))
        cols.update({n: np.asarray(u(self.ts)) for n, u in self.inputs.items()})
        return cols


# ---------------------------------------------------------------------------------------
# Files


def load_data(
    path: str | os.PathLike,
    *,
    t_col: str = "t",
    phi_col: str = "phi",
    angle_unit: str = "rad",
    P_col: str = "P",
    tau_col: str = "tau",
    interp: str = "cubic",
    sensors: Sequence[Sensor] | None = None,
    inputs: Sequence[str] = (),
) -> Data:
    """Read a record from a text file with a header line.

    Comma-, semicolon- or whitespace-separated; blank lines and lines starting with `#` or
    `%` are skipped. Columns are found by name in the header. Read as pandas reads CSV: a
    byte-order mark (UTF-8, as Excel writes, or UTF-16), quoted names and values, and CRLF
    line ends are all fine; semicolon-separated files may use decimal commas. Columns other
    than the four below are ignored (only their count is checked).

    **Arguments:**

    - `path`: the file.
    - `t_col`, `phi_col`: names of the time (s) and angle columns (both required).
    - `angle_unit`: `"rad"` or `"deg"` (the angle column's unit).
    - `P_col`, `tau_col`: names of the optional slider-force (N) and crank-torque (N*m)
      columns. When present they become [`SampledLoad`][]s that replace the scene's loads.
    - `sensors`: the record's channels ([`Sensor`][crank_jax.records.sensors.Sensor]s: each
      reads its column, in its unit, into SI). Default: the angle column `phi_col`.
    - `inputs`: columns of measured inputs (an `InputLoad`'s, e.g. `"volts"`), read into
      `Data.inputs` and interpolated like the load columns.
    - `interp`: how those load columns are interpolated between samples (see
      [`INTERPOLATIONS`][]): `"cubic"` (default, a C2 not-a-knot spline: for measured,
      smooth signals), `"linear"`, or `"zoh"` (zero-order hold: exact for a command a
      digital controller holds between samples).

    **Returns:** a [`Data`][].

    Raises [`DataError`][] (a `ValueError`) naming the line and column for a missing
    column, a non-numeric, NaN or infinite value, a time that does not increase, times
    too close together or spanning too long (see [`Data`][]), a ragged
    row, too few samples or more than [`MAX_RECORD_SAMPLES`][], and for a path that is not
    a regular file (a FIFO, a device, a directory, a missing file); `OSError` if the file
    cannot be read.
    """
    if interp not in INTERPOLATIONS:
        raise DataError(f"load interpolation {interp!r} is unknown; choose from "
                        f"{list(INTERPOLATIONS)}")
    if angle_unit not in ("rad", "deg"):
        raise DataError(f"angle unit must be 'rad' or 'deg', got {angle_unit!r}")
    where = str(path)
    if sensors or inputs:
        sensors = tuple(sensors or (Sensor("phi", phi_col, angle_unit),))
        return _load_channels(path, t_col, P_col, tau_col, interp, sensors, tuple(inputs))
    names, col, numbers = read_table(
        path, t_col, phi_col, (t_col, phi_col, P_col, tau_col),
        roles=[(t_col, TIME_ROLE), (phi_col, "the angle (`phi_col=`)")],
        optional=load_roles(P_col, tau_col))
    labels = LineLabels(numbers)
    ts = col[t_col]
    phi = col[phi_col] * (math.pi / 180 if angle_unit == "deg" else 1.0)
    # Check every column used (not just t and phi): a NaN in a load column is as fatal.
    _check_columns(where, names, col, labels)
    _check_series(ts, phi, where, labels)
    load = SampledLoad(ts, col[P_col], interp) if P_col in col else None
    torque = SampledLoad(ts, col[tau_col], interp) if tau_col in col else None
    return Data(ts, phi, load, torque, source=where)


def _check_columns(where: str, names, col: dict, labels) -> None:
    """A NaN or inf in any column used is fatal: name its row."""
    for name in (n for n in names if n in col):
        bad = ~np.isfinite(col[name])
        if bad.any():
            i = int(np.argmax(bad))
            raise DataError(f"{where}: {labels[i]}: column {name!r} is {float(col[name][i])} "
                            "(NaN or inf); remove or repair that row")


def _load_channels(path, t_col, P_col, tau_col, interp, sensors: tuple[Sensor, ...],
                   inputs: tuple[str, ...] = ()) -> Data:
    """[`load_data`][] for a record read through sensors, or with inputs."""
    where = str(path)
    dup = sorted({s.name for s in sensors if [x.name for x in sensors].count(s.name) > 1})
    if dup:
        raise DataError(f"channel {dup[0]!r} is given twice; give each channel once")
    required = [(t_col, "`t_col=`")] + [
        (s.column, f"`sensors=` (sensor {s.name}'s column, or the scene's [sensors] "
                   f"{s.name} column)")
        for s in sensors] + [(c, f"the scene's input = {c!r} (a load's input column)")
                             for c in inputs]
    used = tuple(dict.fromkeys([t_col, P_col, tau_col] + [s.column for s in sensors]
                               + list(inputs)))
    roles = [(t_col, TIME_ROLE)] + [
        (s.column, f"channel {s.name} (`sensors=`, or the scene's [sensors])")
        for s in sensors] + [(c, f"the input of a load (the scene's input = {c!r})")
                             for c in inputs]
    names, col, numbers = read_table(path, t_col, "", used, required, roles,
                                      load_roles(P_col, tau_col))
    labels = LineLabels(numbers)
    _check_columns(where, names, col, labels)
    ts = col[t_col]
    channels = {s.name: s.to_si(col[s.column]) for s in sensors}
    for s in sensors:
        _check_series(ts, channels[s.name], where, labels, s.column)
    load = SampledLoad(ts, col[P_col], interp) if P_col in col else None
    torque = SampledLoad(ts, col[tau_col], interp) if tau_col in col else None
    ins = {c: SampledLoad(ts, col[c], interp) for c in inputs}
    plain = len(sensors) == 1 and sensors[0].name == "phi" and sensors[0].scale == 1.0 \
        and sensors[0].offset == 0.0
    if plain:  # an angle column as measured: the record's phi
        return Data(ts, channels["phi"], load, torque, source=where, inputs=ins)
    return Data(ts, None, load, torque, source=where, channels=channels, sensors=sensors,
                inputs=ins)


def save_data(data: Data, path: str | os.PathLike, comment: str = "") -> None:
    """Write a record as CSV (`t,phi[,P][,tau]`, full precision), atomically.

    `comment` lines are written first, each prefixed with `# `.
    """
    cols = data.columns()
    with atomic_write(path) as f:
        for line in comment.splitlines():
            f.write(f"# {line}\n")
        f.write(",".join(cols) + "\n")
        np.savetxt(f, np.column_stack(list(cols.values())), delimiter=",", fmt="%.17g")
