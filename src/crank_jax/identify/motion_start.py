"""Start values from the motion: the equation of motion on the smoothed angle, solved for
the free parameters that enter it linearly.

On the angle the channels tell (`angle.py`), smoothed with its first two derivatives
(`start.smooth_derivatives`), the equation of motion

    M(phi) phi'' + K(phi) phi'^2 - q(phi, phi', t) - f(t, phi, phi') = 0

is affine in every parameter that multiplies one of its terms: the masses and inertias,
k, c, the friction coefficients, the loads' means, amplitudes and input gains, a user
force's linear coefficients. Least squares over the record's samples then gives them all
at once, from the motion itself, whatever the start values were: for a motor-driven crank,
the gain, the damping and the Coulomb friction from the mean speeds at two voltages and
the speed ripple that the known masses set (DESIGN.md section 3).

This is the regressor start (`start.regressor_start`) written over the fit's own problem,
so it serves every free name that enters linearly, found numerically: a name whose column
changes between two steps is left at its start value. It is tried when the fit from the
scene's values stalls (`escalation.optimize_fit`), before random restarts: a wrong branch of a
slide-only record (the crank's half-turn ambiguity) starts far from where the motion
puts it.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..model.dynamics import coriolis, generalized_force, mass
from ..runtime.arrays import device_array
from .physical import RUNAWAY
from .problem import Problem
from .request import record_mech
from .start import padded_rows, regressor_samples
from .userforce import PREFIX

__all__ = ["motion_start", "LINEARITY_TOLERANCE"]

#: A column that changes by more than this (relative) between a step of 1 and of 2 in
#: the parameter is not linear: that parameter keeps its start value.
LINEARITY_TOLERANCE = 1e-6


@eqx.filter_jit
def _eom(problem: Problem, z, rows):
    """The equation-of-motion residual, N*m, at each record's rows `(phi, dphi, ddphi, t)`
    (each a tuple of (m_i,) arrays) under the parameters of coordinates `z`."""
    mech, per = problem.unpack(z)
    out = []
    for (load, torque, _, own), (p, dp, ddp, t) in zip(per, rows):
        m = record_mech(mech, own)
        e = mass(m, p) * ddp + coriolis(m, p) * dp**2 - generalized_force(m, p, dp, t, load,
                                                                          torque)
        force = own.get(PREFIX)
        if force is not None:
            e = e - jax.vmap(force)(t, p, dp)
        out.append(e)
    return jnp.concatenate(out)


def motion_start(problem: Problem, z: np.ndarray, records, angles, periods
                 ) -> np.ndarray | None:
    """Coordinates (p,) of `problem` with every free global parameter that enters the
    equation of motion linearly solved from the motion (see the module); the others, and
    the records' states, as in `z`.

    **Arguments:** `problem`, a single-shooting [`Problem`][]; `z` (p,), its start
    coordinates; `records`, the [`Data`][] records; `angles`, each record's crank angle as
    its channels tell it, rad; `periods`, each record's cycle, s (sets the smoothing).

    **Returns:** the new coordinates, or None when no free parameter enters linearly or
    the least squares is rank-deficient: then the motion says nothing the scene's values
    do not. The least squares is bounded: each value stays in its physical range (see
    `_bounds`), a damping at 0 rather than the whole start discarded.
    """
    rows, keep = padded_rows([regressor_samples(d.ts, np.asarray(a, float), per)
                              for d, a, per in zip(records, angles, periods)],
                             [len(d.ts) for d in records])

    def eom(zz):
        return np.asarray(_eom(problem, device_array(zz), rows))[keep]

    z = np.asarray(z[:problem.p], dtype=float)
    v0 = np.asarray(problem.host_values(z), dtype=float)
    base = eom(z)
    cols, idx = [], []
    for i in range(problem.n_global):
        h = max(abs(v0[i]), 1e-3 * max(np.abs(v0[:problem.n_global]).max(), 1e-12))

        def at(step, i=i, h=h):
            v = v0.copy()
            v[i] += step * h
            if problem.log[i] and v[i] <= 0:
                return None
            return eom(problem.to_z(v)) - base

        one, two = at(1.0), at(2.0)
        if one is None or two is None or not np.any(one):
            continue
        if np.linalg.norm(two - 2 * one) > LINEARITY_TOLERANCE * np.linalg.norm(two):
            continue
        cols.append(one / h)
        idx.append(i)
    if not idx or not np.all(np.isfinite(base)):
        return None
    Y = np.stack(cols, axis=1)
    scale = np.linalg.norm(Y, axis=0)
    if np.linalg.matrix_rank(Y / scale, tol=1e-10) < len(idx):
        return None
    lo, hi = _bounds(problem, v0, idx)
    # Bounded least squares (each value in its physical range) rather than the free
    # solution discarded whole when one value leaves its domain: the angle differentiated
    # twice shrinks some terms, and one negative damping cost every other value.
    from scipy.optimize import lsq_linear

    sol = lsq_linear(Y / scale, -base, bounds=((lo - v0[idx]) * scale,
                                               (hi - v0[idx]) * scale),
                     method="bvls").x
    v = v0.copy()
    v[idx] += sol / scale
    v[idx] = np.clip(v[idx], lo, hi)  # (bvls meets its bounds to rounding)
    return problem.to_z(v)


def _bounds(problem: Problem, v0: np.ndarray, idx) -> tuple[np.ndarray, np.ndarray]:
    """The range of each solved value (`idx` of `v0`): a field in log coordinates within
    [`RUNAWAY`][crank_jax.identify.physical.RUNAWAY] of its start either way (a start
    outside that is no start the fit would call converged), a folded one at least 0,
    the others free."""
    lo = np.full(len(idx), -np.inf)
    hi = np.full(len(idx), np.inf)
    for k, i in enumerate(idx):
        if problem.log[i]:
            lo[k], hi[k] = v0[i] / RUNAWAY, v0[i] * RUNAWAY
        elif problem.folded[i]:
            lo[k] = 0.0
    return lo, hi
