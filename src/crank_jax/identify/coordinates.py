"""The optimisers' coordinates `z` of a fit's free parameters, all O(1), chosen per name
by [`coordinate`][]:

- `z = ln(value)` for a mechanism field that cannot be negative and starts positive: a
  step is a relative change, positivity needs no constraint, and the Jacobian's columns
  are the sensitivities scaled by the values, as the identifiability analysis needs;
- *folded*, `value = ref |z|`, for one that starts at 0 and for the damping and friction
  terms [`FOLDED`][]: valid whatever the step (a step below 0 is reflected), with a
  non-zero sensitivity at the start (unlike `z^2` or a softplus at its floor), and a
  true 0 converges near 0 (its interval cut at 0);
- linear, `z = value / ref`, for everything else (a signed field, the states, the loads),
  `ref` a typical magnitude.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ..model.params import FIELDS, FRICTION_SCALED, SliderCrank
from ..simulation import linearize
from .request import LOAD_NAMES, SIGNED_FIELDS

__all__ = ["coordinate", "coordinates", "folded", "fold", "FOLDED", "values_of", "values_program",
           "own_scale"]

# Linear scale of a mechanism field that starts at 0 (a friction coefficient, an offset
# in units of r): the optimiser's first steps are O(1) in z.
_ZERO_START_REF = 1e-3


def coordinate(name: str, start: float, mech: SliderCrank, omega: float | None = None,
               torque: float | None = None) -> tuple[bool, float]:
    """`(log, ref)` of a global free name: log coordinates for a mechanism field that
    cannot be negative and starts positive (but for the friction terms [`FOLDED`][]);
    otherwise linear with scale `ref` (folded for a field that cannot be negative, see
    [`folded`][]).

    A field that starts at 0 takes its scale from the record's observed angular frequency
    `omega` (rad/s) and the linearised inertia `mu`: `mu omega^2` for k, 5% damping
    (`0.1 mu omega`) for c; an offset e takes a tenth of r; a load's mean or amplitude
    takes the records' torque scale `torque` (N*m, see
    [`load_scale`][crank_jax.identify.physical.load_scale]; over the crank radius for a
    slider force).
    """
    if name in FIELDS and name not in SIGNED_FIELDS and start > 0 and name not in FOLDED:
        return True, 1.0
    if start != 0:
        return False, abs(start)
    if name in SIGNED_FIELDS:
        return False, 0.1 * float(mech.r)
    side, role = LOAD_NAMES.get(name, (None, None))
    if torque and role in ("mean", "amp"):
        return False, torque if side == "torque" else torque / float(mech.r)
    if omega and name in ("k", "c"):
        mu = float(np.asarray(linearize(mech).mu))
        if math.isfinite(mu) and mu > 0:
            return False, mu * omega**2 if name == "k" else 0.1 * mu * omega
    return False, _ZERO_START_REF


#: Damping and friction terms (viscous crank damping, Coulomb torque, slider friction)
#: whose true value may be 0: always folded, whatever their start. In log coordinates a
#: true 0 sends ln(value) to -inf, LM crawls there, and the estimate (1e-265, say) is then
#: reported as "ln T_c not determined" instead of "0, at most v + 1.96 se"; in linear ones
#: a step below 0 fails every solve (a wall LM stalls on, every parameter frozen).
FOLDED = frozenset(FRICTION_SCALED + ("c",))


def folded(name: str, log: bool) -> bool:
    """True for a free name fitted as `ref |z|`: a mechanism field that cannot be negative
    and is not in log coordinates (it starts at 0)."""
    return name in FIELDS and name not in SIGNED_FIELDS and not log


def coordinates(name: str, start: float, mech: SliderCrank, omega: float | None,
                 linear: bool, torque: float | None = None) -> tuple[bool, float, bool]:
    """`(log, ref, folded)` of a free name (see [`coordinate`][], [`folded`][]). `linear`:
    a name that would be in log coordinates is folded instead, `value = start |z|`: linear
    where the value is positive (multiple shooting's straight valleys), and a step below 0
    is reflected, not a failed point (every solve failing there is a wall the optimiser
    stalls on, every parameter frozen). These are multiple shooting's coordinates (see
    [`build_problem`][crank_jax.identify.problem.build_problem])."""
    lg, rf = coordinate(name, start, mech, omega, torque)
    if linear and lg:
        return False, abs(start), True
    return lg, rf, folded(name, lg)


def own_scale(values, log, ref) -> np.ndarray:
    """(p,) z units per unit of each parameter's own magnitude: 1 for a log coordinate
    (a step of 1 is a factor e), `max(|value|, ref) / ref` for a linear one
    (`z = value / ref`)."""
    ref = np.asarray(ref, dtype=float)
    own = np.maximum(np.abs(np.asarray(values, dtype=float)), ref) / np.where(ref > 0, ref, 1)
    return np.where(np.asarray(log, dtype=bool) | ~(own > 0), 1.0, own)


def fold(z):
    """`|z|` with derivative +1 at 0 (`jnp.abs` has 0 there, which would make a folded
    parameter that starts at 0 look exactly flat: `fit` holds flat directions fixed)."""
    return jnp.where(z >= 0, z, -z)


def values_of(z, ref, log: tuple, folded: tuple):
    """Physical values (p,) of coordinates `z` (p,): `exp(z)` where `log`, `ref |z|`
    where `folded`, else `ref z` (`ref`, (p,), each one's unit)."""
    return jnp.stack([jnp.exp(z[i]) if log[i] else fold(z[i]) * ref[i] if folded[i]
                      else z[i] * ref[i] for i in range(len(log))])


#: [`values_of`][] compiled, for coordinates on the host (`Problem.host_values`).
values_program = jax.jit(values_of, static_argnums=(2, 3))
