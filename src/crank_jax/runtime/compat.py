"""Every use of another library's private or undocumented API by the runtime, in one place.

Each entry says why no public API serves and which versions it was written against
(`constraints.txt` pins the versions the suite passed with); tests/test_compat.py fails
loudly, naming the entry, when one of them moves. Everything else in crank-jax uses public
APIs only. Nothing here runs on import. The solver libraries' entries (diffrax's result
codes and Dopri8's dense output, `equinox.internal.while_loop`) are the core's own:
[`crank_jax.solve.library_api`][], under the same rule and the same tests.

Replaced by public APIs: `diffrax.RESULTS` codes were read as `result._value`;
they are now the result's single pytree leaf
([`result_code`][crank_jax.solve.library_api.result_code],
[`result_from_code`][crank_jax.solve.library_api.result_from_code]),
and comparisons use `==` on `diffrax.RESULTS` items. The process-wide switch of
equinox's check mode (`equinox._errors.EQX_ON_ERROR`, set while the fit's programs were
traced so that diffrax's `SaveAt(ts)` check held no host callback) is gone: the fit's
solves go through `simulate`'s solve core, whose fused solvers hold no check and whose
diffrax solvers save inside their steps (`solve/saves.py`, public diffrax API), and a
program that does hold one (an implicit diffrax solver's forward mode, diffrax's reverse
mode) runs unstored (`persistent.py`).
"""

from __future__ import annotations

__all__ = ["backends_are_initialized", "initialize_lapack", "distributed_client"]


# --- jax internals ---------------------------------------------------------------------

def backends_are_initialized() -> bool:
    """Whether JAX has started its backends (after which `XLA_FLAGS` and the CPU device
    count no longer change anything).

    Why private: JAX has no public query; `jax.devices()` would start the backends itself.
    `jax._src.xla_bridge.backends_are_initialized`, jax 0.4-0.10 (0.10.2 tested)."""
    from jax._src import xla_bridge

    return bool(xla_bridge.backends_are_initialized())


def distributed_client():
    """The client of JAX's coordination service once `jax.distributed.initialize` has run
    (a `DistributedRuntimeClient`: a multi-process sweep waits at its barriers with
    `wait_at_barrier(name, timeout_ms)`), else `None`.

    Why private: JAX has no public handle on its coordination service; Gloo's collectives
    time out after 30 s, which a peer still compiling exceeds, and a barrier of the service
    has a timeout of ours. `jax._src.distributed.global_state.client`, jax 0.4-0.10 (0.10.2
    tested)."""
    from jax._src import distributed

    return distributed.global_state.client


def initialize_lapack() -> None:
    """Register LAPACK's custom-call targets with XLA:CPU, as lowering any linear algebra
    does (needed before a deserialised program that calls them runs).

    Why private: JAX registers them lazily, on the first lowering of a linear-algebra
    primitive; `jax._src.lax.linalg.initialize_lapack` does just that, cheaper than
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
