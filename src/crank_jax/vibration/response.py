"""Forced response curves: periodic orbits of the driven crank continued in the forcing
frequency (pseudo-arclength, `continuation.py`), with their Floquet stability.

The continued variable is `u = (phi0, dphi0 / w_ref, f / f_ref)`: an orbit's start at
t = 0 and its frequency, scaled so that each is ~ the amplitude in rad or ~1 (`f_ref` the
middle of the range, `w_ref = 2 pi f_ref`). The periodicity condition is the one of
`orbit.py`. The corrector's Jacobian `dG/du` (forward mode through the solve) serves
three ends at once: Newton's steps, the tangent (its null vector) and the monodromy matrix
(`I + dG/d(phi0, dphi0)`, in scaled coordinates, which leave its eigenvalues unchanged).
"""

from __future__ import annotations

import json
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..model.dynamics import Structure
from ..runtime.lazy import lazy_import
from ..simulation import linearize
from .backbone import backbone
from .continuation import Point, continue_curve, null_vector
from .drive import VibrationError, as_range, check_rtol, check_scene, drive_side, field_at
from .floquet import STABLE_MARGIN, multipliers
from .flow import flow
from .orbit import extremes, lever_at, linear_guess

optx = lazy_import("optimistix")  # imported on first use (see lazy.py)

__all__ = ["Branch", "ForcedResponse", "forced_response"]


class Branch(NamedTuple):
    """One continued branch; every array has one entry per orbit (n,) (floquet (n, 2)):
    `freq_hz` (Hz), `amplitude`, `phi_max`, `phi_min` (rad), `stable`, `floquet` (the
    multipliers' moduli, largest first), and each orbit's start at t = 0, `phi0` (rad),
    `dphi0` (rad/s): a guess for [`periodic_orbit`][crank_jax.periodic_orbit]."""

    freq_hz: np.ndarray
    amplitude: np.ndarray
    phi_max: np.ndarray
    phi_min: np.ndarray
    stable: np.ndarray
    floquet: np.ndarray
    phi0: np.ndarray
    dphi0: np.ndarray

    def to_dict(self) -> dict:
        return {k: np.asarray(v).tolist() for k, v in self._asdict().items()}


class ForcedResponse(NamedTuple):
    """A forced response curve: `branches` ([`Branch`][]), `folds` (dicts with `freq_hz`
    and `amplitude`), `drive` ("torque" or "load"), `stopped` (why the continuation
    ended, in Hz), `linear` (`freq_hz`, `amplitude` of the linearised response, for plots)
    and `complete`: whether the branch reached the range's end f1. A partial curve
    (`complete` False) covers only part of the range; `stopped` says which and why."""

    branches: list
    folds: list
    drive: str
    stopped: str
    linear: dict
    complete: bool = True

    def to_dict(self) -> dict:
        return {"drive": self.drive, "branches": [b.to_dict() for b in self.branches],
                "folds": self.folds, "stopped": self.stopped, "complete": self.complete,
                "linear": self.linear}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1)


def _scales(f_ref):
    return jnp.stack([jnp.ones_like(f_ref), 2 * jnp.pi * f_ref, f_ref])


@eqx.filter_jit
def _correct(scene, side, structure, f_ref, u_pred, t, rtol):
    scale = _scales(f_ref)

    def G(u):
        x = u * scale
        field = field_at(scene, side, x[2], structure)
        y1 = flow(field, x[:2], 1.0 / x[2], rtol=scene.rtol, atol=scene.atol)
        return (y1 - x[:2]) / scale[:2]

    def H(u, _):
        return jnp.concatenate([G(u), jnp.dot(t, u - u_pred)[None]])

    sol = optx.root_find(H, optx.Newton(rtol=rtol, atol=rtol * 1e-2), u_pred, None,
                         max_steps=12, throw=False)
    u = sol.value
    ok = (sol.result == optx.RESULTS.successful) & (u[2] > 0)
    jac = jax.jacfwd(G)(u)
    lam = multipliers(jnp.eye(2) + jac[:, :2])
    x = u * scale
    field = field_at(scene, side, x[2], structure)
    pmax, pmin = extremes(field, x[:2], 1.0 / x[2], rtol=scene.rtol, atol=scene.atol)
    return u, jac, ok, sol.stats["num_steps"], (pmax, pmin, jnp.abs(lam))


