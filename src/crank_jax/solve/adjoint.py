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
  10x and 6x dearer than the field's own, and 60 s of compile time).

The step sizes and the accept/reject decisions are constants (the forward pass chose them
on values, `stop_gradient`), so the result is the exact gradient of the computed discrete
solution: the transpose of what forward mode (`jax.jacfwd` through the same solve)
computes, equal to it to rounding (tests/test_adjoint.py).

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

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..model import trig
from .adaptive import WINDOW, dopri8_dense, solve_adaptive
from .erk import dopri8, packer
from .steplog import PENDING, Log, recorder

__all__ = ["forward", "backward", "LOG_ROWS"]

#: Steps the log holds (a ring; see the module docstring). The lab rig (10 s, rtol 1e-8)
#: takes ~900 steps; one row of the crank's state is 5 floats, so 4096 rows are 160 kB.
LOG_ROWS = 4096


def _rows(max_steps: int) -> int:
    return max(1, min(int(max_steps), LOG_ROWS))


def forward(field, y0, ts, rtol, atol, *, max_steps: int, error_size=None, upto=None,
            controller=None):
    """The solve of [`solve_adaptive`][] (one member, not batched) with its log.

    **Arguments:** as `solve_adaptive`; `upto`: log accepted steps below this index only
    (default: all, the last `LOG_ROWS` kept); `controller`, the step-size law.

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
                          record=record, controller=controller)


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
             error_size=None, controller=None, program: str = "blocks"):
    """The cotangents of the field's array leaves `dyn` and of `y0` from `g_ys`, the
    cotangent of the solve's `ys` (a pytree like `y0` with a leading axis n), by the
    steps of `log` in reverse (see the module docstring).

    **Arguments:** `rebuild(dyn) -> field`; `dyn`, the field's array leaves (a list);
    `y0`, `ts`, `rtol`, `atol`, `max_steps`, `error_size`, `controller`: the forward
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
            upto=(m + 1) * S, controller=controller)[3])
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
        st = _stages(arithmetic(dd), pack, unpack, rows, n_state)
        # G[i]: the cotangent of stage i that the dense output sends directly, (B, N).
        G = _dense_cotangents(rows, tw, gw)
        # Each step is the affine map ybar = A^T u + c of its end state's cotangent u.
        c = gw.sum(1) + jnp.einsum("kbij,kbi->bj", st.D, G)
        a = jnp.where(valid[:, None, None], jnp.swapaxes(st.A, 1, 2), jnp.eye(n_state))
        ybar = _reverse_affine(a, c, u_end)
        u_in = jnp.where(valid[:, None], jnp.concatenate([ybar[1:], u_end[None]]), 0.0)
        kbar = _stage_cotangents(st, rows[:, 2], G, u_in)
        d = _field_vjp(arithmetic, dd, pack, unpack, st.T, st.Y, kbar)
        return ybar[0], [x + y for x, y in zip(dbar, d)]

    # The block's field evaluations run over its B x 14 points side by side. With the CPU
    # flags these blocks took 3.3 ms against 2.5 ms for a loop of one VJP per step
    # (2026-11-27), so the flags keep the loop (`_deferred`).
    if program == "blocks":
        return block
    return _deferred(full, arithmetic, dd, pack, unpack, window, B, n_state)


class _Stages(NamedTuple):
    """A block of B logged steps recomputed side by side (`_stages`), each step's 13
    stages and its last, `f(t1, y1)` (14 evaluations of the field, first same as last),
    stage first:

    - `T` (14, B), `Y` (14, B, N): where the field was evaluated (time, s; packed state);
    - `J` (14, B, N, N): the field's Jacobian with respect to the state there;
    - `D` (14, B, N, N): the derivative of each stage `k_i` with respect to the step's
      start state; `A` (B, N, N): that of its end state `y1`."""

    T: jax.Array
    Y: jax.Array
    J: jax.Array
    D: jax.Array
    A: jax.Array


def _tableau(dtype):
    """Dopri8's `(a, b, c)` over its 14 stages, the 14th `f(t1, y1)`: `a` (14, 14)
    strictly lower (row 13 the solution's weights `b`), `c` (14,)."""
    tab = dopri8().tableau
    a = np.zeros((14, 14))
    for i, row in enumerate(tab.a_lower):
        a[i + 1, :len(row)] = np.asarray(row)
    c = np.concatenate([[0.0], np.asarray(tab.c)])
    return jnp.asarray(a, dtype), jnp.asarray(a[13], dtype), jnp.asarray(c, dtype)


def _point_field(field, pack, unpack, dtype):
    """`f(t, y) -> dy/dt` on one packed state (N,) at a scalar time `t`."""
    return lambda t, y: pack(field(t, unpack(y), None)).astype(dtype)


