"""Validation on a record the model was not fitted to: predict it open-loop and score it.

[`validate`][] estimates only the initial state `(phi0, dphi0)` from the first
`init_window` seconds of the record (a fit with every mechanism parameter fixed), then
simulates the whole window open-loop from that state, with the record's own load columns
where it has them (by time or by angle, `load_by`) and the scene's elsewhere (as [`fit`][]
takes them), and scores the prediction on the samples after the initial-state window
(those were not used at all):

- `rms = sqrt(mean((y - yhat)^2))` and `max_abs = max |y - yhat|`, rad;
- `fit_percent = 100 (1 - |y - yhat| / |y - mean(y)|)` with 2-norms (MATLAB's `compare`):
  100 is a perfect prediction, 0 is no better than the record's mean; it can be negative.

A record with several channels (see [`sensors`][crank_jax.records.sensors]) is predicted and
scored in each (what its sensor reads under the model, `scale h + offset`, SI); the
top-level scores are the first channel's.

`horizon=T` scores a k-step-ahead prediction instead (MATLAB's `compare(data, sys, k)`): after
the initial-state window the record is cut into windows of `T` s, each window's state is
estimated from its first samples and the rest of the window is predicted (see
[`crank_jax.validation.horizon`][]). A driven rig whose drive level is a few percent off drifts
by radians over a long open-loop prediction, yet predicts one revolution ahead to a small
fraction of a radian: that is what `T` of one revolution measures. `init_free` names
parameters (e.g. `tau0`, the record's own drive level) estimated with the state on the
initial-state window: the operating point of a held-out record.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ..identify.fit import fit
from ..identify.request import LOAD_NAMES, STATE_NAMES, free_names, record_loads
from ..model.loads import AbstractLoad, InputLoad, NoLoad, set_param
from ..model.outputs import SI_UNITS, output
from ..model.params import FIELDS
from ..records.data import Data, DataError
from ..records.load_by import loads_by
from ..runtime.blas import one_blas_thread
from ..scene import Scene
from ..stats.diagnostics import residual_diagnostics
from . import horizon as hz
from .state_window import default_init_window
from .state_window import init_window as state_window

__all__ = ["validate", "Validation", "default_init_window", "MIN_SPREAD_EPS", "init_free_names"]


class Validation(NamedTuple):
    """The outcome of [`validate`][].

    Scores (over the `n_samples` samples after the initial-state window): `rms`,
    `max_abs` (rad), `fit_percent`. `phi0`, `dphi0` (rad, rad/s): the state estimated at
    `ts[0]`. `ts`, `phi`, `predicted` (m,): the whole window's times (s), data and
    prediction (rad); `scored` (m,) bool: the samples that were scored. `init_window`: its
    length, s. `source`: the record's label. `warnings`: sentences for the user.
    """

    rms: float
    max_abs: float
    fit_percent: float
    n_samples: int
    phi0: float
    dphi0: float
    ts: np.ndarray
    phi: np.ndarray
    predicted: np.ndarray
    scored: np.ndarray
    init_window: float
    source: str
    warnings: list[str]
    channels: dict | None = None
    """Per channel: `rms`, `max_abs`, `fit_percent`, `n_samples` (SI), `unit`."""
    predicted_channels: dict | None = None
    """Per channel: the prediction (m,), SI."""
    data_channels: dict | None = None
    """Per channel: the data (m,), SI."""
    horizon: float | None = None
    """The prediction horizon, s (`None`: open loop over the whole window)."""
    windows: list | None = None
    """With `horizon`, per window: `t_start`, `t_end` (s), `n_head` (samples its
    state was estimated from, in every window), `n_predicted`, `phi0`, `dphi0` (its state
    at its first sample), `rms` (first channel, over its predicted samples) and
    `converged` (its state fit)."""
    init_values: dict | None = None
    """The `init_free` parameters' values estimated on the initial-state window."""

    def to_json(self) -> dict:
        """The `VAL.json` document."""
        def num(x):
            return float(x) if math.isfinite(x) else None

        return {
            "rms": num(self.rms), "max_abs": num(self.max_abs),
            "fit_percent": num(self.fit_percent), "n_samples": int(self.n_samples),
            "phi0": num(self.phi0), "dphi0": num(self.dphi0),
            "t_start": float(self.ts[0]), "t_end": float(self.ts[-1]),
            "init_window": float(self.init_window), "source": self.source,
            "warnings": list(self.warnings),
            "channels": {n: {k: num(v) if k != "n_samples" else int(v)
                             for k, v in c.items() if k != "unit"}
                         for n, c in (self.channels or {}).items()},
            **({"init_free": {n: num(v) for n, v in self.init_values.items()}}
               if self.init_values else {}),
            **({"horizon": float(self.horizon),
                "windows": [{k: (num(v) if isinstance(v, float) else v)
                             for k, v in w.items()} for w in self.windows or []]}
               if self.horizon is not None else {}),
            "predictions": self.predictions(),
        }

    def predictions(self) -> dict:
        """The window's times, measurements and predictions per channel, SI (see
        [`prediction_table`][crank_jax.identify.predictions.prediction_table]), and
        `scored` per sample (False: in the initial-state window, or a window's head)."""
        from ..identify.predictions import prediction_table

        measured = self.data_channels or {"phi": self.phi}
        predicted = self.predicted_channels or {"phi": self.predicted}
        return {**prediction_table(self.ts, measured, predicted),
                "scored": [bool(x) for x in np.asarray(self.scored)]}

    def error_diagnostics(self):
        """The whiteness of the scored prediction errors (a
        [`Diagnostics`][crank_jax.stats.diagnostics.Diagnostics]), or None where there
        are too few finite ones to test."""
        e = (np.asarray(self.phi) - np.asarray(self.predicted))[np.asarray(self.scored)]
        try:
            return residual_diagnostics(e)
        except ValueError:  # too few or non-finite errors: nothing to test
            return None

    def report(self, path, *, scene=None, command=None, title: str = "") -> None:
        """Write a self-contained HTML report to `path` (see
        [`write_validation_report`][crank_jax.report.write_validation_report])."""
        from ..report import write_validation_report

        write_validation_report(self, path, scene=scene, command=command, title=title)

    def summary(self) -> str:
        """One paragraph for the terminal."""
        chans = self.channels or {"phi": {"unit": "rad"}}
        unit = next(iter(chans.values()))["unit"]
        how = ("open-loop" if self.horizon is None else
               f"at most {self.horizon:g} s ahead in {len(self.windows or [])} windows (each "
               "window's state from its first samples)")
        own = "".join(f", {n} = {v:.6g}" for n, v in (self.init_values or {}).items())
        text = (f"validation on {self.source} over [{self.ts[0]:g}, {self.ts[-1]:g}] s: "
                f"initial state phi0 = {self.phi0:.6g} rad, dphi0 = {self.dphi0:.6g} rad/s"
                f"{own} from the first {self.init_window:g} s; predicted {self.n_samples} "
                f"samples {how}: rms {self.rms:.4g} {unit}, max |error| {self.max_abs:.4g} "
                f"{unit}, fit {self.fit_percent:.2f}%")
        for n, c in chans.items() if len(chans) > 1 else ():
            text += (f"\nchannel {n}: rms {c['rms']:.4g} {c['unit']}, max |error| "
                     f"{c['max_abs']:.4g} {c['unit']}, fit {c['fit_percent']:.2f}%")
        return text


