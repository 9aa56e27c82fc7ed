"""What a fit request's channels tell before any fit: each record's crank angle and each
channel's noise level, resolved once when the request is made
([`normalize`][crank_jax.identify.request.normalize]).

A channel's level is given (`fit(sigma=)`: a dict, channel -> SI level, or a number for
the first channel) or estimated from its record alone (`start.channel_level`, the largest
over the records); the fit's residuals are in the first channel's unit.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..records.data import Data
from ..scene import Scene
from .angle import angle_estimate
from .start import channel_level

__all__ = ["channel_names", "check_sigma_names", "given_levels", "channel_angles",
           "channel_sigmas", "direction"]


def channel_names(records: Sequence[Data]) -> tuple[str, ...]:
    """Every channel of `records`, each once, in the order they first appear."""
    return tuple(dict.fromkeys(s.name for d in records for s, _ in d.outputs()))


def check_sigma_names(sigma, records: Sequence[Data]) -> None:
    """`ValueError` naming the channel when `sigma` (a dict) names one no record has."""
    if not isinstance(sigma, dict):
        return
    have = channel_names(records)
    bad = [k for k in sigma if k not in have]
    if bad:
        raise ValueError(f"sigma names channel {bad[0]!r}, which no record has; the channels "
                         f"are {sorted(have)}")


def given_levels(sigma, first: str) -> dict[str, float]:
    """The levels `sigma` gives (SI): a dict's, or a number's for the `first` channel."""
    if isinstance(sigma, dict):
        return dict(sigma)
    return {} if sigma is None else {first: float(sigma)}


def direction(state) -> float:
    """The sense the crank turns in from a record's `(phi0, dphi0)`: -1 or 1."""
    return -1.0 if state[1] < 0 else 1.0


def channel_angles(scene: Scene, records: Sequence[Data], states, loads
                   ) -> tuple[np.ndarray, ...]:
    """Each record's crank angle (n,), rad, as its channels tell it (`angle.py`); for a
    record with only slider speed or acceleration, `scene`'s motion simulated over it
    (from the record's `states` `(phi0, dphi0)` under its `loads` `(load, torque)`)."""
    out = []
    for d, st, (load, torque) in zip(records, states, loads):
        est = angle_estimate(d, scene.mech, direction(st), st[0])
        if est is None:
            ts = d.ts if d.ts[0] == 0.0 else np.concatenate([[0.0], d.ts])
            traj = scene.simulate(ts, phi0=st[0], dphi0=st[1], load=load, torque=torque,
                                  throw=False)
            est = np.asarray(traj.phi)[-d.n:]
        out.append(np.asarray(est, dtype=float))
    return tuple(out)


def channel_sigmas(records: Sequence[Data], given: dict[str, float]) -> dict[str, float]:
    """Each channel's noise level, SI: `given`'s, else estimated from the records alone
    (`channel_level`, the largest over the records)."""
    out: dict[str, float] = {}
    for d in records:
        for s, y in d.outputs():
            out[s.name] = max(out.get(s.name, 0.0), channel_level(d.ts, y))
    out.update(given)
    return out
