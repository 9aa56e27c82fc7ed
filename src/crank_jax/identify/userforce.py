"""A user's force term in a fit: `fit(..., force=f)` takes the generalised force that
`simulate` takes (an `eqx.Module` callable `f(t, phi, dphi) -> N*m`, added to q), and its
array fields can be freed as `force.<field>` (a scalar field) or `force.<field>[i]` (each
element of an array field)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

__all__ = ["force_names", "force_starts", "with_force_values", "PREFIX"]

PREFIX = "force."


def _fields(force):
    """(field name, value) of each inexact-array field of `force`, in declaration order."""
    if force is None:
        return []
    out = []
    for name in getattr(force, "__dataclass_fields__", {}):
        v = getattr(force, name)
        if eqx.is_inexact_array(v) or isinstance(v, float):
            out.append((name, v))
    return out


def force_names(force) -> dict[str, tuple[str, int | None]]:
    """Free name -> (field, element index or None for a scalar field) of every element
    of `force`'s float fields."""
    out = {}
    for name, v in _fields(force):
        # Shapes only (static under tracing): the values may be traced.
        if jnp.ndim(v) == 0:
            out[f"{PREFIX}{name}"] = (name, None)
        else:
            for i in range(int(jnp.size(v))):
                out[f"{PREFIX}{name}[{i}]"] = (name, i)
    return out


def force_starts(force, free) -> dict[str, float]:
    """The start value of each free `force.` name: the force's own value."""
    names = force_names(force)
    out = {}
    for n in free:
        if n in names:
            field, i = names[n]
            a = np.asarray(getattr(force, field), dtype=float)
            out[n] = float(a if i is None else a.reshape(-1)[i])
    return out


def with_force_values(force, values: dict):
    """`force` with the free names' `values` (name -> scalar array, traced or not)."""
    if force is None or not values:
        return force
    names = force_names(force)
    for field in {names[n][0] for n in values}:
        old = jnp.asarray(getattr(force, field), dtype=float)
        flat = old.reshape(-1)
        for n, v in values.items():
            f, i = names[n]
            if f == field:
                flat = flat.at[0 if i is None else i].set(v)
        force = eqx.tree_at(lambda x, f=field: getattr(x, f), force, flat.reshape(old.shape))
    return force
