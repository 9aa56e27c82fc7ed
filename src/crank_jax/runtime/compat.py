"""Every use of another library's private or undocumented API, in one place.

Each entry says why no public API serves and which versions it was written against
(`constraints.txt` pins the versions the suite passed with); tests/test_compat.py fails
loudly, naming the entry, when one of them moves. Everything else in crank-jax uses public
APIs only. Nothing here runs on import.

Replaced by public APIs (issue 26): `diffrax.RESULTS` codes were read as `result._value`;
they are now the result's single pytree leaf ([`result_code`][], [`result_from_code`][]),
and comparisons use `==` on `diffrax.RESULTS` items. The process-wide switch of
equinox's check mode (`equinox._errors.EQX_ON_ERROR`, set while the fit's programs were
traced so that diffrax's `SaveAt(ts)` check held no host callback) is gone: the fit's
solves go through `simulate`'s solve core, whose fused solvers hold no check and whose
diffrax solvers save inside their steps (`solve/saves.py`, public diffrax API), and a
program that does hold one (an implicit diffrax solver's forward mode, diffrax's reverse
mode) runs unstored (`persistent.py`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["result_code", "result_from_code", "dopri8_dense_coefficients", "while_loop",
           "backends_are_initialized", "initialize_lapack"]


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


# --- jax internals ---------------------------------------------------------------------

def backends_are_initialized() -> bool:
    """Whether JAX has started its backends (after which `XLA_FLAGS` and the CPU device
    count no longer change anything).

    Why private: JAX has no public query; `jax.devices()` would start the backends itself.
    `jax._src.xla_bridge.backends_are_initialized`, jax 0.4-0.10 (0.10.2 tested)."""
    from jax._src import xla_bridge

    return bool(xla_bridge.backends_are_initialized())


def initialize_lapack() -> None:
    """Register LAPACK's custom-call targets with XLA:CPU, as lowering any linear algebra
    does (needed before a deserialised program that calls them runs).

    Why private: JAX registers them lazily, on the first lowering of a linear-algebra
    primitive; `jax._src.lax.linalg.initialize_lapack` does just that, 0.1 s cheaper than
    lowering a QR, which is the public fallback used when it is missing. jax 0.7-0.10
    (0.10.2 tested)."""
    try:
        from jax._src.lax.linalg import initialize_lapack as init

        init()
        return
    except Exception:  # moved or failed: the public way
        pass
    import jax
    import jax.numpy as jnp

    jax.jit(jnp.linalg.qr).lower(jax.ShapeDtypeStruct((2, 2), jnp.float32))
