"""Normalise and check a fit request before any compute, then make it complete: a frozen
[`FitRequest`][] with each record's crank angle and each channel's noise level resolved.

Every mistake a user can make in a call to [`fit`][] (an unknown name, a profile of a
parameter that is not free, a start value outside a parameter's domain, scenes that
disagree about the mechanism, a window with too few samples) is found here and raised as
one `ValueError` naming the field and the fix, before a single ODE is solved.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
from collections.abc import Sequence

import numpy as np

from ..model.loads import LOAD_PARAMS, AbstractLoad, get_param, load_kind
from ..model.outputs import SI_UNITS
from ..model.params import FIELDS, SliderCrank
from ..model.params import SIGNED_FIELDS as PARAM_SIGNED_FIELDS
from ..model.sampled import bind_input
from ..records.data import Data
from ..records.load_by import loads_by
from ..records.sensors import OFFSET_NAMES
from ..scene import Scene
from ..sweep.distributions import MAX_SEED
from .channels import (
    channel_angles,
    channel_names,
    channel_sigmas,
    check_sigma_names,
    given_levels,
)
from .fit_options import Init, Method, ShootingMode, check_options
from .userforce import force_names, force_starts

__all__ = ["FitRequest", "normalize", "STATE_NAMES", "LOAD_NAMES", "SIGNED_FIELDS",
           "free_names", "load_param", "reported_names", "window_data", "record_mech",
           "record_loads"]

STATE_NAMES = ("phi0", "dphi0")
#: Load parameters that can be free, name -> (side, role), from the one load table
#: (`model.loads.LOAD_PARAMS`): each load's mean, amplitude and input gain (they enter
#: linearly).
LOAD_NAMES = {n: sr for n, sr in LOAD_PARAMS.items() if sr[1] in ("mean", "amp", "gain")}
#: Mechanism fields that may be negative (the slider line's offset, from `model.params`);
#: every other field is >= 0, and r, L strictly positive.
SIGNED_FIELDS = frozenset(PARAM_SIGNED_FIELDS)
_STRICTLY_POSITIVE = frozenset({"r", "L"})
def free_names() -> tuple[str, ...]:
    """Every name that can be free: the mechanism fields (read from `FIELDS`, so new
    fields can be free as soon as the model has them), the load amplitudes, the channels'
    offsets (`phi_offset`, `x_s_offset`, ...) and the initial state."""
    return tuple(FIELDS) + tuple(LOAD_NAMES) + tuple(OFFSET_NAMES) + STATE_NAMES


def load_param(load: AbstractLoad, role: str) -> float | None:
    """The value of a load's `role` ("mean" or "amp", see `model.loads.ROLES`), or None
    when that load's kind has no such parameter."""
    v = get_param(load, role)
    return None if v is None else float(np.asarray(v))


def reported_names(free: Sequence[str], n_records: int, per_record: Sequence[str] = ()
                   ) -> tuple[str, ...]:
    """The names a fit reports: the global free names, then per record `n[i]` for each
    name of `per_record` and `phi0[i]`/`dphi0[i]` (no suffix for a single record)."""
    glob = [n for n in free if n not in STATE_NAMES and n not in per_record]
    states = [n for n in STATE_NAMES if n in free]
    if n_records == 1:
        return tuple(glob + list(per_record) + states)
    return tuple(glob + [f"{n}[{i}]" for i in range(n_records)
                         for n in list(per_record) + states])


