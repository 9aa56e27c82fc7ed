"""The physical range of a fit's estimates, read from the records: the scale of a load
that starts at 0, and the estimates that ran off.

A channel that cannot see a direction (a slide position repeats every turn), or a start
on the wrong branch, can lead the optimiser along a flat, physically absurd direction (an
inertia 10^5 times its start) to a point that fits a little better than the start; the
cost is flat there, so a step test alone may pass: such a point is never converged.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..model.params import FIELDS, SCALE_GROUP, SliderCrank
from ..simulation import linearize
from .request import LOAD_NAMES, SIGNED_FIELDS
from .start import half_window, smooth_derivatives

__all__ = ["Ranges", "ranges", "load_scale", "RUNAWAY", "SPEED_RUNAWAY"]

#: An estimate more than this factor from its start (a field that cannot be negative),
#: or a load more than this many times the record's torque scale, ran off.
RUNAWAY = 1e3
#: A record's initial speed estimate more than this many times the fastest speed the
#: record shows ran off (the record tells the speed to a few percent).
SPEED_RUNAWAY = 10.0
#: Fields whose collapse towards 0 (a factor [`RUNAWAY`][] below the start) is the common
#: scale running off: a body's mass or inertia (a damping or a stiffness may be 0).
_BODIES = tuple(n for n in SCALE_GROUP if n not in ("k", "c"))


@dataclasses.dataclass(frozen=True)
class Ranges:
    """What the records say an estimate may be (see [`ran_off`][Ranges.ran_off]).

    `start`: the start value of each global name; `speeds`: each record's fastest speed
    in the data, rad/s; `torque`: the records' torque scale, N*m (the larger of
    [`load_scale`][] and the start inertia times the fastest speed squared; None:
    unknown); `lever`: the crank radius, m (a slider force's arm)."""

    start: dict
    speeds: tuple[float, ...]
    torque: float | None
    lever: float

    def ran_off(self, names, values) -> str | None:
        """The estimates among `names`/`values` (physical units) outside the physical
        range, in words with the reason, or None."""
        out = [w for n, v in zip(names, values) if (w := self._one(n, float(v)))]
        if not out:
            return None
        return ("the estimate ran off to physically absurd values (" + "; ".join(out)
                + "): the channels cannot determine that direction, or the start lies on "
                "another branch of the motion; start nearer, fix a mass or inertia, or "
                "fit a channel that measures the angle")

    def _one(self, name: str, v: float) -> str | None:
        base, _, idx = name.partition("[")
        i = int(idx[:-1]) if idx else 0
        if not math.isfinite(v):
            return f"{name} = {v}"
        s = self.start.get(base)
        if base in FIELDS and base not in SIGNED_FIELDS and s and s > 0:
            if v > RUNAWAY * s or (base in _BODIES and v < s / RUNAWAY):
                return f"{name} = {v:.4g}, {v / s:.3g} times its start {s:.4g}"
        if base == "dphi0" and i < len(self.speeds):
            bound = SPEED_RUNAWAY * self.speeds[i]
            if self.speeds[i] > 0 and abs(v) > bound:
                return (f"{name} = {v:.4g} rad/s, where the record turns at most "
                        f"{self.speeds[i]:.3g} rad/s")
        side = LOAD_NAMES.get(base, (None, None))
        if self.torque and side[1] in ("mean", "amp"):
            scale = self.torque if side[0] == "torque" else self.torque / self.lever
            if abs(v) > RUNAWAY * scale:
                unit = "N*m" if side[0] == "torque" else "N"
                return (f"{name} = {v:.4g} {unit}, {abs(v) / scale:.3g} times what the "
                        f"record's motion needs ({scale:.3g} {unit})")
        return None


def _motion(records, angles, periods) -> list[tuple[float, float]]:
    """Per record: its fastest speed (rad/s) and rms angular acceleration (rad/s^2), from
    one smoothing of its angle (0 for a record too short to smooth)."""
    out = []
    for d, a, p in zip(records, angles, periods):
        if len(d.ts) < 7:
            out.append((0.0, 0.0))
            continue
        ts = np.asarray(d.ts, dtype=float)
        _, dphi, ddphi = smooth_derivatives(ts, np.asarray(a, dtype=float),
                                            half_window(ts, p))
        out.append((float(np.max(np.abs(dphi))), float(np.sqrt(np.mean(ddphi**2)))))
    return out


def _scale(mu: float, motion) -> float | None:
    scale = mu * max((acc for _, acc in motion), default=0.0)
    return scale if math.isfinite(scale) and scale > 0 else None


def load_scale(mech: SliderCrank, records, angles, periods) -> float | None:
    """The records' torque scale, N*m: the start model's inertia at rest times the rms
    angular acceleration the records show (a coast-down's drag, an oscillation's spring
    torque), or None where neither is finite and positive. A load that starts at 0
    takes it for its unit (a slider force that divided by the crank radius), so that the
    optimiser's first steps are of the size the data need: at 10^-3 N*m, a drag torque of
    0.6 N*m was a column so small that the fit held it fixed as a flat direction."""
    return _scale(float(np.asarray(linearize(mech).mu)), _motion(records, angles, periods))


def ranges(mech: SliderCrank, records, angles, periods, start: dict) -> Ranges:
    """The [`Ranges`][] of a fit's records (their `angles` as the channels tell them,
    rad, and `periods`, s or None) at the start mechanism `mech` and start values."""
    motion = _motion(records, angles, periods)  # one smoothing a record serves both
    speeds = tuple(v for v, _ in motion)
    # A load's range: what the records' accelerations need, or a torque that would change
    # the fastest speed by its own size within a radian (a steady rotation's drive balances
    # a drag the accelerations do not show).
    mu = float(np.asarray(linearize(mech).mu))
    torque = max(_scale(mu, motion) or 0.0, mu * max(speeds, default=0.0) ** 2)
    ok = math.isfinite(torque) and torque > 0
    return Ranges(dict(start), speeds, torque if ok else None, float(mech.r))
