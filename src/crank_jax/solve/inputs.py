"""Checks on a solve's inputs that need no physics: tolerances and batch shapes.

Each raises a `ValueError` of one line that names the argument and the fix, before any
compilation (so the CLI can turn it into exit 2).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import numpy as np

__all__ = ["check_tolerances", "check_scene_values", "check_unbatched"]


# Below this a relative tolerance cannot be verified in float64: the embedded error
# estimate itself carries rounding noise of a few eps (2.2e-16), so the solver could only
# shrink its steps until max_steps.
MIN_RTOL = 1e-15
# Above this the step-size control no longer bounds the error: near rtol = 1 a solve ran
# out of steps where a tighter tolerance passed, or finished with a wrong trajectory
# (issue 24). scene.MAX_RTOL, the scene files' and `simulate --rtol`'s bound, is this.
MAX_RTOL = 1e-2
# The state is (phi, dphi) in rad and rad/s: an absolute tolerance above this lets each
# step err by more than 0.06 degree, and at 1 the solver steps over a
# whole swing (a rest called unstable, a backbone frequency off in its third digit).
# Scene files, `simulate --atol` and the library take this bound.
MAX_ATOL = 1e-3


def check_tolerances(rtol, atol) -> None:
    """`ValueError` unless `MIN_RTOL <= rtol <= MAX_RTOL` and `0 < atol <= MAX_ATOL`, both
    finite (concrete values only; traced ones are the caller's)."""
    for name, value, ok, rule in (
        ("rtol", rtol, lambda v: (v >= MIN_RTOL) & (v <= MAX_RTOL),
         f"a finite number >= {MIN_RTOL:g} (float64 resolves ~2.2e-16) and <= "
         f"{MAX_RTOL:g} (a looser one does not bound the error), e.g. rtol=1e-8"),
        ("atol", atol, lambda v: (v > 0) & (v <= MAX_ATOL),
         f"a finite number > 0 and <= {MAX_ATOL:g} (rad, rad/s: a looser one lets every "
         "step err by more), e.g. atol=1e-10"),
    ):
        if isinstance(value, jax.core.Tracer):
            continue
        if isinstance(value, float) and math.isfinite(value) and ok(value):
            continue  # the common case, without NumPy's per-call cost
        v = np.asarray(value, dtype=float)
        if not (np.all(np.isfinite(v)) and np.all(ok(v))):
            shown = v.item() if v.size == 1 else v
            raise ValueError(f"{name} must be {rule}; got {name}={shown}")


def check_scene_values(phi0, dphi0, rtol, atol) -> None:
    """`ValueError` naming the argument unless the tolerances pass [`check_tolerances`][]
    and the initial state `phi0` (rad), `dphi0` (rad/s) is finite: a scene's solve
    settings, checked as its file's are (concrete values only)."""
    check_tolerances(rtol, atol)
    for name, value, unit in (("phi0", phi0, "rad"), ("dphi0", dphi0, "rad/s")):
        if isinstance(value, jax.core.Tracer) or not eqx.is_array_like(value):
            continue
        v = np.asarray(value, dtype=float)
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be finite ({unit}), got {name}="
                             f"{v.item() if v.size == 1 else v}")


def check_unbatched(name: str, tree) -> None:
    """`ValueError` if an array leaf of the Module `tree` (named `name`) is not a scalar.

    A simulation integrates one system; a batch of parameters is `jax.vmap`'s job (inside
    the `vmap` every leaf is a scalar again).
    """
    fields = getattr(tree, "__dataclass_fields__", {})
    for field in fields:
        value = getattr(tree, field, None)
        if eqx.is_array(value) and np.ndim(value) > 0:
            raise ValueError(
                f"{name}.{field} has shape {tuple(np.shape(value))}: simulate integrates one "
                f"system; to run a batch, map over it with jax.vmap, e.g. jax.vmap(lambda v: "
                f"simulate(mech.replace({field}=v), ...))(values)")
