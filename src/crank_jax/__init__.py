"""crank-jax: the single slider-crank mechanism with a flexible crank axis, as a fast,
differentiable JAX model (El-Adawi & El-Kafrawy's minimal form, corrected, plus offset
and friction).

The public API, by topic (everything else is private; the subpackages
`model`, `solve`, `identify`, `sweep` and `cli` are the implementation):

- Parameters: `SliderCrank`, `FIELDS`, `SIGNED_FIELDS`.
- Physics: `geometry`, `Geometry`, `coupler_angle`, `CouplerAngle`, `kinematics`,
  `Kinematics`, `Structure`, `CrankField`, `mass`, `coriolis`, `generalized_force`,
  `acceleration`, `energy`, `kinetic_energy`, `potential_energy`, `power_in`,
  `global_form`, `GlobalForm`, `distribution_matrix`, `reactions`, `Reactions`,
  `linearize`, `Linearization`, `equilibrium`, `coulomb_note`.
- Loads: `AbstractLoad`, `NoLoad`, `ConstantLoad`, `HarmonicLoad`, `MultiSineLoad`,
  `SampledLoad`, `INTERPOLATIONS`, `LOAD_PARAMS`.
- Simulation: `simulate`, `Trajectory`, `OUTPUTS`, `output_columns`, `SOLVERS`,
  `resolve_solver`, `choose_solver`, `fastest_mode`.
- Solvers for any vector field: `solve`, `Solution`, `solver_named`, `AbstractSolver`,
  `AdaptiveDopri8`, `UniformDopri8`, `Diffrax`.
- Scenes: `Scene`, `SceneError`, `load_scene`, `save_scene`, `scene_to_toml`, `presets`,
  `PRESETS`.
- Data: `Data`, `DataError`, `load_data`, `save_data`, `synthesize`.
- Identification: `fit`, `FitResult`, `Profile`, `regressor_start`, `FREE_NAMES`,
  `IdentifiabilityWarning`, `ConvergenceWarning`; `posterior`, `Posterior` (NUTS);
  `design`, `Design` (a multisine torque for the Fisher information).
- Residual diagnostics and validation: `residual_diagnostics`, `Diagnostics`,
  `hac_covariance`, `widen`, `robust_uncertainty`, `RobustUncertainty`, `validate`,
  `Validation`.
- Monte Carlo: `sweep`, `SweepResult`, `REDUCTIONS`, `STATUS`, `VARIABLES`,
  `sweep_cost`, `initialize_distributed`, `distributions`, `load_trajectories`,
  `Trajectories` (a sweep's saved trajectories, read lazily).
- Nonlinear vibration: `backbone`, `periodic_orbit`, `forced_response`,
  `stability_chart`, `VibrationError` (`crank_jax.vibration`).
- Files, the compilation cache and XLA's CPU flags: `atomic_write`,
  `enable_compilation_cache`, `default_cache_dir`, `with_cpu_flags` (an `XLA_FLAGS`
  value for a program to set before JAX starts: faster solves on the CPU),
  `configure_cpu` (that, and a JAX CPU device per core; see `crank_jax.runtime.xla_flags`).
"""

