"""The fit as immutable stages: what each stage of [`fit`][crank_jax.identify.fit.fit]
hands the next.

    request -> Plan (fit_plan.make_plan) -> FitState -> optimise (escalate) -> reweight
    -> result

Each stage takes a frozen value and returns a new one; none changes what it was given.
[`Shooting`][] is how the optimised problem is shot and which start won: the result's
`strategy` and `shooting` labels are made from its fields, never parsed back.
"""

from __future__ import annotations

import dataclasses
import enum

import numpy as np

from ..solve.solvers import AbstractSolver
from .outcome import Run
from .physical import Ranges
from .problem import Problem
from .request import FitRequest

__all__ = ["Shot", "Shooting", "Plan", "FitState"]

class Shot(enum.StrEnum):
    """`Shooting.kind`: refused before any solve, one shot per record, or segments."""

    NONE = "none"
    SINGLE = "single"
    MULTIPLE = "multiple"


@dataclasses.dataclass(frozen=True)
class Shooting:
    """How a fit's problem is shot, and which start won.

    - `kind`: a [`Shot`][] (or its name).
    - `segments`: with `Shot.MULTIPLE`, the number of segments of each record.
    - `starts`: the escalation's starts that won over the planned one, in words (e.g.
      "a start from the motion", "multistart start 2 of 4"), in the order they won.
    """

    kind: Shot
    segments: tuple[int, ...] = ()
    starts: tuple[str, ...] = ()

    def __post_init__(self):
        if self.kind not in tuple(Shot):
            raise ValueError(f"Shooting kind must be one of {[k.value for k in Shot]}, got "
                             f"{self.kind!r}")
        object.__setattr__(self, "kind", Shot(self.kind))  # a name given: its enum
        if (self.kind is Shot.MULTIPLE) != bool(self.segments):
            raise ValueError("Shooting: segments are given with kind 'multiple', and only then")

    def _segments(self) -> str:
        return f"({'+'.join(map(str, self.segments))} segments)"

    @property
    def mode(self) -> str:
        """`FitResult.shooting`: `"single"` or e.g. `"multiple (3+3 segments)"` (a refused
        fit says `"single"`: nothing was shot)."""
        return f"multiple {self._segments()}" if self.kind is Shot.MULTIPLE else "single"

    @property
    def label(self) -> str:
        """`FitResult.strategy`: the shooting, then each start that won, e.g. "multiple
        shooting (6 segments), a start from the motion"."""
        base = {Shot.NONE: "none", Shot.SINGLE: "single shooting"}.get(
            self.kind, f"multiple shooting {self._segments()}")
        return ", ".join((base, *self.starts))

    def won_by(self, start: str) -> Shooting:
        """This shooting, with `start` (words) the start that won."""
        return dataclasses.replace(self, starts=(*self.starts, start))


@dataclasses.dataclass(frozen=True)
class Plan:
    """What the fit works with, once the start solve has been looked at (frozen: a later
    stage that changes the weights makes a new plan, see `dataclasses.replace`)."""

    single: Problem  # single shooting, with the fit's step budget
    shoot: Problem  # the problem optimised (multiple shooting, or `single`)
    z0: np.ndarray  # start coordinates of `shoot`
    Bg: np.ndarray  # (p, q) basis of the global directions optimised (flat ones held)
    start: dict  # start value of every reported name
    periods: list  # each record's cycle, s: its observed period, or the time of a turn
    # for a crank that turns (None: neither), once planned
    notes: tuple[str, ...]
    shooting: Shooting  # as planned (the escalation may win with another)
    start_g: dict  # start values of the global names
    states: list  # start state of each record
    solver: AbstractSolver  # the ODE solver of every solve (`pick_solver`'s)
    abort: str | None = None
    ranges: Ranges | None = None  # the estimates' physical range (None: not judged)


@dataclasses.dataclass(frozen=True)
class FitState:
    """What a fit holds between its stages: the request (its channels' weights may be
    changed by the reweighting stage), the plan, the best run so far, the iterations spent
    by every try, the notes in the order they were made, and the shooting that won."""

    req: FitRequest
    plan: Plan
    best: Run
    iterations: int
    notes: tuple[str, ...]
    shooting: Shooting

    def but(self, **changes) -> FitState:
        """A new state with `changes` (this one is unchanged)."""
        return dataclasses.replace(self, **changes)
