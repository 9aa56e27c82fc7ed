"""Priors of the posterior: the sweep's distribution syntax, checked against each
parameter's valid values, and their log density on the sampler's coordinates.

A `[priors]` table in a scene file gives them, e.g. `k = "lognormal(0.7, 0.5)"`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence

import jax.numpy as jnp
import numpy as np

from ..identify.problem import Problem
from ..model.params import FIELDS, SIGNED_FIELDS
from ..sweep.distributions import (
    AbstractDistribution,
    Const,
    LogNormal,
    LogUniform,
    Normal,
    Uniform,
    parse_distribution,
)

__all__ = ["PRIOR_FAMILIES", "MIN_PRIOR_SPREAD", "MIN_PRIOR_WIDTH", "parse_priors",
           "load_priors", "prior_arrays", "log_prior", "prior_precision", "in_support",
           "base_name"]

#: Prior families (the sweep's distribution syntax), without `const` (a constant is a
#: fixed parameter: leave it out of `free`).
PRIOR_FAMILIES = ("normal", "uniform", "lognormal", "loguniform")
#: The narrowest prior: its spread relative to its location (sd / |mu|, sigma of a
#: lognormal, (hi - lo) / max(|lo|, |hi|), log(hi / lo)). A narrower one fixes the value to
#: within rounding of the sampler's coordinates, and its density's scale overflows (a
#: lognormal(2, 1e-300) divided by zero).
MIN_PRIOR_SPREAD = 1e-9
#: The smallest absolute spread of a normal or uniform prior (about zero): its square stays
#: a normal float64.
MIN_PRIOR_WIDTH = 1e-150
# Codes of the families inside the compiled program (static).
_FLAT, _NORMAL, _UNIFORM, _LOGNORMAL, _LOGUNIFORM, _FLAT_NONNEGATIVE = range(6)


def base_name(name: str) -> str:
    return name.split("[", 1)[0]


def _nonnegative(name: str) -> bool:
    """Whether a free name's valid values are >= 0 (a mechanism field that is not signed)."""
    return base_name(name) in FIELDS and base_name(name) not in SIGNED_FIELDS


def parse_priors(priors: Mapping[str, str | AbstractDistribution] | None, free: Sequence[str],
                 where: str = "priors") -> dict[str, AbstractDistribution]:
    """Check and parse priors: `{name: "lognormal(0.7, 0.5)" | distribution}`.

    Names must be free names of the fit (`phi0`, `dphi0` apply to every record). A prior's
    support must lie inside the parameter's valid values (a mass cannot be negative, so
    `normal(...)` or `uniform(-1, 1)` is refused for it).

    **Raises:** `ValueError` naming `where`, the parameter and the fix.
    """
    out: dict[str, AbstractDistribution] = {}
    free_bases = {base_name(n) for n in free}
    for name, spec in dict(priors or {}).items():
        if name not in free_bases:
            raise ValueError(f"{where}: {name!r} is not a free parameter (free: "
                             f"{sorted(free_bases)}); give priors for free parameters only")
        try:
            d = spec if isinstance(spec, AbstractDistribution) else parse_distribution(str(spec))
        except ValueError as e:
            raise ValueError(f"{where}.{name}: {e}; prior families: "
                             f"{', '.join(PRIOR_FAMILIES)}") from None
        if isinstance(d, Const) or not isinstance(d, (Normal, Uniform, LogNormal, LogUniform)):
            raise ValueError(f"{where}.{name}: {d} is not a prior; use one of "
                             f"{', '.join(PRIOR_FAMILIES)} (fix a known value by leaving "
                             f"{name} out of free)")
        width = d.sd if isinstance(d, Normal) else (
            d.sigma if isinstance(d, LogNormal) else d.hi - d.lo)
        if not width > 0:
            raise ValueError(f"{where}.{name}: {d} has zero width; a prior needs a spread > 0")
        if _too_narrow(d):
            raise ValueError(f"{where}.{name}: {d} is narrower than a relative spread of "
                             f"{MIN_PRIOR_SPREAD:g}, which fixes {name}: widen the prior, or "
                             f"leave {name} out of the free parameters (its value in the "
                             "scene)")
        if _nonnegative(name) and (isinstance(d, Normal)
                                   or (isinstance(d, Uniform) and d.lo < 0)):
            raise ValueError(f"{where}.{name}: {d} puts mass below 0, outside {name}'s valid "
                             f"values (>= 0); use lognormal, loguniform or uniform(lo >= 0, "
                             "hi)")
        out[name] = d
    return out


def _too_narrow(d: AbstractDistribution) -> bool:
    """Whether a prior is narrower than [`MIN_PRIOR_SPREAD`][] (or, about zero,
    [`MIN_PRIOR_WIDTH`][])."""
    if isinstance(d, LogNormal):
        return not d.sigma >= MIN_PRIOR_SPREAD
    if isinstance(d, LogUniform):
        return not math.log(d.hi / d.lo) >= MIN_PRIOR_SPREAD
    width, scale = ((d.sd, abs(d.mu)) if isinstance(d, Normal)
                    else (d.hi - d.lo, max(abs(d.lo), abs(d.hi))))
    return not (width >= MIN_PRIOR_SPREAD * scale and width >= MIN_PRIOR_WIDTH)


