"""Reverse mode of `"dopri8-adaptive"`: a discrete adjoint of its steps.

The forward pass ([`forward`][]) is the solve itself ([`solve_adaptive`][]) with a log of
its accepted steps (steplog.py): each step's start `t`, end `t1`, size `h` and packed
state `y` at `t`, one row each. The backward pass ([`backward`][]) takes the steps in
reverse, carrying the state's cotangent from step to step and summing the field's
parameter cotangents, by one of two programs (`program`, the static field
`DiscreteAdjoint.backward` of adjoints.py, chosen at the edge from the XLA flags):

- **`"loop"`, for the CPU flags** (XLA hoists the loop into one function): one step after another,
  each the VJP of the step `(y, stage values) -> (y1, dense output at the save times the
  step covers)` (the step's save window gathered for a block of steps before the loop);
  the parameters' cotangents after the loop, from the stage points and the stages'
  cotangents, by VJPs of the field over 64 points at a time (`_deferred`);
- **`"blocks"`, otherwise** (each kernel dispatched on its own): a block of 256 steps side by side,
  by a hand-written adjoint of the stage recursion that needs of the field only its
  Jacobian with respect to the state at each stage (forward mode, N tangents) and one VJP
  with respect to its parameters over all the block's 14 x 256 evaluation points, with
  sin, cos and 1/sqrt as arithmetic that XLA:CPU vectorises (`trig.traced_as`): no JAX
  transformation of the whole step (whose vectorised Jacobian and VJP compiled to kernels
  many times dearer than the field's own, after a long compile;
  docs/benchmarks/design-figures.md).

The step sizes and the accept/reject decisions are constants (the forward pass chose them
on values, `stop_gradient`), so the result is the exact gradient of the computed discrete
solution: the transpose of what forward mode (`jax.jacfwd` through the same solve)
computes, equal to it to rounding (tests/test_adjoint.py).

Why not differentiate the solve's loops? A `while_loop` has no reverse mode, and the
batched solve is a `custom_vmap` (lockstep.py), which has none either; before this module
the backward pass re-solved the problem with diffrax's Dopri8 and its checkpointed
reverse mode, many forward solves' worth (the Reverse mode table of
docs/benchmarks/performance.md, experiments/bench_reverse.py).

**Memory.** The log holds [`LOG_ROWS`][] steps (at most the step budget), as a ring: a
solve of more steps keeps the last `LOG_ROWS`, and the backward pass, after those, runs
the forward solve again for each earlier segment of `LOG_ROWS` steps, logging only that
segment (a solve of `n` steps costs `ceil(n / LOG_ROWS) - 1` more forward solves, and
memory for `LOG_ROWS` rows, whatever `n`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp

from ..model import trig
from .adaptive import WINDOW, solve_adaptive
from .dense_output import dopri8_dense
from .erk import dopri8, packer
from .stage_adjoint import dense_cotangents, field_vjp, reverse_affine, stage_cotangents, stages
from .steplog import PENDING, Log, recorder

__all__ = ["forward", "backward", "LOG_ROWS"]

#: Steps the log holds (a ring; see the module docstring). The lab rig (10 s, rtol 1e-8)
#: takes ~900 steps; one row of the crank's state is 5 floats, so 4096 rows are 160 kB.
LOG_ROWS = 4096


def _rows(max_steps: int) -> int:
    return max(1, min(int(max_steps), LOG_ROWS))


def forward(field, y0, ts, rtol, atol, *, max_steps: int, error_size=None, upto=None,
            solver=None):
    """The solve of [`solve_adaptive`][] (one member, not batched) with its log.

    **Arguments:** as `solve_adaptive`; `upto`: log accepted steps below this index only
    (default: all, the last `LOG_ROWS` kept); `solver`, the steps' `AdaptiveERK` (its
    method Dopri8, whose steps `backward` reverses).

    **Returns:** `(ys, result, num_steps, log)`, a [`Log`][] fourth."""
    # A rerun (`backward`) must take the same steps bit for bit; but XLA folds the inputs
    # that a forward pass sees as constants (all not differentiated: a load's frequency)
    # into its arithmetic, while the rerun gets them at run time: other rounding, other
    # steps (a harmonic torque: the gradient 4e-5 off). Run-time values in both, so.
    arrays, rest = eqx.partition((field, y0, ts, rtol, atol), eqx.is_array)
    field, y0, ts, rtol, atol = eqx.combine(jax.lax.optimization_barrier(arrays), rest)
    n_state = packer(y0)[0](y0).shape[-1]
    upto = jnp.asarray(max_steps + 1 if upto is None else upto, jnp.int32)
    record = recorder(_rows(max_steps), n_state, ts.dtype, upto)
    return solve_adaptive(field, y0, ts, rtol, atol, max_steps=max_steps, error_size=error_size,
                          record=record, solver=solver)


def _step_outputs(field, pack, unpack, row, tw, n_state, e=None):
    """One logged step as a function of its start state and of the field: `(y1, values)`,
    the state at its end and the dense output at the save times `tw` (W,), (W, N)
    (zero-weighted where the step does not cover them). The same arithmetic as the
    forward pass (adaptive.py), so that the VJP is that of the computed solution.

    With `e` (14, N), zeros, each stage is `f(t_i, Y_i) + e_i`, and the result is
    `((y1, values), (T, Y))`: the cotangent of `e` is then that of the 14 stages, and
    `T` (14,), `Y` (14, N) are where the field was evaluated (see `_deferred`)."""
    erk = dopri8()
    dtype = row.dtype
    t, t1, h, y = row[0:1], row[1:2], row[2:3], row[3:3 + n_state]
    points = []

    def f(tt, yp):
        points.append((tt[0], yp))
        k = pack(field(tt[..., 0], unpack(yp), None)).astype(dtype)
        return k if e is None else k + e[len(points) - 1]

    ks = erk.stages(lambda tt, yy, _: f(tt, yy), t, y, None, h)[:erk.num_stages]
    y1 = erk.solution(y, h, ks)
    ks = ks + [f(t1, y1)]
    dense = dopri8_dense()
    coef = []
    for j in range(dense.shape[1]):  # h sum_i P_ij k_i, unrolled over nonzero weights
        terms = [float(dense[i, j]) * k for i, k in enumerate(ks) if float(dense[i, j])]
        coef.append(h * sum(terms[1:], terms[0]))
    theta = ((tw - t) / h)[:, None]
    poly = coef[0][None]
    for c in coef[1:]:
        poly = poly * theta + c[None]
    out = y1, y[None] + theta * poly
    if e is None:
        return out
    return out, (jnp.stack([p[0] for p in points]), jnp.stack([p[1] for p in points]))


def backward(rebuild, dyn, y0, ts, rtol, atol, log: Log, g_ys, *, max_steps: int,
             error_size=None, solver=None, program: str = "blocks"):
    """The cotangents of the field's array leaves `dyn` and of `y0` from `g_ys`, the
    cotangent of the solve's `ys` (a pytree like `y0` with a leading axis n), by the
    steps of `log` in reverse (see the module docstring).

    **Arguments:** `rebuild(dyn) -> field`; `dyn`, the field's array leaves (a list);
    `y0`, `ts`, `rtol`, `atol`, `max_steps`, `error_size`, `solver`: the forward
    solve's (a rerun of an earlier segment needs them); `program`, the backward program,
    `"blocks"` or `"loop"` (see the module docstring).

    **Returns:** `(d_dyn, d_y0)`: a list like `dyn` (None for a leaf that is not a float
    array) and a pytree like `y0`."""
    pack, unpack = packer(y0)
    S = log.rows.shape[0] - PENDING  # the ring's rows (see `Log`)
    g = pack(g_ys).astype(ts.dtype)  # (n, N)
    live = [eqx.is_inexact_array(d) for d in dyn]
    diff = [d for d, b in zip(dyn, live) if b]

    def full(dd):
        it = iter(dd)
        return rebuild([next(it) if b else d for d, b in zip(dyn, live)])

    B = min(_BLOCK, S)
    block = _block_vjp(full, diff, pack, unpack, ts, g, B, program)
    count = log.count

    def segment(rows, m, carry):
        # The steps mS, ..., of segment m (ring positions 0, ...), in blocks of B from
        # the last; `carry`: (the cotangent of the state after them, of the field).
        size = jnp.clip(count - m * S, 0, S)

        def body(c):
            kb, carry = c
            return kb - 1, block(rows, kb, size, carry)

        return jax.lax.while_loop(lambda c: c[0] >= 0, body, (-(-size // B) - 1, carry))[1]

    carry = (jnp.zeros_like(g[0]), [jnp.zeros_like(d) for d in diff])
    m_last = (count - 1) // S  # the segment the forward pass's ring ends with

    def each(c):
        # Segments from the last: its rows are the forward pass's; an earlier one's come
        # from a rerun of the forward solve that logs that segment only. (One loop, so
        # that the backward pass is compiled once; under `jax.vmap` the `cond` runs both
        # branches, a rerun per gradient.) `head`: the first row of the segment after m.
        m, carry, head = c
        r = jax.lax.cond(m == m_last, lambda: log._replace(mark=head), lambda: forward(
            rebuild(dyn), y0, ts, rtol, atol, max_steps=max_steps, error_size=error_size,
            upto=(m + 1) * S, solver=solver)[3])
        # A rerun that does not take the forward pass's steps bit for bit (its step
        # (m + 1) S, `mark`, the next segment's first) would give a wrong gradient. (m < 0:
        # a member done while others of a `vmap` go on, its result not taken.)
        off = jnp.any(r.mark != head) | (r.count != count)
        rows = eqx.error_if(r.rows, off & (m >= 0),
                            "the discrete adjoint's rerun of an earlier segment of the "
                            "solve did not take the forward pass's steps (adjoint.py)")
        return m - 1, segment(rows, m, carry), rows[0]

    c0 = (m_last, carry, jnp.zeros_like(log.rows[0]))
    _, (ybar, dbar), _ = jax.lax.while_loop(lambda c: c[0] >= 0, each, c0)
    ybar = ybar + g[0]  # ys[0] is y0 itself
    it = iter(dbar)
    return [next(it) if b else None for b in live], unpack(ybar)


#: Steps the backward pass takes at once (at most `LOG_ROWS`, which should be a multiple
#: of it): under XLA's defaults a block is one vectorised computation of few, wide kernels
#: (its cost is linear in the block: 128, 256 or 1024 steps cost the same per step); with
#: the CPU flags, the steps whose save windows are gathered at once.
_BLOCK = 256


def _block_vjp(full, dd, pack, unpack, ts, g, B, program):
    """`block(rows, kb, size, carry) -> carry`: the steps of block `kb` (of `B` rows) of a
    segment's `rows` (those at positions below `size`), in reverse, by the backward
    program `program` (`"blocks"` or `"loop"`)."""
    W = WINDOW
    n_state = g.shape[1]

    def arithmetic(dd):
        # The field's sin, cos and 1/sqrt as arithmetic that XLA:CPU vectorises over a
        # block's points, where it offers the choice (trig.py; the module docstring).
        return trig.traced_as(full(dd), trig.ARITHMETIC)

    ts_pad = jnp.concatenate([ts, jnp.full((W,), jnp.inf, ts.dtype)])
    g_pad = jnp.concatenate([g, jnp.zeros((W, n_state), g.dtype)])

    def window(row, method="scan"):
        return _window(ts, ts_pad, g_pad, row, method)

    def block(rows, kb, size, carry):
        u_end, dbar = carry
        rows = jax.lax.dynamic_slice_in_dim(rows, kb * B, B)
        valid = kb * B + jnp.arange(B) < size
        # Rows past the last step hold no step: they take the first row's (finite) values
        # and act as the identity with no cotangent.
        rows = jnp.where(valid[:, None], rows, rows[:1])
        tw, gw = jax.vmap(lambda r: window(r, "compare_all"))(rows)
        gw = jnp.where(valid[:, None, None], gw, 0.0)
        st = stages(arithmetic(dd), pack, unpack, rows, n_state)
        # G[i]: the cotangent of stage i that the dense output sends directly, (B, N).
        G = dense_cotangents(rows, tw, gw)
        # Each step is the affine map ybar = A^T u + c of its end state's cotangent u.
        c = gw.sum(1) + jnp.einsum("kbij,kbi->bj", st.D, G)
        a = jnp.where(valid[:, None, None], jnp.swapaxes(st.A, 1, 2), jnp.eye(n_state))
        ybar = reverse_affine(a, c, u_end)
        u_in = jnp.where(valid[:, None], jnp.concatenate([ybar[1:], u_end[None]]), 0.0)
        kbar = stage_cotangents(st, rows[:, 2], G, u_in)
        d = field_vjp(arithmetic, dd, pack, unpack, st.T, st.Y, kbar)
        return ybar[0], [x + y for x, y in zip(dbar, d)]

    # The block's field evaluations run over its B x 14 points side by side. With the CPU
    # flags these blocks took 3.3 ms against 2.5 ms for a loop of one VJP per step
    # (2026-11-27), so the flags keep the loop (`_deferred`).
    if program == "blocks":
        return block
    return _deferred(full, arithmetic, dd, pack, unpack, window, B, n_state)


def _window(ts, ts_pad, g_pad, row, method):
    """`(tw, gw)`: the save times (W,) a logged step `row` covers, and their cotangents
    (W, N) (zero where it does not cover them). They lie in the window of W pending save
    times that the forward pass stepped within (adaptive.py never steps past it)."""
    W = WINDOW
    t, t1 = row[0], row[1]
    j = jnp.searchsorted(ts, t, side="right", method=method)
    tw = jax.lax.dynamic_slice_in_dim(ts_pad, j, W)
    mine = (tw > t) & (tw <= t1)
    gw = jnp.where(mine[:, None], jax.lax.dynamic_slice_in_dim(g_pad, j, W), 0.0)
    # Save times the step does not cover evaluate at its start (theta 0): an infinite
    # padding time would make the VJP's 0 * inf a NaN.
    return jnp.where(mine, tw, t), gw


#: Stage points per VJP of the field in `_deferred`'s loop over a block's points (a divisor
#: of 14 `_BLOCK`). Measured with the CPU flags (lab rig, grad / forward solve, one run,
#: load ~12-19): 8: 3.39x, 16: 3.44x, 32: 3.33x, 64: 3.12x; all 14 B points at once:
#: 4.04x, as slow as the VJP in each step (4.0x): XLA:CPU runs that VJP's ~440 kernels
#: over 3584 points one after another, each streaming its arrays through memory.
_CHUNK = 64


def _deferred(full, arithmetic, dd, pack, unpack, window, B, n_state):
    """`block` as `_block_vjp`'s, with the block's steps one after another, each one VJP
    of the step with respect to its start state and its 14 stages' values (`e` of
    `_step_outputs`), not the field's parameters. The parameters' cotangents are the sum
    over every stage of every step of `K_i^T df/dtheta(T_i, Y_i)`, `K_i` the stage's
    cotangent, `(T_i, Y_i)` its point: after the loop, VJPs of the field over `_CHUNK`
    of the block's points at a time form it (one loop), instead of one small VJP per stage in the
    loop (those took most of the backward pass: `experiments/reverse_split.py`, the
    Reverse mode section of docs/benchmarks/performance.md). The same sum in
    another order: equal to rounding."""

    def step(row, tw, e):
        return _step_outputs(full(dd), pack, unpack, row, tw, n_state, e)

    def block(rows, kb, size, carry):
        ybar, dbar = carry
        blk = jax.lax.dynamic_slice_in_dim(rows, kb * B, B)
        tws, gws = jax.vmap(window)(blk)
        n = jnp.minimum(size - kb * B, B)
        e0 = jnp.zeros((14, n_state), blk.dtype)

        def one(k, c):
            ybar, K, T, Y = c
            i = n - 1 - k
            row, tw, gw = blk[i], tws[i], gws[i]
            _, pull, (t_i, y_i) = jax.vjp(lambda y, e: step(row.at[3:].set(y), tw, e),
                                          row[3:], e0, has_aux=True)
            yb, kbar = pull((ybar, gw))
            return yb, K.at[i].set(kbar), T.at[i].set(t_i), Y.at[i].set(y_i)

        # Rows past the last step keep a valid point (the block's first step's start)
        # and a zero cotangent: they add nothing (an invalid point could add 0 * NaN).
        K = jnp.zeros((B, 14, n_state), blk.dtype)
        T = jnp.full((B, 14), blk[0, 0])
        Y = jnp.broadcast_to(blk[0, 3:3 + n_state], (B, 14, n_state))
        ybar, K, T, Y = jax.lax.fori_loop(0, n, one, (ybar, K, T, Y))
        W = math.gcd(_CHUNK, 14 * B)  # B may be a short log's rows
        T, Y, K = T.reshape(-1, W), Y.reshape(-1, W, n_state), K.reshape(-1, W, n_state)

        def chunk(j, dbar):
            d = field_vjp(arithmetic, dd, pack, unpack, T[j], Y[j], K[j])
            return [a + b for a, b in zip(dbar, d)]

        return ybar, jax.lax.fori_loop(0, (14 * n + W - 1) // W, chunk, dbar)

    return block