def _loads(scene: Scene, data: Data, scene_loads: bool) -> tuple[AbstractLoad, AbstractLoad]:
    """The record's loads as a fit takes them (`request.record_loads`: its own columns,
    else the scene's). With `scene_loads` False, a scene's load (not driven by an input
    column) that the record does not carry is refused by name instead."""
    for own, model, col, what in ((data.load, scene.load, "P", "slider force P"),
                                  (data.torque, scene.torque, "tau", "crank torque tau")):
        if not (scene_loads or own is not None or isinstance(model, (InputLoad, NoLoad))):
            raise DataError(f"{data.source}: the record has no {col!r} column, but the scene "
                            f"has a {what} ({type(model).__name__}) and scene_loads=False; "
                            "add the column with the load measured during this record, or "
                            "let the scene's load serve (scene_loads=True, the default)")
    return record_loads(scene, data)


#: The scored angles must spread (rms about their mean) by more than this many float64
#: epsilons of their largest magnitude: a smaller spread is rounding noise of a constant
#: record, and `fit_percent` divided by it is meaningless (it gave -5.4e17).
MIN_SPREAD_EPS = 1024


_WHAT = {"phi": "angle", "dphi": "crank rate (dphi)", "x_s": "slider position (x_s)",
         "v_s": "slider speed (v_s)", "a_s": "slider acceleration (a_s)"}


