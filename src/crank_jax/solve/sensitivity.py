"""Forward sensitivities of a fused fixed-step solve, generic over the vector field.

Why not let `jax.jvp` differentiate the solve? Forward mode through an explicit
Runge-Kutta step *is* that step applied to the variational equation, so the arithmetic is
the same, but XLA's CPU fusion handles `jvp`'s tangents badly here: with the 10 tangents of
a full Jacobian a step cost ~7.5x a plain step (30 -> 130 kernels per step, measured on the
lab rig). Here each state component carries one row: its value and its sensitivities to
all P parameter leaves and to y0,

    S' = f_y S + f_theta,

with `f_y`, `f_theta` from *reverse* mode of each (scalar) component of the field (scalar
code that fuses like the solve), stepped with the same stages and the same step counts as
the solve. The sensitivity matrix does not depend on the tangent, so any number of tangents
(`jax.jacfwd`'s `vmap`) costs one pass plus one small matrix product. The steps themselves
are not differentiated: a step count is an integer.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .erk import FusedERK

__all__ = ["attach_sensitivities"]


def attach_sensitivities(erk: FusedERK, field, args, y0, ts, ys, ms):
    """`ys`, with a JVP that is the forward sensitivity of the fixed-step solve.

    **Arguments:** `erk`, the method; `field(t, y, args)`, the vector field (its
    inexact-array leaves and those of `args` are the parameters); `y0`, the initial state
    (a pytree of arrays; its total size N should be small: each component is one row, and
    the field's Jacobian takes N reverse passes); `ts` (n,), the save times; `ys`, the
    solution (`y0`'s pytree, leading axis n); `ms` (n - 1,), the equal steps per interval
    that the solve took.

    **Returns:** `ys`, unchanged in value.
    """
    diff, static = eqx.partition((field, args), eqx.is_inexact_array)
    attach = _make_attach(erk, static)
    return attach(diff, y0, ts, ys, ms)


def flatten_state(y):
    """The leaves of `y` and a function from N scalar components back to `y`'s pytree."""
    leaves, treedef = jax.tree_util.tree_flatten(y)
    shapes = [np.shape(x) for x in leaves]
    sizes = [int(np.prod(s, dtype=int)) for s in shapes]

    def components(tree):
        out = []
        for x, s in zip(jax.tree_util.tree_leaves(tree), shapes):
            out += [x] if s == () else list(jnp.ravel(x))
        return out

    def rebuild(comps):
        out, i = [], 0
        for s, k in zip(shapes, sizes):
            out.append(comps[i] if s == () else jnp.stack(comps[i:i + k]).reshape(s))
            i += k
        return jax.tree_util.tree_unflatten(treedef, out)

    return components, rebuild, sum(sizes)


def copied_components(g, x, theta) -> list:
    """For each output component of `g(x, theta)` (a tuple of scalars), the index of the
    input component of `x` that it returns unchanged, else None (read off the jaxpr)."""
    closed = jax.make_jaxpr(g)(tuple(x), theta)
    ins = closed.jaxpr.invars[: len(x)]
    out = []
    for v in closed.jaxpr.outvars:
        hit = [i for i, u in enumerate(ins) if u is v]
        out.append(hit[0] if hit else None)
    return out


def _variational_field(g, copies, flat, N, y0_cols, dtype):
    """`f(t, Y, _)`: the field of the augmented state. Row j of `Y` is component j of the
    state (column 0) and its sensitivities to the P parameters and the y0 columns; the rows'
    derivative is `(f_j, sum_k f_j,x_k S_k + f_j,theta)`, `f_y` and `f_theta` by one reverse
    pass per component that is not a plain copy (`copies`) of a state component."""
    work = [j for j in range(N) if copies[j] is None]

    def f(t, Y, _):
        x = tuple(row[0] for row in Y)
        val, vjp = jax.vjp(lambda x, theta: tuple(g(t, x, theta)[j] for j in work), x, flat)
        rows = {}
        for w, j in enumerate(work):
            ct = tuple(jnp.ones_like(v) if i == w else jnp.zeros_like(v)
                       for i, v in enumerate(val))
            dx, dth = vjp(ct)
            d = jnp.concatenate([dth.astype(dtype), jnp.zeros(y0_cols, dtype)])
            for k in range(N):
                d = d + dx[k] * Y[k][1:]
            rows[j] = jnp.concatenate([val[w][None], d])
        for j in range(N):
            if copies[j] is not None:
                rows[j] = Y[copies[j]]
        return tuple(rows[j] for j in range(N))

    return f


def columns_to_tree(dys, y0):
    """(n, N) tangent columns back to `y0`'s pytree: a leaf of shape s becomes (n,) + s."""
    n = dys.shape[0]
    out, i = [], 0
    for v in jax.tree_util.tree_leaves(y0):
        k = int(np.size(v))
        out.append(dys[:, i:i + k].reshape((n,) + np.shape(v)))
        i += k
    return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(y0), out)


def _make_attach(erk: FusedERK, static):
    @jax.custom_jvp
    def attach(params, y0, ts, ys, ms):
        return ys

    def attach_jvp(primals, tangents):
        params, y0, ts, ys, ms = primals
        dtype = ts.dtype
        # With `symbolic_zeros`, a leaf nobody differentiates (under `jacfwd` over 10
        # parameters: r, g and y0) has a SymbolicZero tangent and gets no column.
        zero = jax.custom_derivatives.SymbolicZero
        is_zero = lambda x: isinstance(x, zero)  # noqa: E731
        leaves, treedef = jax.tree_util.tree_flatten(params)
        dleaves = jax.tree_util.tree_leaves(tangents[0], is_leaf=is_zero)
        live = [i for i, d in enumerate(dleaves) if not is_zero(d)]
        components, rebuild, N = flatten_state(y0)
        dy0_leaves = ([tangents[1]] * len(jax.tree_util.tree_leaves(y0)) if is_zero(tangents[1])
                      else jax.tree_util.tree_leaves(tangents[1], is_leaf=is_zero))
        y0_cols = N if any(not is_zero(d) for d in dy0_leaves) else 0
        if not live and not y0_cols:
            return ys, jax.tree_util.tree_map(jnp.zeros_like, ys)
        sizes = [int(np.size(leaves[i])) for i in live]
        offsets = np.cumsum([0] + sizes)
        P = int(offsets[-1])
        flat = jnp.concatenate([jnp.ravel(leaves[i]).astype(dtype) for i in live]
                               + [jnp.zeros(0, dtype)])
        dflat = jnp.concatenate([jnp.ravel(dleaves[i]).astype(dtype) for i in live]
                                + [jnp.zeros(0, dtype)])

        def g(t, x, theta):
            # Scalars by indexing, not by `ravel_pytree`'s slices: that fuses ~2x better.
            out = list(leaves)
            for i, o, k in zip(live, offsets, sizes):
                v = leaves[i]
                out[i] = (theta[o] if np.shape(v) == () else
                          theta[o:o + k].reshape(np.shape(v))).astype(v.dtype)
            field, args = eqx.combine(jax.tree_util.tree_unflatten(treedef, out), static)
            return tuple(components(field(t, rebuild(list(x)), args)))

        # Components of the field that merely copy a state component (the crank's
        # phi' = dphi) need no reverse pass: their sensitivity row is that component's.
        copies = copied_components(lambda x, th: g(ts[0], x, th), components(y0), flat)
        f = _variational_field(g, copies, flat, N, y0_cols, dtype)

        def interval(Y, x):
            t0, t1, m = x
            h = (t1 - t0) / m.astype(dtype)

            def step(i, Y):
                return erk.solution(Y, h, erk.stages(f, t0 + i.astype(dtype) * h, Y, None, h))

            Y = jax.lax.fori_loop(0, m, step, Y)
            return Y, jnp.stack([row[1:] for row in Y])

        unit = jnp.eye(N, dtype=dtype)[:, :y0_cols]
        Y0 = tuple(jnp.concatenate([v[None].astype(dtype), jnp.zeros(P, dtype), unit[j]])
                   for j, v in enumerate(components(y0)))
        _, S = jax.lax.scan(interval, Y0, (ts[:-1], ts[1:], ms))
        S = jnp.concatenate([jnp.stack([row[1:] for row in Y0])[None], S])  # (n, N, P + c)
        dys = S[..., :P] @ dflat
        if y0_cols:
            dy0 = [jnp.zeros_like(v) if is_zero(d) else d
                   for v, d in zip(jax.tree_util.tree_leaves(y0), dy0_leaves)]
            dys = dys + S[..., P:] @ jnp.concatenate([jnp.ravel(d).astype(dtype) for d in dy0])
        return ys, columns_to_tree(dys, y0)

    attach.defjvp(attach_jvp, symbolic_zeros=True)
    return attach
