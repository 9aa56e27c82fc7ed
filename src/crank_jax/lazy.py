"""Third-party modules imported on first use.

diffrax (with optimistix and lineax, which it imports) and optax take about 0.35 s to
import, a sixth of a warm `crank-jax fit`, which runs stored programs (see
`persistent.py`) and never calls them. A module made by [`lazy_import`][] is imported at
its first attribute access, with the standard library's `importlib.util.LazyLoader`.
"""

from __future__ import annotations

import importlib.util
import sys
from types import ModuleType

__all__ = ["lazy_import"]


def lazy_import(name: str) -> ModuleType:
    """The module `name`, imported when one of its attributes is first used (at once if
    it is already imported)."""
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.find_spec(name)
    if spec is None or spec.loader is None:
        raise ModuleNotFoundError(f"No module named {name!r}", name=name)
    loader = importlib.util.LazyLoader(spec.loader)
    spec.loader = loader
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    loader.exec_module(module)
    return module
