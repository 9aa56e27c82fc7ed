"""Which record columns a [`Data`][crank_jax.records.data.Data] or a
[`Scene`][crank_jax.scene.Scene] names, and the checks of those fields (messages, not
exceptions: `data.py` and `scene.py` raise their own errors with them). Every column
plays one role ([`columns`][crank_jax.records.columns])."""

from __future__ import annotations

from ..model.loads import AbstractLoad, NoLoad
from ..model.sampled import InputLoad
from .columns import RESERVED, column_problem, role_conflict
from .sensors import CHANNELS, Sensor, sensor_columns_conflict

__all__ = ["data_roles", "data_fields_problem", "scene_columns_problem"]


def _sensors_problem(sensors, owner: str) -> str | None:
    if not isinstance(sensors, tuple) or not all(isinstance(s, Sensor) for s in sensors):
        return (f"{owner}.sensors must be a tuple of Sensor objects, e.g. (Sensor('phi', "
                f"unit='deg'),); got {sensors!r:.80}")
    return None


def data_roles(data) -> list[tuple[str, str]]:
    """(column, role) of every column [`save_data`][crank_jax.records.data.save_data]
    writes for `data`:
    `t`, each channel's (its sensor's column, else its name), `P` and `tau` when the loads
    are known, and the inputs'."""
    cal = {s.name: s.column for s in data.sensors}
    out = [("t", "the time")] + [(cal.get(n, n), f"channel {n}")
                                 for n, _ in data.outputs_items()]
    out += [(c, role) for c, role, x in (("P", "the slider force P", data.load),
                                        ("tau", "the crank torque tau", data.torque))
            if x is not None and not isinstance(x, NoLoad)]
    return out + [(c, f"the input {c!r} of a load") for c in data.inputs]


def data_fields_problem(data) -> str | None:
    """Why a [`Data`][crank_jax.records.data.Data]'s fields would trip a later step (or be silently
    misread), naming the field and the fix; None when they are fine."""
    bad = [n for n in data.channels if n not in CHANNELS]
    if bad:
        return f"Data.channels: channel {bad[0]!r} is unknown; choose from {list(CHANNELS)}"
    if data.phi is not None and "phi" in data.channels:
        return ("the angle is given twice, as Data.phi and as Data.channels['phi']; give it "
                "once")
    problem = _sensors_problem(data.sensors, "Data")
    if problem:
        return problem
    for name, u in data.inputs.items():
        problem = column_problem(name)
        if problem:
            return f"Data.inputs: the input's column name {problem}"
        if not isinstance(u, AbstractLoad):
            return (f"Data.inputs[{name!r}] must be the input's samples as a SampledLoad, "
                    f"e.g. SampledLoad(ts, {name}_values); got {type(u).__name__}")
    return role_conflict(data_roles(data))


def scene_columns_problem(sensors, load, torque) -> str | None:
    """Why the record columns a scene names (its sensors' and its loads' inputs) cannot
    each play one role, or None."""
    problem = _sensors_problem(sensors, "Scene") or sensor_columns_conflict(sensors)
    if problem:
        return problem
    inputs = [(side, x.column) for side, x in (("load", load), ("torque", torque))
              if isinstance(x, InputLoad)]
    for side, c in inputs:
        problem = column_problem(c) or (f"{c!r} is {RESERVED[c]}, which records keep for it"
                                        if c in RESERVED else None)
        if problem:
            return f"[{side}] input: the input's column {problem}; rename the column"
    return role_conflict([(s.column, f"[sensors] {s.name}'s column") for s in sensors]
                         + [(c, "a load's input (input = COLUMN)") for _, c in inputs])
