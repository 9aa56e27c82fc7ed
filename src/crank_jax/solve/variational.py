"""Forward sensitivities of an adaptive solve: the variational equation stepped beside the
solution, with the solution's steps, generic over the vector field.

Why not let `jax.jvp` carry tangents through the solve? Forward mode through an explicit
Runge-Kutta step *is* that step applied to the variational equation, so the arithmetic is
the same; but XLA's CPU code for `jvp`'s tangents through the fused field is poor (the
Gradients table of docs/benchmarks/performance.md, experiments/bench_gradients.py). Here
the sensitivity matrix `S = dy/dtheta` is part of the state,

    S' = f_y S + f_C dC/dtheta,

with one reverse pass of each (scalar) component of the field per stage, taken with respect
to the state and to the *prepared* field's parameters `C` (the crank's packed coefficients,
whose slices pass their cotangents back as one array: `coefficients.unpack`), and the chain
rule to the parameters being differentiated, `theta`, as a constant matrix `dC/dtheta`
formed once, outside the loop. One reverse pass costs a small multiple of a field
evaluation however many parameters there are, and the chain rule is a few
scalar-times-row products, so the whole Jacobian costs a few forward solves with the CPU
flags (`xla_flags.py`); with XLA's defaults, which dispatch the loop body's kernels one by
one, the reverse passes split into more kernels and it costs as much as the tangents
(experiments/bench_gradients.py: the Gradients table of docs/benchmarks/performance.md).

The step control sees the sensitivities as well as the solution, as CVODES's does with
`errconS`: a step must meet the tolerance on the state and on each column of `S`, the
columns scaled by their parameter's size (`pbar`), so that column q's tolerance is the
state's for a relative change of theta_q. Why: forward mode through the solve (the steps
chosen on the solution's values alone) differentiates a discrete solution whose steps need
not resolve what the sensitivities see. Smoothed Coulomb friction (tanh of width w) puts a
spike of height ~F/w into f_y as the velocity crosses zero; the state's error barely sees
it, the sensitivities jump by O(1) across it: with the solution's steps the Jacobian is
far off a tight reference, with these it meets the tolerance, for some more steps
(docs/benchmarks/design-figures.md). The primal `ys` of a JVP is then the augmented
solve's, which
differs from a plain solve's within the tolerance. `CONTROL_SENSITIVITIES` off restores
the solution's steps (the tests check the arithmetic against `jax.jvp` so).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .adaptive import outcome
from .library_api import result_code

__all__ = ["with_sensitivities", "flatten_state"]

# Columns (parameters and initial-state components differentiated) and prepared parameter
# elements above which the JVP falls back to `jax.jvp` through the solve: the variational
# state and the chain rule grow with both (e.g. a neural-network force's weights).
MAX_COLUMNS = 64
MAX_ELEMENTS = 256
# Whether the step control sees the sensitivities (CVODES's `errconS`; issue 38). Off, the
# steps are the solution's and the Jacobian is the derivative of the discrete solution,
# as `jax.jvp` through the solve gives it (the tests check the arithmetic so); but where
# the field has a sharp feature the state crosses (smoothed Coulomb friction, tanh of
# width w), f_y has a spike of height ~F/w that the state's error barely sees and the
# sensitivities integrate to an O(1) jump: measured on the lab rig with friction (2 s,
# rtol 1e-9), 2.2e-5 off a tight reference with it off, 2.4e-8 with it on.
CONTROL_SENSITIVITIES = True


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


def columns_to_tree(dys, y0):
    """(n, N) tangent columns back to `y0`'s pytree: a leaf of shape s becomes (n,) + s."""
    n = dys.shape[0]
    out, i = [], 0
    for v in jax.tree_util.tree_leaves(y0):
        k = int(np.size(v))
        out.append(dys[:, i:i + k].reshape((n,) + np.shape(v)))
        i += k
    return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(y0), out)


