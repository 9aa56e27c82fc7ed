"""Periodic orbits of the forced crank by shooting, differentiable by the implicit function
theorem.

An orbit of period `T = 1/f` (the drive's) starts at the root `y0` of the periodicity
condition `G(y0) = (flow_T(y0) - y0) / scale = 0`, found by Newton's method
(`optimistix.root_find`). Its derivative with respect to any array of the scene is
`dy0/dtheta = -(dG/dy0)^-1 dG/dtheta` (`optimistix.ImplicitAdjoint`): the root find is
never unrolled. Forward mode (`jax.jvp`, `jax.jacfwd`) goes through that rule directly. For
reverse mode (`jax.grad`) [`periodic_orbit`][] is a `jax.custom_jvp` whose rule forms the
full Jacobian with respect to the scene's arrays in forward mode (a few dozen columns for
this one-degree-of-freedom model, each a variational solve) and returns it applied to the
tangents: a linear map, which JAX transposes.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..model.dynamics import Structure
from ..runtime.lazy import lazy_import
from ..simulation import linearize
from ..solve.policy import is_concrete
from .drive import VibrationError, check_rtol, check_scene, drive_side, field_at
from .floquet import STABLE_MARGIN, monodromy, multipliers
from .flow import flow, flow_samples

optx = lazy_import("optimistix")  # imported on first use (see lazy.py)

__all__ = ["Orbit", "periodic_orbit", "extremes", "linear_guess", "lever_at", "SAMPLES"]

#: Samples per period from which the extremes are refined (quadratic in time about the
#: extreme sample: relative error ~ (pi / SAMPLES)^3 / 6, 8e-10 at 1024).
SAMPLES = 1024


class Orbit(NamedTuple):
    """One periodic orbit of a forced scene (SI units; angles in rad)."""

    amplitude: Array
    """(phi_max - phi_min) / 2, rad."""
    phi_max: Array
    """Largest angle over the orbit, rad."""
    phi_min: Array
    """Smallest angle over the orbit, rad."""
    period: Array
    """The orbit's period, 1 / freq_hz, s."""
    floquet: Array
    """(2,) moduli of the Floquet multipliers, largest first (not differentiated)."""
    stable: Array
    """Every multiplier inside the unit circle (bool)."""
    y0: Array
    """(2,) the orbit's state (phi, dphi) at t = 0 (rad, rad/s)."""
    ok: Array
    """The root find converged (bool); where it did not, the other fields are NaN."""


def extremes(field, y0: Array, span: Array, *, rtol, atol, t0=0.0,
             samples: int = SAMPLES) -> tuple[Array, Array]:
    """`(phi_max, phi_min)` over `[t0, t0 + span]` from `y0`: the extreme samples of
    `samples + 1`, each refined by one Newton step in time (`phi' = 0`), `phi_i -
    phi'_i^2 / (2 phi''_i)`. By the envelope theorem the derivative of an extreme with
    respect to a parameter is the derivative of phi at the extreme's (fixed) time, which
    is what differentiating the refined sample gives."""
    s = jnp.linspace(0.0, 1.0, samples + 1)
    ys, _ = flow_samples(field, y0, span, s, rtol=rtol, atol=atol, t0=t0)
    ts = t0 + span * s

    def refine(i, sign):
        phi, dphi = ys[i, 0], ys[i, 1]
        acc = field.acceleration(ts[i], phi, dphi)
        # Only a curvature of the right sign is an extreme; a flat one is left as sampled.
        good = sign * acc < 0
        return phi - jnp.where(good, dphi * dphi / (2 * jnp.where(good, acc, 1.0)), 0.0)

    return refine(jnp.argmax(ys[:, 0]), 1.0), refine(jnp.argmin(ys[:, 0]), -1.0)


