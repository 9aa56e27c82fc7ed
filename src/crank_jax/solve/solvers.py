"""Solvers as objects, and [`solve`][], the one entry point that steps any vector field.

A solver is an `eqx.Module`, as diffrax's are: it holds its settings, not the problem, and
its `run` method steps a vector field `field(t, y, args)` over the save times. The policy
(`policy.py`) returns one, made once per name by the table (`names.py`); `simulate`, the
fit's residuals and Jacobians (`solve_crank`) and sweeps (through `simulate`) all reach
it through [`solve`][], so a solver is added by writing its class and one table row, not
a branch in a core.

- [`AdaptiveDopri8`][], `"dopri8-adaptive"`: adaptive fused Dopri8 steps with dense output
  (`adaptive.py`), a `vmap`-ed batch in lockstep (`lockstep.py`); forward mode by the
  variational equation (`variational.py`), reverse mode by the discrete adjoint
  (`adjoint.py`).
- [`UniformDopri8`][], `"dopri8-uniform"`: equal fused steps per save interval
  (`uniform.py`), each batch member on its own; JAX differentiates its loops.
- [`Diffrax`][]: any of diffrax's solvers through `diffrax.diffeqsolve`, with diffrax's
  step control, clipped at the field's kinks, and diffrax's adjoints.
"""

from __future__ import annotations

import abc
import dataclasses
from collections.abc import Callable
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .adaptive import AdaptiveERK
from .adjoints import ADJOINTS, AbstractAdjoint, DiscreteAdjoint, as_adjoint
from .controller import PIDController
from .erk import FusedERK, dopri8
from .lockstep import adaptive_solve
from .uniform import UniformERK, solve_uniform
from .variational import flatten_state

__all__ = ["solve", "Solution", "AbstractSolver", "AdaptiveDopri8", "UniformDopri8",
           "Diffrax", "ADJOINTS"]


class Solution(NamedTuple):
    """What a solve returns.

    - `ys`: the state at the save times: a pytree like `y0`, each leaf with a leading
      axis n (the number of save times).
    - `result`: a `diffrax.RESULTS`; `successful` when the solve reached `ts[-1]`. With
      `throw=False` a failed solve's samples after the failure are inf or NaN.
    - `num_steps`: the steps taken, accepted and rejected (int scalar)."""

    ys: Any
    result: Any
    num_steps: Array


def _same(field):
    return field


class _Bound(eqx.Module):
    """`field` with its `args` bound, so that the fused solvers see one pytree whose
    array leaves (the field's and the args') are all differentiable parameters."""

    field: Callable
    args: Any

    def __call__(self, t, y, args=None):
        return self.field(t, y, self.args)


def _bind(field, args, prepare):
    """`(field, prepare)` for a solver that steps `field(t, y)` alone: `args` bound into
    the field (and `prepare` applied inside the binding), or both unchanged when there
    are no args."""
    if args is None:
        return field, prepare
    return _Bound(field, args), lambda b: _Bound(prepare(b.field), b.args)


class AbstractSolver(eqx.Module):
    """A solver: [`solve`][] calls its `run`. Subclass it and add one row to `names.py`'s
    table to give a new solver a name."""

    #: Whether the solver is implicit (stable on any decaying mode): `policy.py` then
    #: does not hold it to an explicit solver's stability limit.
    implicit: ClassVar[bool] = False

    @abc.abstractmethod
    def run(self, field, ts, y0, args, *, rtol, atol, max_steps: int, adjoint: AbstractAdjoint,
            throw: bool, prepare: Callable, rate, step_ts, jump_ts) -> Solution:
        """Step `field` from `y0` at `ts[0]` over `ts`: [`solve`][]'s arguments, with
        `prepare` a function (identity by default)."""

    def unchecked(self) -> AbstractSolver:
        """This solver with no runtime check of its inputs in its program, for a caller
        that has checked them ([`solve`][]`(checks=False)`). The solvers that hold none
        return themselves (the default)."""
        return self


