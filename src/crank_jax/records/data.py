"""Measured or synthetic crank-angle records: the [`Data`][] record, CSV in and out, and
validation ([`synthesize`][crank_jax.records.synth.synthesize], in `synth.py`, makes synthetic
records with a documented noise model).

A record is a [`Data`][]: sample times `ts` (s), crank angles `phi` (rad) or other sensor
channels (see [`sensors`][crank_jax.records.sensors]), and optionally the loads that acted during
it (slider force P, N; crank torque tau, N*m). Loads that come from a file are
[`SampledLoad`][]s and replace the scene's loads when fitting.
"""

from __future__ import annotations

import csv
import math
import os
from array import array
from collections.abc import Sequence

import equinox as eqx
import numpy as np

from ..model.loads import INTERPOLATIONS, AbstractLoad, NoLoad, SampledLoad
from ..runtime.io import atomic_write, check_input
from .checks import MAX_TIME_SPAN, MIN_STEP_ULPS, MIN_TIME_STEP, series_problem
from .column_checks import data_fields_problem, data_roles
from .columns import TIME_ROLE, load_roles, role_conflict
from .fields import LineLabels, cut_names, split_fields, to_float
from .sensors import DEFAULT_SENSOR, Sensor

__all__ = ["Data", "load_data", "save_data", "DataError", "MIN_SAMPLES",
           "MAX_RECORD_SAMPLES", "header_columns", "MAX_TIME_SPAN", "MIN_TIME_STEP",
           "MIN_STEP_ULPS"]

#: The fewest samples a record may have.
MIN_SAMPLES = 5


class DataError(ValueError):
    """A data file or array is malformed; the message names the row or column."""


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
                            f"{MIN_SAMPLES}: widen the window (t_start/t_end)")
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


#: The most samples [`load_data`][] reads: a longer record is refused as soon as it is
#: seen, before it fills memory (each used column takes 8 bytes per sample).
MAX_RECORD_SAMPLES = 10**7


def _open_text(path: str | os.PathLike):
    """Open a text file as pandas would read it: a UTF-8 byte-order mark (as Excel writes)
    is dropped, a UTF-16 one selects UTF-16, and CRLF or CR line ends read as LF. Anything
    but a regular file (a FIFO would wait for a writer forever) is refused unopened."""
    try:
        check_input(path, "data file")
    except ValueError as e:
        raise DataError(str(e)) from None
    with open(path, "rb") as f:
        head = f.read(2)
    enc = "utf-16" if head in (b"\xff\xfe", b"\xfe\xff") else "utf-8-sig"
    return open(path, encoding=enc, errors="replace", newline=None)


def _header(where: str, lines, t_col: str, phi_col: str, used: tuple[str, ...],
            required: Sequence[tuple[str, str]] | None = None):
    """Find the header line; return (its line number, delimiter, column names).
    `required`: (column, the option that names it) of every column that must be there
    (default: `t_col` and `phi_col`)."""
    if required is None:
        required = ((t_col, "--t-col"), (phi_col, "--phi-col"))
    for lineno, text in lines:
        delim = "," if "," in text else (";" if ";" in text else None)
        names = split_fields(text, delim)
        dup = sorted({n for n in names if n in used and names.count(n) > 1})
        if dup:
            raise DataError(f"{where}: line {lineno}: column {dup[0]!r} appears more than "
                            "once in the header; rename one")
        for want, opt in required:
            if want in names:
                continue
            try:
                [to_float(x, delim) for x in names]
            except ValueError:
                raise DataError(f"{where}: missing column {want!r}; the header (line "
                                f"{lineno}) has {cut_names(names)}; choose the column with "
                                f"{opt}") from None
            raise DataError(f"{where}: line {lineno} is data, not a header: add a header "
                            f"line naming the columns, e.g. '{t_col},{phi_col}'")
        return lineno, delim, names
    raise DataError(f"{where}: no header line and no data (the file is empty or all "
                    "comments)")