def load_priors(path: str | os.PathLike) -> dict[str, str]:
    """The `[priors]` table of a scene file (`{}` when it has none or `path` is a preset).

    **Raises:** `ValueError` when `[priors]` is not a table of strings."""
    from ..scene import PRESETS, read_scene_doc

    if str(path) in PRESETS:
        return {}
    doc = read_scene_doc(path)  # as load_scene reads it (a byte-order mark, the checks)
    table = doc.get("priors", {})
    if not isinstance(table, dict) or not all(isinstance(v, str) for v in table.values()):
        raise ValueError(f"{path}: [priors] must be a table of strings like "
                         'k = "lognormal(0.7, 0.5)"')
    return dict(table)


def prior_arrays(names, priors, log=None) -> tuple[tuple[int, ...], np.ndarray]:
    """Static family codes (p,) and parameters (p, 2) of the priors on the coordinates."""
    codes, params = [], []
    for n in names:
        d = priors.get(n, priors.get(base_name(n)))
        if d is None:
            # Flat, within the valid values: a field >= 0 in linear coordinates (a
            # friction that starts at 0) must not go negative.
            linear = log is not None and not log[len(codes)]
            codes.append(_FLAT_NONNEGATIVE if linear and _nonnegative(n) else _FLAT)
            params.append((0.0, 0.0))
        elif isinstance(d, Normal):
            codes.append(_NORMAL)
            params.append((d.mu, d.sd))
        elif isinstance(d, Uniform):
            codes.append(_UNIFORM)
            params.append((d.lo, d.hi))
        elif isinstance(d, LogNormal):
            codes.append(_LOGNORMAL)
            params.append((math.log(d.median), d.sigma))
        else:
            codes.append(_LOGUNIFORM)
            params.append((math.log(d.lo), math.log(d.hi)))
    return tuple(codes), np.asarray(params, dtype=float).reshape(len(names), 2)


def prior_precision(codes, params, problem: Problem, z) -> np.ndarray:
    """(p,) approximate precision of each prior in the coordinate z (0 for flat): its
    variance carried to z at the point z (for a start scale, not for the density)."""
    x = np.asarray(problem.values(z), dtype=float)
    out = np.zeros(len(codes))
    for i, code in enumerate(codes):
        a, b = float(params[i, 0]), float(params[i, 1])
        # dz/dx: 1/x for log coordinates, 1/ref for linear ones
        dzdx = 1.0 / abs(x[i]) if problem.log[i] else 1.0 / float(np.asarray(problem.ref)[i])
        if code == _NORMAL:
            sd_z = b * dzdx
        elif code == _UNIFORM:
            sd_z = (b - a) / math.sqrt(12) * dzdx
        elif code == _LOGNORMAL:  # sd of ln x is b; of z: b for log coordinates
            sd_z = b if problem.log[i] else b * abs(x[i]) * dzdx
        elif code == _LOGUNIFORM:
            sd_z = (b - a) / math.sqrt(12) * (1.0 if problem.log[i] else abs(x[i]) * dzdx)
        else:
            continue
        out[i] = 1.0 / max(sd_z, MIN_PRIOR_WIDTH) ** 2  # (1e-300)**2 underflowed to 0
    return out


def log_prior(z, problem: Problem, codes, params):
    """Log prior density of the coordinates z (p,), up to a constant: the density of the
    physical value, times `|dx/dz|` (= x for log coordinates, constant for linear)."""
    x = problem.values(z)
    total = 0.0
    for i, code in enumerate(codes):
        if code == _FLAT:
            continue
        if code == _FLAT_NONNEGATIVE:
            total = total + jnp.where(x[i] >= 0, 0.0, -jnp.inf)
            continue
        a, b = params[i, 0], params[i, 1]
        xi, lx = x[i], jnp.log(jnp.abs(x[i]))
        inside = lambda lo, hi, v: jnp.where((v >= lo) & (v <= hi), 0.0, -jnp.inf)  # noqa: E731
        if code == _NORMAL:
            lp = -0.5 * ((xi - a) / b) ** 2
        elif code == _UNIFORM:
            lp = inside(a, b, xi)
        elif code == _LOGNORMAL:  # density of x: N(ln x; a, b) / x
            lp = -0.5 * ((lx - a) / b) ** 2 - lx
        else:  # loguniform: 1 / x on [e^a, e^b]
            lp = inside(a, b, lx) - lx
        total = total + lp + (z[i] if problem.log[i] else 0.0)
    return total


def in_support(d: AbstractDistribution, x: float) -> bool:
    if isinstance(d, Uniform):
        return d.lo <= x <= d.hi
    if isinstance(d, LogUniform):
        return d.lo <= x <= d.hi
    return not isinstance(d, LogNormal) or x > 0
