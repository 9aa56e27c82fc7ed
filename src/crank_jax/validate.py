"""Validation on a record the model was not fitted to: predict it open-loop and score it.

[`validate`][] estimates only the initial state `(phi0, dphi0)` from the first
`init_window` seconds of the record (a fit with every mechanism parameter fixed), then
simulates the whole window open-loop from that state, with the record's own load columns
when it has them, and scores the prediction on the samples after the initial-state window
(those were not used at all):

- `rms = sqrt(mean((y - yhat)^2))` and `max_abs = max |y - yhat|`, rad;
- `fit_percent = 100 (1 - |y - yhat| / |y - mean(y)|)` with 2-norms (MATLAB's `compare`):
  100 is a perfect prediction, 0 is no better than the record's mean, and it can be
  negative.

A record with several channels (see [`sensors`][crank_jax.sensors]) is predicted and
scored in each (what its sensor reads under the model, `scale h + offset`, SI); the
top-level scores are the first channel's.
"""

from __future__ import annotations

import math
import os
from typing import NamedTuple

import numpy as np

from .data import MIN_SAMPLES, Data, DataError
from .identify.fit import fit
from .model.linear import linearize
from .model.loads import AbstractLoad, InputLoad, NoLoad
from .model.outputs import SI_UNITS, output
from .model.sampled import bind_input
from .scene import Scene

__all__ = ["validate", "Validation", "default_init_window", "plot_validation", "MIN_SPREAD_EPS"]


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
        }

    def report(self, path, *, scene=None, command=None, title: str = "") -> None:
        """Write a self-contained HTML report to `path` (see
        [`write_validation_report`][crank_jax.report.write_validation_report])."""
        from .report import write_validation_report

        write_validation_report(self, path, scene=scene, command=command, title=title)

    def summary(self) -> str:
        """One paragraph for the terminal."""
        chans = self.channels or {"phi": {"unit": "rad"}}
        unit = next(iter(chans.values()))["unit"]
        text = (f"validation on {self.source} over [{self.ts[0]:g}, {self.ts[-1]:g}] s: "
                f"initial state phi0 = {self.phi0:.6g} rad, dphi0 = {self.dphi0:.6g} rad/s "
                f"from the first {self.init_window:g} s; predicted {self.n_samples} samples "
                f"open-loop: rms {self.rms:.4g} {unit}, max |error| {self.max_abs:.4g} "
                f"{unit}, fit {self.fit_percent:.2f}%")
        for n, c in chans.items() if len(chans) > 1 else ():
            text += (f"\nchannel {n}: rms {c['rms']:.4g} {c['unit']}, max |error| "
                     f"{c['max_abs']:.4g} {c['unit']}, fit {c['fit_percent']:.2f}%")
        return text


def default_init_window(scene: Scene, load: AbstractLoad | None = None) -> float:
    """About one period: the linearised period `2 pi / omega_n` of the scene (with `load`
    at its mean), or 1 s when phi = 0 is not a stable equilibrium."""
    w = float(np.asarray(linearize(scene.mech, load if load is not None else scene.load)
                         .omega_n))
    return 2 * math.pi / w if math.isfinite(w) and w > 0 else 1.0


def _loads(scene: Scene, data: Data, scene_loads: bool) -> tuple[AbstractLoad, AbstractLoad]:
    """The record's own loads, else (with `scene_loads`, or when the scene has none) the
    scene's; raise naming the missing column otherwise."""
    out = []
    for own, model, col, what in ((data.load, scene.load, "P", "slider force P"),
                                  (data.torque, scene.torque, "tau", "crank torque tau")):
        if own is not None:
            out.append(own)
        elif isinstance(model, InputLoad):
            out.append(bind_input(model, data.inputs, data.source, what))
        elif isinstance(model, NoLoad) or scene_loads:
            out.append(model)
        else:
            raise DataError(f"{data.source}: the record has no {col!r} column, but the scene "
                            f"has a {what} ({type(model).__name__}); add the column with the "
                            "load measured during this record, or use the scene's load "
                            "(scene_loads=True, --scene-loads)")
    return out[0], out[1]


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
            f"{spread:.3g} "
            f"{SI_UNITS[name]}, float rounding "
            "at most), so fit_percent is undefined: validate on a record in which the crank "
            "moves after the initial-state window")


