"""Adjoints as objects, as diffrax's are: how a solve is differentiated (`solve(adjoint=)`).

An adjoint is an `eqx.Module` that owns its derivative rule for each solver family, so a
solver asks it rather than branching on a name, and a new adjoint is one class here:

- [`DiscreteAdjoint`][]: reverse mode (`jax.grad`). `"dopri8-adaptive"`: the discrete
  adjoint of its steps (`adjoint.py`); diffrax: `RecursiveCheckpointAdjoint`.
- [`ForwardSensitivities`][]: forward mode (`jax.jvp`, `jax.jacfwd`). `"dopri8-adaptive"`:
  the variational equation stepped beside the solution (`variational.py`); diffrax:
  `ForwardMode`.
- [`DirectAdjoint`][]: both, by JAX's tangents through the steps (slower). diffrax:
  `DirectAdjoint`.

Every field that changes the program is static, so it is part of a compiled program's
key (the program store keys on the static structure: runtime/persistent.py).

The names `"reverse"`, `"forward"` and `"direct"` stay a shorthand ([`as_adjoint`][]):
`simulate` resolves them at the front door, where the reverse mode's backward program is
chosen from the machine's XLA flags (`runtime.xla_flags.backward_program`).
"""

from __future__ import annotations

import abc
import functools
from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx

from .variational import with_sensitivities

__all__ = ["AbstractAdjoint", "DiscreteAdjoint", "ForwardSensitivities", "DirectAdjoint",
           "as_adjoint", "ADJOINTS", "BACKWARD_PROGRAMS"]

#: The backward programs of [`DiscreteAdjoint`][] (see its docstring).
BACKWARD_PROGRAMS: tuple[str, ...] = ("blocks", "loop")


class AbstractAdjoint(eqx.Module):
    """How a solve is differentiated: each solver family asks its adjoint for its rule.

    - `loop_kind` (`"dopri8-uniform"`, JAX differentiating its loops): the kind of
      while loop its steps run in (`uniform.py`).
    - `forward_only`: the adjoint needs no reverse mode, so a diffrax explicit solver
      may save inside its steps in a `lax.while_loop` (`saves.py`)."""

    loop_kind: ClassVar[str]
    forward_only: ClassVar[bool] = False

    @abc.abstractmethod
    def diffrax_adjoint(self) -> Any:
        """The matching `diffrax.AbstractAdjoint` ([`Diffrax`][]'s solves)."""

    def adaptive(self, steps: Callable, field, prepare: Callable, y0, ts, rtol, atol):
        """`"dopri8-adaptive"`'s solve, `steps(field, y0, ts, rtol, atol, error_size)`:
        by default the prepared field's solve itself (JAX's tangents, or the rule of
        [`fused`][], differentiate it)."""
        return steps(prepare(field), y0, ts, rtol, atol, None)

    def fused(self, solve: Callable, with_vjp: Callable) -> Callable:
        """The batched fused solve (`lockstep.py`) with this adjoint's rule: `solve` has
        the `vmap` rule and JAX's forward mode; `with_vjp(backward)` is it with the
        discrete adjoint's `custom_vjp`, by the backward program `backward`."""
        return solve


class DiscreteAdjoint(AbstractAdjoint):
    """Reverse mode (`jax.grad`): for `"dopri8-adaptive"` the discrete adjoint of its
    steps (`adjoint.py`, the exact gradient of the computed solution), for diffrax's
    solvers `diffrax.RecursiveCheckpointAdjoint`. `"dopri8-uniform"`: JAX's reverse mode
    of its checkpointed loops.

    **Field:** `backward` (static): the discrete adjoint's backward program:

    - `"blocks"` (default): 256 steps side by side by a hand-written adjoint of the
      stages, for XLA's defaults, which dispatch each kernel of a loop body on its own;
    - `"loop"`: one VJP of a step after another, for XLA:CPU with its small-loop
      threshold raised (the `crank-jax` program, `configure_cpu`), which compiles the
      loop into one function; without them the loop is the slowest
      (`experiments/bench_reverse.py`: docs/benchmarks/performance.md, Reverse mode, and
      docs/benchmarks/design-figures.md).

    The two give the same gradient to rounding (the same sum in another order). The
    choice reads the machine, so it is made at the edge: `simulate`, the fit and sweeps
    pass `runtime.xla_flags.backward_program()`; a caller of `solve` picks it."""

    backward: str = eqx.field(static=True, default="blocks")
    loop_kind: ClassVar[str] = "checkpointed"

    def __check_init__(self):
        if self.backward not in BACKWARD_PROGRAMS:
            raise ValueError(f"DiscreteAdjoint: backward must be one of {BACKWARD_PROGRAMS}, "
                             f"got {self.backward!r}")

    def diffrax_adjoint(self):
        import diffrax

        return diffrax.RecursiveCheckpointAdjoint()

    def fused(self, solve, with_vjp):
        return with_vjp(self.backward)


class ForwardSensitivities(AbstractAdjoint):
    """Forward mode (`jax.jvp`, `jax.jacfwd`): for `"dopri8-adaptive"` the variational
    equation stepped beside the solution (`variational.py`: a column per parameter with a
    tangent, so a Jacobian costs a few solves), for diffrax's solvers
    `diffrax.ForwardMode`. No reverse mode."""

    loop_kind: ClassVar[str] = "lax"
    forward_only: ClassVar[bool] = True

    def diffrax_adjoint(self):
        import diffrax

        return diffrax.ForwardMode()

    def adaptive(self, steps, field, prepare, y0, ts, rtol, atol):
        # With the CPU flags a 10-parameter Jacobian costs ~3 forward solves, not 7-12.
        return with_sensitivities(steps, field, prepare, y0, ts, rtol, atol)


class DirectAdjoint(AbstractAdjoint):
    """Both modes, by JAX's tangents through the solve's steps (bounded loops): slower,
    and cheaper than [`ForwardSensitivities`][] for one direction through many
    parameters. diffrax: `diffrax.DirectAdjoint`."""

    loop_kind: ClassVar[str] = "bounded"

    def diffrax_adjoint(self):
        import diffrax

        return diffrax.DirectAdjoint()


#: The shorthand names [`as_adjoint`][] takes: `"reverse"` (`jax.grad`), `"forward"`
#: (`jax.jvp`, `jax.jacfwd`), `"direct"` (both, slower).
ADJOINTS: tuple[str, ...] = ("reverse", "forward", "direct")


def as_adjoint(adjoint: str | AbstractAdjoint, backward: str = "blocks") -> AbstractAdjoint:
    """The adjoint object for `adjoint`: an [`AbstractAdjoint`][] as it is, or a name of
    [`ADJOINTS`][], `"reverse"` a [`DiscreteAdjoint`][] with the backward program
    `backward`. Raises `ValueError` for anything else."""
    if isinstance(adjoint, AbstractAdjoint):
        return adjoint
    if isinstance(adjoint, str) and adjoint in ADJOINTS:
        return _named(adjoint, backward)
    raise ValueError(f"adjoint must be an adjoint object (DiscreteAdjoint(), "
                     f"ForwardSensitivities(), DirectAdjoint()) or one of {ADJOINTS}, "
                     f"got {adjoint!r}")


@functools.cache
def _named(name: str, backward: str) -> AbstractAdjoint:
    # Made once: an equinox module's construction (its checks) cost 20-75 us, measured
    # on the shared 2-core machine, against ~2 ms for a whole fast `simulate`.
    return {"reverse": lambda: DiscreteAdjoint(backward), "forward": ForwardSensitivities,
            "direct": DirectAdjoint}[name]()
