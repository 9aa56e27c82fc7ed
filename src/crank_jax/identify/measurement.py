"""The measurement side of the fit's residuals: each channel's model reading
`scale * h(x) + offset` against its data (DESIGN.md section 4: nothing in the solver
knows about sensors; a channel's Jacobian is `dh/dx dx/dtheta` by forward mode through
[`output`][crank_jax.model.outputs.output])."""

from __future__ import annotations

from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from ..model.outputs import output
from ..records.sensors import Sensor
from ..runtime.arrays import device_array

__all__ = ["calibration", "channel_weights", "channel_errors", "fitted_channels"]


def channel_weights(names: Sequence[str], sigmas, first_sigma: float) -> list[float]:
    """Each channel's residual weight: the first channel's level `first_sigma` over its
    own (`sigmas`, name -> SI level; a channel it lacks, or None, weighs 1), so every
    channel counts by its noise in the first channel's unit."""
    return [first_sigma / (sigmas or {}).get(n, first_sigma) for n in names]


def calibration(sensors: Sequence[Sensor], sigmas, first_sigma: float, mech,
                omega: float):
    """(scale, offset, weight, per_radian, channel names) of an `Experiment`: `per_radian`
    is the first channel's typical reading change per radian of crank (1 for an angle;
    `|scale| r` for the slider's position, times `omega` (rad/s) per time derivative)."""
    weight = channel_weights([s.name for s in sensors], sigmas, first_sigma)
    first = sensors[0]
    r = float(mech.r)
    per = {"phi": 1.0, "dphi": omega, "x_s": r, "v_s": r * omega, "a_s": r * omega**2}
    return (device_array([float(s.scale) for s in sensors]),
            device_array([float(s.offset) for s in sensors]), device_array(weight, float),
            device_array(abs(float(first.scale)) * per[first.name], float),
            tuple(s.name for s in sensors))


def channel_errors(mech, e, load, torque, phi, dphi, offsets, structure, force=None):
    """(C, S, m) model reading minus data for each channel, SI (unweighted)."""
    out = []
    for c, name in enumerate(e.channels):
        h = output(name, mech, e.seg.ts, phi, dphi, load, torque, structure, force)
        out.append(e.scale[c] * h + offsets.get(name, e.offset[c]) - e.seg.ys[c])
    return jnp.stack(out)


def fitted_channels(problem, r) -> list[dict[str, np.ndarray]]:
    """What each channel's sensor reads under the model (`scale h + offset`, SI) at
    each record's samples, from single-shooting residuals `r` (weighted
    model - data): per record, channel name -> (n,)."""
    out, k = [], 0
    r = np.asarray(r)
    for e in problem.exps:
        size = int(np.prod(e.seg.ts.shape))
        w = np.asarray(e.weight)
        ys = np.asarray(e.seg.ys)  # sliced on the host: no compiled slice per shape
        out.append({name: ys[c, 0, :e.n]
                    + r[k + c * size:k + c * size + e.n] / w[c]
                    for c, name in enumerate(e.channels)})
        k += size * len(e.channels)
    return out
