"""The backward pass's `"blocks"` program (adjoint.py): a hand-written adjoint of Dopri8's
stage recursion over a block of logged steps side by side.

A block's steps are recomputed at once ([`stages`][]) with the field's Jacobian with
respect to the state at each stage (forward mode, N tangents); the stages' cotangents
follow by the reverse of the stage recursion ([`stage_cotangents`][]), the steps' state
cotangents by a parallel scan of their affine maps ([`reverse_affine`][]), and the
parameters' by one VJP of the field over the block's evaluation points
([`field_vjp`][], which the `"loop"` program uses too). Why by hand: JAX's transformation of
the whole step vectorised compiled to kernels many times dearer than the field's own,
after a long compile (docs/benchmarks/design-figures.md).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .dense_output import dopri8_dense
from .erk import dopri8

__all__ = ["Stages", "stages", "dense_cotangents", "stage_cotangents", "field_vjp",
           "reverse_affine", "point_field"]


class Stages(NamedTuple):
    """A block of B logged steps recomputed side by side (`stages`), each step's 13
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


def tableau(dtype):
    """Dopri8's `(a, b, c)` over its 14 stages, the 14th `f(t1, y1)`: `a` (14, 14)
    strictly lower (row 13 the solution's weights `b`), `c` (14,)."""
    tab = dopri8().tableau
    a = np.zeros((14, 14))
    for i, row in enumerate(tab.a_lower):
        a[i + 1, :len(row)] = np.asarray(row)
    c = np.concatenate([[0.0], np.asarray(tab.c)])
    return jnp.asarray(a, dtype), jnp.asarray(a[13], dtype), jnp.asarray(c, dtype)


def point_field(field, pack, unpack, dtype):
    """`f(t, y) -> dy/dt` on one packed state (N,) at a scalar time `t`."""
    return lambda t, y: pack(field(t, unpack(y), None)).astype(dtype)


def stages(field, pack, unpack, rows, n_state):
    """The [`Stages`][] of the logged steps `rows` (B, 3 + N), with forward-mode
    derivatives with respect to the start state carried through them: N tangents, for a
    state of a few components the cheapest way to each step's (N, N) Jacobians (one
    field Jacobian per stage). One `scan` over the stages, so that the program holds one
    copy of the field's derivative (compile time), not 14."""
    B, dtype = rows.shape[0], rows.dtype
    t, t1, h, y = rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3:3 + n_state]
    f = point_field(field, pack, unpack, dtype)
    a, _, c = tableau(dtype)
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
    return Stages(T, Y, J, D, A)


def dense_cotangents(rows, tw, gw):
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


def stage_cotangents(st: Stages, h, G, u):
    """The cotangents of the 14 stages of each step (14, B, N), given `u` (B, N), that of
    its end state, and `G`, what the dense output sends directly: the reverse of the stage
    recursion `Y_i = y + h sum_j a_ij k_j`, `k_i = f(t_i, Y_i)`, one transposed field
    Jacobian per stage (the step size is a constant of the computed solution); a reverse
    `scan` over the stages."""
    a, b, _ = tableau(G.dtype)
    y1bar = u + jnp.einsum("bij,bi->bj", st.J[13], G[13])
    kbar = G + (b[:, None] * h[None])[:, :, None] * y1bar[None]

    def stage(kbar, i):
        ybar_i = jnp.einsum("bij,bi->bj", st.J[i], kbar[i])
        return kbar + (a[i][:, None] * h[None])[:, :, None] * ybar_i[None], None

    kbar, _ = jax.lax.scan(stage, kbar, jnp.arange(1, 13), reverse=True)
    return kbar


def field_vjp(full, dd, pack, unpack, T, Y, kbar):
    """The cotangent of the field's parameters `dd` from the stages of a block of steps:
    one VJP of the field over all its evaluation points, times `T` (...,) and packed
    states `Y` (..., N), with cotangents `kbar` (..., N)."""
    n_state = kbar.shape[-1]
    T, Y, K = T.reshape(-1), Y.reshape(-1, n_state), kbar.reshape(-1, n_state)

    def at_points(dd):
        return jax.vmap(point_field(full(dd), pack, unpack, Y.dtype))(T, Y)

    _, pull = jax.vjp(at_points, dd)
    return pull(K)[0]


def reverse_affine(a, c, u_end):
    """`x[i] = a[i] x[i + 1] + c[i]` for i = B-1, ..., 0, with `x[B] = u_end`: a parallel
    (associative) scan of the affine maps, log2(B) vectorised levels rather than B
    dependent steps. `a` (B, N, N), `c` (B, N), `u_end` (N,); returns x (B, N)."""

    def compose(p, q):  # q after p
        ap, cp = p
        aq, cq = q
        return (jnp.einsum("bij,bjk->bik", aq, ap), jnp.einsum("bij,bj->bi", aq, cp) + cq)

    a_all, c_all = jax.lax.associative_scan(compose, (a[::-1], c[::-1]))
    return (jnp.einsum("bij,j->bi", a_all, u_end) + c_all)[::-1]