@dataclasses.dataclass(frozen=True)
class FitRequest:
    """A checked fit request, complete when made (see [`fit`][] for the meaning of each
    option; [`normalize`][] makes it).

    `records` are the windowed records; `loads` holds each record's `(load, torque)` (its
    own, else its scene's); `states` each record's fixed `(phi0, dphi0)` (its scene's),
    used for a state that is not free. `start` holds the start value of every free global
    name (the initial states start from the data, later). `angles` holds each record's
    crank angle as the data tell it (n,), rad (see `angle.py`), and `sigmas` each
    channel's noise level, SI (given, else estimated from the record; see `channels.py`).
    """

    scene: Scene
    records: tuple[Data, ...]
    loads: tuple[tuple[AbstractLoad, AbstractLoad], ...]
    states: tuple[tuple[float, float], ...]
    free: tuple[str, ...]
    start: dict
    init: Init
    method: Method
    shooting: ShootingMode
    segments: int | None
    multistart: int
    seed: int
    max_steps: int
    tol: float
    sigma: float | dict | None
    profile: str | None
    progress: bool
    warn: bool
    angles: tuple[np.ndarray, ...]
    sigmas: dict[str, float]
    #: Free names with a separate value per record (`n[i]`), besides the states.
    per_record: tuple = ()
    #: A user's force term (`fit(force=...)`), its free fields named `force.<field>`.
    force: object = None

    # What follows from the fields, worked out once per request (a frozen request's
    # values never change; a new weighting is a new request, `dataclasses.replace`).

    @functools.cached_property
    def names(self) -> tuple[str, ...]:
        """The names the fit reports (`reported_names`)."""
        return reported_names(self.free, len(self.records), self.per_record)

    @functools.cached_property
    def first_channel(self) -> str:
        """The first record's first channel: the fit's residuals are in its unit."""
        return self.records[0].outputs()[0][0].name

    @functools.cached_property
    def unit(self) -> str:
        """The SI unit of the first channel, the unit of the fit's residuals."""
        return SI_UNITS[self.first_channel]

    @functools.cached_property
    def noise(self) -> float:
        """The first channel's noise level: the level of the fit's residuals, SI."""
        return self.sigmas[self.first_channel]

    @functools.cached_property
    def estimated(self) -> tuple[str, ...]:
        """The channels whose noise level the fit estimates (not given by `sigma`)."""
        given = given_levels(self.sigma, self.first_channel)
        return tuple(n for n in channel_names(self.records) if n not in given)

    @functools.cached_property
    def known_sigma(self) -> float | None:
        """The noise level of the weighted residuals (the first channel's unit) when every
        channel's is given, else None (estimated from the residuals)."""
        return None if self.estimated else self.noise


def record_mech(mech: SliderCrank, own: dict) -> SliderCrank:
    """The shared mechanism `mech` with a record's own values (`own`, name -> value, from
    `Problem.unpack`) of its per-record mechanism fields (`per_record`)."""
    return SliderCrank(**{**{f: getattr(mech, f) for f in FIELDS},
                          **{n: v for n, v in own.items() if n in FIELDS}})


def record_loads(scene: Scene, data: Data) -> tuple[AbstractLoad, AbstractLoad]:
    """`(load, torque)` of a record as a fit and a validation take them: the record's own
    `P`/`tau` column where it has one, else the scene's load (an input-driven one bound to
    the record's input column; `ValueError` naming the record and the column where it
    lacks it)."""
    return (bind_input(data.load if data.load is not None else scene.load, data.inputs,
                       data.source, "slider force"),
            bind_input(data.torque if data.torque is not None else scene.torque,
                       data.inputs, data.source, "crank torque"))


def window_data(d: Data, window: tuple[float, float] | None) -> Data:
    """The samples of `d` with `t_start <= t <= t_end` (either end may be +-inf)."""
    if window is None:
        return d
    lo, hi = window
    keep = (d.ts >= lo) & (d.ts <= hi)
    if int(keep.sum()) < 8:
        raise ValueError(f"window [{lo:g}, {hi:g}] s keeps {int(keep.sum())} samples of "
                         f"{d.source} (which spans [{d.ts[0]:g}, {d.ts[-1]:g}] s); widen "
                         "`window=`")
    return d.select(keep)


def _check_scenes(scenes: list[Scene]) -> None:
    # A multi-experiment fit shares one mechanism and one solver; scenes may differ only
    # in what an experiment changes: its loads and its initial state.
    first = scenes[0]
    for i, sc in enumerate(scenes[1:], start=1):
        for n in FIELDS:
            if not np.array_equal(np.asarray(getattr(sc.mech, n)),
                                  np.asarray(getattr(first.mech, n))):
                raise ValueError(f"scene {i} has {n} = {float(getattr(sc.mech, n)):g}, scene "
                                 f"0 has {float(getattr(first.mech, n)):g}: the scenes of a "
                                 "multi-record fit must share the mechanism (they may differ "
                                 "only in loads and initial state)")
        for n in ("solver", "rtol", "atol"):
            a, b = getattr(sc, n), getattr(first, n)
            if not np.array_equal(np.asarray(a), np.asarray(b)):
                raise ValueError(f"scene {i} has {n} = {a}, scene 0 has {b}: the scenes of a "
                                 "multi-record fit must share the solver settings")


