"""Deprecated spellings of the public API, kept one release: each warns with a
`DeprecationWarning` that names the new spelling, and gives the very object the old name
gave.

Two kinds:

- a name moved off a namespace (`crank_jax.energy` -> `crank_jax.model.energy`, or renamed:
  `crank_jax.widen` -> `crank_jax.identify.widen_covariance`): a namespace's module-level
  `__getattr__` calls `moved` with a table `old name -> "namespace:new name"`;
- a function that shadowed its own subpackage (`cj.sweep(...)`, `cj.solve(...)`): the
  subpackage is the attribute now, and `make_callable` lets a call to it still run the
  function, with the warning, so old code keeps working for a release instead of failing
  with "'module' object is not callable".
"""

from __future__ import annotations

import importlib
import sys
import warnings
from collections.abc import Callable, Mapping
from types import ModuleType

__all__ = ["moved", "make_callable"]


def moved(namespace: str, name: str, table: Mapping[str, str]):
    """`namespace`'s attribute `name` by its deprecated spelling in `table` (old name ->
    `"module:new name"`, or `"module:name|what to use instead"` for a name that goes), with
    a `DeprecationWarning`; `AttributeError` if it is not one."""
    if name not in table:
        raise AttributeError(f"module {namespace!r} has no attribute {name!r}")
    where, _, advice = table[name].partition("|")
    module, new = where.split(":")
    warnings.warn(f"{namespace}.{name} is deprecated and goes in the next release; "
                  f"use {advice or f'{module}.{new}'}", DeprecationWarning, stacklevel=3)
    return getattr(importlib.import_module(module), new)


class _CallableModule(ModuleType):
    """A module whose call runs the function that used to stand in its place."""

    def __call__(self, *args, **kwargs):
        fn, new = self.__dict__["_deprecated_call"]
        warnings.warn(f"calling the module {self.__name__} is deprecated and goes in the "
                      f"next release; call {new}", DeprecationWarning, stacklevel=2)
        return fn(*args, **kwargs)


def make_callable(module_name: str, fn: Callable, new: str) -> None:
    """Let a call to the module `module_name` run `fn` (spelled `new` now), warning."""
    module = sys.modules[module_name]
    module.__dict__["_deprecated_call"] = (fn, new)
    module.__class__ = _CallableModule
