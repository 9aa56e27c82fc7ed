"""A solve whose primal steps one form of a vector field and whose reverse-mode derivatives
come from another form of the same field.

Why: the form that steps fastest is not always the one whose backward pass is cheapest.
`CrankField.packed()` forms the parameter parts of M, K, q once, in one array, which makes
the primal step loop compile like one with constant parameters; but a backward pass through
that array's slices accumulates each stage's cotangent slice by slice, and reverse passes of
the field cost ~2.4x more than through the parameters themselves. Measured on the lab rig
(`"dopri8-uniform"`, jitted `grad` of a sum over 1001 samples, 10 parameters): 233 ms and
38 s of compilation stepping the plain field, 570 ms and 83 s stepping the packed one,
283 ms and 47 s with the primal packed and the backward pass plain (this module).

Generic over the field: `prepare` maps it to the form the primal steps.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax

from ..compat import result_code
from .adaptive import outcome

__all__ = ["reverse_twin"]


def reverse_twin(run: Callable, field, prepare: Callable, *args):
    """`run(prepare(field), *args)`, with the reverse-mode derivatives (`jax.grad`,
    `jax.vjp`) of `run(field, *args)`.

    **Arguments:** `run(field, *args) -> (ys, result, steps)`, a solve (`result` a
    `diffrax.RESULTS`); `field`, a pytree whose array leaves are differentiable;
    `prepare(field)`, the same vector field in the form the primal steps; `args`, arrays.

    **Returns:** `(ys, result, steps)`; `result` and `steps` carry no derivative. The
    backward pass runs the plain solve's forward pass again (one more solve). The two
    forms must be the same function (for the crank: tests/test_dynamics.py). No forward
    mode (a `jax.custom_vjp`).
    """
    dyn, static = eqx.partition(field, eqx.is_array)

    def arrays(fld, *rest):  # a custom_vjp returns arrays: the outcome as its code
        ys, result, steps = run(fld, *rest)
        return ys, result_code(result), steps

    def plain(d, *rest):
        return arrays(eqx.combine(d, static), *rest)

    @jax.custom_vjp
    def solve(d, *rest):
        return arrays(prepare(eqx.combine(d, static)), *rest)

    def fwd(d, *rest):
        return solve(d, *rest), (d,) + rest

    def bwd(res, g):
        return jax.vjp(plain, *res)[1](g)

    solve.defvjp(fwd, bwd)
    ys, code, steps = solve(dyn, *args)
    return (ys, *outcome(code, steps))