def _stages(field, pack, unpack, rows, n_state):
    """The [`_Stages`][] of the logged steps `rows` (B, 3 + N), with forward-mode
    derivatives with respect to the start state carried through them: N tangents, for a
    state of a few components the cheapest way to each step's (N, N) Jacobians (one
    field Jacobian per stage). One `scan` over the stages, so that the program holds one
    copy of the field's derivative (compile time), not 14."""
    B, dtype = rows.shape[0], rows.dtype
    t, t1, h, y = rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3:3 + n_state]
    f = _point_field(field, pack, unpack, dtype)
    a, _, c = _tableau(dtype)
    eye = jnp.eye(n_state, dtype=dtype)

    def value_and_jac(tt, yy):
        # vmap over the N unit tangents: the value once, the Jacobian (N, N) by columns.
        return jax.vmap(lambda v: jax.jvp(lambda z: f(tt, z), (yy,), (v,)),
                        out_axes=(None, 1))(eye)

    def stage(carry, i):
        ks, Ds = carry  # (14, B, N), (14, B, N, N): the stages so far (zero after)
        w = a[i][:, None] * h[None]  # (14, B): h a_ij
        yi = y + jnp.einsum("jb,jbn->bn", w, ks)
        di = eye + jnp.einsum("jb,jbmn->bmn", w, Ds)
        ti = jnp.where(i == 13, t1, t + c[i] * h)  # the 14th at the step's end, t1
        k, jac = jax.vmap(value_and_jac)(ti, yi)
        d = jnp.einsum("bij,bjk->bik", jac, di)
        return (ks.at[i].set(k), Ds.at[i].set(d)), (ti, yi, jac, d)

    zeros = (jnp.zeros((14, B, n_state), dtype), jnp.zeros((14, B, n_state, n_state), dtype))
    _, (T, Y, J, D) = jax.lax.scan(stage, zeros, jnp.arange(14))
    # y1 is the 14th stage's point; its derivative D's 14th input, I + h sum_j b_j D_j.
    A = eye + jnp.einsum("j,b,jbmn->bmn", a[13], h, D)
    return _Stages(T, Y, J, D, A)


def _dense_cotangents(rows, tw, gw):
    """`G` (14, B, N): the cotangent that the dense output at the save times `tw` (B, W),
    with cotangents `gw` (B, W, N), sends to each stage `k_i` of its step: the output is
    `y + h sum_i w_i(theta) k_i`, `w_i(theta) = theta P_i(theta)` (`dopri8_dense`),
    `theta = (tw - t) / h` (0 where a step does not cover a save time, and `gw` 0)."""
    dense = jnp.asarray(dopri8_dense(), rows.dtype)  # (14, powers), highest first
    t, h = rows[:, 0:1], rows[:, 2:3]
    theta = (tw - t) / h
    powers = dense.shape[1]
    basis = jnp.stack([theta ** (powers - j) for j in range(powers)], -1)  # theta P_i
    w = jnp.einsum("bsp,ip->ibs", basis, dense)
    return h[None] * jnp.einsum("ibs,bsn->ibn", w, gw)


def _stage_cotangents(st: _Stages, h, G, u):
    """The cotangents of the 14 stages of each step (14, B, N), given `u` (B, N), that of
    its end state, and `G`, what the dense output sends directly: the reverse of the stage
    recursion `Y_i = y + h sum_j a_ij k_j`, `k_i = f(t_i, Y_i)`, one transposed field
    Jacobian per stage (the step size is a constant of the computed solution); a reverse
    `scan` over the stages."""
    a, b, _ = _tableau(G.dtype)
    y1bar = u + jnp.einsum("bij,bi->bj", st.J[13], G[13])
    kbar = G + (b[:, None] * h[None])[:, :, None] * y1bar[None]

    def stage(kbar, i):
        ybar_i = jnp.einsum("bij,bi->bj", st.J[i], kbar[i])
        return kbar + (a[i][:, None] * h[None])[:, :, None] * ybar_i[None], None

    kbar, _ = jax.lax.scan(stage, kbar, jnp.arange(1, 13), reverse=True)
    return kbar


def _field_vjp(full, dd, pack, unpack, T, Y, kbar):
    """The cotangent of the field's parameters `dd` from the stages of a block of steps:
    one VJP of the field over all its evaluation points, times `T` (...,) and packed
    states `Y` (..., N), with cotangents `kbar` (..., N)."""
    n_state = kbar.shape[-1]
    T, Y, K = T.reshape(-1), Y.reshape(-1, n_state), kbar.reshape(-1, n_state)

    def at_points(dd):
        return jax.vmap(_point_field(full(dd), pack, unpack, Y.dtype))(T, Y)

    _, pull = jax.vjp(at_points, dd)
    return pull(K)[0]


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
    loop (issue 40: 1.51 of the backward pass's 2.35 ms, 2026-11-27). The same sum in
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
            d = _field_vjp(arithmetic, dd, pack, unpack, T[j], Y[j], K[j])
            return [a + b for a, b in zip(dbar, d)]

        return ybar, jax.lax.fori_loop(0, (14 * n + W - 1) // W, chunk, dbar)

    return block


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
