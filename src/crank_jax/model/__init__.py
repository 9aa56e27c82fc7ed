"""The physics, written once: parameters, loads, geometry, dynamics, Newton-Euler,
linearization.

`crank_jax.model` is a documented namespace: the physics helpers a user calls
beside a simulation (energy, kinematics, reactions, the mass matrix, ...) live here, off the
package's front door, which keeps the parameters, the loads and `linearize`. Names here
that differ from their module's (`geometry_at`, `ModelTerms`, `nonconservative_power`,
`newton_euler_form`, `NewtonEulerForm`, `coulomb_friction_note`) are the public spellings;
no name here is also one of this package's modules (`geometry_at`, not `geometry`, which is
the module `crank_jax.model.geometry`).
"""

from .angle_load import AngleLoad
from .dynamics import (
    CrankField,
    acceleration,
    coriolis,
    energy,
    generalized_force,
    kinetic_energy,
    mass,
    potential_energy,
)
from .dynamics import power_in as nonconservative_power
from .geometry import CouplerAngle, Geometry, Kinematics, coupler_angle, kinematics
from .geometry import geometry as geometry_at
from .linear import Linearization, equilibrium, linearize
from .linear import coulomb_note as coulomb_friction_note
from .loads import (
    INTERPOLATIONS,
    LOAD_PARAMS,
    AbstractLoad,
    ConstantLoad,
    HarmonicLoad,
    InputLoad,
    MultiSineLoad,
    NoLoad,
    Nonsmooth,
    SampledLoad,
)
from .newton_euler import GlobalForm as NewtonEulerForm
from .newton_euler import Reactions, distribution_matrix, reactions
from .newton_euler import global_form as newton_euler_form
from .params import FIELDS, SIGNED_FIELDS, SliderCrank
from .structure import Structure as ModelTerms

__all__ = [
    # parameters
    "SliderCrank", "FIELDS", "SIGNED_FIELDS",
    # loads
    "AbstractLoad", "NoLoad", "ConstantLoad", "HarmonicLoad", "MultiSineLoad", "SampledLoad",
    "InputLoad", "AngleLoad", "Nonsmooth", "INTERPOLATIONS", "LOAD_PARAMS",
    # geometry and kinematics
    "geometry_at", "Geometry", "coupler_angle", "CouplerAngle", "kinematics", "Kinematics",
    # the equation of motion
    "ModelTerms", "CrankField", "mass", "coriolis", "generalized_force", "acceleration",
    # energy and power
    "energy", "kinetic_energy", "potential_energy", "nonconservative_power",
    # Newton-Euler form and reactions
    "newton_euler_form", "NewtonEulerForm", "distribution_matrix", "reactions", "Reactions",
    # linearization
    "linearize", "Linearization", "equilibrium", "coulomb_friction_note",
]
