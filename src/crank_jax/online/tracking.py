"""`track`: follow a running machine's parameters sample by sample, with honest bands and
change alarms (DESIGN.md section 9).

The record is read as [`fit`][crank_jax.fit] reads it (channels, sensors, calibrations,
measured `P`/`tau` columns and input-driven loads, per-channel noise levels). The filter
starts from a batch fit of the record's first seconds (`start="batch"`, the default) or
from the scene's values (`start="scene"`), then runs the extended Kalman filter of
[`ekf`][crank_jax.online.ekf] over the whole record in chunks of a fixed shape (one
compiled program whatever the record's length, memory bounded by the chunk), and turns
the CUSUM's alarms into named changes ([`alarms`][crank_jax.online.alarms]).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ..identify.request import normalize
from ..identify.start import half_window, smooth_derivatives
from ..model.params import FIELDS, SIGNED_FIELDS, WIDTH_FIELDS
from ..records.data import Data
from ..scene import Scene
from ..simulation import linearize
from .alarms import name_alarms
from .ekf import FilterSettings, FilterState, TrackModel, init_state
from .runner import CHUNK, array_chunks, run_chunks
from .tracked import TrackResult

__all__ = ["track", "prepare", "finish", "TrackProblem", "STARTS", "CHUNK"]

#: How the filter starts: a batch fit of the record's first seconds, or the scene.
STARTS = ("batch", "scene")
#: A Runge-Kutta step covers at most this fraction of the linearised period, and at most
#: `_MAX_TURN` rad of the fastest speed the record shows.
_PERIOD_FRACTION, _MAX_TURN = 1 / 40, 0.05
#: The batch start's covariance is inflated by this factor (it saw the samples the filter
#: sees again) and a scene start's relative standard deviation.
_BATCH_INFLATION, _SCENE_PRIOR = 10.0, 0.1


def _check_free(free: Sequence[str]) -> tuple[str, ...]:
    free = tuple(dict.fromkeys(free))
    bad = [n for n in free if n not in FIELDS or n in WIDTH_FIELDS]
    if not free or bad:
        ok = [n for n in FIELDS if n not in WIDTH_FIELDS]
        raise ValueError(f"`free=` must name mechanism fields to follow, got {list(free)}; "
                         f"choose from {ok}")
    return free


def _positive(name: str, v) -> None:
    if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
        raise ValueError(f"`{name}=` must be a finite number > 0, got {v!r}")


def _check_options(start, start_seconds, false_alarm_rate, change_ratio):
    if start not in STARTS:
        raise ValueError(f"`start=` must be one of {STARTS}, got {start!r}")
    _positive("start_seconds", start_seconds)
    _positive("false_alarm_rate", false_alarm_rate)
    if not (isinstance(change_ratio, (int, float)) and math.isfinite(change_ratio)
            and change_ratio > 1):
        raise ValueError(f"`change_ratio=` must be a finite variance ratio > 1, got "
                         f"{change_ratio!r}")


class TrackProblem(NamedTuple):
    """A record made ready for the filter: its [`TrackModel`][crank_jax.online.ekf.TrackModel],
    [`FilterSettings`][crank_jax.online.ekf.FilterSettings] and first
    [`FilterState`][crank_jax.online.ekf.FilterState]; its times `ts` (n,), s, and
    channels `ys` (n, C), SI; the free names and which are in log coordinates; the
    settings in words (`track.json`'s) and the record's name. Records of one scene,
    free set and length give problems of one structure: `jax.vmap` of
    [`run_filter`][crank_jax.online.ekf.run_filter] runs them as a fleet."""

    model: TrackModel
    settings: FilterSettings
    state: FilterState
    ts: np.ndarray
    ys: np.ndarray
    free: tuple
    log: tuple
    info: dict
    source: str


def prepare(scene: Scene, data: Data, free: Sequence[str] = ("k", "c"), *,
            start: str = "batch", start_seconds: float = 5.0, false_alarm_rate: float = 1.0,
            change_ratio: float = 4.0, q_param: float = 1e-4, load_by: str = "time",
            progress: bool = True) -> TrackProblem:
    """The [`TrackProblem`][] of `data` (arguments as [`track`][]'s)."""
    free = _check_free(free)
    _check_options(start, start_seconds, false_alarm_rate, change_ratio)
    req = normalize(
        scene, data, free + ("phi0", "dphi0"), init="scene", method="lm", shooting="auto",
        segments=None, multistart=1, seed=0, max_steps=None, tol=1e-8, sigma=None,
        profile=None, window=None, progress=progress, warn=False, load_by=load_by)
    rec = req.records[0]
    ts = np.asarray(rec.ts, float)
    outs = rec.outputs()
    values, se, x0_state, se_state, start_note = _start(req, scene, data, free, start,
                                                          start_seconds, progress, load_by)
    log = tuple(n not in SIGNED_FIELDS and values[n] > 0 for n in free)
    # The record's speeds and accelerations at most 512 samples (the step size and the
    # acceleration noise need their scale, not every sample: 2 s of a 12,000-sample call).
    at = np.unique(np.linspace(0, ts.size - 1, min(ts.size, 512)).astype(int))
    _, dphi, ddphi = smooth_derivatives(ts, req.angles[0], half_window(ts, None), at)
    model = TrackModel(scene.mech.replace(**values), *req.loads[0],
                       jnp.asarray([float(s.scale) for s, _ in outs]),
                       jnp.asarray([float(s.offset) for s, _ in outs]), free, log,
                       tuple(s.name for s, _ in outs), _substeps(req, values, ts, dphi))
    z0 = np.array([math.log(values[n]) if lg else values[n] for n, lg in zip(free, log)])
    sz = np.array([se[n] / values[n] if lg else se[n] for n, lg in zip(free, log)])
    dt = float(np.median(np.diff(ts)))
    alpha = min(false_alarm_rate * dt / 3600.0, 0.5)
    # The state's acceleration noise, (rad/s^2)^2 per Hz: a thousandth of the record's rms
    # angular acceleration per sample interval (what a model that is nearly right misses).
    q_accel = float((1e-3 * np.sqrt(np.mean(ddphi**2))) ** 2 * dt)
    settings = FilterSettings(
        R=jnp.asarray([req.sigmas[s.name] ** 2 for s, _ in outs]), q_accel=jnp.asarray(q_accel),
        q_param=jnp.asarray([(q_param if lg else q_param * max(abs(values[n]), 1e-12)) ** 2
                             for n, lg in zip(free, log)]),
        P_param=jnp.asarray(np.diag(sz**2)), threshold=jnp.asarray(math.log(1 / alpha)),
        lam=jnp.asarray(float(change_ratio)))
    P0 = np.diag(np.concatenate([se_state**2, sz**2]))
    state = init_state(np.concatenate([x0_state, z0]), P0, ts[0])
    ys = np.stack([np.asarray(y, float) for _, y in outs], axis=1)
    info = {"filter": "extended Kalman filter on the state and parameters",
            "start": start_note, "substeps": model.substeps, "chunk": CHUNK,
            "noise": {s.name: float(req.sigmas[s.name]) for s, _ in outs},
            "q_param": q_param, "q_accel": q_accel,
            "alarm_test": "CUSUM on the log-likelihood ratio of the normalised innovations "
                          f"(variance ratio {change_ratio:g})",
            "false_alarm_rate_per_hour": false_alarm_rate,
            "threshold": float(settings.threshold), "log": dict(zip(free, log)),
            "load_by": load_by}
    return TrackProblem(model, settings, state, ts, ys, free, log, info, rec.source)


def track(scene: Scene, data: Data, free: Sequence[str] = ("k", "c"), *,
          start: str = "batch", start_seconds: float = 5.0, false_alarm_rate: float = 1.0,
          change_ratio: float = 4.0, settle: float = 5.0, q_param: float = 1e-4,
          every: int = 1, load_by: str = "time", progress: bool = True) -> TrackResult:
    """Follow the free parameters of `scene` through the record `data`, sample by sample.

    **Arguments:**

    - `scene`: the fixed values, loads and sensors (as for [`fit`][crank_jax.fit]);
      `data`: one record (its channels, measured inputs and `P`/`tau` columns).
    - `free`: mechanism fields to follow (the others stay at the scene's values).
    - `start`: `"batch"` (a fit of the first `start_seconds` s, its covariance inflated
      tenfold) or `"scene"` (the scene's values, 10% relative standard deviation).
    - `false_alarm_rate`: alarms per hour of record the change test may raise on a
      machine that does not change (an upper bound, by Lorden's inequality).
    - `change_ratio`: the growth of the innovations' variance the test looks for.
    - `settle`: seconds after an alarm at which the new values are read.
    - `q_param`: each parameter's random walk, per sqrt(s): relative for a field that
      cannot be negative, in its unit otherwise.
    - `every`: keep every `every`-th sample in the result (a long record's memory).
    - `load_by`: what the record's measured `P`/`tau` columns follow, `"time"` or
      `"angle"` (as for [`fit`][crank_jax.fit]: a force that follows the crank).
    - `progress`: show progress on stderr.

    **Returns:** a [`TrackResult`][crank_jax.online.tracked.TrackResult].
    **Raises:** `ValueError` naming the argument for a request it cannot serve.
    """
    # (prepare checks its own options; these two are the result's.)
    _positive("settle", settle)
    if not (isinstance(every, int) and every >= 1):
        raise ValueError(f"`every=` must be an integer >= 1, got {every!r}")
    p = prepare(scene, data, free, start=start, start_seconds=start_seconds,
                false_alarm_rate=false_alarm_rate, change_ratio=change_ratio,
                q_param=q_param, load_by=load_by, progress=progress)
    run = run_chunks(p.model, p.settings, p.state, array_chunks(p.ts, p.ys), every,
                     progress, total=p.ts.shape[0])
    return finish(p, run, settle, every)


def finish(p: TrackProblem, run, settle: float, every: int, **info) -> TrackResult:
    """The [`TrackResult`][crank_jax.online.tracked.TrackResult] of a filtered record
    (`run`, a [`Run`][crank_jax.online.runner.Run] of the problem `p`); `info` adds to its
    settings."""
    alarms = name_alarms(run.steps, run.events, p.free, p.log, settle, every, run.dt, run.n)
    return TrackResult.build(run.t, run.steps, p.free, p.log, alarms,
                             p.info | {"settle": settle, "every": every} | info,
                             source=p.source)


def _start(req, scene, data, free, start, seconds, progress, load_by):
    """Parameter values and standard errors (physical units), the initial state (2,) and
    its standard errors, and the start in words."""
    rec = req.records[0]
    ts = np.asarray(rec.ts, float)
    if start == "batch":
        from ..identify.fit import fit

        t_end = min(float(ts[0]) + seconds, float(ts[-1]))
        res = fit(scene, data, free=free + ("phi0", "dphi0"), window=(None, t_end),
                  progress=progress, warn=False, load_by=load_by)
        if res.converged and all(res.stderr[n] is not None for n in free + ("phi0", "dphi0")):
            k = _BATCH_INFLATION
            vals = {n: res.values[n] for n in free}
            se = {n: math.sqrt(k) * res.stderr[n] for n in free}
            st = np.array([res.values["phi0"], res.values["dphi0"]])
            sst = math.sqrt(k) * np.array([res.stderr["phi0"], res.stderr["dphi0"]])
            return vals, se, st, sst, (f"a batch fit of the first {t_end - ts[0]:.3g} s "
                                       f"({res.iterations} LM iterations, covariance x{k:g})")
        why = res.message if not res.converged else "some standard errors not determined"
        note = f"the scene's values (the batch fit of the first {seconds:g} s: {why})"
    else:
        note = "the scene's values"
    vals = {n: float(getattr(scene.mech, n)) for n in free}
    se = {n: _SCENE_PRIOR * abs(v) if abs(v) > 0 else _SCENE_PRIOR for n, v in vals.items()}
    per = 2 * math.pi / max(_omega(req, vals), 1e-9)
    ps, dps, _ = smooth_derivatives(ts, req.angles[0], half_window(ts, per), [0])
    noise = float(req.sigmas.get("phi", 1e-2))
    st = np.array([float(ps[0]), float(dps[0])])
    return vals, se, st, np.array([10 * noise + 1e-3, 0.1 * abs(st[1]) + 1e-2]), note


def _omega(req, values) -> float:
    """The linearised natural frequency at `values` (rad/s), or 0."""
    w = float(np.asarray(linearize(req.scene.mech.replace(**values), req.loads[0][0]).omega_n))
    return w if math.isfinite(w) else 0.0


def _substeps(req, values, ts, dphi) -> int:
    """Runge-Kutta steps per sample interval: a fortieth of the linearised period and
    `_MAX_TURN` rad of the fastest speed `dphi` (rad/s) the record shows, at most."""
    dt = float(np.max(np.diff(ts))) if ts.size > 1 else 0.0
    w = _omega(req, values)
    h = min(_PERIOD_FRACTION * 2 * math.pi / w if w > 0 else math.inf,
            _MAX_TURN / max(float(np.max(np.abs(dphi))), 1e-9))
    return int(min(max(1, math.ceil(dt / h)), 64))