def _check_spread(y: np.ndarray, win: Data, t_init: float, name: str = "phi") -> None:
    """Raise [`DataError`][] when channel `name`'s scored data `y` (SI) are constant up to
    rounding."""
    scale = float(np.max(np.abs(y)))
    spread = float(np.sqrt(np.mean((y - y.mean()) ** 2)))
    if spread <= MIN_SPREAD_EPS * np.finfo(np.float64).eps * scale or spread == 0:
        raise DataError(
            f"{win.source}: the {y.size} scored samples (t > {t_init:g} s) hold a constant "
            f"{_WHAT.get(name, name)} ({float(y.mean()):.17g} {SI_UNITS[name]}; spread "
            f"{spread:.3g} {SI_UNITS[name]}, float rounding at most), so fit_percent is "
            "undefined: validate on a record in which the crank moves after the "
            "initial-state window")


@one_blas_thread
def validate(
    scene: Scene,
    data: Data,
    *,
    t_start: float | None = None,
    t_end: float | None = None,
    init_window: float | None = None,
    scene_loads: bool = True,
    progress: bool = False,
    horizon: float | None = None,
    init_free: tuple[str, ...] | list[str] = (),
    load_by: str = "time",
) -> Validation:
    """Predict a record from an initial state estimated on its start, and score it.

    **Arguments:**

    - `scene`: the (fitted) [`Scene`][]: its mechanism, solver settings and, where the
      record has no load columns, its loads.
    - `data`: the validation record, a [`Data`][].
    - `t_start`, `t_end`: the window of the record to use, s (`None`: its own ends).
    - `init_window`: length of the initial-state window at the start, s (default: from
      the record, [`record_init_window`][crank_jax.validation.state_window.record_init_window]:
      one revolution of a crank that turns (at least 30 samples), else about one period;
      at most half the record; at least
      [`MIN_SAMPLES`][crank_jax.records.data.MIN_SAMPLES] samples).
    - `scene_loads`: the scene's loads serve where the record has no `P`/`tau` column,
      exactly as in [`fit`][] (default); False: a record must carry every load the scene
      has (an input-driven one excepted), and one that lacks a column is refused.
    - `progress`: show the initial-state fit's progress bar.
    - `horizon`: `None` (default) predicts everything after the initial-state window open
      loop; a time `T` > 0 s predicts k steps ahead: after the initial-state window the
      record is cut into windows of `T` s, each window's state is estimated from its first
      `max(MIN_SAMPLES samples, T / 10)` (the first window's too) and the rest of it
      predicted open loop (see [`crank_jax.validation.horizon`][]). Scores are over the predicted
      samples. A `T` at least the rest of the record is one window: an open-loop
      prediction from the state its own head gives.
    - `init_free`: parameters estimated with the state on the initial-state window and
      then held (names a fit can free: mechanism fields, load amplitudes such as `tau0`,
      channel offsets such as `phi_offset`): the operating point of a held-out record.
    - `load_by`: what the record's `P`/`tau` columns follow: `"time"` or `"angle"`, as in
      [`fit`][].

    **Returns:** a [`Validation`][]. Raises `ValueError` (naming the argument) for a
    window with fewer than [`MIN_SAMPLES`][crank_jax.records.data.MIN_SAMPLES] samples, an
    initial-state window that leaves fewer than that many to score, a horizon that leaves
    none to predict, a name `init_free` cannot take, a missing load column (with
    `scene_loads=False`), a record `load_by='angle'` cannot table, or scored angles that are
    constant up to float rounding ([`MIN_SPREAD_EPS`][]; `fit_percent` would be
    meaningless); `RuntimeError` if a prediction's solve fails.
    """
    if not isinstance(scene, Scene) or not isinstance(data, Data):
        raise TypeError("validate(scene, data): expected a Scene and a Data record")
    if horizon is not None and not (isinstance(horizon, (int, float))
                                    and math.isfinite(horizon) and horizon > 0):
        raise ValueError(f"`horizon=` must be a time > 0 s, got {horizon!r}")
    win = loads_by(data.window(t_start, t_end), load_by)
    init_free = _check_init_free(init_free, win)
    load, torque = _loads(scene, win, scene_loads)
    win = Data(win.ts, win.phi, load, torque, source=win.source, channels=win.channels,
               sensors=win.sensors, inputs=win.inputs)
    init_window = state_window(scene, win, load, init_window)
    t_init = float(win.ts[0]) + init_window
    scored = win.ts > t_init
    windows = None
    if horizon is not None:
        windows, scored = hz.scored_windows(np.asarray(win.ts), t_init, float(horizon))
    for sensor, y in win.outputs():
        _check_spread(np.asarray(y)[scored], win, t_init, sensor.name)
    warnings: list[str] = []
    res = _state_fit(scene, win.window(None, t_init), load, torque, init_free, progress)
    if not res.converged:
        warnings.append(f"the initial-state fit did not converge ({res.message}); the "
                        "prediction starts from its last iterate")
    phi0, dphi0 = res.values["phi0"], res.values["dphi0"]
    own = {n: float(res.values[n]) for n in init_free}
    mech, load, torque, sensors = _with_values(scene, load, torque,
                                               [s for s, _ in win.outputs()], own)
    model = scene if mech is scene.mech else dataclasses.replace(scene, mech=mech)
    predicted = {s.name: np.full(win.n, np.nan) for s in sensors}
    info = None
    if windows is None:
        _open_loop(model, load, torque, sensors, np.asarray(win.ts), (phi0, dphi0),
                   predicted)
    else:
        info = hz.predict_windows(scene, mech, load, torque, sensors, win, windows,
                        (float(phi0), float(dphi0)), predicted, warnings)
    scores = {}
    for sensor, y in win.outputs():
        scores[sensor.name] = _scores(y[scored], predicted[sensor.name][scored], sensor.name)
    (first, y0), = win.outputs()[:1]
    top = scores[first.name]
    return Validation(
        rms=top["rms"], max_abs=top["max_abs"], fit_percent=top["fit_percent"],
        n_samples=int(scored.sum()), phi0=float(phi0), dphi0=float(dphi0),
        ts=np.asarray(win.ts), phi=np.asarray(y0), predicted=predicted[first.name],
        scored=scored, init_window=float(init_window), source=win.source, warnings=warnings,
        channels=scores, predicted_channels=predicted, data_channels=dict(win.outputs_items()),
        horizon=None if horizon is None else float(horizon), windows=info,
        init_values=own or None)


