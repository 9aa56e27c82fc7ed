"""`"dopri8-adaptive"` under JAX's transformations: a `jax.vmap`-ed batch steps in lockstep.

A `vmap` of an adaptive solve already runs in lockstep (the loop runs until its slowest
member is done), but each member keeps its own save position, so every output update
becomes a batched scatter and every carry a select: several times slower per trajectory
than the batched solver of `solve_adaptive`, whose members share the loop and the window
of save times being written (docs/benchmarks/design-figures.md; the batch throughput
table of docs/benchmarks/performance.md, experiments/bench_throughput.py).
`jax.custom_batching.custom_vmap` gives that rule to `jax.vmap`: mapped over parameters,
initial states, tolerances or save times, the members' fields are evaluated side by side.
Members with their own save times (a fit's multiple-shooting segments, records sampled
at other instants) write their own samples at a shared index of save time: the window
moves on when every member has passed its own. Before, they fell back to a plain `vmap`
of one member's solve, whose batching JAX traced through the whole solver: most of a
cold fit's trace of its multiple-shooting Jacobian (docs/benchmarks/design-figures.md).

Every member gets its own answer: each has its own time, step size, accept/reject
decisions, step budget and outcome (`solve_adaptive`, `batched=True`), so a member that
needs tiny steps or runs out of budget changes neither the others' results nor their
statuses (a single shared step size, as the batch once had, let one stiff member fail the
whole batch). A member that is done with the current save window, or out of budget,
waits, frozen, while the others step; the window moves on when every member still
stepping has passed it. What that costs on a uniform batch:
experiments/bench_batch_isolation.py. On the CPU a batch of more than `CHUNK` members
steps in groups of `CHUNK`, one group after another (see `CHUNK`); where the program made
several CPU devices (`jax_num_cpu_devices`), the groups are spread over them, one core
each (`_spread`), with the same results.

Differentiation: forward mode (`jax.jvp`, `jax.jacfwd`; `adjoint="forward"`) goes through
the solve along the chosen steps (`custom_vmap` has a JVP rule). Reverse mode
(`adjoint="reverse"`) cannot go through a `custom_vmap` (JAX has no transpose for it), so
the solve carries a `custom_vjp` whose forward pass is one member's solve with a log of
its steps and whose backward pass is the discrete adjoint of those steps (adjoint.py):
the exact gradient of the computed solution, as forward mode's Jacobian is. Under
`jax.vmap` both are a plain `vmap` of one member's (each member its own steps). Before this
solver the backward pass differentiated a diffrax Dopri8 re-solve (many forward solves'
worth: the Reverse mode table of docs/benchmarks/performance.md).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_batching import custom_vmap

from ..model import trig
from . import adjoint as discrete
from .adaptive import outcome, solve_adaptive
from .erk import dopri8
from .library_api import result_code

__all__ = ["adaptive_solve", "repeats_of_the_end"]


def adaptive_solve(field, y0, ts, rtol, atol, *, max_steps: int, adjoint,
                   error_size: int | None = None, solver=None):
    """Solve with [`solve_adaptive`][] so that `jax.vmap` steps a batch in lockstep.

    **Arguments:** `field`, the vector field (a pytree; its array leaves may be traced or
    batched); `y0`, one member's state, a pytree of small arrays (the crank: `(phi,
    phi')`); `ts` (n,) save times; `rtol`, `atol` scalars; `max_steps`, the step budget;
    `adjoint`, an adjoint object (`adjoints.py`: `DiscreteAdjoint` for `jax.grad` by the
    discrete adjoint of adjoint.py); `solver`, the steps' method and step-size law (an
    `AdaptiveERK`, default `AdaptiveERK()`, Dopri8 with an integral controller; reverse
    mode takes Dopri8 only); `error_size`, the leading state components the step control
    sees (see `solve_adaptive`).

    **Returns:** `(ys, result, num_steps)`, as `solve_adaptive` (`ys` like `y0` with a
    leading axis n; `result` a `diffrax.RESULTS`); save times that repeat the last take
    its value ([`repeats_of_the_end`][]).
    """
    out = _adaptive(field, y0, ts, rtol, atol, max_steps, adjoint, error_size, solver)
    ys, code, steps = out
    ys = jax.tree_util.tree_map(lambda y: repeats_of_the_end(y, ts), ys)
    return (ys, *outcome(code.astype(jnp.int32), steps.astype(jnp.int32)))


def repeats_of_the_end(ys, ts):
    """`ys` (n, ...) with every save time equal to the last given the value at the first
    of them. The step loop stops when it reaches the last time, so it writes no repeat
    past its window: a fit pads its rows with repeats of the last time, and they cost no
    step. Outside the solve's derivative rules, so that each derivative sends a repeat's
    share to the first (the discrete adjoint sees the rows the loop wrote). Strictly
    increasing times give `ys` as it is."""
    at_end = ts >= ts[-1]
    first = jnp.argmax(at_end)
    return jnp.where(at_end.reshape((-1,) + (1,) * (ys.ndim - 1)), ys[first], ys)


def _side_by_side(rebuild, dyn, batched):
    """The field of a batch: each member's field (its leaves with a leading batch axis where
    `batched`) evaluated side by side, `(t, y) -> dy` with `y`'s leaves (B,). A `vmap` of
    the member's field, so that leaves of any shape batch (the packed coefficients, a
    tabulated load); on scalar leaves it is the same elementwise code. `t` (B,): each
    member's own time."""
    axes = [0 if b else None for b in batched]

    def field(t, y, args):
        return jax.vmap(lambda d, tt, yy: rebuild(d)(tt, yy, args),
                        in_axes=(axes, 0, 0))(dyn, t, y)

    return field


