"""The table of sweep reductions: what a [`sweep`][] can compute from each trajectory.

Each reduction is one number per sample, except `"phi"` and `"dphi"`, which keep the whole
(n_t,) trajectory. Only the requested ones are compiled and leave the device.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array

from ..model.dynamics import energy

__all__ = ["REDUCTIONS", "DEFAULT_OUTPUTS", "TRAJECTORY_OUTPUTS", "reduce",
           "settling_time", "dominant_freq"]

#: Reductions a sweep can compute, name -> description (units).
REDUCTIONS: dict[str, str] = {
    "peak_phi": "max |phi| over the saved times, rad",
    "peak_dphi": "max |dphi|, rad/s",
    "final_phi": "phi at t1, rad",
    "final_dphi": "dphi at t1, rad/s",
    "final_energy": "mechanical energy T + V at t1, J",
    "peak_O": "max |O|, the crank-bearing reaction force, N",
    "dominant_freq": "frequency of the largest peak of |FFT(phi - mean)|, Hz",
    "settling_time": "last time |phi - phi(t1)| exceeds 2% of its maximum, s",
    "phi": "the whole crank angle trajectory, rad (n_t values per sample)",
    "dphi": "the whole crank rate trajectory, rad/s (n_t values per sample)",
}
DEFAULT_OUTPUTS = ("peak_phi", "peak_dphi", "final_energy")
#: Reductions that store (n_t,) values per sample.
TRAJECTORY_OUTPUTS = ("phi", "dphi")


def settling_time(ts: Array, phi: Array) -> Array:
    """The save time after the last one where `|phi - phi[-1]|` exceeds 2% of its
    maximum, s (`ts[0]` if it never does). **Arguments:** `ts`, `phi`: (n_t,)."""
    dev = jnp.abs(phi - phi[-1])
    outside = dev > 0.02 * jnp.max(dev)
    last = jnp.max(jnp.where(outside, jnp.arange(ts.shape[0]), -1))
    return jnp.where(last < 0, ts[0], ts[jnp.minimum(last + 1, ts.shape[0] - 1)])


def dominant_freq(ts: Array, phi: Array) -> Array:
    """The frequency of the largest peak of `|FFT(phi - mean)|`, Hz, refined between bins.
    **Arguments:** `ts` (n_t,) uniform save times, s; `phi` (n_t,)."""
    n = ts.shape[0]
    dt = (ts[-1] - ts[0]) / (n - 1)
    spec = jnp.abs(jnp.fft.rfft(phi - jnp.mean(phi)))
    m = spec.shape[0]
    k = jnp.clip(1 + jnp.argmax(spec[1:]), 1, m - 2)
    # Quadratic interpolation of log|FFT| over the peak and its neighbours: the bins are
    # 1/t1 apart, far coarser than the frequency differences a sweep looks for.
    a, b, c = (jnp.log(spec[i] + 1e-300) for i in (k - 1, k, k + 1))
    den = a - 2 * b + c
    shift = jnp.where(den < 0, 0.5 * (a - c) / jnp.where(den < 0, den, -1.0), 0.0)
    return (k + jnp.clip(shift, -0.5, 0.5)) / (n * dt)


_REDUCERS = {
    "peak_phi": lambda tr, mech: jnp.max(jnp.abs(tr.phi)),
    "peak_dphi": lambda tr, mech: jnp.max(jnp.abs(tr.dphi)),
    "final_phi": lambda tr, mech: tr.phi[-1],
    "final_dphi": lambda tr, mech: tr.dphi[-1],
    "final_energy": lambda tr, mech: energy(mech, tr.phi[-1], tr.dphi[-1]),
    "peak_O": lambda tr, mech: jnp.max(jnp.hypot(tr.extras["O_x"], tr.extras["O_y"])),
    "dominant_freq": lambda tr, mech: dominant_freq(tr.ts, tr.phi),
    "settling_time": lambda tr, mech: settling_time(tr.ts, tr.phi),
    "phi": lambda tr, mech: tr.phi,
    "dphi": lambda tr, mech: tr.dphi,
}
assert set(_REDUCERS) == set(REDUCTIONS)


def reduce(name: str, traj, mech) -> Array:
    """Reduction `name` of a [`Trajectory`][] of `mech` (one sample, inside the vmap)."""
    return _REDUCERS[name](traj, mech)
