"""Which terms of the equation of motion a scene has: static, so a zero term compiles out."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from .params import SliderCrank

__all__ = ["Structure"]


@dataclasses.dataclass(frozen=True)
class Structure:
    """Which terms of the equation of motion are present (static, hashable).

    `Structure.of(mech)` reads it from concrete parameters: a body whose masses and inertia
    are all zero is a body the scene does not have, a zero offset or friction coefficient
    a term it does not have. `Structure()` keeps every term, which is always correct and is
    the default everywhere.
    """

    crank: bool = True
    """m_c s^2 + I_c and m_c s (the crank's inertia and weight)."""
    coupler: bool = True
    """m_p or I_p nonzero."""
    slider: bool = True
    """m_s nonzero."""
    gravity: bool = True
    """g nonzero."""
    spring: bool = True
    """k nonzero."""
    damper: bool = True
    """c nonzero."""
    offset: bool = True
    """e nonzero (slider line off the crank centre)."""
    crank_coulomb: bool = True
    """T_c nonzero (Coulomb friction of the crank bearing)."""
    slider_damper: bool = True
    """c_s nonzero (viscous friction of the slider guide)."""
    slider_coulomb: bool = True
    """F_s nonzero (Coulomb friction of the slider guide)."""
    tilt: bool = True
    """gravity_angle nonzero (gravity off the paper's -x: its y-part and the cos(gravity_angle)
    factor of its x-part are formed)."""

    @classmethod
    def of(cls, mech: SliderCrank) -> Structure:
        """The structure of `mech`'s values. Batched fields count a term as present if any
        member of the batch has it; a traced field (inside `jit`, `vmap`, `grad`) counts as
        present, and a concrete one beside it is read as it is: a zero constant in a traced
        program stays zero, so its terms cost nothing there either (e.g. the friction and
        offset terms of `jax.vmap(lambda k: simulate(mech.replace(k=k), ...))`)."""
        names = ("m_c", "s", "m_p", "I_p", "m_s", "g", "k", "c", "e", "T_c", "c_s", "F_s",
                 "gravity_angle")
        v = {n: getattr(mech, n) for n in names}

        def nz(x):
            if isinstance(x, jax.core.Tracer):
                return True
            return bool((np.asarray(x) != 0).any())  # ndarray.any: ~5x np.any's speed
        return cls(
            crank=True,  # M > 0 requires crank inertia; it is always present.
            coupler=nz(v["m_p"]) or nz(v["I_p"]),
            slider=nz(v["m_s"]),
            gravity=nz(v["g"]),
            spring=nz(v["k"]),
            damper=nz(v["c"]),
            offset=nz(v["e"]),
            crank_coulomb=nz(v["T_c"]),
            slider_damper=nz(v["c_s"]),
            slider_coulomb=nz(v["F_s"]),
            tilt=nz(v["gravity_angle"]),
        )

    def union(self, other: Structure) -> Structure:
        """A structure with every term that either has."""
        return Structure(*(a or b for a, b in zip(dataclasses.astuple(self),
                                                  dataclasses.astuple(other))))