def forced_response(scene, freq_hz: tuple[float, float], *, max_points: int = 400,
                    step: float | None = None, rtol: float = 1e-10,
                    backbone_points: int = 0) -> ForcedResponse:
    """The forced response curve of a harmonically driven scene over a frequency range.

    **Arguments:**

    - `scene`: a [`Scene`][crank_jax.Scene] with a harmonic crank torque (`tau1`) or slider
      force (`P1`): the drive (the torque if both), whose frequency is continued; its
      `rtol`, `atol` are the solver's.
    - `freq_hz`: `(f0, f1)`, Hz, 0 < f0 < f1: the curve starts at the orbit at f0 (found
      from the linearised response) and follows its branch, through folds, until the
      frequency leaves the range.
    - `max_points`: the most orbits kept. `step`: the largest arclength step in the
      scaled variables (default (f1 - f0) / f_mid / 40). `rtol`: Newton's tolerance.
    - `backbone_points`: if > 0, the mechanism's backbone at that many amplitudes up to the
      curve's largest is added to `linear` (for plots).

    **Returns:** a [`ForcedResponse`][]: one branch with a stability flag and the Floquet
    multipliers' moduli per orbit, and the folds between them (linearly interpolated where
    the tangent's frequency component changes sign).
    """
    f0, f1 = as_range("freq_hz", freq_hz, "Hz")
    side = drive_side(scene)
    check_scene(scene, "forced_response")
    check_rtol(rtol)
    _check_budget(max_points, backbone_points)
    structure = Structure.of(scene.mech)
    f_ref = jnp.asarray((f0 + f1) / 2)
    scale = np.asarray(_scales(f_ref))
    ds_max = _check_step(step, (f1 - f0) / float(f_ref))

    def correct(u_pred, t):
        u, jac, ok, steps, (pmax, pmin, mods) = _correct(
            scene, side, structure, f_ref, jnp.asarray(u_pred), jnp.asarray(t), rtol)
        return Point(np.asarray(u), null_vector(np.asarray(jac)), bool(ok), int(steps),
                     (float(pmax), float(pmin), np.asarray(mods)))

    guess = np.asarray(linear_guess(scene, side, f0))
    u0 = np.concatenate([guess, [f0]]) / scale
    start = correct(u0, np.array([0.0, 0.0, 1.0]))
    if not start.ok:
        raise VibrationError(f"no periodic orbit found at the start frequency {f0:g} Hz "
                             "from the linearized response; start the range farther from "
                             "resonance (a lower f0 in `freq_hz=`)")
    curve = continue_curve(correct, start, direction=1.0, lo=f0 / float(f_ref),
                           hi=f1 / float(f_ref), ds=ds_max / 2, ds_max=ds_max,
                           ds_min=ds_max * 1e-4, max_points=max_points)
    freq = curve.u[:, 2] * float(f_ref)
    pmax = np.array([e[0] for e in curve.extra])
    pmin = np.array([e[1] for e in curve.extra])
    mods = np.array([e[2] for e in curve.extra])
    amp = (pmax - pmin) / 2
    stable = mods[:, 0] < 1 + STABLE_MARGIN
    folds = []
    for i in curve.folds:
        a, b = curve.t[i, 2], curve.t[i + 1, 2]
        w = a / (a - b)
        folds.append({"freq_hz": float(freq[i] + w * (freq[i + 1] - freq[i])),
                      "amplitude": float(amp[i] + w * (amp[i + 1] - amp[i]))})
    branch = Branch(freq, amp, pmax, pmin, stable, mods, curve.u[:, 0] * scale[0],
                    curve.u[:, 1] * scale[1])
    linear = _linear(scene, side, np.linspace(f0, f1, 200))
    if backbone_points > 0 and np.isfinite(amp).any():
        amps = np.linspace(np.nanmax(amp) / backbone_points, np.nanmax(amp), backbone_points)
        bb = backbone(scene.mech, amps)
        ok = np.asarray(bb.ok)
        linear["backbone_freq_hz"] = np.asarray(bb.frequency_hz)[ok].tolist()
        linear["backbone_amplitude"] = np.asarray(bb.amplitude)[ok].tolist()
    complete, stopped = _ending(curve.reason, freq, (f0, f1), max_points)
    return ForcedResponse([branch], folds, side, stopped, linear, complete)


def _ending(reason: str, freq: np.ndarray, asked: tuple[float, float], max_points: int):
    """`(complete, why)`: whether the branch reached f1, and why it ended, in Hz."""
    f0, f1 = asked
    if reason == "range" and freq[-1] > f1:
        return True, f"left the range at {f1:g} Hz"
    covered = (f"partial: the curve covers {np.nanmin(freq):.6g} to {np.nanmax(freq):.6g} Hz "
               f"of the {f0:g} to {f1:g} Hz asked")
    why = {"range": f"the branch turned back below {f0:g} Hz",
           "max_points": f"it reached max_points = {max_points} at {freq[-1]:.6g} Hz (raise "
                         "max_points)",
           "corrector": f"no orbit was found beyond {freq[-1]:.6g} Hz even at the smallest "
                        "step (a bifurcation, or an orbit the solver cannot follow)"}[reason]
    return False, f"{covered}: {why}"


def _check_budget(max_points, backbone_points) -> None:
    for name, v, low in (("max_points", max_points, 2), ("backbone_points", backbone_points, 0)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
            raise VibrationError(f"{name} must be an integer >= {low}, got {v!r:.40}")


def _check_step(step, span: float) -> float:
    """The largest arclength step: `step`, or 1/40 of the range's scaled length `span`.
    A step <= 0 never advances; one beyond `span` leaves the range in one step."""
    if step is None:
        return span / 40
    try:
        value = float(step) if not isinstance(step, bool) else np.nan
    except (TypeError, ValueError):
        value = np.nan
    if not (np.isfinite(value) and 0 < value <= span):
        raise VibrationError(f"step must be a number > 0 and at most {span:.4g} (the range's "
                             f"length in the scaled frequency, (f1 - f0) / f_mid), got "
                             f"{step!r:.40}; the default is a 40th of it")
    return value


def _linear(scene, side, freqs) -> dict:
    """The linearised system's response amplitude over `freqs` (Hz)."""
    lin = linearize(scene.mech, scene.load, scene.torque)
    drive = getattr(scene, side)
    phi_eq = float(np.nan_to_num(lin.phi_eq))
    gain = 1.0 if side == "torque" else float(lever_at(scene.mech, jnp.asarray(phi_eq)))
    w = 2 * np.pi * freqs
    h = 1.0 / (float(lin.xi) - float(lin.mu) * w * w + 1j * float(lin.chi) * w)
    return {"freq_hz": freqs.tolist(), "amplitude": np.abs(gain * float(drive.X1) * h).tolist()}
