"""Monte Carlo sweeps: a scene simulated for many sampled parameter values at once.

`crank_jax.sweep` is a documented namespace. `run_sweep`, `SweepResult`,
`sweep_cost`, `load_trajectories` and `Trajectories` are also at the front door; here too
are the distributions a sweep samples from (`Normal`, `Uniform`, `LogNormal`, `LogUniform`,
`Const`, `AbstractDistribution`), the names a sweep accepts (`VARIABLES`: the fields and
load parameters it can vary; `REDUCTIONS`: its outputs; `STATUS`: each sample's outcome)
and `initialize_distributed` (a sweep over several hosts).

`crank_jax.sweep` is this package, never a function: `import crank_jax.sweep` and the
attribute `crank_jax.sweep` are the same module.
"""

from .distributions import AbstractDistribution, Const, LogNormal, LogUniform, Normal, Uniform
from .run import REDUCTIONS, STATUS, VARIABLES, SweepResult, initialize_distributed, sweep_cost
from .run import sweep as run_sweep
from .trajectories import Trajectories, load_trajectories

__all__ = ["run_sweep", "SweepResult", "sweep_cost", "load_trajectories", "Trajectories",
           "Normal", "Uniform", "LogNormal", "LogUniform", "Const", "AbstractDistribution",
           "VARIABLES", "REDUCTIONS", "STATUS", "initialize_distributed"]

