"""What [`track`][crank_jax.online.tracking.track] returns: the parameters' paths with
their standard errors, the alarms, and the settings, as `track.json` holds them."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..model.params import UNITS

__all__ = ["TrackResult"]


@dataclasses.dataclass(frozen=True)
class TrackResult:
    """A tracked record.

    `t` (n,), s; `values`, `stderr`: {name: (n,)} in the parameter's unit (a log
    coordinate's standard error taken to first order, `value * se(ln value)`); `phi`,
    `dphi` (n,): the filtered state, rad and rad/s; `innovations` (n, C): the normalised
    innovations (white, unit variance when the model and its noise levels are right);
    `statistic` (n,): the change test's CUSUM; `alarms`: see
    [`name_alarms`][crank_jax.online.alarms.name_alarms]; `settings`: the filter, its noise
    levels and the change test; `source`: the record."""

    t: np.ndarray
    values: dict
    stderr: dict
    phi: np.ndarray
    dphi: np.ndarray
    innovations: np.ndarray
    statistic: np.ndarray
    alarms: list
    settings: dict
    source: str = ""

    @classmethod
    def build(cls, t, steps, free, log, alarms, settings, source="") -> TrackResult:
        """From the filter's kept [`Steps`][crank_jax.online.ekf.Steps] (coordinates)."""
        z, sz = steps.x[:, 2:], steps.se[:, 2:]
        values, stderr = {}, {}
        for j, (n, lg) in enumerate(zip(free, log)):
            values[n] = np.exp(z[:, j]) if lg else z[:, j].copy()
            stderr[n] = values[n] * sz[:, j] if lg else sz[:, j].copy()
        return cls(np.asarray(t), values, stderr, steps.x[:, 0], steps.x[:, 1],
                   steps.innovation, steps.g, list(alarms), dict(settings), source)

    def band(self, name: str, level: float = 1.96) -> tuple[np.ndarray, np.ndarray]:
        """The `level`-sigma band of `name` (n,) each: on the log scale for a field in log
        coordinates (positive, as the value), else symmetric."""
        v, s = self.values[name], self.stderr[name]
        if self.settings.get("log", {}).get(name):
            f = np.exp(level * s / np.where(v > 0, v, 1.0))
            return v / f, v * f
        return v - level * s, v + level * s

    def to_json(self) -> dict:
        """The `track.json` document (lists; non-finite numbers as null)."""
        def num(a):
            return [float(x) if math.isfinite(x) else None for x in np.asarray(a, float)]

        return {"source": self.source, "t": num(self.t),
                "values": {n: num(v) for n, v in self.values.items()},
                "stderr": {n: num(v) for n, v in self.stderr.items()},
                "units": {n: UNITS[n] for n in self.values},
                "alarms": self.alarms, "settings": self.settings}

    def summary(self) -> str:
        """The final estimates and the alarms, in words."""
        lines = [f"tracked {self.t.size} samples of {self.source} ({self.t[0]:g} to "
                 f"{self.t[-1]:g} s); start: {self.settings.get('start', '')}"]
        for n, v in self.values.items():
            lines.append(f"{n:>8} at the end {v[-1]:.6g} +- {1.96 * self.stderr[n][-1]:.3g} "
                         f"{UNITS[n]} (95%)")
        if not self.alarms:
            lines.append("no change alarm (false-alarm rate "
                         f"{self.settings.get('false_alarm_rate_per_hour')} per hour)")
        for a in self.alarms:
            moved = ", ".join(f"{n} {a['before'][n]:.5g} -> {a['after'][n]:.5g}"
                              for n in a["parameters"])
            lines.append(f"ALARM at {a['t']:.3f} s (change from {a['t_change']:.3f} s): "
                         f"{moved} (statistic {a['statistic']:.3g})")
        return "\n".join(lines)
