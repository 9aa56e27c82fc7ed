"""The step log of `"dopri8-adaptive"`'s reverse mode: the forward pass's record of its
accepted steps, which the discrete adjoint (adjoint.py) takes in reverse.

The log ([`Log`][]) is a ring of rows `(t, t1, h, y...)`, one per accepted step: its
start and end times and step size (s) and its packed state at the start. The step loop
does not write it directly: it holds each step attempt in a [`Pending`][] buffer of
[`PENDING`][] rows ([`write`][]; a rejected attempt is overwritten by the next), stops
when the buffer may not hold another iteration's attempts ([`room`][]), and the loop
around it (once per chunk of save times) moves the buffer to the ring ([`flush`][]).
[`recorder`][] bundles these as adaptive.py's `Recorder`, which `solve_adaptive` takes.

Why the buffer: under XLA's defaults the CPU runtime runs a loop body's kernels one after
the other in the calling thread (inline, no dispatch per kernel) only while every buffer
they touch is <= 512 bytes. A step loop that carried the whole log slowed the forward
pass (docs/benchmarks/design-figures.md).
The buffer is small enough for the step loop to stay inline; the ring, written once per
chunk by the outer loop, may be as large as the log needs (adjoint.py's `LOG_ROWS`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .adaptive import Recorder

__all__ = ["Log", "Pending", "PENDING", "write", "room", "flush", "recorder"]


class Log(NamedTuple):
    """The forward pass's record of its accepted steps.

    - `rows` (S + P, 3 + N): `(t, t1, h, y...)` of accepted step `i` in row `i % S`, `y`
      the packed state (N,) at `t` (s); P = `PENDING` rows of slack (see [`flush`][]);
    - `count`: accepted steps so far (int scalar);
    - `upto`: steps from this index on are not written (a rerun that logs one segment);
    - `mark` (3 + N,): the row of step `upto` itself, the first one not written (zeros
      until it is taken): the backward pass checks with it that a rerun segment joins the
      next one bit for bit (adjoint.py)."""

    rows: jax.Array
    count: jax.Array
    upto: jax.Array
    mark: jax.Array


#: Steps the step loop holds before the loop around it moves them to the log (each column
#: <= 512 bytes: see adaptive.py's `Recorder`).
PENDING = 32


class Pending(NamedTuple):
    """The step loop's buffer of accepted steps not yet in the [`Log`][]: `cols`, the
    columns `(t, t1, h)` (P,) and `y` (P, N), apart so that each is one small buffer (see
    `PENDING`), accepted step `i` in row `i`; `n`, the rows held (int scalar)."""

    cols: tuple
    n: jax.Array


def write(p: Pending, rec) -> Pending:
    """Hold a step attempt `rec` (adaptive.py's record of one member) in row `n`; a rejected
    one is overwritten by the next attempt (`n` moves on when one is accepted)."""
    new = (rec.t[0], rec.t1[0], rec.h[0], rec.y)
    cols = tuple(jax.lax.dynamic_update_slice_in_dim(c, x[None].astype(c.dtype), p.n, 0)
                 for c, x in zip(p.cols, new))
    return Pending(cols, p.n + rec.ok[0].astype(p.n.dtype))


def room(p: Pending, k: int):
    return p.n + k <= p.cols[0].shape[0]


def flush(log: Log, p: Pending):
    """The log with the pending steps in ring rows `count % S`, ... (none from `upto` on;
    step `upto` to `mark`), and an empty buffer: two in-place writes, of the steps before
    the ring's end and of those that wrap to row 0 (S >= P, or fewer than S steps in all:
    they wrap at most once); with the CPU flags a scatter kept XLA from hoisting the loop
    around it."""
    P = p.cols[0].shape[0]
    S = log.rows.shape[0] - P
    block = jnp.column_stack(p.cols).astype(log.rows.dtype)
    k = jnp.arange(P, dtype=log.count.dtype)

    def put(rows, blk, first, at):
        # `blk[j]` is step count + first + j, for row `at + j`; rows with no step keep theirs.
        i = k + first
        keep = (i < p.n) & (log.count + i < log.upto) & (at + k < S)
        blk = jnp.where(keep[:, None], blk, jax.lax.dynamic_slice_in_dim(rows, at, P))
        return jax.lax.dynamic_update_slice_in_dim(rows, blk, at, 0)

    pos = log.count % S
    rows = put(log.rows, block, 0, pos)
    shift = S - pos  # the step that lands in row 0, if any (>= P: none, and none kept)
    padded = jnp.concatenate([block, jnp.zeros_like(block)])
    rows = put(rows, jax.lax.dynamic_slice_in_dim(padded, jnp.minimum(shift, P), P),
               shift, jnp.zeros_like(pos))
    j = log.upto - log.count  # step `upto`'s row in the buffer, if it is there
    mark = jnp.where((j >= 0) & (j < p.n), block[jnp.clip(j, 0, P - 1)], log.mark)
    return Log(rows, log.count + p.n, log.upto, mark), p._replace(n=jnp.zeros_like(p.n))


def recorder(rows: int, n_state: int, dtype, upto) -> Recorder:
    """The `Recorder` that logs a solve's accepted steps to an empty ring of `rows` rows
    (steps from index `upto` on are not written) through an empty [`Pending`][] buffer;
    `n_state`: N, the packed state's size; `dtype`: the rows' (the save times')."""
    log0 = Log(jnp.zeros((rows + PENDING, 3 + n_state), dtype), jnp.zeros((), jnp.int32),
               upto, jnp.zeros((3 + n_state,), dtype))
    col = jnp.zeros((PENDING,), dtype)
    p0 = Pending((col, col, col, jnp.zeros((PENDING, n_state), dtype)), log0.count)
    return Recorder(log0, p0, write, room, flush)