class AdaptiveDopri8(AdaptiveERK, AbstractSolver):
    """`"dopri8-adaptive"`: adaptive fused Dopri8 steps with dense output (`adaptive.py`).
    Error per step as diffrax's `PIDController` measures it; a `jax.vmap`-ed batch steps
    in one loop, each member with its own steps (`lockstep.py`). Forward mode steps the
    variational equation beside the solution (`variational.py`: a Jacobian costs a few
    solves); reverse mode is the discrete adjoint of the steps (`adjoint.py`). Kinks in
    the field (`step_ts`, `jump_ts`) are not stepped to: the policy sends sampled loads to
    [`Diffrax`][].

    **Field:** `loop_stages` (static, default False): forward mode's variational solve
    evaluates its stages in a loop (`FusedERK.rolled`) instead of unrolled. Its field, a
    reverse pass per state component, is costly to trace and compile unrolled: in a loop
    `jax.jacfwd` compiles in about half the time and runs a little longer. The fit uses
    it (`identify.problem.pick_solver`): its first fit in a process takes about half as
    long, its later fits no longer (experiments/fit_speed.py,
    experiments/fit_solver_tradeoff.py; docs/benchmarks/design-figures.md).

    **Fields:** `erk`, the method, a [`FusedERK`][crank_jax.solve.erk.FusedERK]: Dopri8,
    `erk.dopri8()` (its dense output and adjoint are Dopri8's); `controller`, the
    step-size law, a [`PIDController`][crank_jax.solve.controller.PIDController] (default:
    an integral controller, as diffrax's default). The tolerances come with each solve.
    Its step is [`AdaptiveERK`][crank_jax.solve.adaptive.AdaptiveERK]'s `init` and
    `step`, which `solve_adaptive`'s one loop drives (diffrax's solver shape)."""

    loop_stages: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        # The dense output (dense_output.dopri8_dense) and the adjoint are Dopri8's: another
        # tableau would give wrong samples, not an error.
        if not isinstance(self.erk, FusedERK) or self.erk.tableau != dopri8().tableau:
            raise ValueError("AdaptiveDopri8: erk must be Dopri8's tableau, "
                             "crank_jax.solve.erk.dopri8() (its dense output is Dopri8's)")
        if not isinstance(self.controller, PIDController):
            raise TypeError("AdaptiveDopri8: controller must be a "
                            f"crank_jax.solve.controller.PIDController, got {self.controller!r}")

    def with_loop_stages(self) -> AdaptiveDopri8:
        """This solver with `loop_stages=True`."""
        return dataclasses.replace(self, loop_stages=True)

    def run(self, field, ts, y0, args, *, rtol, atol, max_steps, adjoint, throw, prepare,
            rate=None, step_ts=None, jump_ts=None):
        import diffrax

        field, prepare = _bind(field, args, prepare)

        def steps(fld, y, ts_, r, a, error_size):
            # `error_size` is set for the variational solve only.
            solver = (dataclasses.replace(self, erk=dataclasses.replace(self.erk, rolled=True))
                      if error_size is not None and self.loop_stages else self)
            return adaptive_solve(fld, y, ts_, r, a, max_steps=max_steps, adjoint=adjoint,
                                  error_size=error_size, solver=solver)

        # The adjoint's rule: forward mode steps the variational equation (adjoints.py).
        ys, result, num = adjoint.adaptive(steps, field, prepare, y0, ts, rtol, atol)
        if throw:
            ys = result.error_if(ys, result != diffrax.RESULTS.successful)
        return Solution(ys, result, num)


class UniformDopri8(UniformERK, AbstractSolver):
    """`"dopri8-uniform"`: `m_i` equal fused Dopri8 steps in save interval i, chosen from a
    summed error estimate and checked a posteriori (`uniform.py`). Needs uniform save
    times; each member of a `vmap`-ed batch takes its own steps, so a batch's results do
    not depend on its other members (sweeps).

    JAX differentiates its loops itself, the while-loop kind chosen as the matching
    diffrax adjoint. Its own derivative rules (a variational equation in forward mode, a
    plain-field backward pass in reverse mode) were removed: sweeps, its reason
    to exist, never differentiate, and diffrax's Dopri8 was faster than them
    (docs/benchmarks/design-figures.md). To differentiate, use `"dopri8-adaptive"` or
    `"dopri8"`.

    **Field:** `erk`, the method, a [`FusedERK`][crank_jax.solve.erk.FusedERK] (default
    Dopri8, `erk.dopri8()`). Its step is [`UniformERK`][crank_jax.solve.uniform.UniformERK]'s
    `init` and `step` (one save interval), which `solve_uniform`'s passes drive (diffrax's
    solver shape)."""

    def __check_init__(self):
        if not isinstance(self.erk, FusedERK):
            raise TypeError("UniformDopri8: erk must be a crank_jax.solve.erk.FusedERK, "
                            f"got {self.erk!r}")

    def run(self, field, ts, y0, args, *, rtol, atol, max_steps, adjoint, throw, prepare,
            rate=None, step_ts=None, jump_ts=None):
        import diffrax

        kind = adjoint.loop_kind
        guess = rate() if callable(rate) else (0.0 if rate is None else rate)
        ys, result, num = solve_uniform(prepare(field), y0, ts, rtol, atol, args,
                                        rate=guess, max_steps=max_steps, kind=kind,
                                        solver=self)
        if throw:
            ys = result.error_if(ys, result != diffrax.RESULTS.successful)
        return Solution(ys, result, num)


