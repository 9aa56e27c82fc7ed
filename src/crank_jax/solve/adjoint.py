"""Reverse mode of `"dopri8-adaptive"`: a discrete adjoint of its steps.

The forward pass ([`forward`][]) is the solve itself ([`solve_adaptive`][]) with a log of
its accepted steps: each step's start `t`, end `t1`, size `h` and packed state `y` at `t`,
one row each. The backward pass ([`backward`][]) takes the steps in reverse and applies
the VJP of one step, `(y, theta) -> (y1, dense output at the save times the step
covers)`, carrying the state's cotangent from step to step and summing the field's
parameter cotangents. The step sizes and the accept/reject decisions are constants (the
forward pass chose them on values, `stop_gradient`), so the result is the exact gradient
of the computed discrete solution: the transpose of what forward mode (`jax.jacfwd`
through the same solve) computes, equal to it to rounding (tests/test_adjoint.py).

Why not differentiate the solve's loops? A `while_loop` has no reverse mode, and the
batched solve is a `custom_vmap` (lockstep.py), which has none either; before this module
the backward pass re-solved the problem with diffrax's Dopri8 and its checkpointed
reverse mode: 12x one forward solve with the CPU flags, 68x under XLA's defaults (lab
rig, issue 26).

**Memory.** The log holds [`LOG_ROWS`][] steps (at most the step budget), as a ring: a
solve of more steps keeps the last `LOG_ROWS`, and the backward pass, after those, runs
the forward solve again for each earlier segment of `LOG_ROWS` steps, logging only that
segment (a solve of `n` steps costs `ceil(n / LOG_ROWS) - 1` more forward solves, and
memory for `LOG_ROWS` rows, whatever `n`).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from ..xla_flags import SMALL_LOOP_BYTES, small_loop_bytes
from .adaptive import WINDOW, dopri8_dense, solve_adaptive
from .erk import dopri8, packer

__all__ = ["forward", "backward", "LOG_ROWS"]

#: Steps the log holds (a ring; see the module docstring). The lab rig (10 s, rtol 1e-8)
#: takes ~900 steps; one row of the crank's state is 5 floats, so 4096 rows are 160 kB.
LOG_ROWS = 4096


class Log(NamedTuple):
    """The forward pass's record of its accepted steps.

    - `rows` (S, 3 + N): `(t, t1, h, y...)` of accepted step `i` in row `i % S`, `y` the
      packed state (N,) at `t` (s);
    - `count`: accepted steps so far (int scalar);
    - `upto`: steps from this index on are not written (a rerun that logs one segment)."""

    rows: jax.Array
    count: jax.Array
    upto: jax.Array


def _rows(max_steps: int) -> int:
    return max(1, min(int(max_steps), LOG_ROWS))


def _write(log: Log, rec) -> Log:
    """Log a step attempt `rec` (adaptive.py's record of one member). A rejected attempt
    writes the row that the next accepted one overwrites; nothing from `upto` on."""
    S = log.rows.shape[0]
    row = jnp.concatenate([rec.t, rec.t1, rec.h, rec.y]).astype(log.rows.dtype)
    pos = jnp.where(log.count < log.upto, log.count % S, S)  # S: out of range, dropped
    rows = log.rows.at[pos].set(row, mode="drop")
    return Log(rows, log.count + rec.ok[0].astype(log.count.dtype), log.upto)


def forward(field, y0, ts, rtol, atol, *, max_steps: int, error_size=None, upto=None):
    """The solve of [`solve_adaptive`][] (one member, not batched) with its log.

    **Arguments:** as `solve_adaptive`; `upto`: log accepted steps below this index only
    (default: all, the last `LOG_ROWS` kept).

    **Returns:** `(ys, result, num_steps, log)`, a [`Log`][] fourth."""
    n_state = packer(y0)[0](y0).shape[-1]
    S = _rows(max_steps)
    upto = jnp.asarray(max_steps + 1 if upto is None else upto, jnp.int32)
    log0 = Log(jnp.zeros((S, 3 + n_state), ts.dtype), jnp.zeros((), jnp.int32), upto)
    return solve_adaptive(field, y0, ts, rtol, atol, max_steps=max_steps,
                          error_size=error_size, record=(log0, _write))


def _step_outputs(field, pack, unpack, row, tw, n_state):
    """One logged step as a function of its start state and of the field: `(y1, values)`,
    the state at its end and the dense output at the save times `tw` (W,), (W, N)
    (zero-weighted where the step does not cover them). The same arithmetic as the
    forward pass (adaptive.py), so that the VJP is that of the computed solution."""
    erk = dopri8()
    dtype = row.dtype
    t, t1, h, y = row[0:1], row[1:2], row[2:3], row[3:3 + n_state]

    def f(tt, yp):
        return pack(field(tt[..., 0], unpack(yp), None)).astype(dtype)

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
    return y1, y[None] + theta * poly


def backward(rebuild, dyn, y0, ts, rtol, atol, log: Log, g_ys, *, max_steps: int,
             error_size=None):
    """The cotangents of the field's array leaves `dyn` and of `y0` from `g_ys`, the
    cotangent of the solve's `ys` (a pytree like `y0` with a leading axis n), by the
    steps of `log` in reverse (see the module docstring).

    **Arguments:** `rebuild(dyn) -> field`; `dyn`, the field's array leaves (a list);
    `y0`, `ts`, `rtol`, `atol`, `max_steps`, `error_size`: the forward solve's (a rerun
    of an earlier segment needs them).

    **Returns:** `(d_dyn, d_y0)`: a list like `dyn` (None for a leaf that is not a float
    array) and a pytree like `y0`."""
    pack, unpack = packer(y0)
    S = log.rows.shape[0]
    g = pack(g_ys).astype(ts.dtype)  # (n, N)
    live = [eqx.is_inexact_array(d) for d in dyn]
    diff = [d for d, b in zip(dyn, live) if b]

    def full(dd):
        it = iter(dd)
        return rebuild([next(it) if b else d for d, b in zip(dyn, live)])

    B = min(_BLOCK, S)
    block = _block_vjp(full, diff, pack, unpack, ts, g, B)
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
        # branches, a rerun per gradient.)
        m, carry = c
        rows = jax.lax.cond(m == m_last, lambda: log.rows, lambda: forward(
            rebuild(dyn), y0, ts, rtol, atol, max_steps=max_steps, error_size=error_size,
            upto=(m + 1) * S)[3].rows)
        return m - 1, segment(rows, m, carry)

    _, (ybar, dbar) = jax.lax.while_loop(lambda c: c[0] >= 0, each, (m_last, carry))
    ybar = ybar + g[0]  # ys[0] is y0 itself
    it = iter(dbar)
    return [next(it) if b else None for b in live], unpack(ybar)


#: Steps the backward pass takes at once under XLA's defaults (at most `LOG_ROWS`, which
#: should be a multiple of it): the Jacobians of a block's steps with respect to the
#: state, the VJP of their parameters and the recursion of the state's cotangent (an
#: associative scan) are each one vectorised computation of few, wide kernels.
_BLOCK = 256


def _block_vjp(full, dd, pack, unpack, ts, g, B):
    """`block(rows, kb, size, carry) -> carry`: the steps of block `kb` (of `B` rows) of a
    segment's `rows` (those at positions below `size`), in reverse."""
    W = WINDOW
    n_state = g.shape[1]
    ts_pad = jnp.concatenate([ts, jnp.full((W,), jnp.inf, ts.dtype)])
    g_pad = jnp.concatenate([g, jnp.zeros((W, n_state), g.dtype)])

    def window(row, method="scan"):
        return _window(ts, ts_pad, g_pad, row, method)

    def outputs(row, tw, dd):
        return _step_outputs(full(dd), pack, unpack, row, tw, n_state)

    def block(rows, kb, size, carry):
        u_end, dbar = carry
        rows = jax.lax.dynamic_slice_in_dim(rows, kb * B, B)
        valid = kb * B + jnp.arange(B) < size
        # Rows past the last step hold no step: they take the first row's (finite) values
        # and act as the identity with no cotangent.
        rows = jnp.where(valid[:, None], rows, rows[:1])
        tw, gw = jax.vmap(lambda r: window(r, "compare_all"))(rows)
        gw = jnp.where(valid[:, None, None], gw, 0.0)

        def out_y(row, tw, y):
            return outputs(row.at[3:].set(y), tw, dd)

        # d(y1, values) / dy per step, (B, N, N) and (B, W, N, N).
        j1, jv = jax.vmap(jax.jacfwd(out_y, argnums=2))(rows, tw, rows[:, 3:])
        eye = jnp.eye(n_state, dtype=j1.dtype)
        a = jnp.where(valid[:, None, None], jnp.swapaxes(j1, 1, 2), eye)
        c = jnp.einsum("bwij,bwi->bj", jv, gw)
        # ybar[i], the cotangent of step i's start state, is a[i] u[i] + c[i], u[i] that of
        # its end state: ybar[i + 1], or `u_end` for the block's last step.
        ybar = _reverse_affine(a, c, u_end)
        u_in = jnp.where(valid[:, None], jnp.concatenate([ybar[1:], u_end[None]]), 0.0)
        # Per-step copies of the parameters, summed after: a shared parameter's
        # cotangent would be reduced over the block at every use (measured 3x dearer).
        ddb = [jnp.broadcast_to(d, (B,) + d.shape) for d in dd]
        _, pull = jax.vjp(lambda ddb: jax.vmap(outputs)(rows, tw, ddb), ddb)
        (d_block,) = pull((u_in, gw))
        return ybar[0], [x + y.sum(0) for x, y in zip(dbar, d_block)]

    return _sequential(outputs, window, dd, B) if _hoisted() else block


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


