"""What a sensor can see: the model's outputs `h(t, phi, phi')` (DESIGN.md section 1,
"Sensors are a measurement model, not the state").

Each output is a function of the state (and, for the slider's acceleration, of the
equation of motion), written once from [`geometry`][] and [`acceleration`][]:

| name | meaning | formula | SI unit |
|---|---|---|---|
| `phi` | crank angle | `phi` | rad |
| `dphi` | crank rate | `phi'` | rad/s |
| `x_s` | slider position along x | `r cos(phi) + L cos(delta)` | m |
| `v_s` | slider speed | `-lever phi'` | m/s |
| `a_s` | slider acceleration | `-(dlever phi'^2 + lever phi'')` | m/s^2 |
"""

from __future__ import annotations

from collections.abc import Callable

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .dynamics import acceleration
from .geometry import geometry
from .loads import AbstractLoad
from .params import SliderCrank
from .structure import Structure

__all__ = ["OUTPUT_NAMES", "SI_UNITS", "output"]

#: The outputs a record's channel may carry, in the order they are reported.
OUTPUT_NAMES: tuple[str, ...] = ("phi", "dphi", "x_s", "v_s", "a_s")
#: Each output's SI unit.
SI_UNITS: dict[str, str] = {"phi": "rad", "dphi": "rad/s", "x_s": "m", "v_s": "m/s",
                            "a_s": "m/s^2"}


def output(
    name: str,
    mech: SliderCrank,
    t: ArrayLike,
    phi: ArrayLike,
    dphi: ArrayLike,
    load: AbstractLoad | None = None,
    torque: AbstractLoad | None = None,
    structure: Structure | None = None,
    force: Callable | None = None,
) -> Array:
    """The model output `name` (one of [`OUTPUT_NAMES`][]) along a trajectory.

    **Arguments:** `mech`; `t` (s), `phi` (rad), `dphi` (rad/s): broadcastable arrays (a
    solve's save times and states); `load`, `torque`, `structure`, `force`: the equation
    of motion's, needed only by `a_s` (its phi'').

    **Returns:** an array of the broadcast shape, in the output's SI unit.
    """
    phi, dphi = jnp.asarray(phi), jnp.asarray(dphi)
    if name == "phi":
        return phi
    if name == "dphi":
        return dphi
    g = geometry(mech, phi)
    if name == "x_s":
        return g.x_s
    if name == "v_s":
        return -g.lever * dphi
    if name == "a_s":
        kw = {} if structure is None else {"structure": structure}
        ddphi = acceleration(mech, phi, dphi, t, load, torque, force=force, **kw)
        return -(g.dlever * dphi * dphi + g.lever * ddphi)
    raise ValueError(f"output {name!r} is unknown; choose from {list(OUTPUT_NAMES)}")