def _flat_state(y0):
    """`(flat y0, to_tree, to_flat)`: diffrax steps one flat array (its per-leaf costs
    add up for a state of scalars). A state of scalar leaves (the crank's `(phi, dphi)`)
    is stacked and indexed, other pytrees ravelled."""
    components, rebuild, size = flatten_state(y0)
    if all(jnp.ndim(x) == 0 for x in jax.tree_util.tree_leaves(y0)):
        def to_tree(y):
            return rebuild([y[..., i] for i in range(size)])

        def to_flat(tree):
            return jnp.stack(components(tree), axis=-1)

        return to_flat(y0), to_tree, to_flat
    flat, unravel = jax.flatten_util.ravel_pytree(y0)

    def to_tree(y):  # (N,) or, the saved states, (n, N)
        return unravel(y) if y.ndim == 1 else jax.vmap(unravel)(y)

    return flat, to_tree, lambda tree: jax.flatten_util.ravel_pytree(tree)[0]


class Diffrax(AbstractSolver):
    """One of diffrax's solvers through `diffrax.diffeqsolve`: `PIDController(rtol, atol)`
    step control, clipped to end steps at the field's kinks (`step_ts`) and to restart
    after its jumps (`jump_ts`), `SaveAt(ts=ts)`, and diffrax's adjoints
    (`RecursiveCheckpointAdjoint`, `ForwardMode`, `DirectAdjoint`).

    With `checks=False` (`unchecked`, as [`solve`][]`(checks=False)` makes it), an
    explicit solver in forward mode saves at `ts` inside its steps instead (`saves.py`):
    the same numbers, and no `SaveAt(ts)` check of the save times, a host callback that
    kept the fit's programs out of the program store.

    **Fields:** `solver`, a diffrax solver instance, e.g. `diffrax.Kvaerno5()`; `checks`:
    whether diffrax checks the save times in the program (static)."""

    solver: Any = eqx.field(static=True)
    checks: bool = eqx.field(static=True, default=True)

    def unchecked(self) -> Diffrax:
        """This solver with `checks=False`: the caller has checked the save times."""
        return dataclasses.replace(self, checks=False)

    @property
    def implicit(self) -> bool:  # type: ignore[override]
        import diffrax

        return isinstance(self.solver, diffrax.AbstractImplicitSolver)

    def run(self, field, ts, y0, args, *, rtol, atol, max_steps, adjoint, throw, prepare,
            rate=None, step_ts=None, jump_ts=None):
        import diffrax

        adj = adjoint.diffrax_adjoint()
        flat0, to_tree, to_flat = _flat_state(y0)

        def flat_field(t, y, a):
            fld, inner = a
            return to_flat(fld(t, to_tree(y), inner))

        controller = diffrax.PIDController(rtol=rtol, atol=atol)
        if step_ts is not None or jump_ts is not None:
            # A step across a kink (or a jump in a higher derivative) loses accuracy that
            # the error estimate does not see in time, so steps end exactly there; across
            # a jump in the field itself diffrax steps to just before it and restarts.
            controller = diffrax.ClipStepSizeController(controller, step_ts=step_ts,
                                                        jump_ts=jump_ts)
        own_saves = not self.checks and adjoint.forward_only and not self.implicit
        if own_saves:  # no `SaveAt(ts)` check in the program (see saves.py)
            from .saves import saved, saving

            solver, read = saving(self.solver, ts), saved
            saveat = diffrax.SaveAt(t1=True, solver_state=True)
        else:
            solver, saveat, read = self.solver, diffrax.SaveAt(ts=ts), _saved_at_ts
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(flat_field), solver, t0=ts[0], t1=ts[-1], dt0=None,
            y0=flat0, args=(prepare(field), args), saveat=saveat,
            stepsize_controller=controller, max_steps=max_steps, adjoint=adj, throw=throw)
        steps = sol.stats["num_steps"] + sol.stats.get("num_rejected_steps", 0)
        return Solution(to_tree(read(sol)), sol.result, steps)


