"""The initial-state window of a validation: how many seconds at a record's start its
state `(phi0, dphi0)` is estimated from.

By default the window is the record's own time scale, judged from the record:

- a crank that turns at least one full revolution over the record: **one revolution**
  at the record's mean speed (the angle its channels tell, see
  [`angle_estimate`][crank_jax.identify.angle.angle_estimate]), whatever that speed,
  and at least [`STATE_SAMPLES`][] samples;
- otherwise about one linearised period of the scene ([`default_init_window`][]), or
  1 s where phi = 0 is not a stable equilibrium;

and never more than half the record (the rest is what is scored), nor fewer than
[`MIN_SAMPLES`][crank_jax.records.data.MIN_SAMPLES] samples.
"""

from __future__ import annotations

import math

import numpy as np

from ..identify.angle import angle_estimate
from ..model.loads import AbstractLoad
from ..records.data import MIN_SAMPLES, Data
from ..scene import Scene
from ..simulation import linearize

__all__ = ["default_init_window", "record_init_window", "init_window", "STATE_SAMPLES"]

#: The fewest samples a default initial-state window takes (where the record has them):
#: a fit tells a short record's motion from its noise only well above it (the refusal of
#: a record with no motion, `strategy.no_motion`, takes pure noise to reach a variance
#: ratio of 1e4 at 20 samples, 212 at 30), and one revolution of a fast crank sampled at
#: 50 Hz is 14 samples.
STATE_SAMPLES = 30


def default_init_window(scene: Scene, load: AbstractLoad | None = None) -> float:
    """About one period: the linearised period `2 pi / omega_n` of the scene (with `load`
    at its mean), or 1 s when phi = 0 is not a stable equilibrium."""
    w = float(np.asarray(linearize(scene.mech, load if load is not None else scene.load)
                         .omega_n))
    return 2 * math.pi / w if math.isfinite(w) and w > 0 else 1.0


def record_init_window(scene: Scene, win: Data, load: AbstractLoad | None = None) -> float:
    """The default initial-state window of the record `win`, s (see the module's
    docstring): one revolution of a crank that turns (at least [`STATE_SAMPLES`][]
    samples), else about one period; then at most half the record; and at least
    [`MIN_SAMPLES`][crank_jax.records.data.MIN_SAMPLES] samples."""
    ts = np.asarray(win.ts, dtype=float)
    angle = angle_estimate(win, scene.mech, phi_start=float(scene.phi0))
    turned = (abs(float(angle[-1] - angle[0]))
              if angle is not None and np.all(np.isfinite(angle[[0, -1]])) else 0.0)
    span = float(ts[-1] - ts[0])
    if turned >= 2 * math.pi:
        # The mean time per revolution: the record's speed, not the scene's.
        s = max(2 * math.pi * span / turned, float(ts[min(STATE_SAMPLES, win.n) - 1] - ts[0]))
    else:
        s = default_init_window(scene, load)
    # Half the record at most: a window as long as the record would leave nothing to
    # score (a free-running rig has no period, and its 1 s can exceed a short record).
    s = min(s, 0.5 * span)
    return max(s, float(ts[min(MIN_SAMPLES, win.n) - 1] - ts[0]))


def init_window(scene: Scene, win: Data, load, init_window: float | None) -> float:
    """The initial-state window's length, s: `init_window`, or
    [`record_init_window`][] when None. `ValueError` naming `init_window`
    (the CLI's `--init-window`) where it takes or leaves fewer than
    [`MIN_SAMPLES`][crank_jax.records.data.MIN_SAMPLES] samples."""
    if init_window is None:
        init_window = record_init_window(scene, win, load)
    elif not (math.isfinite(init_window) and init_window > 0):
        raise ValueError(f"`init_window=` must be a time > 0 s, got {init_window}")
    t_init = float(win.ts[0]) + float(init_window)
    n_init = int(np.sum(win.ts <= t_init))
    n_scored = int(np.sum(win.ts > t_init))
    if n_init < MIN_SAMPLES or n_scored < MIN_SAMPLES:
        raise ValueError(f"`init_window=` {init_window:g} s takes {n_init} of the window's "
                         f"{win.n} samples and leaves {n_scored} to score; both need at "
                         f"least {MIN_SAMPLES}: change the window or `init_window=`")
    return float(init_window)
