"""Time integration of the equation of motion: `simulate`, `Trajectory`, derived outputs.

`simulate` builds the vector field, a [`CrankField`][], and hands it with the policy's
solver object to [`solve`][] (`solvers.py`), the one entry point, which knows nothing of
the mechanism. It is one of the two modules of `solve/` that import the model: it builds
the field, checks the inputs, and computes the derived outputs; `policy.py` linearises
for the stiffness test.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..lazy import lazy_import
from ..model.dynamics import CrankField, Structure, acceleration, energy
from ..model.geometry import kinematics
from ..model.linear import linearize
from ..model.loads import AbstractLoad, as_load, nonsmooth_times
from ..model.newton_euler import reactions
from ..model.params import SliderCrank
from ..persistent import PersistentProgram, enum_code, enum_name
from .policy import check_travel, host_plan, is_concrete
from .solvers import AbstractSolver, solve

diffrax = lazy_import("diffrax")  # imported on first use (see lazy.py)

__all__ = ["Trajectory", "simulate", "solve_crank", "OUTPUTS", "output_columns"]


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


_solve = eqx.filter_jit(_solve_impl)


def solve_crank(mech, load, torque, force, y0, ts, rtol, atol, *, solver: AbstractSolver,
                max_steps: int, adjoint: str, structure: Structure) -> Trajectory:
    """The solve `simulate` runs, for a caller tracing its own program (the fit's
    residuals and Jacobians): the same entry ([`solve`][]), field and derivative rules, with
    no runtime checks (invalid values fail the solve) and never raising (a failure is in
    `result`, and the samples after it hold the last state reached).

    **Arguments:** as [`simulate`][]'s, with `solver` the object the policy resolved
    (`policy.resolve_solver`), `y0` (2,) `(phi0, dphi0)`, `structure` given, and `load`,
    `torque` loads (not numbers).

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


