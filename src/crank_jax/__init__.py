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
"""

from ._cache import default_cache_dir, enable_compilation_cache
from ._dynamics import (
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
from ._io import atomic_write
from ._kinematics import CouplerAngle, Kinematics, coupler_angle, kinematics
from ._linear import Linearization, linearize
from ._loads import AbstractLoad, ConstantLoad, HarmonicLoad, NoLoad, SampledLoad
from ._newton_euler import GlobalForm, Reactions, distribution_matrix, global_form, reactions
from ._params import FIELDS, SliderCrank
from ._scene import PRESETS, Scene, SceneError, load_scene, presets, save_scene, scene_to_toml
from ._simulate import OUTPUTS, SOLVERS, Trajectory, choose_solver, output_columns, simulate

__version__ = "0.1.0"

enable_compilation_cache()

__all__ = [
    "AbstractLoad", "ConstantLoad", "CouplerAngle", "FIELDS", "GlobalForm", "HarmonicLoad",
    "Kinematics", "Linearization", "NoLoad", "OUTPUTS", "PRESETS", "Reactions", "SOLVERS",
    "SampledLoad", "Scene", "SceneError", "SliderCrank", "Structure", "Trajectory",
    "acceleration", "atomic_write", "choose_solver", "coriolis", "coupler_angle",
    "default_cache_dir", "distribution_matrix", "enable_compilation_cache", "energy",
    "generalized_force", "global_form", "kinematics", "kinetic_energy", "linearize",
    "load_scene", "mass", "output_columns", "potential_energy", "power_in", "presets",
    "reactions", "save_scene", "scene_to_toml", "simulate",
]

# --- sweeps ---
from . import distributions  # noqa: E402
from ._simulate import fastest_mode  # noqa: E402
from ._sweep import (  # noqa: E402
    REDUCTIONS,
    STATUS,
    VARIABLES,
    SweepResult,
    initialize_distributed,
    sweep,
    sweep_cost,
)

__all__ += ["REDUCTIONS", "STATUS", "SweepResult", "VARIABLES", "distributions", "fastest_mode",
            "initialize_distributed", "sweep", "sweep_cost"]

# --- identification ---
from ._data import Data, DataError, MultiSineLoad, load_data, save_data, synthesize  # noqa: E402
from ._identify import (  # noqa: E402
    FREE_NAMES,
    ConvergenceWarning,
    FitResult,
    IdentifiabilityWarning,
    Profile,
    fit,
    regressor_start,
)

__all__ += ["ConvergenceWarning", "Data", "DataError", "FREE_NAMES", "FitResult", "MultiSineLoad",
            "IdentifiabilityWarning", "Profile", "fit", "load_data", "regressor_start",
            "save_data", "synthesize"]
