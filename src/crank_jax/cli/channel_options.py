"""The fit's channel options: `--channel NAME[=COLUMN[:UNIT]]` and `--sigma [NAME=]VALUE`
(both repeatable), and which sensors each record is read through."""

from __future__ import annotations

import argparse
import math

from .errors import UserError

__all__ = ["add_channel_options", "add_angle_options", "parse_sigma", "record_sensors",
           "scene_inputs", "read_records", "read_sensors", "distinct_files"]


def add_channel_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--channel", action="append", default=[], metavar="NAME[=COLUMN[:UNIT]]",
                   help="fit this channel (repeatable): phi, dphi, x_s, v_s or a_s, read from "
                        "COLUMN (default: the scene's [sensors] column, else NAME) in UNIT "
                        "(rad, deg, rev; rad/s, deg/s, rpm; m, mm; m/s, mm/s; m/s^2, g), with "
                        "the scene's calibration; default: every scene sensor in the record, "
                        "else the phi column")


def add_angle_options(p: argparse.ArgumentParser) -> None:
    """`--phi-col` and `--angle-unit`: the plain angle column (default `phi`, rad). Their
    defaults are None so that a use beside `--channel` or the scene's sensors, which
    choose the channels instead, is seen and refused (`record_sensors`)."""
    p.add_argument("--phi-col", help="name of the angle column (phi); with --channel or the "
                                     "scene's [sensors], give it as --channel phi=COLUMN")
    p.add_argument("--angle-unit", choices=("rad", "deg"),
                   help="unit of the angle column (rad); with --channel or the scene's "
                        "[sensors], give it as --channel phi=COLUMN:deg")


def parse_sigma(values: list[str] | None, option: str = "--sigma", zero: bool = False
                ) -> float | dict[str, float] | None:
    """`--sigma` texts -> the fit's `sigma`: one bare VALUE is the first channel's (rad for
    an angle); NAME=VALUE gives a channel's, in its SI unit. `zero`: 0 is allowed (a
    noise level to synthesise)."""
    from ..identify.fit_options import SIGMA_RANGE
    from ..records.sensors import CHANNELS

    if not values:
        return None
    out: dict[str, float] = {}
    for text in values:
        name, eq, value = text.rpartition("=")
        name = name.strip() if eq else ""
        if eq and name not in CHANNELS:
            raise UserError(f"{option} {text}: channel {name!r} is unknown; choose from "
                            f"{', '.join(CHANNELS)}")
        try:
            v = float(value)
        except ValueError:
            raise UserError(f"{option} {text}: {value!r} is not a number; give VALUE or "
                            "NAME=VALUE") from None
        if not (math.isfinite(v) and (SIGMA_RANGE[0] <= v <= SIGMA_RANGE[1]
                                      or zero and v == 0)):
            raise UserError(f"{option} must be a noise level from {SIGMA_RANGE[0]:g} to "
                            f"{SIGMA_RANGE[1]:g} (rad, or the channel's SI unit), got {v:g}")
        if name in out:
            raise UserError(f"{option} gives {name or 'the first channel'} twice; give it once")
        out[name] = v
    if "" in out and len(out) > 1:
        raise UserError(f"{option}: give either one bare VALUE (the first channel's) or "
                        "NAME=VALUE for each channel, not both")
    return out[""] if "" in out else out


def record_sensors(a: argparse.Namespace, scene, path: str):
    """The sensors to read `path` through (`sensors.select_sensors`'s rules), or None for
    the plain angle column (`--phi-col`, `--angle-unit`). `--phi-col` or `--angle-unit`
    beside sensors that choose the channels is refused: it would be ignored."""
    from ..records.data import header_columns
    from ..records.sensors import SensorError, select_sensors

    channels = getattr(a, "channel", None) or []
    if not channels and not scene.sensors:
        return None
    try:
        found = select_sensors(channels, scene.sensors,
                               None if channels else header_columns(path))
    except SensorError as e:
        raise UserError(str(e)) from None
    if not channels and found == select_sensors([], ()):
        return None  # no scene sensor in this record: its angle column, as without any
    angle = [f"{o} {v}" for o, v in (("--phi-col", getattr(a, "phi_col", None)),
                                      ("--angle-unit", getattr(a, "angle_unit", None)))
             if v is not None]
    if angle:
        by = (f"--channel {channels[0]}" if channels else
              f"the scene's [sensors] ({', '.join(s.name for s in found)} in {path})")
        raise UserError(f"{' and '.join(angle)} would be ignored: {by} chooses the record's "
                        "channels; give the angle's column and unit as --channel "
                        "phi=COLUMN:UNIT instead (it keeps the scene's calibration)")
    return found


def read_sensors(a: argparse.Namespace, scene, path: str):
    """The sensors `path` is read through, each record's as `read_records` reads it: those
    of `record_sensors`, else the plain angle column as a sensor (`--phi-col` in
    `--angle-unit`)."""
    from ..records.sensors import Sensor

    found = record_sensors(a, scene, path)
    return found if found is not None else (
        Sensor("phi", getattr(a, "phi_col", None) or "phi",
               getattr(a, "angle_unit", None) or "rad"),)


def read_records(a: argparse.Namespace, scene, files) -> list:
    """Every record of a command, read alike by `fit`, `validate` and `posterior`: through
    the sensors of `record_sensors` (or the plain angle column), with the scene's input
    columns, the time column `--t-col` and the loads' interpolation `--load-interp`.
    Options a command lacks take their defaults."""
    from ..records.data import load_data

    distinct_files(files)
    return [load_data(f, t_col=getattr(a, "t_col", None) or "t",
                      phi_col=getattr(a, "phi_col", None) or "phi",
                      angle_unit=getattr(a, "angle_unit", None) or "rad",
                      interp=getattr(a, "load_interp", None) or "cubic",
                      sensors=record_sensors(a, scene, f), inputs=scene_inputs(scene))
            for f in files]


def distinct_files(files) -> None:
    """Refuse a record given twice (DATA and --more-data, or two --more-data): the same
    file by its resolved path, or a copy of it by its content. The same data twice would
    count twice: the intervals narrow as if there were twice the data."""
    import hashlib
    import os

    seen: dict[tuple[str, str], int] = {}
    for i, f in enumerate(files):
        keys = [("path", os.path.realpath(f))]
        if len(files) > 1 and os.path.isfile(f):  # (never opened unless a regular file)
            with open(f, "rb") as fh:
                keys.append(("content", hashlib.file_digest(fh, "sha256").hexdigest()))
        for key in keys:
            if key in seen:
                j = seen[key]
                how = "the same file as" if key[0] == "path" else "a copy of"
                raise UserError(f"{_record_option(i)} {f!r} is {how} {_record_option(j)} "
                                f"{files[j]!r}: the same record given twice would count "
                                "twice (intervals as if there were twice the data); give "
                                "each record once")
            seen[key] = i


def _record_option(i: int) -> str:
    return "DATA" if i == 0 else "--more-data"


def scene_inputs(scene) -> tuple[str, ...]:
    """The record columns the scene's input-driven loads read (`[load]`/`[torque]`
    `input = COLUMN`)."""
    from ..model.loads import InputLoad

    return tuple(x.column for x in (scene.load, scene.torque) if isinstance(x, InputLoad))
