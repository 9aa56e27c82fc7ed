"""crank-jax: the single slider-crank mechanism with a flexible crank axis, as a fast,
differentiable JAX model (El-Adawi & El-Kafrawy's minimal form, corrected, plus offset
and friction).

The front door (`__all__`, 50 names; the reasons in docs/reference/index.md):

- Scenes and parameters: `SliderCrank`, `Scene`, `SceneError`, `load_scene`, `save_scene`,
  `scene_to_toml`, `presets`, `Sensor`, `SensorError`.
- Loads: `AbstractLoad`, `NoLoad`, `ConstantLoad`, `HarmonicLoad`, `MultiSineLoad`,
  `SampledLoad`.
- Simulation: `simulate`, `Trajectory`, `linearize`, `Linearization`; the solvers
  `simulate(solver=...)` also takes by name: `AbstractSolver`, `AdaptiveDopri8`,
  `UniformDopri8`, `Diffrax`.
- Records: `Data`, `DataError`, `load_data`, `save_data`, `synthesize`.
- Identification: `fit`, `FitResult`, `IdentifiabilityWarning`, `ConvergenceWarning`;
  `validate`, `Validation`; `posterior`, `Posterior` (NUTS); `design`, `Design` (a
  multisine torque for the Fisher information).
- Monte Carlo: `run_sweep`, `SweepResult`, `sweep_cost`, `load_trajectories`,
  `Trajectories`.
- Nonlinear vibration: `backbone`, `periodic_orbit`, `forced_response`, `stability_chart`,
  `VibrationError`.
- The runtime: `configure_cpu` (XLA's CPU flags and a JAX CPU device per core, for a
  program before JAX starts), `enable_compilation_cache`.

Documented namespaces, each with its own `__all__`: `crank_jax.model` (physics helpers:
energy, kinematics, reactions, the mass matrix, ...), `crank_jax.solve` (`solve` for any
vector field, the solver policy), `crank_jax.identify` (residual diagnostics, profiles,
start values), `crank_jax.fleet` (`fit_many`: many records, each fitted by
itself, side by side), `crank_jax.sweep` (distributions, the names a sweep takes),
`crank_jax.vibration` (result classes), `crank_jax.report` (HTML reports),
`crank_jax.online` (`track`: follow a running machine's parameters, change alarms). Every other
module is internal. The names of earlier releases are gone (docs/reference/index.md,
"Changes").
"""

import sys as _sys
from types import ModuleType as _ModuleType

from .bayes.design import Design, design
from .bayes.posterior import Posterior, posterior
from .identify.fit import (
    ConvergenceWarning,
    FitResult,
    IdentifiabilityWarning,
    fit,
)
from .model.linear import Linearization
from .model.loads import (
    AbstractLoad,
    ConstantLoad,
    HarmonicLoad,
    MultiSineLoad,
    NoLoad,
    SampledLoad,
)
from .model.params import SliderCrank
from .records.data import (
    Data,
    DataError,
    load_data,
    save_data,
)
from .records.sensors import Sensor, SensorError
from .records.synth import synthesize
from .runtime.cache import enable_compilation_cache
from .runtime.xla_flags import configure_cpu
from .scene import (
    Scene,
    SceneError,
    load_scene,
    presets,
    save_scene,
    scene_to_toml,
)
from .simulation import linearize, simulate
from .solve.solvers import (
    AbstractSolver,
    AdaptiveDopri8,
    Diffrax,
    UniformDopri8,
)
from .solve.trajectory import Trajectory
from .sweep.run import (
    SweepResult,
    sweep_cost,
)
from .sweep.run import sweep as run_sweep
from .sweep.trajectories import Trajectories, load_trajectories
from .validation.kstep import (
    Validation,
    validate,
)
from .vibration import (
    VibrationError,
    forced_response,
    periodic_orbit,
    stability_chart,
)
from .vibration.backbone import backbone

#: The documented namespaces beside the front door: reachable as attributes (imported on
#: first use) and shown by `dir(crank_jax)`. Every other module of the package is internal:
#: importable by its full name (`import crank_jax.runtime.io as io`), never an attribute.
_NAMESPACES = ("model", "solve", "identify", "fleet", "sweep", "vibration", "report",
               "online")


class _FrontDoor(_ModuleType):
    """The package's module: the import system binds every submodule it loads as an
    attribute of its parent; here only the namespaces are bound, so that importing an
    internal module (now, or lazily later) never puts it on the front door."""

    def __setattr__(self, name: str, value) -> None:
        if not _internal(name, value):
            super().__setattr__(name, value)


def _internal(name: str, value) -> bool:
    """Whether `name = value` binds an internal submodule of this package."""
    return (isinstance(value, _ModuleType) and name not in _NAMESPACES
            and value.__name__ == f"{__name__}.{name}")


__version__ = "0.1.0"

# The front door: 50 names, by task (docs/reference/index.md gives the reasons).
__all__ = [
    # scenes and parameters
    "SliderCrank", "Scene", "SceneError", "load_scene", "save_scene", "scene_to_toml",
    "presets", "Sensor", "SensorError",
    # loads (the slider force P and the crank torque tau)
    "AbstractLoad", "NoLoad", "ConstantLoad", "HarmonicLoad", "MultiSineLoad",
    "SampledLoad",
    # simulation and solvers
    "simulate", "Trajectory", "linearize", "Linearization", "AbstractSolver",
    "AdaptiveDopri8", "UniformDopri8", "Diffrax",
    # records
    "Data", "DataError", "load_data", "save_data", "synthesize",
    # identification
    "fit", "FitResult", "IdentifiabilityWarning", "ConvergenceWarning", "validate",
    "Validation", "posterior", "Posterior", "design", "Design",
    # Monte Carlo sweeps
    "run_sweep", "SweepResult", "sweep_cost", "load_trajectories", "Trajectories",
    # nonlinear vibration
    "backbone", "periodic_orbit", "forced_response", "stability_chart", "VibrationError",
    # the runtime
    "configure_cpu", "enable_compilation_cache",
]

def __getattr__(name: str):
    # Called only for names not found in the module: a namespace not yet imported.
    if name in _NAMESPACES:
        import importlib

        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*__all__, *_NAMESPACES, "__version__"])


def _unbind_internal_modules() -> None:
    g = globals()
    for name in [n for n, v in g.items() if _internal(n, v)]:
        del g[name]


# From here on, importing an internal module does not bind it; those imported above are
# unbound now.
_sys.modules[__name__].__class__ = _FrontDoor
_unbind_internal_modules()
