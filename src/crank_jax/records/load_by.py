"""What a record's measured loads follow: the clock (`load_by="time"`, the default: the `P`
and `tau` columns interpolated in time) or the crank (`load_by="angle"`: each column
tabled by the record's own angle and evaluated at the model's, an
[`AngleLoad`][crank_jax.model.angle_load.AngleLoad]).

The convention: the record's angle channel `phi` as its sensor reads it, brought to the
model's angle by the sensor's inverse calibration, `(data - offset) / scale`, as the
residuals compare them. Samples may be irregular (a toothed wheel's edge times, with a
gap at the reference tooth): the table takes them as they are.
"""

from __future__ import annotations

import numpy as np

from ..model.angle_load import AngleLoad, angle_problem
from ..model.sampled import SampledLoad
from .data import Data

__all__ = ["LOAD_BY", "check_load_by", "record_angle", "loads_by"]

#: What a record's `P`/`tau` columns may follow.
LOAD_BY: tuple[str, ...] = ("time", "angle")


def check_load_by(load_by, option: str = "load_by") -> str:
    """`load_by` if it is one of [`LOAD_BY`][]; `ValueError` naming `option` otherwise."""
    if not isinstance(load_by, str) or load_by not in LOAD_BY:
        raise ValueError(f"{option} must be 'time' or 'angle', got {load_by!r}")
    return load_by


def record_angle(data: Data) -> np.ndarray:
    """The record's crank angle (n,) as the model's phi, rad: its `phi` channel through
    the inverse of its calibration. `ValueError` naming `load_by` when it has none."""
    for sensor, y in data.outputs():
        if sensor.name == "phi":
            return np.asarray(sensor.model(np.asarray(y)), dtype=float)
    have = [s.name for s, _ in data.outputs()]
    raise ValueError(f"{data.source}: `load_by='angle'` tables the loads by the record's angle "
                     f"channel phi, which it lacks (its channels are {have}); give the "
                     "record its angle column, or `load_by='time'`")


def _tabled(load: SampledLoad | None, data: Data, angle: np.ndarray,
            period: float | None) -> AngleLoad | None:
    if load is None or isinstance(load, AngleLoad):
        return load
    if not isinstance(load, SampledLoad):
        raise ValueError(f"{data.source}: `load_by='angle'` tables a measured load (a P/tau "
                         f"column); this record's is a {type(load).__name__}")
    values = np.asarray(load(data.ts), dtype=float)
    return AngleLoad.from_samples(angle, values, data.ts, load.interp, period)


def loads_by(data: Data, load_by: str = "time", period: float | None = None) -> Data:
    """The record with its `P`/`tau` columns following `load_by` (see [`LOAD_BY`][]):
    itself for `"time"`; for `"angle"`, each column an
    [`AngleLoad`][crank_jax.model.angle_load.AngleLoad] tabled by the record's angle
    (`period`, rad: wrap a periodic load by it; None: hold the end values past the
    record's angles).

    Raises `ValueError` naming `load_by` for a record without an angle channel, without
    `P`/`tau` columns, or whose angle is not strictly monotone (with the first sample
    where it is not, and the fix).
    """
    if check_load_by(load_by) == "time":
        return data
    angle = record_angle(data)
    if data.load is None and data.torque is None:
        raise ValueError(f"{data.source}: `load_by='angle'` tables a record's P or tau column by "
                         "its angle, and this record has neither; add the measured load's "
                         "column, or `load_by='time'`")
    problem = angle_problem(angle)
    if problem:
        i, why = problem
        raise ValueError(f"{data.source}: `load_by='angle'` needs a crank turning one way "
                         f"over the record, but {why} at t = {data.ts[i]:.6g} s; window the "
                         "record to where it turns one way (`t_start=`, `t_end=`), or give "
                         "`load_by='time'`")
    return Data(data.ts, data.phi, _tabled(data.load, data, angle, period),
                _tabled(data.torque, data, angle, period), source=data.source,
                channels=data.channels, sensors=data.sensors, inputs=data.inputs)
