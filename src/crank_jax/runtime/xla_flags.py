"""The XLA flags that make crank-jax's solves faster on the CPU, for programs to set.

Two settings of XLA's CPU compiler, both process-wide and read from the `XLA_FLAGS`
environment variable when JAX starts its CPU backend:

- **The small-loop threshold.** XLA's CPU runtime (jax >= 0.7) runs a compiled program as a
  sequence of kernels ("thunks"), one call each, and a loop body's kernels once per
  iteration. A small solver step is ~30 kernels of a few scalars each, so the dispatch,
  not the arithmetic, sets its cost. XLA compiles a `while` loop into a single function
  instead (its `SmallWhileLoopHoistingPass`) when one iteration touches fewer bytes than
  `xla_cpu_small_while_loop_byte_threshold`, 1024 by default: too few for an eighth-order
  step (13 stages, each reading the packed coefficients) or for the loop that writes the
  saved samples. [`SMALL_LOOP_BYTES`][] hoists them: single trajectories, forward
  Jacobians and a fit's iterations run faster and compile sooner; a large batch does not
  change (its kernels are large).
- **512-bit vectors** (`xla_cpu_prefer_vector_width`, 256 by default), only on a CPU with
  AVX-512: a lockstep batch is SIMD arithmetic over its members, and twice the lanes per
  instruction make a large batch faster there (single trajectories: no change, they are
  scalar code).

The figures: the "With the CPU flags" table of docs/benchmarks/performance.md (the
benchmark scripts run with the flags set, their results tagged `_cpu_flags`) and
docs/benchmarks/design-figures.md.

Results are the same up to rounding (tests/test_xla_flags.py). `jax.jit`'s
`compiler_options` cannot set the threshold (it lives in a map field of XLA's options),
and a library must not reconfigure its host, so crank-jax never sets them: the `crank-jax`
program does, before JAX starts, keeping any value the user put in `XLA_FLAGS`. A Python
program sets them the same way, before its first JAX computation:

    import crank_jax as cj
    cj.configure_cpu(devices=1)  # the flags; one device is JAX's default

or calls [`configure_cpu`][] without `devices`, which also asks JAX for one CPU device per
core: JAX makes
one CPU device by default, and one device's program runs its loops on one core. With a
device per core, a `vmap`-ed lockstep batch spreads its groups over them
(`solve/lockstep.py`) and a sweep its chunks (`sweep/run.py`), about twice as fast on two
cores (experiments/bench_sweep_devices.py and the batch rows of the "With the CPU flags"
table, docs/benchmarks/performance.md). A program's single solves and fits stay on the
first device.
"""

from __future__ import annotations

import contextlib
import os
import platform
import re

__all__ = ["SMALL_LOOP_BYTES", "small_loop_bytes", "with_cpu_flags", "cpu_flags", "configure_cpu",
           "instruction_sets", "backward_program"]

#: Loops touching fewer bytes per iteration than this are compiled into one function. 1 MiB
#: takes in the solvers' step loops and the loops that write their saved samples (XLA counts
#: the bytes of one iteration: a save writes its rows, not the whole output); a loop that
#: touches more per iteration runs kernels large enough that their dispatch does not
#: matter, and keeps XLA's multi-threaded kernels.
SMALL_LOOP_BYTES = 1 << 20

_LOOP_KEY = "xla_cpu_small_while_loop_byte_threshold"
_EXTRA = "--xla_backend_extra_options="
_VECTOR = "--xla_cpu_prefer_vector_width="


_VECTOR_512 = f"{_VECTOR}512"


def instruction_sets() -> str:
    """The CPU's instruction-set flags (Linux's cpuinfo line), else the processor's name.
    Also part of a stored program's key (persistent.py: an executable is machine code)."""
    with contextlib.suppress(OSError), open("/proc/cpuinfo") as f:
        for line in f:
            if line.startswith(("flags", "Features")):
                return line
    return platform.processor()