from .identify.design import Design, design
from .identify.diagnostics import (
    Diagnostics,
    RobustUncertainty,
    hac_covariance,
    residual_diagnostics,
    robust_uncertainty,
    widen,
)
from .identify.fit import (
    FREE_NAMES,
    ConvergenceWarning,
    FitResult,
    IdentifiabilityWarning,
    Profile,
    fit,
    regressor_start,
)
from .identify.posterior import Posterior, posterior
from .identify.validation import (
    Validation,
    validate,
)
from .model.dynamics import (
    CrankField,
    Structure,
    acceleration,
    coriolis,
    energy,
    generalized_force,
    kinetic_energy,
    mass,
    potential_energy,
    power_in,
)
from .model.geometry import (
    CouplerAngle,
    Geometry,
    Kinematics,
    coupler_angle,
    geometry,
    kinematics,
)
from .model.linear import (
    Linearization,
    coulomb_note,
    equilibrium,
)
from .model.loads import (
    INTERPOLATIONS,
    LOAD_PARAMS,
    AbstractLoad,
    ConstantLoad,
    HarmonicLoad,
    MultiSineLoad,
    NoLoad,
    SampledLoad,
)
from .model.newton_euler import (
    GlobalForm,
    Reactions,
    distribution_matrix,
    global_form,
    reactions,
)
from .model.params import (
    FIELDS,
    SIGNED_FIELDS,
    SliderCrank,
)
from .records.data import (
    Data,
    DataError,
    load_data,
    save_data,
)
from .records.sensors import Sensor, SensorError
from .records.synth import synthesize
from .runtime.cache import (
    default_cache_dir,
    enable_compilation_cache,
)
from .runtime.io import (
    atomic_write,
)
from .runtime.xla_flags import configure_cpu, with_cpu_flags
from .scene import (
    PRESETS,
    Scene,
    SceneError,
    load_scene,
    presets,
    save_scene,
    scene_to_toml,
)
from .simulate import linearize, simulate
from .solve.names import solver_named
from .solve.policy import (
    SOLVERS,
    choose_solver,
    fastest_mode,
    resolve_solver,
)
from .solve.solvers import (
    AbstractSolver,
    AdaptiveDopri8,
    Diffrax,
    Solution,
    UniformDopri8,
    solve,
)
from .solve.trajectory import (
    OUTPUTS,
    Trajectory,
    output_columns,
)
from .sweep import distributions
from .sweep.run import (
    REDUCTIONS,
    STATUS,
    VARIABLES,
    SweepResult,
    initialize_distributed,
    sweep,
    sweep_cost,
)
from .sweep.trajectories import Trajectories, load_trajectories
from .vibration import (
    VibrationError,
    backbone,
    forced_response,
    periodic_orbit,
    stability_chart,
)

__version__ = "0.1.0"

__all__ = [
    "AbstractLoad",
    "acceleration",
    "atomic_write",
    "choose_solver",
    "configure_cpu",
    "ConstantLoad",
    "ConvergenceWarning",
    "coriolis",
    "coulomb_note",
    "coupler_angle",
    "CouplerAngle",
    "CrankField",
    "Data",
    "DataError",
    "default_cache_dir",
    "Design",
    "design",
    "Diagnostics",
    "distribution_matrix",
    "distributions",
    "enable_compilation_cache",
    "energy",
    "equilibrium",
    "fastest_mode",
    "FIELDS",
    "fit",
    "FitResult",
    "FREE_NAMES",
    "generalized_force",
    "Geometry",
    "geometry",
    "global_form",
    "GlobalForm",
    "hac_covariance",
    "HarmonicLoad",
    "IdentifiabilityWarning",
    "initialize_distributed",
    "INTERPOLATIONS",
    "Kinematics",
    "kinematics",
    "kinetic_energy",
    "Linearization",
    "linearize",
    "load_data",
    "load_trajectories",
    "LOAD_PARAMS",
    "load_scene",
    "mass",
    "MultiSineLoad",
    "NoLoad",
    "output_columns",
    "OUTPUTS",
    "potential_energy",
    "power_in",
    "presets",
    "PRESETS",
    "Posterior",
    "posterior",
    "Profile",
    "reactions",
    "Reactions",
    "REDUCTIONS",
    "regressor_start",
    "residual_diagnostics",
    "resolve_solver",
    "robust_uncertainty",
    "RobustUncertainty",
    "SampledLoad",
    "save_data",
    "save_scene",
    "Scene",
    "scene_to_toml",
    "SceneError",
    "SIGNED_FIELDS",
    "simulate",
    "solve",
    "SliderCrank",
    "SOLVERS",
    "STATUS",
    "Structure",
    "sweep",
    "sweep_cost",
    "SweepResult",
    "synthesize",
    "Sensor",
    "SensorError",
    "Trajectories",
    "Trajectory",
    "validate",
    "Validation",
    "VARIABLES",
    "widen",
    "with_cpu_flags",
    "AbstractSolver",
    "AdaptiveDopri8",
    "Diffrax",
    "Solution",
    "UniformDopri8",
    "solver_named",
    "backbone",
    "forced_response",
    "periodic_orbit",
    "stability_chart",
    "VibrationError",
]
