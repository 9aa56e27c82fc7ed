"""Third-party modules imported on first use.

diffrax (with optimistix and lineax, which it imports) and optax take a noticeable part
of a warm `crank-jax fit` to import (docs/benchmarks/design-figures.md, Start-up), and
that fit runs stored programs (see `persistent.py`) and never calls them. A module made
by [`lazy_import`][] is imported at its first attribute access.

Why not the standard library's `importlib.util.LazyLoader`: before Python 3.12 it is not
thread-safe (CPython issue 114763). Two threads touching a lazy module at once (a host
program tracing two solves in two threads, say) could see it half executed: seen here as
"module 'diffrax' has no attribute 'PIDController'". Here the first access imports the
module with `importlib.import_module` under a lock; later accesses read it directly.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
import threading
from types import ModuleType

__all__ = ["lazy_import"]

_LOCK = threading.RLock()  # reentrant: an import may touch another lazy module


class _LazyModule(ModuleType):
    """Stands for a module until one of its attributes is used, then forwards to it."""

    def __getattr__(self, attr: str):
        # Called only for names not found on this object: every attribute of the module.
        module = self.__dict__.get("_module")
        if module is None:
            with _LOCK:
                module = self.__dict__.get("_module")
                if module is None:
                    module = importlib.import_module(self.__name__)
                    self.__dict__["_module"] = module
        return getattr(module, attr)


def lazy_import(name: str) -> ModuleType:
    """The module `name`, imported when one of its attributes is first used (at once if
    it is already imported). Raises `ModuleNotFoundError` now if it is not installed."""
    if name in sys.modules:
        return sys.modules[name]
    if importlib.util.find_spec(name) is None:
        raise ModuleNotFoundError(f"No module named {name!r}", name=name)
    return _LazyModule(name)
