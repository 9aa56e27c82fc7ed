"""The model's known flat directions, tested by name so that a fit can say them in words.

- **The common scale** (DESIGN.md section 3): every free mass, inertia, stiffness, damping,
  friction force and load amplitude multiplied by one factor leaves the motion unchanged.
  It exists only while every fixed member of the scale is zero
  ([`fixed_scale_members`][]).
- **The coupler's equivalent masses:** a coupler moves like point masses at its two joints
  plus an inertia, so one more kg of coupler can be undone by the crank, the slider and
  `I_p` when `m_p`, `m_c`, `I_c`, `m_s` and `I_p` are all free.

[`uncertainty.analyze`][crank_jax.identify.uncertainty.analyze] tests each against the
sensitivities and reports those the data leave flat.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..model.params import FRICTION_SCALED, SCALE_GROUP
from .request import LOAD_NAMES

__all__ = ["known_directions", "fixed_scale_members", "name_list"]


def name_list(names: Sequence[str]) -> str:
    """Names as prose: "a", "a and b", "a, b and c"."""
    names = list(names)
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def fixed_scale_members(base, names: Sequence[str], loads) -> list[str]:
    """The members of the common scale that are fixed and not zero: mechanism fields of
    the scale group (and friction) not in `names` with a non-zero value in `base` (a
    `SliderCrank`), and each record's load or torque with a non-zero part that is not free
    (`loads`: `(load, torque)` per record). Any one of them fixes the scale."""
    out = [n for n in SCALE_GROUP + FRICTION_SCALED
           if n not in names and np.any(np.asarray(getattr(base, n)) != 0)]
    free_roles = {LOAD_NAMES[n] for n in names if n in LOAD_NAMES}
    for i, pair in enumerate(loads):
        for side, obj in zip(("load", "torque"), pair):
            label = ("P" if side == "load" else "tau") + (f" of record {i}" if i else "")
            if _fixed_part(obj, side, free_roles) and label not in out:
                out.append(label)
    return out


def _fixed_part(load, side: str, free_roles) -> bool:
    """True when `load` has a non-zero part that is not free: a mean or amplitude that is
    not free, a multisine's amplitudes, a sampled record."""
    from ..model.loads import SampledLoad, get_param, load_kind

    kind = load_kind(load)
    if isinstance(load, SampledLoad):
        return bool(np.any(np.asarray(load.values) != 0))
    for role in ("mean", "amp", "gain"):
        v = get_param(load, role) if role in kind.fields else None
        if v is not None and np.any(np.asarray(v) != 0) and (side, role) not in free_roles:
            return True
    return any(a == "amplitudes" and np.any(np.asarray(getattr(load, a)) != 0)
               for a in kind.arrays)


def known_directions(names, values, log, ref, geometry, fixed_scale=()
                      ) -> list[tuple[np.ndarray, str]]:
    """Unit vectors in z of the structural symmetries whose members are all free (and,
    for the common scale, whose fixed members are all zero: `fixed_scale` is empty)."""
    p = len(names)
    idx = {n: i for i, n in enumerate(names)}
    out = []

    def vector(dv: dict[str, float]) -> np.ndarray | None:
        u = np.zeros(p)
        for n, d in dv.items():
            if d == 0.0:
                continue
            if n not in idx:
                return None  # a member this direction needs is fixed: no symmetry
            i = idx[n]
            u[i] = d / values[i] if log[i] else d / ref[i]
        norm = np.linalg.norm(u)
        return u / norm if norm > 0 else None

    # 1. Common scale: every mass, inertia, k, c and load amplitude times one factor.
    group = [n for n in names if n in SCALE_GROUP or n in LOAD_NAMES or n in FRICTION_SCALED]
    u = vector({n: values[idx[n]] for n in group}) if group and not fixed_scale else None
    if u is not None:
        out.append((u, f"{name_list(group)} are determined only up to a common scale: fix "
                       "one of them or supply a known load"))
    # 2. The coupler is dynamically equivalent to point masses m_p (1 - b/L) at A and
    #    m_p b/L at B plus an inertia I_p - m_p b (L - b) about its centre of mass. So one
    #    more kg of coupler can be undone by the crank (mass at radius r), the slider and
    #    I_p: a second exact symmetry when m_c, I_c, m_s, I_p and m_p are all free.
    if geometry is not None and "m_p" in idx:
        r, L, b, s = (geometry[k] for k in ("r", "L", "b", "s"))
        a = 1 - b / L
        dm_c = -a * r / s if s > 0 else 0.0
        dv = {"m_p": 1.0, "m_s": -b / L, "I_p": b * (L - b), "m_c": dm_c,
              "I_c": -a * r * r - dm_c * s * s}
        if s == 0 and a != 0:
            dv = {}  # the crank cannot absorb the coupler's weight without an offset s
        u = vector(dv) if dv else None
        if u is not None:
            members = [n for n in ("m_p", "m_c", "I_c", "m_s", "I_p") if dv.get(n, 0) != 0]
            out.append((u, f"{name_list(members)} are not separately determined: a coupler "
                           "moves like point masses at its two joints plus an inertia, so "
                           f"m_p trades against {name_list(members[1:])}: fix one of them "
                           "(e.g. weigh the coupler)"))
    return out
