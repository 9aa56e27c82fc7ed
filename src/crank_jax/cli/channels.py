"""The fit's channel options: `--channel NAME[=COLUMN[:UNIT]]` and `--sigma [NAME=]VALUE`
(both repeatable), and which sensors each record is read through."""

from __future__ import annotations

import argparse
import math

from .errors import UserError

__all__ = ["add_channel_options", "parse_sigma", "record_sensors", "scene_inputs"]


def add_channel_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--channel", action="append", default=[], metavar="NAME[=COLUMN[:UNIT]]",
                   help="fit this channel (repeatable): phi, dphi, x_s, v_s or a_s, read from "
                        "COLUMN (default: the scene's [sensors] column, else NAME) in UNIT "
                        "(rad, deg, rev; rad/s, deg/s, rpm; m, mm; m/s, mm/s; m/s^2, g), with "
                        "the scene's calibration; default: every scene sensor in the record, "
                        "else the phi column")


def parse_sigma(values: list[str] | None, option: str = "--sigma", zero: bool = False
                ) -> float | dict[str, float] | None:
    """`--sigma` texts -> the fit's `sigma`: one bare VALUE is the first channel's (rad for
    an angle); NAME=VALUE gives a channel's, in its SI unit. `zero`: 0 is allowed (a
    noise level to synthesise)."""
    from ..identify.request import SIGMA_RANGE
    from ..sensors import CHANNELS

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
    the plain angle column (`--phi-col`, `--angle-unit`)."""
    from ..data import header_columns
    from ..sensors import SensorError, select_sensors

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
    return found


def scene_inputs(scene) -> tuple[str, ...]:
    """The record columns the scene's input-driven loads read (`[load]`/`[torque]`
    `input = COLUMN`)."""
    from ..model.loads import InputLoad

    return tuple(x.column for x in (scene.load, scene.torque) if isinstance(x, InputLoad))
