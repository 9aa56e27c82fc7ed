"""The rest position a vibration analysis swings about: the statically stable equilibrium.

The linearisation's equilibrium is the root of the static generalised force nearest
phi = 0. That is the rest of a rig held by its spring, but not of a crank that hangs: a
compound pendulum (no spring, gravity along the slider line) balances upside down at
phi = 0 and rests at phi = pi. Small swings, backbones and parametric charts are about
the stable rest, so where the root nearest 0 is unstable the stable one is looked for
over a whole turn.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..model.dynamics import acceleration, potential_energy
from ..model.loads import ConstantLoad, NoLoad
from ..simulation import linearize

__all__ = ["stable_rest", "rest_rate", "largest_swing"]

#: Grid over one turn on which the static acceleration's sign changes are looked for; its
#: points sit half a cell off 0 and pi, the equilibria that symmetry makes exact.
_GRID = 720


@eqx.filter_jit
def _static(mech, load, phi):
    """Static acceleration phi'' at rest (rad/s^2) and its slope d phi''/d phi (1/s^2)."""
    def f(p):
        return acceleration(mech, p, 0.0, load=load)

    return jax.vmap(f)(phi), jax.vmap(jax.grad(f))(phi)


def _mean(load):
    return NoLoad() if load is None or isinstance(load, NoLoad) else ConstantLoad(load.mean())


def rest_rate(mech, load, phi: float) -> float:
    """omega^2 = -d phi''/d phi (1/s^2) at the equilibrium `phi` (rad), the load at its
    mean: > 0 where the equilibrium is statically stable (its small-swing frequency)."""
    _, slope = _static(mech, _mean(load), jnp.asarray([phi], float))
    return -float(slope[0])


def stable_rest(mech, load=None) -> tuple[float, float]:
    """`(phi_eq, omega_n)`: the statically stable equilibrium (rad) nearest phi = 0, the
    load at its mean, and its small-swing angular frequency (rad/s); `(nan, nan)` where
    there is none. The linearisation's when it is stable; otherwise the stable root of the
    static acceleration over one turn, refined by Newton's method."""
    lin = linearize(mech, load)
    if bool(np.asarray(lin.stable)):
        return float(lin.phi_eq), float(lin.omega_n)
    mean = _mean(load)
    step = 2 * np.pi / _GRID
    grid = -np.pi + step * (np.arange(_GRID) + 0.5)
    acc = np.asarray(_static(mech, mean, jnp.asarray(grid))[0])
    # Restoring: phi'' falls through zero as phi increases (the last cell wraps around).
    falls = np.flatnonzero((acc > 0) & (np.roll(acc, -1) <= 0))
    roots = []
    for i in falls:
        phi = grid[i] + step / 2
        for _ in range(30):
            a, s = (float(x[0]) for x in _static(mech, mean, jnp.asarray([phi])))
            if not (np.isfinite(a) and s < 0):
                break
            phi -= a / s
        rate = rest_rate(mech, load, phi)
        if np.isfinite(phi) and rate > 0 and abs(float(_static(
                mech, mean, jnp.asarray([phi]))[0][0])) <= 1e-9 * rate:
            roots.append((abs(np.angle(np.exp(1j * phi))), phi, np.sqrt(rate)))
    if not roots:
        return float("nan"), float("nan")
    _, phi, omega = min(roots)
    return float(np.angle(np.exp(1j * phi))), float(omega)


def largest_swing(mech, phi_eq: float) -> float:
    """The largest amplitude `(phi_max - phi_min) / 2` (rad) of a free, conservative swing
    about the stable rest `phi_eq` (no loads): the one whose energy reaches the lower of
    the potential's nearest peaks on either side, beyond which the crank goes over the top
    and rotates. `inf` where the potential rises for a whole turn on both sides (a stiff
    spring: every swing turns back)."""
    phis = phi_eq + np.linspace(-2 * np.pi, 2 * np.pi, 8 * _GRID + 1)
    v = np.asarray(jax.jit(jax.vmap(lambda p: potential_energy(mech, p)))(jnp.asarray(phis)))
    mid = 4 * _GRID
    right, left = v[mid:], v[mid::-1]  # outwards from the rest on each side
    peaks = []
    for side in (right, left):
        falls = np.flatnonzero(np.diff(side) < 0)
        peaks.append(side[falls[0]] if falls.size else np.inf)
    barrier = min(peaks)
    if not np.isfinite(barrier):
        return float("inf")
    step = phis[1] - phis[0]
    # Where each side first reaches the barrier's energy (linear between grid points).
    reach = []
    for side in (right, left):
        i = int(np.argmax(side >= barrier))
        frac = (barrier - side[i - 1]) / (side[i] - side[i - 1]) if i > 0 else 0.0
        reach.append((i - 1 + frac) * step)
    return float((reach[0] + reach[1]) / 2)
