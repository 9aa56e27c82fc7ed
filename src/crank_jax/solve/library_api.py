"""The solver libraries' APIs that `solve/` uses beyond their documented surface: diffrax's
result codes as arrays, Dopri8's dense-output coefficients (private), and
`equinox.internal.while_loop` (internal). The core's part of the compat rule: each entry
says why no public API serves and which versions it was written against
(`constraints.txt` pins the versions the suite passed with), and tests/test_compat.py
fails loudly, naming the entry, when one of them moves. The runtime's part (JAX's
internals: its backends, LAPACK's registration) is [`crank_jax.runtime.compat`][]. Nothing
here runs on import.
"""

from __future__ import annotations

import numpy as np

__all__ = ["result_code", "result_from_code", "dopri8_dense_coefficients", "while_loop"]


# --- diffrax.RESULTS as arrays (public: the pytree interface) -------------------------

def result_code(result):
    """The integer array behind a `diffrax.RESULTS` item (its only pytree leaf), e.g. to
    return it from a `custom_jvp`/`custom_vjp`/`custom_vmap` rule, which take arrays."""
    import jax

    (code,) = jax.tree_util.tree_leaves(result)
    return code


def result_from_code(code):
    """A `diffrax.RESULTS` item from an array that [`result_code`][] gave (any shape)."""
    import diffrax
    import jax

    treedef = jax.tree_util.tree_structure(diffrax.RESULTS.successful)
    return jax.tree_util.tree_unflatten(treedef, [code])


# --- diffrax: Dopri8's dense output ----------------------------------------------------

def dopri8_dense_coefficients() -> np.ndarray:
    """diffrax's Dopri8 dense output coefficients, (14 stages, powers), highest power first.

    Why private: diffrax exposes the interpolation only through a solution
    (`SaveAt(dense=True)`, `sol.evaluate`), never the coefficients a fused step needs;
    they sit on `Dopri8.interpolation_cls` (the private `_Dopri8Interpolation`) as
    `eval_coeffs`. Written against diffrax 0.6 and 0.7 (0.7.2 tested)."""
    import diffrax

    return np.asarray(diffrax.Dopri8.interpolation_cls.eval_coeffs, dtype=float)


# --- equinox.internal.while_loop -------------------------------------------------------

def while_loop(cond_fun, body_fun, init_val, *, max_steps: int, kind: str):
    """`equinox.internal.while_loop`: a bounded while loop, `kind` "lax", "bounded" or
    "checkpointed".

    Why internal: reverse mode through a while loop (the `"checkpointed"` kind, treeverse
    checkpointing, as diffrax's `RecursiveCheckpointAdjoint` uses) has no public API in
    JAX or equinox; `jax.lax.while_loop` is forward-mode only. Written against equinox
    0.11-0.13 (0.13.8 tested)."""
    import equinox.internal as eqxi

    return eqxi.while_loop(cond_fun, body_fun, init_val, max_steps=max_steps, kind=kind)
