"""crank-jax: the single slider-crank mechanism with a flexible crank axis, as a fast,
differentiable JAX model (El-Adawi & El-Kafrawy's minimal form, corrected).

Public API (everything else is private):

- Parameters: `SliderCrank`, `FIELDS`.
- Physics: `coupler_angle`, `kinematics`, `mass` (M), `coriolis` (K),
  `generalized_force` (q), `acceleration`, `energy`, `kinetic_energy`, `potential_energy`,
  `power_in`, `Structure`; `global_form`, `distribution_matrix`, `reactions`;
  `linearize`.
- Loads: `NoLoad`, `ConstantLoad`, `HarmonicLoad`, `SampledLoad`, `AbstractLoad`.
- Simulation: `simulate`, `Trajectory`, `choose_solver`, `SOLVERS`, `OUTPUTS`.
- Scenes: `Scene`, `load_scene`, `save_scene`, `scene_to_toml`, `presets`, `PRESETS`.
- Identification: `synthesize`, `load_data`, `save_data`, `Data`, `DataError`,
  `MultiSineLoad`, `fit`, `FitResult`, `Profile`, `regressor_start`, `FREE_NAMES`,
  `IdentifiabilityWarning`, `ConvergenceWarning`.
- Residual diagnostics: `residual_diagnostics`, `Diagnostics`, `hac_covariance`, `widen`,
  `robust_uncertainty`, `RobustUncertainty`. Validation: `validate`, `Validation`.
- Monte Carlo: `sweep`, `SweepResult`, `distributions`, `REDUCTIONS`, `STATUS`,
  `VARIABLES`, `sweep_cost`, `initialize_distributed`, `fastest_mode`.
"""

from . import distributions
from .cache import default_cache_dir, enable_compilation_cache
from .data import Data, DataError, MultiSineLoad, load_data, save_data, synthesize
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
from .io import atomic_write
from .model.dynamics import (
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
from .model.geometry import CouplerAngle, Kinematics, coupler_angle, kinematics
from .model.linear import Linearization, linearize
from .model.loads import AbstractLoad, ConstantLoad, HarmonicLoad, NoLoad, SampledLoad
from .model.newton_euler import GlobalForm, Reactions, distribution_matrix, global_form, reactions
from .model.params import FIELDS, SliderCrank
from .scene import PRESETS, Scene, SceneError, load_scene, presets, save_scene, scene_to_toml
from .solve.policy import SOLVERS, choose_solver, fastest_mode, resolve_solver
from .solve.simulate import OUTPUTS, Trajectory, output_columns, simulate
from .sweep.run import (
    REDUCTIONS,
    STATUS,
    VARIABLES,
    SweepResult,
    initialize_distributed,
    sweep,
    sweep_cost,
)
from .validate import Validation, validate

__version__ = "0.1.0"


__all__ = [
    "AbstractLoad", "ConstantLoad", "CouplerAngle", "FIELDS", "GlobalForm", "HarmonicLoad",
    "Kinematics", "Linearization", "NoLoad", "OUTPUTS", "PRESETS", "Reactions", "SOLVERS",
    "SampledLoad", "Scene", "SceneError", "SliderCrank", "Structure", "Trajectory",
    "acceleration", "atomic_write", "choose_solver", "coriolis", "coupler_angle",
    "default_cache_dir", "distribution_matrix", "enable_compilation_cache", "energy",
    "generalized_force", "global_form", "kinematics", "kinetic_energy", "linearize",
    "load_scene", "mass", "output_columns", "potential_energy", "power_in", "presets",
    "reactions", "resolve_solver", "save_scene", "scene_to_toml", "simulate",
]
__all__ += [
    "REDUCTIONS",
    "STATUS",
    "SweepResult",
    "VARIABLES",
    "distributions",
    "fastest_mode",
    "initialize_distributed",
    "sweep",
    "sweep_cost",
    "ConvergenceWarning",
    "Data",
    "DataError",
    "FREE_NAMES",
    "FitResult",
    "MultiSineLoad",
    "IdentifiabilityWarning",
    "Profile",
    "fit",
    "load_data",
    "regressor_start",
    "save_data",
    "synthesize",
]
__all__ += ["Diagnostics", "RobustUncertainty", "hac_covariance", "residual_diagnostics",
            "robust_uncertainty", "widen", "Validation", "validate"]
