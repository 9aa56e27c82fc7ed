"""The collectives of a multi-process sweep: gather every process's part of a chunk, and
send process 0's checkpointed chunk to the others. A collective whose peer died fails
(at once when the peer's socket closes, else after Gloo's 30 s timeout); it is reported
as one `RuntimeError` that says what happened and what to do.

Gloo's collectives give up after 30 s, but a peer may be busy far longer: compiling the
chunk (hosts compile at their own pace: on a loaded machine one process can take longer
than that timeout more than the other; docs/benchmarks/design-figures.md), or solving a
stiffer part. So every collective first waits at
a barrier of JAX's coordination service ([`sync`][]), whose timeout is ours
([`SYNC_TIMEOUT_S`][]); a dead peer still ends the wait, by the service's heartbeat.
Every process then enters the collective within milliseconds of the others.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
import time

import jax
import numpy as np

from ..runtime.compat import distributed_client

__all__ = ["gather", "broadcast", "lost", "on_process_0", "sync", "SYNC_TIMEOUT_S",
           "same_everywhere", "check_cluster", "wait_for_coordinator"]

#: The longest a process waits at a barrier for its peers (s): a day, for a chunk that
#: takes long on one host. A peer that dies is noticed sooner (the heartbeat timeout).
SYNC_TIMEOUT_S = 86_400
#: Test hook: seconds this process sleeps before its first collective (a slow peer).
DELAY_ENV = "CRANK_JAX_TEST_COLLECTIVE_DELAY"

_barriers = 0  # barriers passed by this process (their ids; the same on every process)


def _cluster_value(kwargs: dict, key: str, env: str):
    """(value, its name for a message): the argument `key`, else environment variable
    `env` (None when neither is set)."""
    if kwargs.get(key) is not None:
        return kwargs[key], f"{key}="
    text = os.environ.get(env, "").strip()
    return (text or None), f"environment variable {env}="


def check_cluster(kwargs: dict) -> None:
    """`ValueError` naming the argument (or the environment variable it comes from) for a
    cluster that `jax.distributed.initialize(**kwargs)` cannot join, before it tries: a
    coordinator address that is not HOST:PORT with a port from 1 to 65535 (JAX raised
    `IndexError`, aborted, or waited minutes), a process count below 1, a process index
    outside 0 to count - 1."""
    address, where = _cluster_value(kwargs, "coordinator_address", "JAX_COORDINATOR_ADDRESS")
    if address is not None:
        host, sep, port = address.rpartition(":") if isinstance(address, str) else ("",) * 3
        if not (sep and host.strip("[]") and port.isdigit() and 0 < int(port) < 65536):
            raise ValueError(f"{where}{address!r}: expected 'HOST:PORT', the address of "
                             "process 0 with a port from 1 to 65535 (e.g. 'node0:1234')")
    counts = {}
    for key, env, low in (("num_processes", "JAX_NUM_PROCESSES", 1),
                          ("process_id", "JAX_PROCESS_ID", 0)):
        value, where = _cluster_value(kwargs, key, env)
        if isinstance(value, str):
            value = int(value) if value.lstrip("-").isdigit() else value
        if value is not None and (isinstance(value, bool) or not isinstance(
                value, (int, np.integer)) or value < low):
            raise ValueError(f"{where}{value!r}: expected an integer >= {low}")
        counts[key] = (value, where)
    (n, n_where), (pid, pid_where) = counts["num_processes"], counts["process_id"]
    if n is not None and pid is not None and pid >= n:
        raise ValueError(f"{pid_where}{pid} must be below {n_where}{n} (processes are "
                         "numbered from 0)")


def wait_for_coordinator(kwargs: dict) -> None:
    """In a process other than 0: wait, at most `initialization_timeout` s (JAX's default,
    300), until the coordinator accepts connections. JAX aborts the whole Python process
    (a C++ stack dump, no exception) when it cannot reach it; here it is a `RuntimeError`
    naming the address. Call after [`check_cluster`][]."""
    address, where = _cluster_value(kwargs, "coordinator_address", "JAX_COORDINATOR_ADDRESS")
    pid, _ = _cluster_value(kwargs, "process_id", "JAX_PROCESS_ID")
    if address is None or pid is None or int(pid) == 0:
        return
    host, _, port = address.rpartition(":")
    wait = float(kwargs.get("initialization_timeout") or 300)
    deadline = time.monotonic() + wait
    while True:
        try:
            socket.create_connection((host.strip("[]"), int(port)), timeout=2).close()
            return
        except OSError as e:
            if time.monotonic() > deadline:
                raise RuntimeError(f"{where}{address!r}: process 0 (the coordinator) did not "
                                   f"answer within {wait:g} s ({e.strerror or e}); start "
                                   "process 0 first, check the address, or give a longer "
                                   "initialization_timeout") from None
            time.sleep(0.5)


def sync() -> None:
    """Wait until every process reaches this point (no-op with one process). Every
    process calls the collectives in the same order, so the n-th barrier is the same one
    everywhere."""
    global _barriers
    if jax.process_count() == 1:
        return
    client = distributed_client()
    if client is None:
        return
    _barriers += 1
    if _barriers == 1 and os.environ.get(DELAY_ENV):
        time.sleep(float(os.environ[DELAY_ENV]))
    try:
        client.wait_at_barrier(f"crank-jax-sweep-{_barriers}", SYNC_TIMEOUT_S * 1000)
    except Exception as e:  # noqa: BLE001 (a JaxRuntimeError from the service)
        raise lost(e) from None


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

    sync()
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
    sync()
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


_SLOTS = 64  # fields compared by name (more are compared as a whole only)


def same_everywhere(fields: dict, what: str) -> None:
    """Check that every process holds the same `fields` (JSON values, e.g. a sweep's plan),
    before any work: each process sends a digest of the whole and of each field, and
    every process raises the same `ValueError`, naming the processes and fields that
    differ from process 0's, if any does (a process given another `--seed` once wrote a
    file mixing two plans, exit 0)."""
    if jax.process_count() == 1:
        return
    keys = sorted(fields)[:_SLOTS]

    def h(value) -> bytes:
        return hashlib.sha256(json.dumps(value, sort_keys=True).encode()).digest()

    row = np.zeros((1, 32 + 8 * _SLOTS), np.uint8)
    row[0, :32] = np.frombuffer(h(fields), np.uint8)
    for i, k in enumerate(keys):
        row[0, 32 + 8 * i:40 + 8 * i] = np.frombuffer(h(fields[k])[:8], np.uint8)
    rows = gather(row)
    bad = [p for p in range(rows.shape[0]) if not np.array_equal(rows[p], rows[0])]
    if not bad:
        return
    differ = [k for i, k in enumerate(keys)
              if any(not np.array_equal(rows[p, 32 + 8 * i:40 + 8 * i],
                                        rows[0, 32 + 8 * i:40 + 8 * i]) for p in bad)]
    raise ValueError(f"the processes of this distributed run were given different "
                     f"{what}s: process(es) {', '.join(map(str, bad))} differ from process "
                     f"0 in {', '.join(differ) or 'their fields'}; give every process the "
                     "same arguments and files (`samples=`, `n=`, `seed=`, the scene, ...)")
