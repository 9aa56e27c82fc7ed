"""The package's front door for a simulation: [`simulate`][crank_jax.simulate] and
[`linearize`][crank_jax.linearize] as a user calls them, with the runtime applied at this
edge around the pure core (`solve/trajectory.py`, `model/linear.py`):

- the host plan of a concrete call (its checks, the linearisation, the solver: the core's
  [`host_plan`][crank_jax.solve.policy.host_plan]) kept for repeated calls with the same
  inputs ([`IdentityMemo`][crank_jax.runtime.identity_memo.IdentityMemo]);
- concrete solves and linearisations through the program store
  ([`PersistentProgram`][crank_jax.runtime.persistent.PersistentProgram]): a fresh
  process (every CLI call) loads the compiled program instead of tracing it again.

Traced calls (under `jit`, `vmap`, `grad`) run the core as it is.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from .model.dynamics import Structure
from .model.linear import Linearization, linearize_tuple, mean_loads
from .model.linear import linearize as _model_linearize
from .model.loads import AbstractLoad, as_load
from .model.params import SliderCrank
from .runtime.identity_memo import IdentityMemo
from .runtime.persistent import PersistentProgram, enum_code, enum_name, fast_compile_on_cpu
from .runtime.xla_flags import backward_program
from .solve.adjoints import AbstractAdjoint, DiscreteAdjoint, as_adjoint
from .solve.policy import check_travel, host_plan, is_concrete
from .solve.solvers import AbstractSolver
from .solve.trajectory import (
    Trajectory,
    output_columns,
    solve_trajectory,
    succeeded,
    warn_if_float32,
)

__all__ = ["simulate", "linearize"]


def _diffrax_results():
    import diffrax

    return diffrax.RESULTS


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
    adjoint: str | AbstractAdjoint = "reverse",
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
    - `solver`: one of [`SOLVERS`][crank_jax.solve.policy.SOLVERS], or a solver object
      (`crank_jax.solve.solver_named`, `crank_jax.Diffrax`); `"auto"` is `"kvaerno5"` for
      a stiff shaft (see [`choose_solver`][crank_jax.solve.policy.choose_solver]), else
      `"dopri8-adaptive"` (adaptive fused Dopri8 with dense output; a `vmap`-ed batch
      steps in lockstep) unless a load is sampled (then diffrax's Dopri8 or Tsit5, whose
      steps end at the knots). See `solve/policy.py`.
    - `rtol`, `atol`: tolerances of the adaptive step-size controller.
    - `max_steps`: step budget; exceeding it raises (or sets `result` if `throw=False`).
    - `outputs`: derived outputs to add to `Trajectory.extras` (see
      [`OUTPUTS`][crank_jax.solve.trajectory.OUTPUTS]); only
      these are computed.
    - `adjoint`: how the solve is differentiated: an adjoint object
      (`crank_jax.solve.DiscreteAdjoint()`, `ForwardSensitivities()`, `DirectAdjoint()`)
      or its shorthand, resolved here once: `"reverse"` (default; `jax.grad`: a
      `DiscreteAdjoint` whose backward program suits this process's XLA flags),
      `"forward"` (`ForwardSensitivities`, for `jax.jacfwd` and Levenberg-Marquardt) or
      `"direct"` (`DirectAdjoint`: both, slower). With
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
    forward mode) runs as `"forward"`, and so does a `DiscreteAdjoint`. A `jax.jit`
    between `jax.jacfwd` and this call hides the forward tangents from it: there pass
    `adjoint="forward"` yourself.
    """

    warn_if_float32()
    shorthand = isinstance(adjoint, str)
    adjoint = as_adjoint(adjoint)  # checked here; the shorthand's backward program below
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
    plan = _host_plan(mech, load, torque, ts, rtol, atol, solver, max_steps, throw, structure)
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
    adjoint = _adjoint_for(adjoint, shorthand, host,
                           (mech, load, torque, force, y0, ts, rtol_, atol_))
    static = dict(solver=plan.solver, max_steps=int(max_steps), adjoint=adjoint,
                  structure=plan.structure, outputs=tuple(sorted(set(outputs))))
    traj = (_program_solve(mech, load, torque, force, y0, ts, rtol_, atol_, **static)
            if host and force is None else None)
    if traj is None:
        traj = solve_trajectory(mech, load, torque, force, y0, ts, rtol_, atol_, **static,
                                throw=bool(throw) and not host,
                                mode="host" if host else ("checked" if checks else "unchecked"))
    if host and throw and not succeeded(traj.result):
        raise eqx.EquinoxRuntimeError(_diffrax_results()[traj.result])
    return traj