class _Variational(eqx.Module):
    """The vector field of the augmented state `(x, S)`: `x` the state (a pytree), `S`
    (N, Q) its sensitivities to the Q columns. Row j of `S'` is
    `sum_k f_j,x_k S_k + sum_i f_j,C_i chain_i`; a component that merely copies a state
    component (the crank's `phi' = dphi`) copies that component's row."""

    inner: eqx.Module
    """The prepared field, its differentiated leaves left out (`live`)."""
    live: list
    """The prepared field's leaves that depend on theta (the reverse passes' targets)."""
    chain: jax.Array
    """(elements of `live`, Q): `dC/dtheta`, with zero columns for the initial state."""
    copies: tuple = eqx.field(static=True)
    read: tuple = eqx.field(static=True)
    """Indices of the elements of `live` (flattened) whose cotangents can be nonzero."""
    components: Callable = eqx.field(static=True)
    rebuild: Callable = eqx.field(static=True)

    def __call__(self, t, Y, args):
        x, S = Y
        xs = tuple(self.components(x))
        val, vjp = jax.vjp(self._working(t, args), xs, self.live)
        rows, values = [None] * len(xs), [None] * len(xs)
        for w, j in enumerate(self._work):
            dx, dlive = vjp(_unit(val, w))
            # Scalar times row, unrolled: XLA fuses these; a (elements, Q) matrix product
            # per stage cost 2.6x more (measured on the crank).
            dC = jnp.concatenate([jnp.ravel(d) for d in jax.tree_util.tree_leaves(dlive)]
                                 + [jnp.zeros(0, S.dtype)])
            row = None
            for i in self.read:
                term = dC[i] * self.chain[i]
                row = term if row is None else row + term
            for k in range(len(xs)):
                row = dx[k] * S[k] if row is None else row + dx[k] * S[k]
            rows[j], values[j] = row, val[w]
        for j, c in enumerate(self.copies):
            if c is not None:
                rows[j], values[j] = S[c], xs[c]
        return self.rebuild(values), jnp.stack(rows)

    @property
    def _work(self) -> list[int]:
        """The field's components that are not copies (each takes a reverse pass)."""
        return [j for j, c in enumerate(self.copies) if c is None]

    def _working(self, t, args):
        """`(state components, live) -> the field's components that are not copies`."""
        def f(xs, live):
            out = self.components(eqx.combine(live, self.inner)(t, self.rebuild(list(xs)),
                                                                  args))
            return tuple(out[j] for j in self._work)

        return f


def _unit(val, w):
    """The cotangent that picks output `w` of a reverse pass whose outputs are `val`."""
    return tuple(jnp.ones_like(v) if i == w else jnp.zeros_like(v) for i, v in enumerate(val))


def _read_elements(f, xs, live) -> tuple[int, ...]:
    """The elements of `live` (its leaves flattened, in order) whose cotangent in a reverse
    pass of `f(xs, live)` (a tuple of scalars) can be nonzero: read off the jaxpr of the
    pass, where an element `f` never reads gets a literal zero in the `stack` that gathers
    a leaf's cotangent (`coefficients.unpack`'s transpose). Anything else counts as read."""
    val = jax.eval_shape(f, xs, live)

    def passes(xs, live):
        _, vjp = jax.vjp(f, xs, live)
        return [vjp(_unit(val, w))[1] for w in range(len(val))]

    closed = jax.make_jaxpr(passes)(xs, live)
    made = {v: e for e in closed.jaxpr.eqns for v in e.outvars}
    Literal = jax.extend.core.Literal

    def nonzero(v, size):
        if isinstance(v, Literal):
            return np.full(size, np.any(np.asarray(v.val) != 0))
        e = made.get(v)
        if e is not None and e.primitive.name == "stack" and len(e.invars) == size:
            return np.array([not (isinstance(u, Literal) and np.all(np.asarray(u.val) == 0))
                             for u in e.invars])
        if e is not None and e.primitive.name == "add_any":
            return nonzero(e.invars[0], size) | nonzero(e.invars[1], size)
        return np.ones(size, bool)

    leaves = jax.tree_util.tree_leaves(live)
    sizes = [int(np.size(x)) for x in leaves]
    masks = []
    outs = closed.jaxpr.outvars
    per_pass = len(leaves)
    for w in range(len(val)):
        mask = np.concatenate([nonzero(v, k) for v, k in
                               zip(outs[w * per_pass:(w + 1) * per_pass], sizes)]
                              + [np.zeros(0, bool)])
        masks.append(mask)
    read = np.any(masks, axis=0) if masks else np.zeros(sum(sizes), bool)
    return tuple(int(i) for i in np.flatnonzero(read))


def _depends_on_inputs(fn, x) -> list[bool]:
    """For each output leaf of `fn(x)`, whether it may depend on `x` (read off the jaxpr,
    conservatively: an equation's outputs depend on all its inputs)."""
    closed = jax.make_jaxpr(fn)(x)
    dep = set(closed.jaxpr.invars)
    for eqn in closed.jaxpr.eqns:
        if any(not isinstance(v, jax.extend.core.Literal) and v in dep for v in eqn.invars):
            dep.update(eqn.outvars)
    return [not isinstance(v, jax.extend.core.Literal) and v in dep
            for v in closed.jaxpr.outvars]