def simulate(
    mech: SliderCrank,
    phi0: ArrayLike,
    dphi0: ArrayLike,
    ts: ArrayLike,
    *,
    load: AbstractLoad | ArrayLike | None = None,
    torque: AbstractLoad | ArrayLike | None = None,
    solver: str | AbstractSolver = "auto",
    rtol: ArrayLike = 1e-8,
    atol: ArrayLike = 1e-10,
    max_steps: int = 200_000,
    outputs: Sequence[str] = (),
    adjoint: str = "reverse",
    structure: Structure | None = None,
    throw: bool = True,
    force: Callable | None = None,
    checks: bool = True,
) -> Trajectory:
    """Integrate `M(phi) phi'' + K(phi) phi'^2 = q(phi, phi', t)` from `ts[0]` to `ts[-1]`.

    **Arguments:**

    - `mech`: the [`SliderCrank`][] parameters.
    - `phi0`, `dphi0`: the state at `ts[0]` (rad, rad/s); `ts[0]` need not be 0.
    - `ts`: (n,) strictly increasing save times, s, n >= 2.
    - `load`: slider force P(t), N along -x: a load, a number (constant) or `None`.
    - `torque`: crank torque tau(t), N*m about +z, likewise.
    - `solver`: one of [`SOLVERS`][], or a solver object (`crank_jax.solve.solver_named`,
      `crank_jax.Diffrax`); `"auto"` is `"kvaerno5"` for a stiff shaft (see
      [`choose_solver`][]), else `"dopri8-adaptive"` (adaptive fused Dopri8 with dense
      output; a `vmap`-ed batch steps in lockstep) unless a load is sampled (then diffrax's
      Dopri8 or Tsit5, whose steps end at the knots). See `solve/policy.py`.
    - `rtol`, `atol`: tolerances of the adaptive step-size controller.
    - `max_steps`: step budget; exceeding it raises (or sets `result` if `throw=False`).
    - `outputs`: derived outputs to add to `Trajectory.extras` (see [`OUTPUTS`][]); only
      these are computed.
    - `adjoint`: `"reverse"` (default; `jax.grad`), `"forward"` (`diffrax.ForwardMode`, for
      `jax.jacfwd` and Levenberg-Marquardt) or `"direct"` (both, slower). With
      `"dopri8-adaptive"`, `"forward"` steps the variational equation beside the solution
      (solve/variational.py): a column per parameter and initial-state component that has a
      tangent, so a Jacobian costs a few solves, and so does a single JVP through many
      parameters; `"direct"` carries JAX's tangents through the steps instead, cheaper for
      one direction through many parameters.
    - `structure`: the static set of terms; default `Structure.of(mech)`: the terms whose
      parameters are traced or nonzero.
    - `throw`: raise on a failed solve; with `False` the failure is in `result` and the
      samples after it hold the last state reached (never NaN or inf).
    - `force`: a generalised force of your own, `force(t, phi, dphi) -> N*m`, added to q:
      any pytree callable (an `equinox` MLP included), differentiable through the solve.
      The solver policy and the derived outputs see it; `energy` and `reactions` do not
      (they are the mechanism's own).
    - `checks`: validate traced values inside the program with `eqx.error_if` (a host
      callback). `False` leaves those checks out, for programs that must hold no host
      callback (JAX's persistent cache does not keep them; the fit's programs): invalid
      values then fail the solve (`result`) instead of raising. Concrete values are
      always checked on the host.

    **Returns:** a [`Trajectory`][].

    Works under `jax.jit`, `jax.vmap`, `jax.grad` and `jax.jacfwd`: called under
    `jax.jacfwd` or `jax.jvp`, the default `"reverse"` (a `custom_vjp`, which has no
    forward mode) runs as `"forward"`. A `jax.jit` between `jax.jacfwd` and this call
    hides the forward tangents from it: there pass `adjoint="forward"` yourself.
    """
    _warn_if_float32()
    if adjoint not in ("reverse", "forward", "direct"):
        raise ValueError(f"adjoint must be 'reverse', 'forward' or 'direct', got {adjoint!r}")
    output_columns(outputs)  # validates names
    load, torque = as_load(load), as_load(torque)
    dtype = jax.dtypes.canonicalize_dtype(jnp.float64)  # float32 without x64
    if not (isinstance(ts, jax.Array) and ts.dtype == dtype):
        ts = jnp.asarray(ts, dtype=dtype)
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"ts must be a 1-D array of at least 2 times, got shape {ts.shape}")
    for name, v in (("phi0", phi0), ("dphi0", dphi0), ("rtol", rtol), ("atol", atol)):
        if np.ndim(v) > 0:
            raise ValueError(f"{name} has shape {np.shape(v)}: simulate integrates one system; "
                             f"to run a batch, map over it with jax.vmap")
    plan = host_plan(mech, load, torque, ts, rtol, atol, solver, max_steps, throw, structure)
    if (plan.top is not None and is_concrete((phi0, dphi0))
            and np.isfinite(phi0) and np.isfinite(dphi0)):  # NaN: the finite check's
        check_travel(plan.lin, plan.top, phi0, dphi0, plan.span, int(max_steps))
    # Outside any transformation, check on the host and raise there: an `eqx.error_if` in
    # the program is a Python callback, and JAX's persistent compilation cache cannot
    # reuse a program with callbacks, so every process (every CLI call) would recompile.
    host = is_concrete((mech, load, torque, force, phi0, dphi0, ts, rtol, atol))
    if host:
        # NumPy on the host: each eager `jnp` call here cost ~50 us, a third of a fast
        # solve's fixed cost (the jitted solve takes them as inputs all the same).
        y0 = np.array([np.asarray(phi0), np.asarray(dphi0)], dtype=dtype)
        rtol_, atol_ = np.asarray(rtol, dtype), np.asarray(atol, dtype)
        if plan.invalid:
            raise eqx.EquinoxRuntimeError(plan.invalid)
        if not np.all(np.isfinite(y0)):
            raise eqx.EquinoxRuntimeError("initial state (phi0, dphi0) must be finite")
    else:
        y0 = jnp.stack([jnp.asarray(phi0, dtype), jnp.asarray(dphi0, dtype)])
        rtol_, atol_ = jnp.asarray(rtol, dtype), jnp.asarray(atol, dtype)
    args = (mech, load, torque, force, y0, ts, rtol_, atol_)
    # Concrete inputs take no derivative, so the adjoint only picks the program: forward
    # mode's, the same values (the adjoints differ in their backward passes), is the one
    # of diffrax's explicit solvers that saves inside its steps (saves.py) and so holds no
    # host callback, whose program the store keeps (a reverse-mode `SaveAt(ts)` checks
    # the save times in a callback, compiled again in every process).
    adjoint = "forward" if host else adjoint
    if adjoint == "reverse" and _forward_differentiated(args):
        # Under jax.jacfwd / jax.jvp: the reverse adjoint is a custom_vjp, which JAX cannot
        # differentiate forward ("can't apply forward-mode autodiff (jvp) to a custom_vjp
        # function"); forward mode gives the same derivatives of the same solution.
        adjoint = "forward"
    static = dict(solver=plan.solver, max_steps=int(max_steps), adjoint=adjoint,
                  structure=plan.structure, outputs=tuple(sorted(set(outputs))))
    traj = _program_solve(*args, **static) if host and force is None else None
    if traj is None:
        traj = _solve(*args, **static, throw=bool(throw) and not host,
                      mode="host" if host else ("checked" if checks else "unchecked"))
    if host and throw and not _succeeded(traj.result):
        raise eqx.EquinoxRuntimeError(diffrax.RESULTS[traj.result])
    return traj