#: The longest line [`load_data`][] reads, in characters: a binary file or a device such
#: as /dev/zero has no line ends, and reading its "line" would fill memory.
MAX_LINE_CHARS = 1 << 16


def _numbered_lines(f, where: str):
    """(line number, line without its end) for each line, refusing overlong lines."""
    for i, ln in enumerate(iter(lambda: f.readline(MAX_LINE_CHARS + 1), ""), start=1):
        if len(ln) > MAX_LINE_CHARS:
            raise DataError(f"{where}: line {i} is longer than {MAX_LINE_CHARS} characters; "
                            "this is not a text table")
        yield i, ln.rstrip("\n")


def _read_table(path, t_col: str, phi_col: str, used: tuple[str, ...],
                required: Sequence[tuple[str, str]] | None = None,
                roles: Sequence[tuple[str, str]] = (),
                optional: Sequence[tuple[str, str]] = ()):
    """Read the used columns of a text table: (names, {name: array}, line numbers).

    `roles`: (column, role) of every column read; `optional`: those read only when the
    header has them (the load columns). A column with two roles is refused once the header
    is read (see [`role_conflict`][crank_jax.records.columns.role_conflict])."""
    where = str(path)
    with _open_text(path) as f:
        lines = _numbered_lines(f, where)
        body = ((i, ln) for i, ln in lines
                if ln.strip() and not ln.lstrip().startswith(("#", "%")))
        lineno, delim, names = _header(where, body, t_col, phi_col, used, required)
        problem = role_conflict(list(roles) + [(c, r) for c, r in optional if c in names])
        if problem:
            raise DataError(f"{where}: {problem}")
        want = [(j, n) for j, n in enumerate(names) if n in used]
        cols = {n: array("d") for _, n in want}
        numbers = array("q")
        for ln, text in body:
            try:
                fields = split_fields(text, delim)
            except csv.Error as e:
                raise DataError(f"{where}: line {ln}: {e}") from None
            if len(fields) != len(names):
                raise DataError(f"{where}: line {ln}: {len(fields)} values but the header "
                                f"has {len(names)} columns")
            if len(numbers) >= MAX_RECORD_SAMPLES:
                raise DataError(f"{where}: more than {MAX_RECORD_SAMPLES} samples; split the "
                                "record or decimate it")
            for j, name in want:
                try:
                    cols[name].append(to_float(fields[j], delim))
                except ValueError:
                    raise DataError(f"{where}: line {ln}: column {name!r}: "
                                    f"{fields[j][:40]!r} is not a number") from None
            numbers.append(ln)
    return names, {n: np.array(c, dtype=np.float64) for n, c in cols.items()}, numbers


def header_columns(path: str | os.PathLike) -> list[str]:
    """The column names in a record's header line (the first line that is not blank or a
    comment); [`DataError`][] when there is none."""
    where = str(path)
    with _open_text(path) as f:
        for _, text in _numbered_lines(f, where):
            if text.strip() and not text.lstrip().startswith(("#", "%")):
                return split_fields(text, "," if "," in text else (";" if ";" in text else None))
    raise DataError(f"{where}: no header line (the file is empty or all comments)")


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
    names, col, numbers = _read_table(
        path, t_col, phi_col, (t_col, phi_col, P_col, tau_col),
        roles=[(t_col, TIME_ROLE), (phi_col, "the angle (phi_col, --phi-col)")],
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
    required = [(t_col, "--t-col")] + [
        (s.column, f"--channel {s.name}=COLUMN (or the scene's [sensors] {s.name} column)")
        for s in sensors] + [(c, f"the scene's input = {c!r} (a load's input column)")
                             for c in inputs]
    used = tuple(dict.fromkeys([t_col, P_col, tau_col] + [s.column for s in sensors]
                               + list(inputs)))
    roles = [(t_col, TIME_ROLE)] + [
        (s.column, f"channel {s.name} (--channel, or the scene's [sensors])")
        for s in sensors] + [(c, f"the input of a load (the scene's input = {c!r})")
                             for c in inputs]
    names, col, numbers = _read_table(path, t_col, "", used, required, roles,
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
