"""Backbone curves: the frequency of the undamped, unforced swing about the rest position
as a function of its amplitude.

A conservative, reversible swing (the equation of motion is even in phi' with c = 0 and no
friction or load) turns at `phi_max` with phi' = 0 and reaches `phi_min` with phi' = 0
half a period later. So an orbit of amplitude `A = (phi_max - phi_min) / 2` is the root
`(phi_max, T/2)` of

    phi'(T/2; phi_max) = 0,   (phi_max - phi(T/2; phi_max)) / 2 = A,

shooting from a release at rest, scaled so that both unknowns and both residuals are ~1
at any amplitude. Amplitudes are continued in order (`lax.scan`): each root find starts
from the previous point's solution, the first from the linearisation (`linearize`), which
is the backbone's small-amplitude limit.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from ..model.dynamics import CrankField, Structure
from ..model.loads import NoLoad
from ..runtime.lazy import lazy_import
from ..simulation import linearize
from .drive import VibrationError, check_mech, check_rtol
from .flow import flow
from .rest import stable_rest

optx = lazy_import("optimistix")  # imported on first use (see lazy.py)

__all__ = ["Backbone", "backbone", "conservative"]


class Backbone(NamedTuple):
    """A backbone curve; arrays have the shape (n,) of the requested amplitudes."""

    amplitude: Array
    """(phi_max - phi_min) / 2, rad (as requested)."""
    phi_max: Array
    """Turning angle on the positive side, rad."""
    phi_min: Array
    """Turning angle on the negative side, rad."""
    frequency_hz: Array
    """Frequency of the free swing, Hz."""
    period: Array
    """Its period, s."""
    ok: Array
    """(n,) bool: the orbit was found. After the first failure (e.g. the swing reaches the
    unstable position, where it becomes a rotation with no turning point) every later
    point is NaN and False."""
    linear_frequency_hz: Array
    """The linearisation's natural frequency `omega_n / 2 pi`, Hz (scalar)."""


def conservative(mech):
    """`mech` without damping and friction (c, T_c, c_s, F_s = 0): the backbone's system."""
    return mech.replace(c=0.0, T_c=0.0, c_s=0.0, F_s=0.0)


def backbone(mech, amplitudes: ArrayLike, *, rtol: float = 1e-10) -> Backbone:
    """The backbone curve of `mech` at the given swing amplitudes.

    **Arguments:**

    - `mech`: a [`SliderCrank`][crank_jax.SliderCrank]; its damping and friction are set to
      zero (the backbone is the conservative system's), gravity, offset and geometry kept.
    - `amplitudes`: (n,) amplitudes `(phi_max - phi_min) / 2`, rad, > 0, in increasing
      order (each orbit starts from the previous one).
    - `rtol`: the solver's relative tolerance (its absolute one is `rtol` times the
      amplitude) and Newton's.

    **Returns:** a [`Backbone`][] of the swings about the statically stable rest position
    (a hanging crank's at phi = pi). Raises [`VibrationError`][crank_jax.vibration.drive.
    VibrationError] if there is none (no small swings).
    """
    amps = _amplitudes(amplitudes)
    check_mech(mech, "backbone")
    check_rtol(rtol)
    mech = conservative(mech)
    phi_eq, omega = stable_rest(mech)
    if not np.isfinite(omega):
        lin = linearize(mech)
        raise VibrationError(f"the mechanism has no statically stable rest position (xi = "
                             f"{float(lin.xi):.4g} N*m/rad <= 0 at phi = "
                             f"{float(lin.phi_eq):.4g} rad): raise k above k_crit = "
                             f"{float(lin.k_crit):.4g} N*m/rad for a backbone")
    # A swing about phi_eq is resolved to eps |phi_eq| / A relative: below this floor
    # Newton's method cannot meet rtol (a pendulum's 3e-5 rad about pi failed, 1e-4 passed),
    # and below ~1e-200 rad the solver's absolute tolerance, rtol * A, underflows.
    floor = max(16 * np.finfo(float).eps * abs(phi_eq) / rtol, 1e-200)
    if float(amps[0]) < floor:
        raise VibrationError(f"amplitudes must be >= {floor:.2g} rad about the rest at "
                             f"{phi_eq:.6g} rad (smaller swings are lost in rounding at rtol "
                             f"{rtol:g}; their frequency is linear_frequency_hz), got "
                             f"{float(amps[0]):g}")
    return _backbone(mech, amps, Structure.of(mech), rtol, jnp.asarray(phi_eq),
                     jnp.asarray(omega))


def _amplitudes(amplitudes) -> Array:
    """The requested amplitudes as a (n,) float array, or a `VibrationError`."""
    try:
        a = np.atleast_1d(np.asarray(amplitudes, dtype=float))
    except (TypeError, ValueError):
        a = np.array([np.nan])
    if a.ndim != 1 or a.size == 0 or not np.all(np.isfinite(a)) or np.any(a <= 0) \
            or np.any(np.diff(a) <= 0):
        shown = f"shape {a.shape}" if a.ndim != 1 or a.size == 0 else np.array2string(
            a, threshold=6)
        raise VibrationError(f"amplitudes must be one or more finite amplitudes > 0 rad, "
                             f"increasing (a 1-D array, e.g. np.linspace(0.01, 1.0, 20)); "
                             f"got {shown}")
    return jnp.asarray(a)


@eqx.filter_jit
def _backbone(mech, amps, structure, rtol, phi_eq, omega):
    half = jnp.pi / omega  # the linear half period, s
    field = CrankField(mech, NoLoad(), NoLoad(), structure)

    def residual(x, amp):
        # x = ((phi_max - phi_eq) / A, (T/2) / half): both 1 in the linear limit.
        phi_max = phi_eq + amp * x[0]
        y1 = flow(field, jnp.stack([phi_max, 0.0]), half * x[1], rtol=rtol, atol=rtol * amp)
        return jnp.stack([y1[1] / (omega * amp), (phi_max - y1[0]) / (2 * amp) - 1.0])

    solver = optx.Newton(rtol=rtol, atol=rtol * 1e-2)

    def step(carry, amp):
        x_prev, amp_prev, alive = carry
        # Start from the previous orbit with its turning angle scaled to the new amplitude.
        sol = optx.root_find(residual, solver, x_prev, amp, max_steps=40, throw=False)
        ok = alive & (sol.result == optx.RESULTS.successful) & (sol.value[1] > 0)
        x = jnp.where(ok, sol.value, x_prev)
        phi_max = phi_eq + amp * x[0]
        t_half = half * x[1]
        nan = jnp.where(ok, 0.0, jnp.nan)
        out = (phi_max + nan, phi_max - 2 * amp + nan, 1 / (2 * t_half) + nan,
               2 * t_half + nan, ok)
        return (x, amp, ok), out

    x0 = jnp.array([1.0, 1.0])
    _, (pmax, pmin, freq, period, ok) = jax.lax.scan(step, (x0, amps[0], jnp.array(True)),
                                                     amps)
    return Backbone(amps, pmax, pmin, freq, period, ok, omega / (2 * jnp.pi))