def _sequential(outputs, window, dd, B):
    """`block` as `_block_vjp`'s, with the block's steps one after another, each one VJP
    of the step: kernels of one step's size, one compiled function where XLA hoists the
    loop (see `_hoisted`)."""

    def block(rows, kb, size, carry):
        def one(k, carry):
            ybar, dbar = carry
            row = rows[jnp.minimum(size, (kb + 1) * B) - 1 - k]
            tw, gw = window(row)
            _, pull = jax.vjp(lambda y, dd: outputs(row.at[3:].set(y), tw, dd), row[3:], dd)
            yb, db = pull((ybar, gw))
            return yb, [a + b for a, b in zip(dbar, db)]

        return jax.lax.fori_loop(0, jnp.minimum(size - kb * B, B), one, carry)

    return block


def _hoisted() -> bool:
    """Whether XLA:CPU compiles the backward pass's step loop into one function (its
    small-loop threshold raised, `xla_flags.SMALL_LOOP_BYTES`, as the `crank-jax` program
    and `configure_cpu` set it). Then one VJP per step, in a loop, is cheapest: lab rig,
    grad 4.3x one forward solve against ~12x for the blocks (machine loaded). Without it
    every one of the ~600 kernels of a step's VJP is dispatched per step (90x), and the
    vectorised blocks win."""
    threshold = small_loop_bytes()
    return (jax.default_backend() == "cpu" and threshold is not None
            and threshold >= SMALL_LOOP_BYTES)


def _reverse_affine(a, c, u_end):
    """`x[i] = a[i] x[i + 1] + c[i]` for i = B-1, ..., 0, with `x[B] = u_end`: a parallel
    (associative) scan of the affine maps, log2(B) vectorised levels rather than B
    dependent steps. `a` (B, N, N), `c` (B, N), `u_end` (N,); returns x (B, N)."""

    def compose(p, q):  # q after p
        ap, cp = p
        aq, cq = q
        return (jnp.einsum("bij,bjk->bik", aq, ap), jnp.einsum("bij,bj->bi", aq, cp) + cq)

    a_all, c_all = jax.lax.associative_scan(compose, (a[::-1], c[::-1]))
    return (jnp.einsum("bij,j->bi", a_all, u_end) + c_all)[::-1]