# Members per lockstep group on the CPU. A batch steps in groups of this many, one after
# another. Why: the step's stage kernels
# read and write (n, 2) arrays, ~13 per step; at 10^4 members that working set (~2 MB)
# leaves the core's L2 cache, and each kernel then streams from memory. Measured on
# 10^4 lab rigs (rtol 1e-9, 2-core AMD EPYC): 516 us per trajectory in one group, 363 us
# in groups of 1024, 398 us in groups of 512 (the fixed cost per step shows). Two groups
# side by side in one program did not run concurrently on XLA:CPU (no gain), so the
# groups run in a `lax.map`. On accelerators the whole batch is one group: their
# kernels want every member at once.
CHUNK = 1024


def _split(dyn, batched):
    """The batched and the shared leaves of a field, as two lists."""
    return ([d for d, b in zip(dyn, batched) if b], [d for d, b in zip(dyn, batched) if not b])


def _join(dyn_b, dyn_c, batched):
    it_b, it_c = iter(dyn_b), iter(dyn_c)
    return [next(it_b) if b else next(it_c) for b in batched]


def _in_chunks(lockstep, n, dyn_b, y0, rtol, atol, ts, rtol_b, atol_b, ts_b, spread=True):
    """`lockstep(dyn_b, y0, rtol, atol, ts) -> (ys, code, steps)` over the batch of `n` in
    groups of `CHUNK` members (on the CPU; see `CHUNK`), the groups spread over the CPU
    devices when there are several (see [`_spread`][])."""
    if n <= CHUNK or jax.default_backend() != "cpu":
        return lockstep(dyn_b, y0, rtol, atol, ts)
    # This process's devices: in a multi-host run the caller's program is its own.
    devices = jax.local_devices()
    groups = -(-n // CHUNK)
    shards = len(devices) if spread and groups > 1 and _can_spread() else 1
    groups = -(-groups // shards) * shards
    m = groups * CHUNK

    def group(x):  # padded with copies of the last member (valid; dropped afterwards)
        x = jnp.concatenate([x, jnp.repeat(x[-1:], m - n, axis=0)]) if m > n else x
        return x.reshape((groups, CHUNK) + x.shape[1:])

    per_member = (dyn_b, y0, rtol if rtol_b else None, atol if atol_b else None,
                  ts if ts_b else None)

    def run(args):
        d, y, r, a, t = args
        return lockstep(d, y, rtol if r is None else r, atol if a is None else a,
                        ts if t is None else t)

    def run_groups(xs):
        return jax.lax.map(run, xs)

    if shards > 1:
        run_groups = _spread(run_groups, devices)
    out = run_groups(jax.tree_util.tree_map(group, per_member))
    return jax.tree_util.tree_map(lambda x: x.reshape((m,) + x.shape[2:])[:n], out)


def _can_spread() -> bool:
    """Whether the groups may be spread over devices here: not inside a `shard_map` (whose
    body already runs per device) or under a mesh the caller set (whose layout is theirs)."""
    mesh = jax.sharding.get_abstract_mesh()
    return mesh.empty


def _spread(run_groups, devices):
    """`run_groups` over the groups (leading axis) split evenly across `devices`, one part
    per device, all at once: XLA:CPU runs one program's loops one after another on one
    core, but each device of a multi-device CPU client is a thread of its own. Several CPU
    devices exist only where the program asked for them before JAX started
    (`jax.config.update("jax_num_cpu_devices", n)`, or `crank_jax.configure_cpu()`, which
    the `crank-jax` program calls), so JAX's default of one CPU device keeps this path off.
    Two CPU devices nearly halve a large batch's time per trajectory
    (docs/benchmarks/design-figures.md). The groups are independent, so nothing crosses
    devices until the results are gathered."""
    from jax.sharding import Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P

    mesh = Mesh(np.array(devices), ("lockstep",),
                axis_types=(jax.sharding.AxisType.Explicit,))
    spread = jax.shard_map(run_groups, mesh=mesh, in_specs=P("lockstep"),
                           out_specs=P("lockstep"), check_vma=False)

    def call(xs):
        xs = jax.tree_util.tree_map(
            lambda x: jax.reshard(x, NamedSharding(mesh, P("lockstep"))), xs)
        out = spread(xs)
        # Back to one copy everywhere, so the caller's program sees an ordinary array.
        return jax.tree_util.tree_map(lambda x: jax.reshard(x, NamedSharding(mesh, P())), out)

    return call


def _all_batched(out):
    """`custom_vmap`'s out_batched for outputs that all carry the batch axis."""
    return jax.tree_util.tree_map(lambda _: True, out)


def _as_float(x, like):
    return jnp.asarray(x).astype(like.dtype)


def _lockstep(rebuild, dyn_c, in_batched, max_steps, error_size, solver):
    """`lockstep(dyn_b, y0, rtol, atol, ts) -> (ys, code, steps)`: one group of a batch in one
    loop ([`solve_adaptive`][] batched), its members' batched field leaves `dyn_b` joined
    with the shared `dyn_c`; outputs with the batch axis first."""

    def arithmetic(dyn):
        # The field's sin, cos and 1/sqrt as arithmetic that XLA:CPU vectorises over the
        # members, where the field offers that choice (trig.py).
        return trig.traced_as(rebuild(dyn), trig.ARITHMETIC)

    def lockstep(dyn_b, y0, rtol, atol, ts):
        # Per-member tolerances scale that member's state (the last axis); per-member save
        # times, (B, n), are each member's own (`solve_adaptive`).
        rtol = rtol[:, None] if in_batched[3] else rtol
        atol = atol[:, None] if in_batched[4] else atol
        ys, result, steps = solve_adaptive(
            _side_by_side(arithmetic, _join(dyn_b, dyn_c, in_batched[0]), in_batched[0]),
            y0, ts, rtol, atol, max_steps=max_steps, batched=True,
            error_size=error_size, solver=solver)
        ys = jax.tree_util.tree_map(lambda v: jnp.moveaxis(v, 1, 0), ys)
        return ys, _as_float(result_code(result), ts), _as_float(steps, ts)

    return lockstep


def _adaptive(field, y0, ts, rtol, atol, max_steps, adjoint, error_size, solver):
    # The field's arrays as a flat list: `custom_vmap` cannot take the `None` leaves that
    # `eqx.partition` leaves (jax issue 9066).
    dyn_tree, static = eqx.partition(field, eqx.is_array)
    dyn, treedef = jax.tree_util.tree_flatten(dyn_tree)

    def rebuild(dyn):
        return eqx.combine(jax.tree_util.tree_unflatten(treedef, dyn), static)

    def single(dyn, y0, ts, rtol, atol):
        # Inputs at run time, as reverse mode's forward pass has them (adjoint.forward):
        # the same rounding, the same steps as the gradient's.
        dyn, y0, ts, rtol, atol = jax.lax.optimization_barrier((dyn, y0, ts, rtol, atol))
        ys, result, steps = solve_adaptive(rebuild(dyn), y0, ts, rtol, atol,
                                           max_steps=max_steps, error_size=error_size,
                                           solver=solver)
        # Every output a float: JAX's JVP of a `custom_vmap` takes float outputs only.
        return ys, _as_float(result_code(result), ts), _as_float(steps, ts)

    def batch_rule(axis_size, in_batched, dyn, y0, ts, rtol, atol, spread):
        if not any(jax.tree_util.tree_leaves(in_batched)):
            # Nothing mapped (JAX's JVP of this rule asks so): one solve, not batched.
            out = single(dyn, y0, ts, rtol, atol)
            return out, jax.tree_util.tree_map(lambda _: False, out)
        y0 = jax.tree_util.tree_map(
            lambda v, b: v if b else jnp.broadcast_to(v, (axis_size,) + jnp.shape(v)),
            y0, in_batched[1])
        dyn_b, dyn_c = _split(dyn, in_batched[0])
        lockstep = _lockstep(rebuild, dyn_c, in_batched, max_steps, error_size, solver)
        out = _in_chunks(lockstep, axis_size, dyn_b, y0, rtol, atol, ts, in_batched[3],
                         in_batched[4], in_batched[2], spread=spread)
        return out, _all_batched(out)

    def batched(spread: bool):
        """The solve with its `vmap` rule; `spread`: whether a batch may be spread over
        several CPU devices (see `_in_chunks`)."""

        @custom_vmap
        def solve(dyn, y0, ts, rtol, atol):
            return single(dyn, y0, ts, rtol, atol)

        @solve.def_vmap
        def _rule(axis_size, in_batched, dyn, y0, ts, rtol, atol):
            return batch_rule(axis_size, in_batched, dyn, y0, ts, rtol, atol, spread)

        return solve

    # The adjoint's rule (adjoints.py): JAX's tangents through the batched solve, or the
    # discrete adjoint's `custom_vjp` around it.
    with_vjp = functools.partial(_with_adjoint_vjp, batched, rebuild, max_steps, error_size,
                                 solver)
    return adjoint.fused(batched(spread=True), with_vjp)(dyn, y0, ts, rtol, atol)


def _with_adjoint_vjp(batched, rebuild, max_steps, error_size, solver, backward):
    """The solve `batched(spread)` with reverse mode by the discrete adjoint of its steps
    (adjoint.py; see the module's docstring), by the backward program `backward`
    (`DiscreteAdjoint.backward`)."""
    if solver is not None and solver.erk != dopri8():  # the adjoint differentiates Dopri8
        raise ValueError("reverse mode steps the default method only")

    @jax.custom_vjp
    def reverse(dyn, y0, ts, rtol, atol):
        return batched(spread=True)(dyn, y0, ts, rtol, atol)

    def fwd(dyn, y0, ts, rtol, atol):
        # One member's solve with the log of its steps; under `jax.vmap` a plain `vmap` of
        # it (each member its own steps, as in the lockstep batch). A Python number a user
        # differentiates (`jax.grad(f)(2.0)`) arrives here as a literal, not an array:
        # as arrays, so that the backward pass sees it as a float leaf with a cotangent
        # (it returned a gradient of 0.0 otherwise).
        dyn, y0 = jax.tree_util.tree_map(jnp.asarray, (dyn, y0))
        ys, result, steps, log = discrete.forward(rebuild(dyn), y0, ts, rtol, atol,
                                                 max_steps=max_steps, error_size=error_size,
                                                 solver=solver)
        out = (ys, _as_float(result_code(result), ts), _as_float(steps, ts))
        return out, (dyn, y0, ts, rtol, atol, log)

    def bwd(res, g):
        dyn, y0, ts, rtol, atol, log = res
        d_dyn, d_y0 = discrete.backward(rebuild, dyn, y0, ts, rtol, atol, log, g[0],
                                       max_steps=max_steps, error_size=error_size,
                                       solver=solver, program=backward)
        # No derivative with respect to the save times or the tolerances.
        return d_dyn, d_y0, jnp.zeros_like(ts), jnp.zeros_like(rtol), jnp.zeros_like(atol)

    reverse.defvjp(fwd, bwd)
    return reverse
