"""The one table of solver names: `simulate(solver=...)`, scenes, `fit`, `sweep` and the
CLI's `--solver` help all read it, and [`solver_named`][] makes each name's solver object
(`solvers.py`) once.

A solver is added here and nowhere else: one row of [`TABLE`][] (its name, and how to make
its object: a diffrax solver wrapped in `Diffrax`, or an `AbstractSolver` of your own)
makes it a name of [`SOLVERS`][] that `simulate`, scenes, `fit`, `sweep` and the CLI
accept (tests/test_recipes.py does it once). The policy picks it for `"auto"` only if a
rule there names it.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

from .solvers import AbstractSolver, AdaptiveDopri8, Diffrax, UniformDopri8

__all__ = ["SOLVERS", "TABLE", "solver_named", "name_of"]

#: Each solver's name and how to make its object. Made on first use ([`solver_named`][]):
#: diffrax's make it import diffrax (~0.35 s), which a warm fit on the fused solvers never
#: needs.
TABLE: dict[str, Callable[[], AbstractSolver]] = {
    "tsit5": lambda: _diffrax("Tsit5"),
    "dopri5": lambda: _diffrax("Dopri5"),
    "dopri8": lambda: _diffrax("Dopri8"),
    "kvaerno5": lambda: _diffrax("Kvaerno5"),
    "dopri8-uniform": UniformDopri8,
    "dopri8-adaptive": AdaptiveDopri8,
}

def _diffrax(name: str) -> Diffrax:
    """diffrax's solver class `name` wrapped in `Diffrax` (imports diffrax, on first use)."""
    import diffrax

    return Diffrax(getattr(diffrax, name)())


#: Solver names accepted by `simulate(solver=...)`, scenes, `fit` and `sweep`: `"auto"`
#: (the policy's choice, `solve/policy.py`), then the table's. (A sweep stores a solver as
#: its index here.)
SOLVERS: tuple[str, ...] = ("auto", *TABLE)


@functools.cache
def solver_named(name: str) -> AbstractSolver:
    """The solver object of a name in [`TABLE`][] (not `"auto"`), made once per process."""
    if name not in TABLE:
        raise ValueError(f"unknown solver {name!r}; choose from {list(TABLE)}")
    return TABLE[name]()


def name_of(solver: AbstractSolver) -> str | None:
    """The table's name of a solver object (equal to the one it makes), or None."""
    # Rows that are classes first: making a diffrax row's object imports diffrax, which a
    # sweep on the fused solvers would otherwise pay for just to name its solver.
    rows = sorted(TABLE, key=lambda n: not isinstance(TABLE[n], type))
    return next((n for n in rows if solver_named(n) == solver), None)