def linear_guess(scene, side: str, freq_hz) -> Array:
    """The start (2,) of the linearised system's steady response at `freq_hz`: a first
    guess for shooting (exact in the small-amplitude limit)."""
    lin = linearize(scene.mech, scene.load, scene.torque)
    drive = getattr(scene, side)
    phi_eq = jnp.where(jnp.isnan(lin.phi_eq), 0.0, lin.phi_eq)
    gain = 1.0 if side == "torque" else lever_at(scene.mech, phi_eq)
    w = 2 * jnp.pi * freq_hz
    # mu x'' + chi x' + xi x = F sin(w t + p): x = Re(F e^{i(wt+p)} / (xi - mu w^2 + i chi w))
    # with sin = Re(-i e^{i..}).
    h = 1.0 / (lin.xi - lin.mu * w * w + 1j * lin.chi * w)
    z = -1j * gain * drive.X1 * jnp.exp(1j * drive.phase) * h
    return jnp.stack([phi_eq + jnp.real(z), jnp.real(1j * w * z)])


def lever_at(mech, phi):
    """The slider's lever dx_s/dphi (m) at angle `phi` (rad): a slider force's gain."""
    from ..model.coefficients import coefficients
    from ..model.geometry import geometry
    return geometry(coefficients(mech), phi).lever


def _scale(scene, freq_hz) -> Array:
    # phi in rad, dphi over the forcing's angular frequency: both ~ the amplitude.
    return jnp.stack([jnp.ones_like(freq_hz), 2 * jnp.pi * freq_hz])


def _residual(y0s, args):
    scene, side, structure, freq_hz = args
    scale = _scale(scene, freq_hz)
    y0 = y0s * scale
    field = field_at(scene, side, freq_hz, structure)
    y1 = flow(field, y0, 1.0 / freq_hz, rtol=scene.rtol, atol=scene.atol)
    return (y1 - y0) / scale


def _shoot(scene, side, structure, freq_hz, guess, rtol):
    """The orbit's start (2,) and success flag: Newton on the periodicity condition."""
    scale = _scale(scene, freq_hz)
    solver = optx.Newton(rtol=rtol, atol=rtol * 1e-2)
    sol = optx.root_find(_residual, solver, guess / scale,
                         (scene, side, structure, freq_hz), max_steps=40, throw=False,
                         adjoint=optx.ImplicitAdjoint())
    ok = sol.result == optx.RESULTS.successful
    return sol.value * scale, ok


def _values(dyn, static, side, structure, rtol):
    """The differentiable part of an orbit: (y0, phi_max, phi_min), forward mode."""
    scene, freq_hz, guess = eqx.combine(dyn, static)
    y0, ok = _shoot(scene, side, structure, freq_hz, guess, rtol)
    field = field_at(scene, side, freq_hz, structure)
    phi_max, phi_min = extremes(field, y0, 1.0 / freq_hz, rtol=scene.rtol, atol=scene.atol)
    return (y0, phi_max, phi_min), ok


def _differentiable(dyn, static, side, structure, rtol):
    # A custom_jvp whose rule is "forward Jacobian times tangent": linear in the tangents,
    # so JAX transposes it and `jax.grad` works, while the Jacobian itself comes from the
    # root find's implicit rule (no unrolled Newton iterations). Symbolic zeros say which
    # arrays are differentiated: only their columns are formed (one for d/dk).
    leaves, treedef = jax.tree_util.tree_flatten(dyn)

    def values(ls):
        return _values(jax.tree_util.tree_unflatten(treedef, list(ls)), static, side,
                       structure, rtol)

    @jax.custom_jvp
    def f(*ls):
        return values(ls)

    def rule(primals, tangents):
        active = [i for i, t in enumerate(tangents)
                  if not isinstance(t, jax.custom_derivatives.SymbolicZero)]

        def g(xs):
            ls = list(primals)
            for i, x in zip(active, xs):
                ls[i] = x
            out = values(ls)
            return out[0], out

        jac, (out, ok) = jax.jacfwd(g, has_aux=True)(tuple(primals[i] for i in active))

        def apply(j):  # j: per active input, d(output leaf)/d(input), out.shape + in.shape
            total = 0.0
            for ji, i in zip(j, active):
                total = total + jnp.tensordot(ji, tangents[i], axes=jnp.ndim(tangents[i]))
            return total

        # `out` is a tuple of arrays (y0, phi_max, phi_min); `jac` one tuple per output.
        tan = tuple(jnp.zeros_like(o) + apply(j) for o, j in zip(out, jac))
        return (out, ok), (tan, np.zeros(np.shape(ok), jax.dtypes.float0))

    f.defjvp(rule, symbolic_zeros=True)
    return f(*leaves)