def validate(
    scene: Scene,
    data: Data,
    *,
    t_start: float | None = None,
    t_end: float | None = None,
    init_window: float | None = None,
    scene_loads: bool = False,
    progress: bool = False,
) -> Validation:
    """Predict a record open-loop from an initial state estimated on its start, and score it.

    **Arguments:**

    - `scene`: the (fitted) [`Scene`][]: its mechanism, solver settings and, where the
      record has no load columns, its loads.
    - `data`: the validation record, a [`Data`][].
    - `t_start`, `t_end`: the window of the record to use, s (`None`: its own ends).
    - `init_window`: length of the initial-state window at the start, s (default: about
      one period, [`default_init_window`][]; at least [`MIN_SAMPLES`][] samples).
    - `scene_loads`: use the scene's loads where the record has no `P`/`tau` column
      (default: a record must carry the loads the scene has).
    - `progress`: show the initial-state fit's progress bar.

    **Returns:** a [`Validation`][]. Raises `ValueError` (naming the argument) for a
    window with fewer than [`MIN_SAMPLES`][] samples, an initial-state window that leaves
    fewer than that many to score, a missing load column, or scored angles that are
    constant up to float rounding ([`MIN_SPREAD_EPS`][]; `fit_percent` would be
    meaningless); `RuntimeError` if the prediction's solve fails.
    """
    if not isinstance(scene, Scene) or not isinstance(data, Data):
        raise TypeError("validate(scene, data): expected a Scene and a Data record")
    win = data.window(t_start, t_end)
    load, torque = _loads(scene, win, scene_loads)
    win = Data(win.ts, win.phi, load, torque, source=win.source, channels=win.channels,
               sensors=win.sensors, inputs=win.inputs)
    if init_window is None:
        s = default_init_window(scene, load)
        init_window = max(s, float(win.ts[min(MIN_SAMPLES, win.n) - 1] - win.ts[0]))
    elif not (math.isfinite(init_window) and init_window > 0):
        raise ValueError(f"init_window (--init-window) must be a time > 0 s, got {init_window}")
    t_init = float(win.ts[0]) + float(init_window)
    n_init = int(np.sum(win.ts <= t_init))
    scored = win.ts > t_init
    if n_init < MIN_SAMPLES or int(scored.sum()) < MIN_SAMPLES:
        raise ValueError(f"init_window (--init-window) = {init_window:g} s takes {n_init} of "
                         f"the window's {win.n} samples and leaves {int(scored.sum())} to "
                         f"score; both need at least {MIN_SAMPLES}: change the window or "
                         "--init-window")
    for sensor, y in win.outputs():
        _check_spread(np.asarray(y)[scored], win, t_init, sensor.name)
    warnings: list[str] = []
    res = fit(scene, win.window(None, t_init), free=("phi0", "dphi0"), progress=progress,
              warn=False)
    if not res.converged:
        warnings.append(f"the initial-state fit did not converge ({res.message}); the "
                        "prediction starts from its last iterate")
    phi0, dphi0 = res.values["phi0"], res.values["dphi0"]
    traj = scene.simulate(np.asarray(win.ts), phi0=phi0, dphi0=dphi0, load=load,
                          torque=torque, outputs=(), throw=False)
    if not bool(traj.ok):
        raise RuntimeError(f"the prediction's solve failed ({traj.result}); check the scene's "
                           "solver settings")
    predicted, scores = {}, {}
    for sensor, y in win.outputs():
        h = output(sensor.name, scene.mech, np.asarray(win.ts), traj.phi, traj.dphi, load,
                   torque)
        predicted[sensor.name] = np.asarray(sensor.measure(np.asarray(h)))
        scores[sensor.name] = _scores(y[scored], predicted[sensor.name][scored], sensor.name)
    (first, y0), = win.outputs()[:1]
    top = scores[first.name]
    return Validation(
        rms=top["rms"], max_abs=top["max_abs"], fit_percent=top["fit_percent"],
        n_samples=int(scored.sum()), phi0=float(phi0), dphi0=float(dphi0),
        ts=np.asarray(win.ts), phi=np.asarray(y0), predicted=predicted[first.name],
        scored=scored, init_window=float(init_window), source=win.source, warnings=warnings,
        channels=scores, predicted_channels=predicted, data_channels=dict(win.outputs_items()))


def _scores(y: np.ndarray, yhat: np.ndarray, name: str) -> dict:
    """rms, max |error|, fit percent and count of one channel's scored samples (SI). The
    data spread: `_check_spread` refused a constant channel before the fit."""
    e = y - yhat
    fit_pct = 100.0 * (1.0 - float(np.linalg.norm(e)) / float(np.linalg.norm(y - y.mean())))
    return {"rms": float(np.sqrt(np.mean(e**2))), "max_abs": float(np.max(np.abs(e))),
            "fit_percent": fit_pct, "n_samples": int(y.shape[0]), "unit": SI_UNITS[name]}


def plot_validation(val: Validation, path: str | os.PathLike, title: str = "") -> None:
    """Draw, for each channel, data and prediction and below them the error; the
    initial-state window is shaded."""
    from .io import printable
    from .plot import pyplot, save_figure

    plt = pyplot()
    chans = val.channels or {"phi": {"unit": "rad"}}
    preds = val.predicted_channels or {"phi": val.predicted}
    data = val.data_channels or {"phi": val.phi}
    fig, axes = plt.subplots(2 * len(chans), 1, figsize=(9, 1 + 5 * len(chans)), sharex=True,
                             gridspec_kw={"height_ratios": [2, 1] * len(chans)})
    t0 = float(val.ts[0])
    for ax in axes:
        ax.axvspan(t0, t0 + val.init_window, color="0.9", zorder=0)
        ax.grid(alpha=0.3)
    for c, (name, info) in enumerate(chans.items()):
        ax1, ax2 = axes[2 * c], axes[2 * c + 1]
        y = data[name]
        ax1.plot(val.ts, y, ".", ms=2, color="C0", label="data")
        ax1.plot(val.ts, preds[name], "-", lw=1, color="C1", label="prediction (open loop)")
        ax1.set_ylabel(f"{name} [{info['unit']}]")
        ax1.legend(loc="upper right", fontsize=8)
        ax2.plot(val.ts, y - preds[name], "-", lw=0.8, color="C3")
        ax2.set_ylabel(f"data - prediction [{info['unit']}]")
    axes[-1].set_xlabel("t [s] (shaded: initial-state window)")
    unit = next(iter(chans.values()))["unit"]
    head = printable(title) + "\n" if title else ""  # a file name that is not UTF-8
    axes[0].set_title(head + f"fit {val.fit_percent:.2f}%, rms "
                      f"{val.rms:.3g} {unit}, max |error| {val.max_abs:.3g} {unit} over "
                      f"{val.n_samples} samples", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)