def _state_fit(scene: Scene, head: Data, load, torque, init_free: tuple[str, ...],
               progress: bool):
    """The fit of the state (and of `init_free`) on the initial-state window `head`."""
    if any(n in LOAD_NAMES for n in init_free):
        # A free load amplitude is the scene's: hand the fit the record's loads as the
        # scene's (the record's own columns are refused by `_check_init_free`).
        scene = dataclasses.replace(scene, load=load, torque=torque)
        head = Data(head.ts, head.phi, source=head.source, channels=head.channels,
                    sensors=head.sensors, inputs=head.inputs)
    return fit(scene, head, free=STATE_NAMES + init_free, progress=progress, warn=False)


def _open_loop(model: Scene, load, torque, sensors, ts: np.ndarray, state, predicted):
    """`predicted[name]` at `ts`, open loop from `state` (phi0, dphi0); raises if it fails."""
    traj = model.simulate(ts, phi0=state[0], dphi0=state[1], load=load, torque=torque,
                          outputs=(), throw=False)
    if not bool(traj.ok):
        raise RuntimeError(f"the prediction's solve failed ({traj.result}); check the "
                           "scene's solver settings")
    for sensor in sensors:
        h = output(sensor.name, model.mech, ts, traj.phi, traj.dphi, load, torque)
        predicted[sensor.name][:] = np.asarray(sensor.measure(np.asarray(h)))


