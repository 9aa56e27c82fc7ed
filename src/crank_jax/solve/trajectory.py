"""The crank's solve as a pure function: the vector field, the solve through [`solve`][]
(`solvers.py`, the one entry point, which knows nothing of the mechanism), the derived
outputs and the [`Trajectory`][] they fill.

[`solve_trajectory`][] is the jitted solve that the public `simulate` (the package's front
door, `crank_jax/simulation.py`: input checks, the host plan and its memo, the program
store) runs; [`solve_crank`][] is the same solve for a caller tracing its own program (the
fit's residuals and Jacobians). This module imports nothing of the runtime (program store,
memos, flags): tests/test_layout.py.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Sequence
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..model.dynamics import CrankField, Structure, acceleration, energy
from ..model.geometry import kinematics
from ..model.linear import linearize
from ..model.loads import nonsmooth_times
from ..model.newton_euler import reactions
from .adjoints import AbstractAdjoint
from .solvers import AbstractSolver, solve

if TYPE_CHECKING:  # annotations only: diffrax is imported where it is used
    import diffrax

__all__ = ["Trajectory", "solve_trajectory", "solve_crank", "OUTPUTS", "output_columns",
           "succeeded", "warn_if_float32"]


#: Derived outputs `simulate(outputs=...)` can add, with the columns each one produces.
OUTPUTS: dict[str, tuple[str, ...]] = {
    "ddphi": ("ddphi",),
    "delta": ("delta",),
    "slider": ("x_s", "v_s", "a_s"),
    "energy": ("energy",),
    "loads": ("P", "tau"),
    "reactions": ("O_x", "O_y", "A_x", "A_y", "B_x", "B_y", "N", "F"),
}

def output_columns(outputs: Sequence[str]) -> tuple[str, ...]:
    """The CSV/array column names that the requested outputs produce, in order."""
    cols: list[str] = []
    for name in outputs:
        if name not in OUTPUTS:
            raise ValueError(f"unknown output {name!r}; choose from {sorted(OUTPUTS)}")
        cols += OUTPUTS[name]
    return tuple(cols)


class Trajectory(eqx.Module):
    """A simulated trajectory, sampled at the requested times.

    **Fields:**

    - `ts` (n,): times, s. `phi` (n,): crank angle, rad. `dphi` (n,): its rate, rad/s.
    - `extras`: a dict of requested derived outputs, column name -> (n,) array (see
      [`OUTPUTS`][]); empty unless asked for.
    - `result`: a `diffrax.RESULTS` code; `result == diffrax.RESULTS.successful` when the
      solve finished.
    - `num_steps`: accepted plus rejected steps the solver took.
    """

    ts: Float[Array, " n"]
    phi: Float[Array, " n"]
    dphi: Float[Array, " n"]
    extras: dict[str, Array]
    result: diffrax.RESULTS
    num_steps: Array

    def columns(self) -> dict[str, Array]:
        """`t, phi, dphi` and the extras in the documented column order (JAX sorts dict
        keys when a pytree is rebuilt, so `extras` itself has no reliable order)."""
        order = [c for c in output_columns(list(OUTPUTS)) if c in self.extras]
        return {"t": self.ts, "phi": self.phi, "dphi": self.dphi,
                **{c: self.extras[c] for c in order}}

    @property
    def ok(self) -> Array:
        """True where the solve succeeded."""
        import diffrax

        return self.result == diffrax.RESULTS.successful


def _rate(field: CrankField) -> Array:
    """A rate scale of the motion, 1/s, from the linearisation: |omega_n| plus damping."""
    lin = linearize(field.mech, field.load)
    mu = jnp.abs(lin.mu)
    return jnp.sqrt(jnp.abs(lin.xi) / mu) + jnp.abs(lin.chi) / mu


def _derived(mech, load, torque, ts, phi, dphi, outputs, force=None) -> dict[str, Array]:
    if not outputs:
        return {}
    ddphi = jax.vmap(lambda t, p, d: acceleration(mech, p, d, t, load, torque, force=force))(
        ts, phi, dphi)
    out: dict[str, Array] = {}
    if "ddphi" in outputs:
        out["ddphi"] = ddphi
    if "delta" in outputs or "slider" in outputs:
        kin = kinematics(mech, phi, dphi, ddphi)
        if "delta" in outputs:
            out["delta"] = kin.delta
        if "slider" in outputs:
            out.update(x_s=kin.x_s, v_s=kin.v_s, a_s=kin.a_s)
    if "energy" in outputs:
        out["energy"] = energy(mech, phi, dphi)
    if "loads" in outputs:
        out.update(P=load(ts), tau=torque(ts))
    if "reactions" in outputs:
        rx = jax.vmap(lambda t, p, d, a: reactions(mech, p, d, a, t, load, torque))(
            ts, phi, dphi, ddphi)
        out.update(O_x=rx.O[:, 0], O_y=rx.O[:, 1], A_x=rx.A[:, 0], A_y=rx.A[:, 1],
                   B_x=rx.B[:, 0], B_y=rx.B[:, 1], N=rx.N, F=rx.F)
    return out


def _solve_impl(mech, load, torque, force, y0, ts, rtol, atol, *, solver, max_steps, adjoint,
                structure, outputs, throw, mode="checked"):
    # `mode`: "checked" (traced values, validated with `eqx.error_if`), "unchecked"
    # (traced values, no callbacks: `simulate(checks=False)`) or "host" (concrete values,
    # validated on the host before the call). A static argument, so each has its own
    # compiled programs.
    import diffrax

    if mode == "checked":
        mech = mech.checked()
        y0 = eqx.error_if(y0, ~jnp.all(jnp.isfinite(y0)),
                          "initial state (phi0, dphi0) must be finite")
    crank = CrankField(mech, load, torque, structure, force)
    step_ts, jump_ts = nonsmooth_times(load, torque)
    # The solvers step the packed form, `crank.packed()`: the parameter parts formed once,
    # outside the step loop, in one buffer (see model/coefficients.py).
    (phi, dphi), result, steps = solve(
        crank, solver, ts, (y0[0], y0[1]), rtol=rtol, atol=atol, max_steps=max_steps,
        adjoint=adjoint, throw=throw, prepare=CrankField.packed,
        rate=lambda: jax.lax.stop_gradient(_rate(crank)),  # a first guess (uniform.py)
        step_ts=step_ts, jump_ts=jump_ts, checks=mode == "checked")
    if not throw:
        # A failed solve leaves inf after the failure time. No NaN or inf leaves simulate:
        # those samples hold the last state reached, and `result` says the solve failed.
        good = jnp.isfinite(phi) & jnp.isfinite(dphi)
        last = jax.lax.cummax(jnp.where(good, jnp.arange(ts.shape[0]), 0))
        phi, dphi = phi[last], dphi[last]
        result = diffrax.RESULTS.where(
            (result == diffrax.RESULTS.successful) & ~jnp.all(good),
            diffrax.RESULTS.nonfinite, result)
    extras = _derived(mech, load, torque, ts, phi, dphi, outputs, force)
    return Trajectory(ts, phi, dphi, extras, result, steps)


@eqx.filter_jit
def solve_trajectory(mech, load, torque, force, y0, ts, rtol, atol, *, solver, max_steps,
                     adjoint, structure, outputs, throw, mode="checked") -> Trajectory:
    """The solve `simulate` runs, compiled once per static choice (`solver`, `max_steps`,
    `adjoint`, `structure`, `outputs`, `throw`, `mode`; see `_solve_impl`)."""
    return _solve_impl(mech, load, torque, force, y0, ts, rtol, atol, solver=solver,
                       max_steps=max_steps, adjoint=adjoint, structure=structure,
                       outputs=outputs, throw=throw, mode=mode)


def solve_crank(mech, load, torque, force, y0, ts, rtol, atol, *, solver: AbstractSolver,
                max_steps: int, adjoint: AbstractAdjoint, structure: Structure) -> Trajectory:
    """The solve `simulate` runs, for a caller tracing its own program (the fit's
    residuals and Jacobians): the same entry ([`solve`][]), field and derivative rules, with
    no runtime checks (invalid values fail the solve) and never raising (a failure is in
    `result`, and the samples after it hold the last state reached).

    **Arguments:** as [`simulate`][crank_jax.simulate]'s, with `solver` the object the
    policy resolved (`policy.resolve_solver`), `y0` (2,) `(phi0, dphi0)`, `structure`
    given, and `load`, `torque` loads (not numbers).

    **Returns:** a [`Trajectory`][] without extras. Its program holds no host callback
    for the fused solvers (`"dopri8-adaptive"`, `"dopri8-uniform"`) in forward mode, so
    JAX's persistent cache and the program store keep it. So do diffrax's explicit
    solvers' programs in forward mode, which save at `ts` without diffrax's `SaveAt(ts)`
    check (`saves.py`); in reverse mode they hold that check, and an implicit solver's
    forward mode holds lineax's check in optimistix's implicit JVP: such programs run
    unstored (experiments/diffrax_callbacks.py).
    """
    return _solve_impl(mech, load, torque, force, y0, ts, rtol, atol, solver=solver,
                       max_steps=max_steps, adjoint=adjoint, structure=structure,
                       outputs=(), throw=False, mode="unchecked")


def succeeded(result) -> bool:
    """Whether a concrete `diffrax.RESULTS` item is `successful`, read on the host (an
    equinox comparison is an eager device op)."""
    import diffrax

    return bool(np.asarray(result == diffrax.RESULTS.successful))


def warn_if_float32() -> None:
    if not jax.config.jax_enable_x64:
        _warn_float32_once()


@functools.cache
def _warn_float32_once() -> None:
    # Once per process (the cache is the flag): the advice does not change between calls.
    warnings.warn(
        "crank_jax: float64 is off (jax_enable_x64 is False), so simulations run in "
        "float32, about 7 significant digits. Tolerances below rtol ~ 1e-6 cannot be met: "
        "at the default rtol=1e-8 the solver takes ~20x more steps or stops at max_steps, "
        "and energy drifts ~1e-6 relative even at c = 0. Call "
        "jax.config.update('jax_enable_x64', True) at start-up, before creating arrays "
        "(or pass rtol >= 1e-6 and accept float32 accuracy).",
        stacklevel=4,
    )