def with_sensitivities(solve: Callable, field, prepare: Callable, y0, ts, rtol, atol):
    """`solve(prepare(field), y0, ts, rtol, atol)`, whose JVP steps the variational
    equation beside the solution.

    **Arguments:**

    - `solve(field, y0, ts, rtol, atol, error_size) -> (ys, result, steps)`: an adaptive
      solve (`ys` like `y0` with a leading axis n; `result` a `diffrax.RESULTS`) whose step
      control sees the first `error_size` components of the state only (all for None).
    - `field`: the vector field `field(t, y, args)`, a pytree; its inexact-array leaves are
      the parameters theta.
    - `prepare(field)`: the same vector field in the form the solve steps (the crank:
      `CrankField.packed`); its leaves are functions of theta.
    - `y0`: the initial state, a pytree of arrays (small: each component is a row of the
      sensitivity matrix and takes a reverse pass per stage).

    **Returns:** `(ys, result, steps)`; `result` and `steps` carry no derivative.

    Forward mode (`jax.jvp`, `jax.jacfwd`) integrates one column per parameter element and
    initial-state component that has a tangent, whatever the number of tangents; reverse
    mode transposes that (it computes every column). Tangents of `ts`, `rtol` or `atol`,
    more than `MAX_COLUMNS` columns or more than `MAX_ELEMENTS` prepared parameter elements
    depending on theta fall back to `jax.jvp` through the solve.
    """
    dyn, static = eqx.partition(field, eqx.is_inexact_array)

    def primal(dyn, y0, ts, rtol, atol):
        ys, result, steps = solve(prepare(eqx.combine(dyn, static)), y0, ts, rtol, atol, None)
        return ys, result_code(result), steps

    @jax.custom_jvp
    def run(dyn, y0, ts, rtol, atol):
        return primal(dyn, y0, ts, rtol, atol)

    def run_jvp(primals, tangents):
        zero = jax.custom_derivatives.SymbolicZero
        is_zero = lambda x: isinstance(x, zero)  # noqa: E731
        dyn, y0, ts, rtol, atol = primals = _as_arrays(primals)
        leaves, treedef = jax.tree_util.tree_flatten(dyn)
        dleaves = jax.tree_util.tree_leaves(tangents[0], is_leaf=is_zero)
        live = [i for i, d in enumerate(dleaves) if not is_zero(d)]
        dy0 = jax.tree_util.tree_leaves(tangents[1], is_leaf=is_zero)
        *_, N = flatten_state(y0)
        y0_cols = N if any(not is_zero(d) for d in dy0) else 0
        P = sum(int(np.size(leaves[i])) for i in live)
        if not live and not y0_cols and all(is_zero(d) for d in tangents[2:]):
            out = primal(*primals)
            return out, _no_tangents(out)
        theta = jnp.concatenate([jnp.ravel(leaves[i]) for i in live] + [jnp.zeros(0, ts.dtype)])
        dtype = ts.dtype

        prepared = _prepared(prepare, leaves, treedef, static, live)
        inner = prepare(eqx.combine(dyn, static))
        inner_leaves = jax.tree_util.tree_leaves(eqx.filter(inner, eqx.is_inexact_array))
        depends = _depends_on_inputs(prepared, theta)
        elements = sum(int(np.size(v)) for v, d in zip(inner_leaves, depends) if d)
        if (P + y0_cols > MAX_COLUMNS or elements > MAX_ELEMENTS
                or not all(is_zero(d) for d in tangents[2:])):
            dense = jax.tree_util.tree_map(
                lambda d, p: jnp.zeros_like(p) if is_zero(d) else d, tangents, primals,
                is_leaf=is_zero)
            return jax.jvp(primal, primals, dense)
        pbar = _column_scale(theta)
        field_v = _augmented(inner, prepared, theta, depends, y0_cols, y0, ts[0], pbar)
        S0 = jnp.zeros((N, P + y0_cols), dtype)
        if y0_cols:
            S0 = S0.at[:, P:].set(jnp.eye(N, dtype=dtype))
        # The step control sees the sensitivities too (`solve_adaptive`'s `error_size`).
        control = (N, P + y0_cols) if CONTROL_SENSITIVITIES else N
        (ys, S), result, steps = solve(field_v, (y0, S0), ts, rtol, atol, control)
        d = jnp.concatenate([jnp.ravel(dleaves[i]).astype(dtype) for i in live]
                            + [jnp.zeros(0, dtype)]) / pbar
        if y0_cols:
            d = jnp.concatenate([d] + [jnp.zeros(np.shape(v), dtype).ravel() if is_zero(t)
                                       else jnp.ravel(t).astype(dtype)
                                       for v, t in zip(jax.tree_util.tree_leaves(y0), dy0)])
        dys = S @ d  # (n, N)
        out = (ys, result_code(result), steps)
        return out, (columns_to_tree(dys, y0),) + _no_tangents(out)[1:]

    run.defjvp(run_jvp, symbolic_zeros=True)
    ys, code, steps = run(dyn, y0, ts, rtol, atol)
    return (ys, *outcome(code, steps))


