"""Environment variables the CLI reads, each checked before any work: a bad value is a
one-line message naming the variable and the fix (exit 2), never a traceback from the
library that reads it later (JAX's own IndexError for an address without a port)."""

from __future__ import annotations

import os

from .errors import UserError

__all__ = ["env_int", "check_cluster_env"]


def env_int(name: str, default: int, lo: int, what: str) -> int:
    """The integer value of environment variable `name` (`default` when unset or empty);
    [`UserError`][] naming it unless it is an integer >= `lo`. `what`: its meaning, for the
    message (e.g. "seconds to wait")."""
    text = os.environ.get(name, "").strip()
    if not text:
        return default
    try:
        value = int(text)
    except ValueError:
        value = None
    if value is None or value < lo:
        raise UserError(f"environment variable {name}={text!r}: expected {what}, an integer "
                        f">= {lo}; set it to one, or unset it")
    return value


def check_cluster_env() -> None:
    """Check the cluster's variables that a distributed run hands to `jax.distributed`:
    `JAX_COORDINATOR_ADDRESS` (HOST:PORT), `JAX_NUM_PROCESSES` (>= 1) and
    `JAX_PROCESS_ID` (0 to JAX_NUM_PROCESSES - 1), when set."""
    address = os.environ.get("JAX_COORDINATOR_ADDRESS", "").strip()
    if address:
        host, sep, port = address.rpartition(":")
        if not (sep and host.strip("[]") and port.isdigit() and 0 < int(port) < 65536):
            raise UserError(f"environment variable JAX_COORDINATOR_ADDRESS={address!r}: "
                            "expected HOST:PORT, the address of process 0 (e.g. "
                            "node0:1234); set it so or unset it (SLURM/MPI auto-detection)")
    n = env_int("JAX_NUM_PROCESSES", 0, 1, "the number of processes")
    pid = env_int("JAX_PROCESS_ID", 0, 0, "this process's index")
    if n and pid >= n:
        raise UserError(f"environment variable JAX_PROCESS_ID={pid} must be below "
                        f"JAX_NUM_PROCESSES={n} (processes are numbered from 0)")