def _check_window(window) -> tuple[float, float] | None:
    if window is None:
        return None
    lo, hi = window
    lo = -math.inf if lo is None else float(lo)
    hi = math.inf if hi is None else float(hi)
    if not lo < hi:
        raise ValueError(f"window must have t_start < t_end, got [{lo:g}, {hi:g}]")
    return lo, hi


def _load_starts(free, records, loads) -> dict[str, float]:
    start = {}
    for n in free:
        if n not in LOAD_NAMES:
            continue
        which, role = LOAD_NAMES[n]
        for d, (load, torque) in zip(records, loads):
            if (d.load if which == "load" else d.torque) is not None:
                raise ValueError(f"{n} cannot be free: record {d.source} supplies its own "
                                 f"{'P' if which == 'load' else 'tau'} as data")
            obj = load if which == "load" else torque
            v = load_param(obj, role)
            if v is None:
                fix = (f"an input-driven {which} (input = COLUMN, gain = ...)"
                       if role == "gain" else
                       f"a harmonic {which} (or, for {n[:-1]}0, a constant one)")
                raise ValueError(f"{n} cannot be free: the scene's {which} is "
                                 f"{type(obj).__name__} ({load_kind(obj).name}), which has "
                                 f"no {n}; give the scene {fix}")
            start[n] = float(v)
    return start


def _offset_starts(free, records) -> dict[str, float]:
    """Start values of free channel offsets: the first record's sensor calibration."""
    start = {}
    for n in free:
        if n not in OFFSET_NAMES:
            continue
        cal = next((s for d in records for s, _ in d.outputs() if s.name == OFFSET_NAMES[n]),
                   None)
        if cal is None:
            have = sorted(channel_names(records))
            raise ValueError(f"{n} cannot be free: no record has a {OFFSET_NAMES[n]} channel "
                             f"(the channels are {have})")
        start[n] = float(cal.offset)
    return start


def _check_start(start: dict[str, float]) -> None:
    for n, v in start.items():
        if not math.isfinite(v):
            raise ValueError(f"the start value of {n} is {v}; give a finite init={{'{n}': ...}}")
        if n in _STRICTLY_POSITIVE and v <= 0:
            raise ValueError(f"the start value of {n} is {v}; {n} must be > 0 (it is fitted "
                             f"in log space): pass init={{'{n}': ...}}")
        if n in FIELDS and n not in SIGNED_FIELDS and v < 0:
            raise ValueError(f"the start value of {n} is {v}; {n} must be >= 0: pass "
                             f"init={{'{n}': ...}}")


def _check_per_record(per_record, free) -> tuple[str, ...]:
    per_record = tuple(dict.fromkeys(per_record or ()))
    for n in per_record:
        if n in STATE_NAMES:
            raise ValueError(f"`per_record=` names {n}, which is already one per record")
        if n not in free:
            raise ValueError(f"`per_record=` names {n!r}, which is not free; free it "
                             "(`free=`) or leave it out of `per_record=`")
    return per_record


def _pairs(scene, data) -> tuple[list[Scene], list[Data]]:
    """The records of `data` and a scene for each (one `Scene` stands for every record)."""
    records = [data] if isinstance(data, Data) else list(data)
    if not records or not all(isinstance(d, Data) for d in records):
        raise ValueError("data must be a Data record or a non-empty sequence of them")
    scenes = [scene] * len(records) if isinstance(scene, Scene) else list(scene)
    if len(scenes) != len(records) or not all(isinstance(s, Scene) for s in scenes):
        raise ValueError(f"got {len(scenes)} scenes for {len(records)} records; give one "
                         "Scene, or one per record")
    _check_scenes(scenes)
    return scenes, records


def _check_distinct(records: list[Data]) -> None:
    """Refuse two records with the same samples (times and every channel): the same data
    given twice counts twice, and the intervals narrow as if there were twice the data."""
    seen: dict[bytes, int] = {}
    for i, d in enumerate(records):
        h = hashlib.sha256(np.ascontiguousarray(d.ts, dtype=float).tobytes())
        for name, y in d.outputs_items():
            h.update(name.encode() + np.ascontiguousarray(y, dtype=float).tobytes())
        key = h.digest()
        if key in seen:
            raise ValueError(f"data: records {seen[key]} and {i} hold the same samples (the "
                             "same record given twice would count twice, narrowing the "
                             "intervals as if there were twice the data); give each record "
                             "once")
        seen[key] = i


