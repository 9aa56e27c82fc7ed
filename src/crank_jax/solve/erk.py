"""A fused explicit Runge-Kutta step, generic over a Butcher tableau and a vector field.

Why not diffrax's own `AbstractERK.step`? For a state of a few scalars (the crank's
`(phi, phi')`), a diffrax step on the CPU is bound by per-kernel overhead, not arithmetic:
diffrax runs the stages in a `while_loop` over a stacked `k` array, so every stage is
several small XLA kernels. Here the stages of the same tableau are unrolled into
straight-line code on the leaves of `y`, so XLA fuses each stage with the vector field's
arithmetic (a few kernels per stage for the crank), and a step is cheaper (the
work-precision table of docs/benchmarks/performance.md,
experiments/bench_work_precision.py). The tableau
itself is diffrax's, so the method is exactly diffrax's.

`FusedERK` knows nothing of the equation: it steps any `f(t, y, args) -> dy/dt`, with `y`
a pytree of arrays (small: the stages are unrolled per leaf). With `rolled=True` the stages
run in a loop instead, for a field that is costly to trace (the fit's variational solves).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["FusedERK", "Tableau", "dopri8", "rms_error", "packer"]

# Rounding noise in the embedded error estimate, in units of eps h sum |e_i k_i| (`step`).
_NOISE = 8.0


def _nonzero(coeffs, ks):
    return [(float(a), k) for a, k in zip(coeffs, ks) if float(a) != 0.0]


def _combine(y, h, coeffs, ks):
    """`y + h sum_i a_i k_i` leaf by leaf, skipping zero coefficients (unrolled)."""
    terms = _nonzero(coeffs, ks)
    if not terms:
        return y

    def leaf(y_leaf, *k_leaves):
        acc = None
        for (a, _), k in zip(terms, k_leaves):
            acc = a * k if acc is None else acc + a * k
        return y_leaf + h * acc

    return jax.tree_util.tree_map(leaf, y, *[k for _, k in terms])


class Tableau(NamedTuple):
    """A Butcher tableau as tuples of Python floats: `c` (s-1,), `b_sol`, `b_error`
    (s,), `a_lower` (row i: (i,), i = 1..s-1), and whether it is `implicit`. Hashable and
    compared by value (diffrax's `ButcherTableau` holds NumPy arrays, which are neither),
    so that a solver holding its method is a key of compiled programs."""

    c: tuple
    b_sol: tuple
    b_error: tuple | None
    a_lower: tuple
    implicit: bool = False


def as_tableau(tableau) -> Tableau:
    """A [`Tableau`][] from a `diffrax.ButcherTableau` (or a `Tableau`)."""
    if isinstance(tableau, Tableau):
        return tableau

    def floats(x):
        return None if x is None else tuple(float(v) for v in np.asarray(x, float))

    return Tableau(floats(tableau.c), floats(tableau.b_sol), floats(tableau.b_error),
                   tuple(floats(row) for row in tableau.a_lower),
                   bool(getattr(tableau, "implicit", False)))


class FusedERK(eqx.Module):
    """An explicit Runge-Kutta method with an embedded error estimate, its stages unrolled.

    **Fields:** `tableau`, a `diffrax.ButcherTableau` (explicit; e.g.
    `diffrax.Dopri8.tableau`), held as a hashable [`Tableau`][]; `order`, the order of the
    solution (the embedded estimate is of order `order - 1`).

    Trailing stages whose weights are zero in both the solution and the error estimate
    (Dopri8's 14th, first-same-as-last stage) are not evaluated: recomputing such a stage at
    the next step costs what carrying it would.
    """

    tableau: Tableau = eqx.field(static=True, converter=as_tableau, repr=False)
    order: int = eqx.field(static=True)
    rolled: bool = eqx.field(static=True, default=False)
    """Evaluate the stages in a loop (`lax.fori_loop`) instead of unrolled: the field is
    traced once, not once per stage. For a costly field to trace (the variational
    equation's, variational.py: a reverse pass per component per stage), where the
    unrolled step dominated the fit's compilation (see `_rolled_stages`)."""

    def __check_init__(self):
        if self.tableau.implicit:
            raise ValueError("FusedERK needs an explicit tableau")
        if self.tableau.b_error is None:
            raise ValueError("FusedERK needs a tableau with an embedded error estimate")

    @property
    def num_stages(self) -> int:
        """Stages evaluated per step."""
        tab = self.tableau
        n = len(tab.b_sol)
        while n > 1 and float(tab.b_sol[n - 1]) == 0.0 and float(tab.b_error[n - 1]) == 0.0:
            n -= 1
        return n

    def stages(self, f, t, y, args, h, k0=None) -> list:
        """The stage derivatives `k_i = f(t + c_i h, y + h sum_j a_ij k_j, args)`, a list of
        pytrees shaped like `y`. `k0`, if given, is `f(t, y, args)` already known (the last
        stage of the previous step, for a first-same-as-last method)."""
        tab = self.tableau
        c = [0.0] + [float(x) for x in tab.c]
        ks = [f(t, y, args) if k0 is None else k0]
        if self.rolled:
            return self._rolled_stages(f, t, y, args, h, ks[0], c)
        for i in range(1, self.num_stages):
            yi = _combine(y, h, tab.a_lower[i - 1], ks)
            ks.append(f(t + c[i] * h, yi, args))
        return ks

    def _rolled_stages(self, f, t, y, args, h, k0, c) -> list:
        """`stages` in a `fori_loop` over the stages, the stage derivatives stacked
        (stages,) + each leaf's shape. Each stage sums `a_ij k_j` over every earlier stage
        in order, zeros included (adding an exact zero changes nothing), so the values are
        the unrolled stages' up to XLA's choice of fused multiply-adds.

        Why: the multiple-shooting fit's Jacobian steps the variational equation, whose
        field takes a reverse pass per state component; unrolled over Dopri8's 13 stages
        and batched over the segments it took long to trace and most of the fit's XLA
        compile (experiments/fit_solver_tradeoff.py; docs/benchmarks/design-figures.md)."""
        tab, n = self.tableau, self.num_stages
        dtype = jnp.result_type(*jax.tree_util.tree_leaves(k0))
        A = np.zeros((n, n))
        for i in range(1, n):
            A[i, :i] = np.asarray(tab.a_lower[i - 1], float)[:i]
        A, cs = jnp.asarray(A, dtype), jnp.asarray(c[:n], dtype)

        def body(i, K):
            a = A[i]

            def leaf(y_leaf, K_leaf):
                acc = a[0] * K_leaf[0]
                for j in range(1, n - 1):
                    acc = acc + a[j] * K_leaf[j]
                return y_leaf + h * acc

            ki = f(t + cs[i] * h, jax.tree_util.tree_map(leaf, y, K), args)
            return jax.tree_util.tree_map(lambda K_leaf, k: K_leaf.at[i].set(k), K, ki)

        K0 = jax.tree_util.tree_map(
            lambda k: jnp.zeros((n,) + jnp.shape(k), dtype).at[0].set(k), k0)
        K = jax.lax.fori_loop(1, n, body, K0)
        return [k0] + [jax.tree_util.tree_map(lambda K_leaf: K_leaf[i], K)
                       for i in range(1, n)]

    def solution(self, y, h, ks):
        """`y1 = y + h sum_i b_i k_i`."""
        return _combine(y, h, self.tableau.b_sol[: len(ks)], ks)

    def step(self, f, t, y, args, h):
        """One step of size `h` (s) from `(t, y)`.

        **Returns:** `(y1, err)`, both pytrees shaped like `y`: the solution and the
        magnitude of the embedded local-error estimate, with its rounding noise taken off
        (>= 0).
        """
        ks = self.stages(f, t, y, args, h)
        return self.solution(y, h, ks), self.error(h, ks)

    def error(self, h, ks):
        """The magnitude of the embedded local-error estimate of a step of size `h` with
        stages `ks`, its rounding noise taken off (>= 0), a pytree shaped like `y`."""
        terms = _nonzero(self.tableau.b_error[: len(ks)], ks)
        eps = jnp.finfo(jnp.result_type(h)).eps

        def leaf(*k_leaves):
            est = sum(e * k for (e, _), k in zip(terms, k_leaves))
            # The error weights sum to zero, so `est` is a difference of terms of size
            # h |k|: its rounding error is ~eps h sum |e k|. Below a few times that, the
            # estimate is noise that a smaller step does not shrink (it drove the step
            # count to the budget at rtol 1e-12 once), so the noise is taken off.
            noise = _NOISE * eps * sum(abs(e) * jnp.abs(k) for (e, _), k in zip(terms, k_leaves))
            return jnp.maximum(jnp.abs(h) * (jnp.abs(est) - noise), 0.0)

        return jax.tree_util.tree_map(leaf, *[k for _, k in terms])


def packer(y0, batch_dims: int = 0):
    """`(pack, unpack)`: a state pytree to one flat (N,) array and back, the latter for any
    leading axes. The solvers record one array per save time: one XLA update instead of
    one per leaf (a few percent of a `vmap`-ed batch's time). With `batch_dims`, the leaves
    of `y0` carry that many leading batch axes, which `pack` keeps: (B..., N)."""
    leaves, treedef = jax.tree_util.tree_flatten(y0)
    shapes = [jnp.shape(x)[batch_dims:] for x in leaves]
    sizes = [int(np.prod(s, dtype=int)) for s in shapes]

    def pack(y):
        parts = jax.tree_util.tree_leaves(y)
        if all(s == () for s in shapes):
            return jnp.stack(parts, axis=-1)
        return jnp.concatenate([x.reshape(x.shape[:x.ndim - len(s)] + (-1,))
                                for x, s in zip(parts, shapes)], axis=-1)

    def unpack(Y):
        out, i = [], 0
        for s, k in zip(shapes, sizes):
            part = Y[..., i] if s == () else Y[..., i:i + k].reshape(Y.shape[:-1] + s)
            out.append(part)
            i += k
        return jax.tree_util.tree_unflatten(treedef, out)

    return pack, unpack


def rms_error(err, y0, y1, rtol, atol):
    """diffrax's RMS norm of a local error, scaled by `atol + rtol max(|y0|, |y1|)`, over
    every element of every leaf (a scalar)."""
    leaves = jax.tree_util.tree_leaves(
        jax.tree_util.tree_map(
            lambda e, a, b: (e / (atol + rtol * jnp.maximum(jnp.abs(a), jnp.abs(b)))) ** 2,
            err, y0, y1))
    total = sum(jnp.sum(x) for x in leaves)
    size = sum(int(jnp.size(x)) for x in leaves)
    return jnp.sqrt(total / size)


#: diffrax's Dopri8 (order 8, embedded order 7), fused.
@functools.cache
def dopri8(rolled: bool = False) -> FusedERK:
    """Dormand-Prince 8(5,3) (diffrax's tableau) as a [`FusedERK`][]: one object per
    `rolled` (see `FusedERK.rolled`), so that programs keyed on it compile once."""
    # diffrax's numbers, copied (see the module `dopri8_tableau`: reading them from
    # diffrax imports it, 0.6-1.0 s of a process that needs nothing else of it).
    from .dopri8_tableau import DOPRI8

    return FusedERK(Tableau(**DOPRI8), 8, rolled)