def periodic_orbit(scene, freq_hz, guess: Array | None = None, *, rtol: float = 1e-10,
                   structure: Structure | None = None) -> Orbit:
    """One periodic orbit of a harmonically driven scene, by shooting.

    **Arguments:**

    - `scene`: a [`Scene`][crank_jax.Scene] whose crank torque (`tau1`) or slider force
      (`P1`) is a `HarmonicLoad` (the torque if both are); its `rtol`, `atol` are the
      solver's.
    - `freq_hz`: the forcing frequency, Hz (replaces the drive's own); the period is
      `1 / freq_hz`.
    - `guess`: (2,) start `(phi, dphi)` at t = 0 to begin Newton's method from; default the
      linearised steady response (good off resonance and at small amplitude; on a folded
      curve pass a neighbouring orbit's `y0` to pick a branch).
    - `rtol`: Newton's tolerance on the periodicity condition (relative to the amplitude).
    - `structure`: the equation's terms; default those of the scene's (concrete) values.

    **Returns:** an [`Orbit`][]. `amplitude`, `phi_max`, `phi_min`, `period` and `y0` are
    differentiable with respect to every array of the scene and `freq_hz`, by the implicit
    function theorem, in forward and reverse mode: e.g.
    `jax.grad(lambda k: periodic_orbit(eqx.tree_at(lambda s: s.mech.k, scene, k), f)
    .amplitude)(k)`. Not raising: `ok` says whether Newton's method converged.
    """
    side = drive_side(scene)
    check_scene(scene, "periodic_orbit")
    check_rtol(rtol)
    if structure is None:
        structure = Structure.of(scene.mech)
    _check_frequency(freq_hz)
    freq_hz = jnp.asarray(freq_hz, float)
    if guess is None:
        guess = linear_guess(scene, side, freq_hz)
    guess = jnp.asarray(guess, float)
    if guess.shape != (2,) or (is_concrete(guess) and not np.all(np.isfinite(guess))):
        raise VibrationError(f"guess must be a finite state (phi, dphi) of shape (2,), rad "
                             f"and rad/s (an orbit's y0), got shape {guess.shape}")
    return _orbit(scene, freq_hz, guess, side, structure, rtol)


def _check_frequency(freq_hz) -> None:
    """Refuse a concrete forcing frequency that is not one finite number > 0 Hz: a negative
    one gives a negative period and inverted Floquet multipliers."""
    if not is_concrete(freq_hz):
        return
    f = np.asarray(freq_hz, dtype=float)
    if f.ndim or not (np.isfinite(f) and f > 0):
        shown = f.item() if f.ndim == 0 else f"shape {f.shape}"
        raise VibrationError(f"freq_hz must be one finite frequency > 0 Hz, got {shown} "
                             "(for several, map over them with jax.vmap)")


@eqx.filter_jit
def _orbit(scene, freq_hz, guess, side, structure, rtol):
    dyn, static = eqx.partition((scene, freq_hz, guess), eqx.is_inexact_array)
    (y0, phi_max, phi_min), ok = _differentiable(dyn, static, side, structure, rtol)
    period = 1.0 / freq_hz
    # Stability is a verdict, not a smooth function: its inputs are held constant.
    sg = jax.lax.stop_gradient
    field = field_at(sg(scene), side, sg(freq_hz), structure)
    lam = multipliers(monodromy(field, sg(y0), sg(period), rtol=sg(scene.rtol),
                                atol=sg(scene.atol)))
    mod = jnp.abs(lam)
    nan = jnp.where(ok, 0.0, jnp.nan)
    return Orbit(amplitude=(phi_max - phi_min) / 2 + nan, phi_max=phi_max + nan,
                 phi_min=phi_min + nan, period=period, floquet=mod + nan,
                 stable=ok & (mod[0] < 1 + STABLE_MARGIN), y0=y0 + nan, ok=ok)