def _as_arrays(tree):
    """`tree` with every leaf an array: a Python number a user differentiates
    (`jax.jacfwd(f)(2.0)`) reaches a custom rule as a literal, which has no dtype."""
    return jax.tree_util.tree_map(jnp.asarray, tree)


def _column_scale(theta):
    """CVODES's `pbar`: the sensitivity columns are integrated scaled by their parameters'
    sizes, so that the step control's tolerance on column q, `atol + rtol |S_q pbar_q|`,
    is the state's own for a relative change of theta_q; 1 for a parameter that is 0 (the
    initial state's columns are not scaled). A value, no derivative: the columns are
    unscaled after the solve, which is exact whatever it is."""
    return jax.lax.stop_gradient(jnp.where(theta == 0, 1.0, jnp.abs(theta)))


def _prepared(prepare, leaves, treedef, static, live):
    """`theta -> the prepared field's inexact leaves`, with the field's leaves `live` (their
    indices in `leaves`) taken from the flat `theta`, in order, and the others as given."""

    def prepared(theta):
        out, o = list(leaves), 0
        for i in live:
            k = int(np.size(leaves[i]))
            out[i] = theta[o:o + k].reshape(np.shape(leaves[i])).astype(leaves[i].dtype)
            o += k
        inner = prepare(eqx.combine(jax.tree_util.tree_unflatten(treedef, out), static))
        return jax.tree_util.tree_leaves(eqx.filter(inner, eqx.is_inexact_array))

    return prepared


def _augmented(inner, prepared, theta, depends, y0_cols, y0, t0, pbar) -> _Variational:
    """The [`_Variational`][] field of `inner` (the prepared field): its leaves that
    `depends` on theta (`prepared(theta)` gives them) are the reverse passes' targets, and
    `dC/dtheta diag(pbar)` (the columns scaled by `pbar`, theta's shape) is formed once,
    here, outside the solve's loop; `y0_cols` zero columns follow for the initial
    state."""
    dtype = theta.dtype
    inner_dyn, inner_static = eqx.partition(inner, eqx.is_inexact_array)
    inner_leaves, inner_def = jax.tree_util.tree_flatten(inner_dyn)
    chain = jax.jacfwd(lambda th: jnp.concatenate(  # (elements, theta's size)
        [jnp.ravel(v) for v, d in zip(prepared(th), depends) if d]
        + [jnp.zeros(0, dtype)]))(theta).astype(dtype) * pbar.astype(dtype)
    chain = jnp.concatenate([chain, jnp.zeros((chain.shape[0], y0_cols), dtype)], axis=1)
    live = jax.tree_util.tree_unflatten(
        inner_def, [v if d else None for v, d in zip(inner_leaves, depends)])
    rest = eqx.combine(jax.tree_util.tree_unflatten(
        inner_def, [None if d else v for v, d in zip(inner_leaves, depends)]), inner_static)
    components, rebuild, _ = flatten_state(y0)
    # Components of the field that merely copy a state component (the crank's phi' = dphi)
    # need no reverse pass: their row is that component's.
    copies = tuple(copied_components(
        lambda x, _: components(inner(t0, rebuild(list(x)), None)), components(y0), None))
    working = _Variational(rest, live, chain, copies, (), components, rebuild)._working(
        t0, None)
    read = _read_elements(working, tuple(components(y0)), live)
    return _Variational(rest, live, chain, copies, read, components, rebuild)


def _no_tangents(out):
    """Zero tangents for `(ys, code, steps)`: float0 for the integer outcome."""
    ys, code, steps = out
    f0 = lambda x: np.zeros(np.shape(x), jax.dtypes.float0)  # noqa: E731
    return jax.tree_util.tree_map(jnp.zeros_like, ys), f0(code), f0(steps)
