"""The XLA flag that makes crank-jax's solves about 2x faster on the CPU, for programs to set.

XLA's CPU runtime (jax >= 0.7) runs a compiled program as a sequence of kernels ("thunks"),
one call each, and a loop body's kernels once per iteration. A small solver step is ~30
kernels of a few scalars each, so the dispatch, not the arithmetic, sets its cost. XLA
compiles a `while` loop into a single function instead (its `SmallWhileLoopHoistingPass`)
when one iteration touches fewer bytes than `xla_cpu_small_while_loop_byte_threshold`,
1024 by default: too few for an eighth-order step (13 stages, each reading the packed
coefficients) or for the loop that writes the saved samples. Raising it to
[`SMALL_LOOP_BYTES`][] hoists those loops. Measured on the lab rig (2-core AMD EPYC, jax
0.10.2; experiments/bench_throughput.py, bench_gradients.py, bench_end_to_end.py):
one trajectory 1.35 -> 0.57 ms, a 10-parameter forward Jacobian 15.4 -> 6.4 ms, a warm
`crank-jax demo` ~2.2 -> ~1.8 s with its LM iterations 3x faster, its first compile 7.9 ->
5.8 s; a 10^4 batch is unchanged (its kernels are large). Results are the same up to
rounding.

The threshold is a process-wide setting that XLA reads from the `XLA_FLAGS` environment
variable when JAX starts its CPU backend (`jax.jit`'s `compiler_options` cannot set it:
it lives in a map field of XLA's options). So the library never sets it (importing a
library must not reconfigure its host), but the `crank-jax` program does, before JAX
starts, unless `XLA_FLAGS` already names the threshold. A Python user sets it the same
way, before the first JAX computation:

    import os
    from crank_jax.xla_flags import with_small_loops
    os.environ["XLA_FLAGS"] = with_small_loops(os.environ.get("XLA_FLAGS"))

or in the shell (one line):

    export XLA_FLAGS=--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1048576
"""

from __future__ import annotations

import re

__all__ = ["SMALL_LOOP_BYTES", "SMALL_LOOP_FLAG", "with_small_loops", "small_loops_set"]

#: Loops touching fewer bytes per iteration than this are compiled into one function. 1 MiB
#: takes in the solvers' step loops and the loops that write their saved samples (XLA counts
#: the bytes of one iteration: a save writes its rows, not the whole output); a loop that
#: touches more per iteration runs kernels large enough that their dispatch does not
#: matter, and keeps XLA's multi-threaded kernels.
SMALL_LOOP_BYTES = 1 << 20

_KEY = "xla_cpu_small_while_loop_byte_threshold"
#: The flag, as it goes into `XLA_FLAGS`.
SMALL_LOOP_FLAG = f"--xla_backend_extra_options={_KEY}={SMALL_LOOP_BYTES}"


def small_loops_set(flags: str | None) -> bool:
    """Whether an `XLA_FLAGS` value already names the small-loop threshold."""
    return bool(flags) and _KEY in flags


def with_small_loops(flags: str | None) -> str:
    """`flags` (an `XLA_FLAGS` value, or None) with the threshold set to
    [`SMALL_LOOP_BYTES`][], unless it already names the threshold (the user's choice
    wins). Other backend extra options are kept: the threshold joins their
    comma-separated list."""
    flags = (flags or "").strip()
    if small_loops_set(flags):
        return flags
    opt = "--xla_backend_extra_options="
    if opt in flags:
        def join(m):
            theirs = m.group(1) + "," if m.group(1) else ""
            return f"{opt}{theirs}{_KEY}={SMALL_LOOP_BYTES}"

        return re.sub(re.escape(opt) + r"(\S*)", join, flags, count=1)
    return f"{flags} {SMALL_LOOP_FLAG}".strip()
