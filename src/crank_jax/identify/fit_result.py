"""The outcome of a fit: [`FitResult`][] (with its JSON document and summary table),
[`Profile`][], and the warning classes."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..model.params import SliderCrank
from ..records.data import Data
from ..stats.diagnostics import Diagnostics
from .outcome import finite as num

__all__ = ["FitResult", "Profile", "IdentifiabilityWarning", "ConvergenceWarning"]


class IdentifiabilityWarning(UserWarning):
    """The data cannot determine some free parameters (see `FitResult.warnings`)."""


class ConvergenceWarning(UserWarning):
    """A fit stopped without converging (see `FitResult.warnings`)."""


class Profile(NamedTuple):
    """Profile likelihood of one parameter: every other free parameter re-fitted.

    `values` (k,): the pinned values; `deviance` (k,): `n ln(RSS / RSS_min)`, which is
    asymptotically chi-squared with one degree of freedom; `ci95`: the interval where the
    deviance stays below 3.84 (an end is `None` when the grid does not reach the crossing).
    """

    name: str
    values: np.ndarray
    deviance: np.ndarray
    ci95: tuple[float | None, float | None]


class FitResult(NamedTuple):
    """The outcome of [`fit`][]. Every dict is keyed by the reported parameter names
    (`names`: the free names, with `phi0[i]`, `dphi0[i]` per record when there are several).

    `stderr`/`ci95` are `None` where they are undefined: for parameters in an
    unidentifiable direction, and for every parameter when the fit did not converge.
    """

    names: tuple[str, ...]
    values: dict[str, float]
    start: dict[str, float]
    stderr: dict[str, float | None]
    ci95: dict[str, tuple[float, float] | None]
    correlation: np.ndarray
    """(p, p), NaN where undefined."""
    condition_number: float
    """Of the sensitivity matrix with columns scaled by the parameter values."""
    singular_values: np.ndarray
    identifiable: bool | None
    """None when the fit did not converge: identifiability is judged at an estimate."""
    unidentifiable_directions: list[str]
    rms_residual: float
    """Root-mean-square residual, rad (the estimate of the noise level)."""
    n_samples: int
    converged: bool
    iterations: int
    seconds: float
    warnings: list[str]
    message: str
    method: str
    shooting: str
    mech: SliderCrank
    """The mechanism with the fitted values."""
    data: list[Data]
    fitted: list[np.ndarray]
    """Model angle at each record's sample times, rad."""
    profile: Profile | None
    strategy: str = ""
    """What won: the shooting used and, if the first attempt stalled, the escalation."""
    diagnostics: Diagnostics | None = None
    """Whiteness of the residuals at a converged estimate (Ljung-Box p-value, lag-1
    autocorrelation, effective samples); when they are not white the standard errors
    and intervals above already account for the correlation."""
    channels: dict | None = None
    """Per channel (the first is the one `rms_residual` is in): `rms` of its residuals,
    `sigma` the noise level its residuals were weighted by (given, or estimated from
    them), `n_samples`, `ljung_box_p` (None unless converged), `unit` (its SI unit)."""
    fitted_channels: list | None = None
    """Per record, channel name -> what its sensor reads under the fitted model (n,), SI."""
    termination: dict | None = None
    """How the reported optimisation ended, judged in the data's units: `verdict`
    (`"converged"` at a stationary point; `"stalled"`, the cost stopped falling while the
    linearisation predicts more, along `direction`, a ridge or a curved valley;
    `"budget"`; `"ran off"` the physical range; `"failed"`; or `"refused"`), `words` (the
    same in a sentence), `predicted_decrease` (the cost decrease the Gauss-Newton step
    predicts, in noise-level units `sigma^2`), `largest_step` (its largest move of a
    coordinate, in standard errors), `falling_per_iteration` (the cost's fall per
    iteration over the last 8, `sigma^2`) and `noise` (sigma, the first channel's
    unit)."""

    def to_json(self) -> dict:
        """The `fit.json` document (exactly the documented top-level keys)."""
        est = {}
        for i, n in enumerate(self.names):
            ci = self.ci95[n]
            est[n] = {
                "value": num(self.values[n]),
                "stderr": num(self.stderr[n]),
                "ci95": [num(ci[0]), num(ci[1])] if ci is not None else None,
                "start": num(self.start[n]),
                "correlation": {m: num(float(self.correlation[i, j]))
                                for j, m in enumerate(self.names)},
            }
            if self.profile is not None and self.profile.name == n:
                est[n]["profile"] = {
                    "values": [float(v) for v in self.profile.values],
                    "deviance": [num(float(d)) for d in self.profile.deviance],
                    "ci95": [num(c) for c in self.profile.ci95],
                }
        return {
            "estimates": est,
            "identifiable": (None if self.identifiable is None
                             else bool(self.identifiable)),
            "unidentifiable_directions": list(self.unidentifiable_directions),
            "rms_residual": num(self.rms_residual),
            "n_samples": int(self.n_samples),
            "converged": bool(self.converged),
            "iterations": int(self.iterations),
            "seconds": float(self.seconds),
            "warnings": list(self.warnings),
            "diagnostics": (None if self.diagnostics is None
                            else self.diagnostics.to_json()),
            "channels": {n: {"rms": num(c["rms"]), "sigma": num(c["sigma"]),
                             "n_samples": int(c["n_samples"]),
                             "ljung_box_p": num(c["ljung_box_p"])}
                         for n, c in (self.channels or {}).items()},
            "termination": (None if self.termination is None else dict(self.termination)),
            "predictions": self.predictions(),
        }

    def predictions(self) -> list[dict]:
        """Per record (each window fitted), its samples' times, measurements and the
        fitted model's predictions per channel, SI (see
        [`prediction_table`][crank_jax.identify.predictions.prediction_table]), with the
        record's `source`."""
        from .predictions import prediction_table

        fitted = self.fitted_channels or [None] * len(self.data)
        return [{"source": d.source, **prediction_table(d.ts, dict(d.outputs_items()), f)}
                for d, f in zip(self.data, fitted)]

    def fitted_scene(self, scene, record: int = 0, sensors=None, *, anyway: bool = False):
        """`scene` (the scene the fit started from) with this fit's estimates: see
        [`fitted_scene`][crank_jax.identify.fitted.fitted_scene] (a fit that did not
        converge is refused unless `anyway`)."""
        from .fitted import fitted_scene

        return fitted_scene(scene, self, record, sensors, anyway=anyway)

    def report(self, path, *, scene=None, command=None, title: str = "") -> None:
        """Write a self-contained HTML report to `path` (see
        [`write_fit_report`][crank_jax.report.write_fit_report]); `scene`: the fit's."""
        from ..report import write_fit_report

        write_fit_report(self, path, scene=scene, command=command, title=title)

    def summary(self) -> str:
        """A human-readable table of the estimates with their 95% intervals."""
        lines = [f"{'parameter':<10} {'start':>12} {'estimate':>12} {'stderr':>11} "
                 f"{'95% CI':>27}"]
        for n in self.names:
            se, ci = self.stderr[n], self.ci95[n]
            se_s = f"{se:11.4g}" if se is not None else f"{'-':>11}"
            ci_s = (f"[{ci[0]:.6g}, {ci[1]:.6g}]" if ci is not None else "not determined")
            lines.append(f"{n:<10} {self.start[n]:12.6g} {self.values[n]:12.6g} {se_s} "
                         f"{ci_s:>27}")
        state = "converged" if self.converged else f"NOT converged ({self.message})"
        lines.append(f"{state} after {self.iterations} iterations in {self.seconds:.1f} s "
                     f"({self.method}, {self.strategy or self.shooting + ' shooting'}); rms "
                     "residual "
                     f"{self.rms_residual:.3g} rad over {self.n_samples} samples; condition "
                     f"number {self.condition_number:.3g}")
        words = (self.termination or {}).get("words")
        if words:
            lines.append(f"termination: {words}")
        lines.append("identifiable: " + ("not judged (the fit did not converge)"
                                         if self.identifiable is None
                                         else "yes" if self.identifiable else "NO"))
        unit = next(iter((self.channels or {}).values()), {}).get("unit", "rad")
        if unit != "rad":  # the overall rms is in the first channel's unit
            lines = [ln.replace(" rad over ", f" {unit} over ") if "rms residual" in ln
                     else ln for ln in lines]
        for n, c in (self.channels or {}).items() if len(self.channels or {}) > 1 else ():
            lb = c["ljung_box_p"]
            lines.append(f"channel {n}: rms {c['rms']:.3g} {c['unit']} (noise level "
                         f"{c['sigma']:.3g} {c['unit']}) over {c['n_samples']} samples"
                         + (f", Ljung-Box p = {lb:.3g}" if lb is not None else ""))
        d = self.diagnostics
        if d is not None:
            lines.append(f"residuals: {'white' if d.white else 'NOT white'} (Ljung-Box p = "
                         f"{d.ljung_box_p:.3g}, lag-1 autocorrelation "
                         f"{d.lag1_autocorrelation:.3f}, {d.effective_samples:.0f} effective "
                         f"of {d.n_samples} samples)")
        return "\n".join(lines)


def wrap_angle(x: float) -> float:
    """`x` (rad) moved by whole turns into (-pi, pi]."""
    return math.pi - (math.pi - x) % (2 * math.pi)


def with_wrapped_angles(res: FitResult) -> FitResult:
    """`res` with each fitted `gravity_angle` (`gravity_angle[i]` per record) moved by
    whole turns into (-pi, pi], its interval by the same turns (gravity acts along
    `(-cos g, -sin g)`: the fit's linear coordinate may end a turn or more away)."""
    names = [n for n in res.names if n == "gravity_angle" or n.startswith("gravity_angle[")]
    if not names:
        return res
    values, ci = dict(res.values), dict(res.ci95)
    for n in names:
        shift = wrap_angle(values[n]) - values[n]
        values[n] += shift
        if ci.get(n) is not None:
            ci[n] = (ci[n][0] + shift, ci[n][1] + shift)
    mech = res.mech.replace(gravity_angle=wrap_angle(float(res.mech.gravity_angle)))
    return res._replace(values=values, ci95=ci, mech=mech)