def init_free_names(names) -> tuple[str, ...]:
    """`init_free` (a name or names) as a tuple, each a name a fit can free besides the
    state; `ValueError` naming `init_free` (the CLI's `--init-free`) otherwise (the CLI asks this
    before it reads a record)."""
    if isinstance(names, str):
        names = (names,)
    names = tuple(dict.fromkeys(names))
    allowed = [n for n in free_names() if n not in STATE_NAMES]
    for n in names:
        if n in STATE_NAMES:
            raise ValueError(f"`init_free=` names {n}, which is always estimated on the "
                             "initial-state window; leave it out")
        if n not in allowed:
            raise ValueError(f"`init_free=` names {n!r}, which is not a parameter; "
                             f"choose from {', '.join(allowed)}")
    return names


def _check_init_free(names, win: Data) -> tuple[str, ...]:
    """[`init_free_names`][], and for a load amplitude, one the record has no column of."""
    names = init_free_names(names)
    for n in names:
        if n in LOAD_NAMES:
            side = LOAD_NAMES[n][0]
            if (win.load if side == "load" else win.torque) is not None:
                col = "P" if side == "load" else "tau"
                raise ValueError(f"`init_free=` names {n}, but the record "
                                 f"{win.source} supplies its {side} as its {col!r} column; "
                                 f"free it only for a record without that column")
    return names


def _with_values(scene: Scene, load, torque, sensors, own: dict):
    """The prediction's mechanism, loads and sensors, with the `init_free` values `own`."""
    mech = scene.mech
    fields = {n: v for n, v in own.items() if n in FIELDS}
    if fields:
        mech = mech.replace(**fields)
    for n, v in own.items():
        if n in LOAD_NAMES:
            side, role = LOAD_NAMES[n]
            if side == "load":
                load = set_param(load, role, jnp.asarray(v), side)
            else:
                torque = set_param(torque, role, jnp.asarray(v), side)
    sensors = [dataclasses.replace(s, offset=own[f"{s.name}_offset"])
               if f"{s.name}_offset" in own else s for s in sensors]
    return mech, load, torque, sensors


def _scores(y: np.ndarray, yhat: np.ndarray, name: str) -> dict:
    """rms, max |error|, fit % and count of a channel's scored samples (SI; nonzero spread)."""
    e = y - yhat
    fit_pct = 100.0 * (1.0 - float(np.linalg.norm(e)) / float(np.linalg.norm(y - y.mean())))
    return {"rms": float(np.sqrt(np.mean(e**2))), "max_abs": float(np.max(np.abs(e))),
            "fit_percent": fit_pct, "n_samples": int(y.shape[0]), "unit": SI_UNITS[name]}