def _forward_differentiated(tree) -> bool:
    """Whether a leaf of `tree` carries a forward-mode tangent (a `jax.jvp` tracer, as
    `jax.jacfwd` makes). Reverse mode (`jax.grad`, `jax.vjp`) traces with JAX's direct
    linearize (`LinearizeTracer`), which is not one; where a user turned it off
    (`jax_use_direct_linearize=False`), reverse mode traces through `jvp` too, and
    nothing is changed."""
    if not getattr(jax.config, "jax_use_direct_linearize", False):
        return False
    from jax.interpreters.ad import JVPTracer

    return any(isinstance(x, JVPTracer) for x in jax.tree_util.tree_leaves(tree))


# Outcomes of a stored solve, by index (names of `diffrax.RESULTS`): a stored program
# returns arrays only.
_RESULTS = ("successful", "max_steps_reached", "nonfinite", "singular", "breakdown",
            "dt_min_reached")


def _solve_flat(mech, load, torque, force, y0, ts, rtol, atol, solver, max_steps, adjoint,
                structure, outputs):
    traj = _solve(mech, load, torque, force, y0, ts, rtol, atol, solver=solver,
                  max_steps=max_steps, adjoint=adjoint, structure=structure,
                  outputs=outputs, throw=False, mode="host")
    code = enum_code(traj.result, diffrax.RESULTS, _RESULTS)
    extras = tuple(traj.extras[k] for k in sorted(traj.extras))
    return (traj.phi, traj.dphi, code, traj.num_steps) + extras


# Concrete calls (every CLI simulate, a fit's synthetic data) in a fresh process load this
# compiled program instead of tracing the solver again (see persistent.py).
_solve_program = PersistentProgram(_solve_flat, "simulate")


def _program_solve(mech, load, torque, force, y0, ts, rtol, atol, *, solver, max_steps,
                   adjoint, structure, outputs) -> Trajectory | None:
    """`_solve` in host mode through its [`PersistentProgram`][] (stored on disk, or in
    memory without a store), or None for an unexpected outcome (the caller then runs
    `_solve` itself)."""
    phi, dphi, code, steps, *extras = _solve_program(
        mech, load, torque, force, y0, ts, rtol, atol, solver, max_steps, adjoint,
        structure, outputs)
    result = enum_name(code, _RESULTS)
    if result is None:
        return None
    names = sorted(output_columns(outputs))
    return Trajectory(ts, phi, dphi, dict(zip(names, extras)),
                      getattr(diffrax.RESULTS, result), steps)


def _succeeded(result) -> bool:
    """Whether a concrete `diffrax.RESULTS` item is `successful`, read on the host (an
    equinox comparison is an eager device op)."""
    return bool(np.asarray(result == diffrax.RESULTS.successful))


def _warn_if_float32() -> None:
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