def _has_avx512() -> bool:
    """Whether this CPU has AVX-512 (False where it cannot tell)."""
    return "avx512f" in instruction_sets().split()


def cpu_flags() -> list[str]:
    """The flags [`with_cpu_flags`][] adds, for this CPU."""
    return [f"{_EXTRA}{_LOOP_KEY}={SMALL_LOOP_BYTES}"] + ([_VECTOR_512] if _has_avx512() else [])


def small_loop_bytes(flags: str | None = None) -> int | None:
    """The small-loop threshold (bytes) set in `flags` (default: this process's
    `XLA_FLAGS`), or None where it is not set (XLA's default, 1024)."""
    flags = os.environ.get("XLA_FLAGS") if flags is None else flags
    m = re.search(_LOOP_KEY + r"=(\d+)", flags or "")
    return None if m is None else int(m.group(1))


def backward_program() -> str:
    """The backward program of the discrete adjoint (`solve.adjoints.DiscreteAdjoint`'s
    `backward`) for this process: `"loop"` where XLA:CPU compiles the backward pass's
    step loop into one function (its small-loop threshold raised to
    [`SMALL_LOOP_BYTES`][], as the `crank-jax` program and `configure_cpu` set it), else
    `"blocks"`. Read at the edges (`simulate`'s front door, the fit, sweeps), so that the
    core reads no flags. With the flags one VJP per step, in a loop, is cheapest; without
    them every one of the kernels of a step's VJP is dispatched per step (also with a loop
    over a few steps at a time: XLA did not hoist it either), and the vectorised blocks
    win (measured by `experiments/bench_reverse.py`: the Reverse mode table of
    docs/benchmarks/performance.md, and docs/benchmarks/design-figures.md)."""
    import jax

    threshold = small_loop_bytes()
    hoisted = (jax.default_backend() == "cpu" and threshold is not None
               and threshold >= SMALL_LOOP_BYTES)
    return "loop" if hoisted else "blocks"


def with_cpu_flags(flags: str | None) -> str:
    """`flags` (an `XLA_FLAGS` value, or None) with [`cpu_flags`][] added. A setting the
    user made wins: a threshold or a vector width already in `flags` is kept; other backend
    extra options are kept too (the threshold joins their comma-separated list)."""
    flags = (flags or "").strip()
    if _LOOP_KEY not in flags:
        loop = f"{_LOOP_KEY}={SMALL_LOOP_BYTES}"
        if _EXTRA in flags:
            def join(m):
                return f"{_EXTRA}{m.group(1) + ',' if m.group(1) else ''}{loop}"

            flags = re.sub(re.escape(_EXTRA) + r"(\S*)", join, flags, count=1)
        else:
            flags = f"{flags} {_EXTRA}{loop}"
    if _VECTOR not in flags and _has_avx512():
        flags = f"{flags} {_VECTOR_512}"
    return flags.strip()


def _cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def configure_cpu(devices: int | None = None) -> None:
    """For programs, not libraries (the `crank-jax` program calls it): put
    [`cpu_flags`][] into `XLA_FLAGS` and ask JAX for `devices` CPU devices (default: one
    per core this process may use), keeping whatever the user set (`XLA_FLAGS`'s own
    values, `JAX_NUM_CPU_DEVICES`, `--xla_force_host_platform_device_count`).

    Both are read when JAX starts its backends, so call it before the first JAX
    computation; afterwards it raises `RuntimeError` (it would change nothing).
    """
    import jax

    from .compat import backends_are_initialized

    if backends_are_initialized():
        raise RuntimeError("configure_cpu() must run before the first JAX computation (JAX "
                           "reads XLA_FLAGS and its CPU device count when it starts); call "
                           "it right after the imports")
    flags = os.environ.get("XLA_FLAGS")
    os.environ["XLA_FLAGS"] = with_cpu_flags(flags)
    if "JAX_NUM_CPU_DEVICES" in os.environ or "device_count" in (flags or ""):
        return
    jax.config.update("jax_num_cpu_devices", int(devices or _cores()))
