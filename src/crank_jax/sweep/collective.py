"""The collectives of a multi-process sweep: gather every process's part of a chunk, and
send process 0's checkpointed chunk to the others. A collective whose peer died fails
(at once when the peer's socket closes, else after Gloo's 30 s timeout); it is reported
as one `RuntimeError` that says what happened and what to do."""

from __future__ import annotations

import jax
import numpy as np

__all__ = ["gather", "broadcast", "lost", "on_process_0"]


def lost(e: Exception) -> RuntimeError:
    """The error of a collective that failed: in practice another process died or the
    coordinator went away."""
    first = (str(e).strip().splitlines() or [type(e).__name__])[0][:300]
    return RuntimeError(f"the distributed sweep lost a process: a collective with the other "
                        f"{jax.process_count() - 1} process(es) failed ({first}); rerun "
                        "every process (with a checkpoint only the missing chunks are "
                        "computed)")


def gather(tree):
    """This process's part of a chunk's results (a tree of host arrays), joined with every
    other process's, in process order (identity with one process)."""
    if jax.process_count() == 1:
        return tree
    from jax.experimental import multihost_utils

    try:
        got = multihost_utils.process_allgather(tree, tiled=False)
    except Exception as e:  # noqa: BLE001 (JaxRuntimeError, a ValueError, from Gloo)
        raise lost(e) from None
    return jax.tree.map(lambda x: np.concatenate(list(x)), got)


def broadcast(tree):
    """`tree` of NumPy arrays from process 0 to every process, bit for bit: sent as bytes
    (JAX's broadcast is a sum with zeros, which would turn -0.0 into 0.0). The other
    processes pass arrays of the same shapes and dtypes."""
    if jax.process_count() == 1:
        return tree
    from jax.experimental import multihost_utils

    raw = jax.tree.map(lambda a: np.ascontiguousarray(a).reshape(-1).view(np.uint8), tree)
    try:
        got = multihost_utils.broadcast_one_to_all(raw)
    except Exception as e:  # noqa: BLE001 (as in `gather`)
        raise lost(e) from None
    return jax.tree.map(lambda b, a: np.asarray(b).view(a.dtype).reshape(a.shape), got, tree)


def on_process_0(make, what: str):
    """`make()` on process 0 only (which alone touches the disk), and its `ValueError`
    raised on every process, so that no process waits for a refused one. Returns what
    `make` returned on process 0, `None` elsewhere."""
    obj, err = None, None
    if jax.process_index() == 0:
        try:
            obj = make()
        except ValueError as e:
            err = e
    ok = broadcast(np.array([err is None], np.int8))[0]
    if err is not None:
        raise err
    if not ok:
        raise ValueError(f"{what} was refused by process 0 (its message says why)")
    return obj