def _saved_at_ts(sol):
    return sol.ys


def solve(field: Callable, solver: AbstractSolver, ts: ArrayLike, y0, args=None, *,
          rtol: ArrayLike = 1e-8, atol: ArrayLike = 1e-10, max_steps: int = 200_000,
          adjoint: AbstractAdjoint | str = DiscreteAdjoint(), throw: bool = True,
          prepare: Callable | None = None,
          rate: ArrayLike | Callable | None = None, step_ts: ArrayLike | None = None,
          jump_ts: ArrayLike | None = None, checks: bool = True) -> Solution:
    """Integrate `dy/dt = field(t, y, args)` from `y0` at `ts[0]`, saving at `ts`.

    **Arguments:**

    - `field`: the vector field, `field(t, y, args) -> dy/dt` (a pytree like `y`): a
      function or a callable pytree (an `eqx.Module`), whose array leaves are then
      parameters that `jax.vmap`, `jax.jvp` and `jax.grad` see.
    - `solver`: an [`AbstractSolver`][], e.g. `crank_jax.solve.solver_named("dopri8-adaptive")`
      or `crank_jax.Diffrax(diffrax.Tsit5())`.
    - `ts`: (n,) strictly increasing save times (s for the crank), n >= 2; `"dopri8-uniform"`
      needs them equally spaced.
    - `y0`: the state at `ts[0]`: a pytree of arrays (small: the fused solvers unroll
      their stages over its components).
    - `args`: passed to `field`; its array leaves are differentiable too.
    - `rtol`, `atol`: tolerances of the local error, scaled as diffrax's `PIDController`
      (`"dopri8-uniform"`: of its summed error estimate, see `uniform.py`).
    - `max_steps`: the step budget (static); exceeding it fails the solve.
    - `adjoint`: how the solve is differentiated, an adjoint object (`adjoints.py`):
      [`DiscreteAdjoint`][] for `jax.grad` (default; its `backward` program is the
      caller's choice: `"loop"` where XLA:CPU runs with the CPU flags),
      [`ForwardSensitivities`][] for `jax.jvp`/`jax.jacfwd`, [`DirectAdjoint`][] for
      both. A name of [`ADJOINTS`][] is a shorthand for them (`"reverse"`:
      `DiscreteAdjoint()`).
    - `throw`: raise on a failed solve (an `eqx.error_if`), else report it in `result`.
    - `prepare`: `prepare(field)`, the same field in the form to step, formed once
      outside the step loop (the crank's `CrankField.packed`); forward mode of
      `"dopri8-adaptive"` differentiates through it. Default: the field itself.
    - `rate`: a rate scale of the motion, 1/s, or a function of no arguments returning
      one (called only by solvers that use it): the first guess of `"dopri8-uniform"`.
    - `step_ts`, `jump_ts`: (k,) times where the field has a kink or a jump, which
      diffrax's solvers step to exactly (the fused solvers do not).
    - `checks`: `False` when the caller has checked `ts` (strictly increasing): the
      program then holds no runtime check of them (a host callback, which JAX's
      persistent cache and the program store refuse), see `AbstractSolver.unchecked`.

    **Returns:** a [`Solution`][] `(ys, result, num_steps)`.

    Not jitted itself (as any JAX function, call it inside `jax.jit`); works under
    `jax.vmap`, `jax.grad` (`DiscreteAdjoint`) and `jax.jacfwd` (`ForwardSensitivities`).
    """
    adjoint = as_adjoint(adjoint)
    if not isinstance(solver, AbstractSolver):
        raise TypeError(f"solver must be a crank_jax solver object (see "
                        f"crank_jax.solve.solver_named), got {solver!r}")
    if not checks:
        solver = solver.unchecked()
    return solver.run(field, ts, y0, args, rtol=rtol, atol=atol, max_steps=int(max_steps),
                      adjoint=adjoint, throw=throw,
                      prepare=_same if prepare is None else prepare, rate=rate,
                      step_ts=step_ts, jump_ts=jump_ts)
