"""Which load of a scene drives it harmonically, and the field at another forcing frequency.

A forced response needs one harmonic drive: the scene's crank torque `tau(t) = tau0 +
tau1 sin(2 pi f t + phase)` (`[torque]` in the scene file), else its slider force P(t)
(`[load]`). The frequency `f` is then the continuation's variable; the drive's other
numbers stay the scene's.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..model.dynamics import CrankField, Structure
from ..model.loads import ConstantLoad, HarmonicLoad, NoLoad
from ..solve.inputs import check_scene_values, check_tolerances

__all__ = ["VibrationError", "drive_side", "field_at", "check_smooth", "check_scene",
           "check_mech", "check_rtol", "as_range"]


class VibrationError(ValueError):
    """A scene or option that a vibration analysis cannot use; the message names the field
    and the fix."""


def drive_side(scene) -> str:
    """`"torque"` or `"load"`: the scene's harmonic drive (the torque if both are)."""
    for side in ("torque", "load"):
        x = getattr(scene, side)
        if isinstance(x, HarmonicLoad) and (_traced(x.X1) or np.any(np.asarray(x.X1) != 0)):
            other = "load" if side == "torque" else "torque"
            y = getattr(scene, other)
            # Any other time-varying load would break the periodicity at the drive's period.
            if not (isinstance(y, (NoLoad, ConstantLoad)) or (
                    isinstance(y, HarmonicLoad) and not _traced(y.X1)
                    and np.all(np.asarray(y.X1) == 0))):
                raise VibrationError(
                    f"the scene's [{side}] is the harmonic drive, so its [{other}] must be "
                    f"absent or constant (got {type(y).__name__}); remove its varying part")
            return side
    raise VibrationError(
        "the scene has no harmonic drive: set [torque] tau1 and freq_hz (a harmonic crank "
        "torque), or [load] P1 and freq_hz (a harmonic slider force), to a nonzero amplitude")


def _traced(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def field_at(scene, side: str, freq_hz, structure: Structure | None = None) -> CrankField:
    """The scene's vector field with its `side` drive at `freq_hz` (Hz)."""
    load, torque = scene.load, scene.torque
    f = jnp.asarray(freq_hz, float)
    if side == "torque":
        torque = eqx.tree_at(lambda x: x.freq_hz, torque, f)
    else:
        load = eqx.tree_at(lambda x: x.freq_hz, load, f)
    return CrankField(scene.mech, load, torque, structure or Structure())


def check_smooth(mech, what: str) -> None:
    """Refuse Coulomb friction where a smooth linearisation is needed (`what` names the
    analysis): its smoothed slope at rest, `T_c / w_c`, is an artefact, not physics."""
    names = [n for n in ("T_c", "F_s") if not _traced(getattr(mech, n))
             and np.any(np.asarray(getattr(mech, n)) != 0)]
    if names:
        raise VibrationError(
            f"{what} is not defined with Coulomb friction ({', '.join(names)} > 0): its "
            "smoothed slope at rest is an artifact of the width w_c / w_s; set "
            f"{' and '.join(names)} = 0 (model it as viscous damping c, c_s instead)")


def check_scene(scene, what: str) -> None:
    """Refuse a scene whose tolerances or initial state its file could not hold (a scene
    changed with `eqx.tree_at` skips construction's check), or a batch of mechanisms."""
    try:
        check_scene_values(scene.phi0, scene.dphi0, scene.rtol, scene.atol)
    except ValueError as e:
        raise VibrationError(f"the scene's {e}") from None
    check_mech(scene.mech, what)


def check_mech(mech, what: str) -> None:
    """Refuse a batch of mechanisms (a field with a shape): `what` analyses one."""
    for name in getattr(mech, "__dataclass_fields__", {}):
        v = getattr(mech, name)
        if eqx.is_array(v) and np.ndim(v) > 0:
            raise VibrationError(f"mech.{name} has shape {tuple(np.shape(v))}: {what} analyses "
                                 "one mechanism; call it once per mechanism of the batch")


def check_rtol(rtol) -> None:
    """Refuse a Newton (and solver) tolerance `rtol` that a scene's rtol could not be."""
    try:
        check_tolerances(rtol, 1e-10)
    except ValueError as e:
        raise VibrationError(str(e)) from None


def as_range(name: str, value, unit: str, zero_ok: bool = False) -> tuple[float, float]:
    """`(lo, hi)` from a pair of finite numbers with `0 < lo < hi` (`0 <= lo` if
    `zero_ok`), else [`VibrationError`][] naming the argument `name`."""
    try:
        lo, hi = (float(x) for x in value)
    except (TypeError, ValueError):
        raise VibrationError(f"{name} must be a pair (lo, hi) of numbers, {unit}; got "
                             f"{value!r:.60}") from None
    if not (np.isfinite([lo, hi]).all() and (lo >= 0 if zero_ok else lo > 0) and hi > lo):
        low = "0 <= lo" if zero_ok else "0 < lo"
        raise VibrationError(f"{name} must be (lo, hi) with {low} < hi, {unit}; got "
                             f"({lo:g}, {hi:g})")
    return lo, hi