def _init(init, start: dict) -> Init:
    """The kind of `init`; a dict's start values go into `start`, which must already hold
    every free global parameter."""
    if isinstance(init, dict):
        bad = [n for n in init if n not in start]
        if bad:
            raise ValueError(f"init gives start values for {bad}, which are not free global "
                             f"parameters ({sorted(start)})")
        start.update({n: float(v) for n, v in init.items()})
        return Init.DICT
    if init in (Init.SCENE, Init.REGRESSOR):
        return Init(init)
    raise ValueError(f"init must be 'scene', 'regressor' or a dict, got {init!r}")


def _check_free(free, force) -> tuple[str, ...]:
    """`free` once each, every name one that can be free (`ValueError` otherwise)."""
    free = tuple(dict.fromkeys(free))
    known = free_names() + tuple(force_names(force))
    unknown = [n for n in free if n not in known]
    if unknown or not free:
        raise ValueError(f"`free=` names unknown parameter(s) {unknown}; choose from "
                         f"{list(known)}" if unknown
                         else "`free=` must name at least one parameter")
    return free


def _starts(mech: SliderCrank, free, records, loads, force) -> dict[str, float]:
    """The start value of every free global name: the mechanism's, the loads', the
    channels' offsets and the force term's."""
    start = {n: float(getattr(mech, n)) for n in free if n in FIELDS}
    start.update(_load_starts(free, records, loads))
    start.update(_offset_starts(free, records))
    start.update(force_starts(force, free))
    return start


def normalize(scene, data, free, *, init, method, shooting, segments, multistart, seed,
              max_steps, tol, sigma, profile, window, progress, warn, per_record=(),
              force=None, load_by="time") -> FitRequest:
    """Check a fit request and bring it to one complete form (the arguments are those of
    [`fit`][]): the options as enums, each record's crank angle and each channel's noise
    level resolved ([`channels`][crank_jax.identify.channels]).

    **Returns:** a [`FitRequest`][]. **Raises:** `ValueError` naming the field and the fix.
    """
    scenes, records = _pairs(scene, data)
    free = _check_free(free, force)
    check_options(method, shooting, segments, multistart, max_steps, tol, sigma)
    method, shooting = Method(method), ShootingMode(shooting)
    if (isinstance(seed, bool) or not isinstance(seed, (int, np.integer))
            or not 0 <= seed <= MAX_SEED):
        raise ValueError(f"`seed=` must be an integer from 0 to {MAX_SEED}, got {seed!r}")
    per_record = _check_per_record(per_record, free)
    if per_record and len(records) == 1:
        raise ValueError(f"`per_record=` names {', '.join(per_record)}, but there is one "
                         "record: each free parameter is already its own; give several "
                         "records, or leave `per_record=` out")
    _check_distinct(records)
    window = _check_window(window)
    records = [loads_by(window_data(d, window), load_by) for d in records]
    if load_by == "angle" and "phi_offset" in free:
        raise ValueError("phi_offset cannot be free with `load_by='angle'`: the loads are "
                         "tabled by the angle channel through its given calibration; fix "
                         "phi_offset (the sensor's offset), or `load_by='time'`")
    loads = tuple(record_loads(sc, d) for d, sc in zip(records, scenes))
    start = _starts(scenes[0].mech, free, records, loads, force)
    check_sigma_names(sigma, records)
    init_kind = _init(init, start)
    _check_start(start)
    names = reported_names(free, len(records), per_record)
    if profile is not None and profile not in names:
        raise ValueError(f"profile {profile!r} is not a free parameter; choose from "
                         f"{list(names)}")
    n_total = sum(d.n for d in records)
    if n_total <= len(names):
        raise ValueError(f"too few samples: {n_total} samples for {len(names)} free "
                         "parameters")
    scene, states = scenes[0], tuple((float(sc.phi0), float(sc.dphi0)) for sc in scenes)
    first = records[0].outputs()[0][0].name
    sigmas = channel_sigmas(records, given_levels(sigma, first))
    angles = channel_angles(scene, records, states, loads)
    return FitRequest(
        scene=scene, records=tuple(records), loads=loads, states=states, free=free,
        start=start, init=init_kind, method=method, shooting=shooting,
        segments=segments, multistart=int(multistart), seed=int(seed),
        max_steps=int(max_steps if max_steps is not None else
                      (100 if method is Method.LM else 2000)),
        tol=float(tol), sigma=sigma, profile=profile, progress=bool(progress),
        warn=bool(warn), angles=angles, sigmas=sigmas, per_record=per_record, force=force)
