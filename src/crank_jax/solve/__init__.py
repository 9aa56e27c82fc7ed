"""Solvers and the simulation: they know vector fields, not mechanisms.

`crank_jax.solve` is a documented namespace. Its public names:

- `solve(field, solver, ts, y0, ...)` and its `Solution`: any vector field (a
  `crank_jax.model.CrankField` or your own) with the library's solvers;
- the solver classes (also at the front door) and the policy behind `solver="auto"`:
  `SOLVERS` (the names `simulate(solver=...)` takes), `solver_named` (a name's solver
  object), `resolve_solver` and `choose_solver` (which solver `"auto"` gives a scene, and
  why), `fastest_mode_rates` (the rates that choice reads);
- the adjoints `solve(adjoint=...)` takes (`adjoints.py`): `DiscreteAdjoint` (reverse
  mode), `ForwardSensitivities` (forward mode), `DirectAdjoint` (both), and their base
  `AbstractAdjoint`;
- `OUTPUTS` and `output_columns`: the outputs `simulate(outputs=...)` takes and their columns.

To choose a solver, pass `solver=` a name from `SOLVERS` or a solver object to
`crank_jax.simulate`; the rest of this list explains or reuses that choice.

`crank_jax.solve` is this package, never a function: the function is
`crank_jax.solve.solve`.
"""

from .adjoints import AbstractAdjoint, DirectAdjoint, DiscreteAdjoint, ForwardSensitivities
from .names import solver_named
from .policy import SOLVERS, choose_solver, resolve_solver
from .policy import fastest_mode as fastest_mode_rates
from .solvers import AbstractSolver, AdaptiveDopri8, Diffrax, Solution, UniformDopri8, solve
from .trajectory import OUTPUTS, output_columns

__all__ = ["solve", "Solution", "AbstractSolver", "AdaptiveDopri8", "UniformDopri8",
           "Diffrax", "SOLVERS", "solver_named", "resolve_solver", "choose_solver",
           "fastest_mode_rates", "OUTPUTS", "output_columns", "AbstractAdjoint",
           "DiscreteAdjoint", "ForwardSensitivities", "DirectAdjoint"]