def _adjoint_for(adjoint: AbstractAdjoint, shorthand: bool, host: bool, inputs
                 ) -> AbstractAdjoint:
    """The adjoint `simulate` solves with: the caller's, except where the inputs say
    otherwise (`inputs`: the solve's arguments, to see forward-mode tracers)."""
    # Concrete inputs take no derivative, so the adjoint only picks the program: forward
    # mode's, the same values (the adjoints differ in their backward passes), is the one
    # of diffrax's explicit solvers that saves inside its steps (saves.py) and so holds no
    # host callback, whose program the store keeps (a reverse-mode `SaveAt(ts)` checks
    # the save times in a callback, compiled again in every process).
    if host:
        adjoint = as_adjoint("forward")
    elif shorthand and isinstance(adjoint, DiscreteAdjoint):
        # `"reverse"`: the backward program that suits this process's XLA flags, read here
        # at the edge (the core reads none), on traced calls only (~10 us).
        adjoint = as_adjoint("reverse", backward=backward_program())
    if isinstance(adjoint, DiscreteAdjoint) and _forward_differentiated(inputs):
        # Under jax.jacfwd / jax.jvp: the reverse adjoint is a custom_vjp, which JAX cannot
        # differentiate forward ("can't apply forward-mode autodiff (jvp) to a custom_vjp
        # function"); forward mode gives the same derivatives of the same solution.
        adjoint = as_adjoint("forward")
    return adjoint


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

    traj = solve_trajectory(mech, load, torque, force, y0, ts, rtol, atol, solver=solver,
                  max_steps=max_steps, adjoint=adjoint, structure=structure,
                  outputs=outputs, throw=False, mode="host")
    code = enum_code(traj.result, _diffrax_results(), _RESULTS)
    extras = tuple(traj.extras[k] for k in sorted(traj.extras))
    return (traj.phi, traj.dphi, code, traj.num_steps) + extras


# Concrete calls (every CLI simulate, a fit's synthetic data) in a fresh process load this
# compiled program instead of tracing the solver again (see runtime/persistent.py).
_solve_program = PersistentProgram(_solve_flat, "simulate")


def _program_solve(mech, load, torque, force, y0, ts, rtol, atol, *, solver, max_steps,
                   adjoint, structure, outputs) -> Trajectory | None:
    """`solve_trajectory` in host mode through its [`PersistentProgram`][] (stored on disk, or in
    memory without a store), or None for an unexpected outcome (the caller then runs
    `solve_trajectory` itself)."""

    phi, dphi, code, steps, *extras = _solve_program(
        mech, load, torque, force, y0, ts, rtol, atol, solver, max_steps, adjoint,
        structure, outputs)
    result = enum_name(code, _RESULTS)
    if result is None:
        return None
    names = sorted(output_columns(outputs))
    return Trajectory(ts, phi, dphi, dict(zip(names, extras)),
                      getattr(_diffrax_results(), result), steps)


# --- the linearisation, stored ---------------------------------------------------------

# Concrete calls (the solver policy's, before every concrete solve; a fit's start) in a
# fresh CLI process: the stored program skips tracing the Newton loop (0.1-0.3 s). Its
# compile with XLA's older emitters took 0.31 s instead of 0.62-0.71 s, the same bits on
# 960 mechanisms of the four preset scenes with and without loads, under the defaults and
# the CPU flags (tests/test_compile_options.py checks a sample).
_linearize_program = PersistentProgram(linearize_tuple, "linearize", fast_compile_on_cpu)


def linearize(mech: SliderCrank, load: AbstractLoad | None = None,
              torque: AbstractLoad | None = None) -> Linearization:
    """Linearise the equation of motion about its static equilibrium (loads at their means).

    **Arguments:** `mech`; `load`, the slider force P; `torque`, the crank torque tau
    (their `mean()`s set the equilibrium; P's also enters xi).

    **Returns:** a [`Linearization`][crank_jax.model.linear.Linearization]; every field has
    the shape of the parameters. Concrete inputs give concrete outputs even inside a
    caller's `jit` (the solver policy reads them on the host to choose a solver), through
    the program store; traced inputs run the model's own
    [`linearize`][crank_jax.model.linear.linearize].
    """
    loads = mean_loads(load, torque)
    leaves = jax.tree_util.tree_leaves((mech, loads))
    if not any(isinstance(x, jax.core.Tracer) for x in leaves):
        with jax.ensure_compile_time_eval():
            return Linearization(*_linearize_program(mech, loads))
    return _model_linearize(mech, load, torque)


# --- the host plan, kept ---------------------------------------------------------------

# Host plans of the last few concrete calls, oldest first: a concrete call with the inputs
# of one of them (the same mechanism, loads, save times and tolerances; any initial state)
# skips those checks and the linearisation, ~0.5 ms of a ~2 ms lab-rig solve (measured on
# a 2-core VM; 0.15 ms of it the linearisation, the rest NumPy on 0-d arrays and equinox
# attribute reads). A check that raised keeps no plan; a failed parameter check is kept as
# its message, raised again by every such call.
_PLANS = IdentityMemo(kept=8)
# A plan holds references to its save times (so that their `id` stays theirs): only for
# these many samples or fewer (8 plans of 0.8 MB at most).
_PLAN_MAX_SAMPLES = 100_000


def _host_plan(mech, load, torque, ts, rtol, atol, solver, max_steps, throw, structure):
    """The core's `host_plan`, kept in `_PLANS` where every input is immutable."""
    key = (None if ts.shape[0] > _PLAN_MAX_SAMPLES else IdentityMemo.key(
        (mech, load, torque, ts, rtol, atol), solver, int(max_steps), bool(throw), structure))
    return _PLANS.get(key, lambda: host_plan(mech, load, torque, ts, rtol, atol, solver,
                                             max_steps, throw, structure, linearize=linearize))
