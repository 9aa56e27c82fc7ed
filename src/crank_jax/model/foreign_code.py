"""Code from outside crank-jax in a program's inputs (a user's `AbstractLoad` subclass, a
force module of their own), which the program store (`runtime/persistent.py`) never
stores and the field's cached trace of its acceleration never serves (`dynamics.py`).
In the core because both need it, and the core imports nothing from the runtime.

A stored program is loaded without tracing, so its key must hold every input of the
trace. For crank-jax's own classes it does (the package's source, the traced libraries'
versions, the static structure). For a user's class it cannot: its `__call__` may read a
module global, a closure cell, a configuration file, an environment variable, none of
which is in its source or in the arguments. Keyed on its source (as before issue 37), a
load reading `GAIN` gave the first run's trajectory after `GAIN` changed, two classes
from one factory shared one program, and `fit(force=...)` returned wrong, "converged"
values. So a program with any class from outside crank-jax in its inputs is never
stored: it is traced in every process (that is what tracing is for), and JAX's own
persistent cache, keyed on the traced program, still spares the compilation.
"""

from __future__ import annotations

import dataclasses
import sys

__all__ = ["foreign_classes"]

# Modules whose code is covered by the key already (crank-jax's source, the traced
# libraries' versions) or that trace nothing into a program (Python's own, NumPy's types).
_KNOWN = frozenset({"crank_jax", "builtins", "jax", "jaxlib", "equinox", "diffrax",
                    "optimistix", "lineax", "optax", "numpy", "jaxtyping"})

_MAX_DEPTH = 32  # deeper static data than this counts as foreign (not stored)


def _known(module_name) -> bool:
    if not isinstance(module_name, str):
        return False
    top = module_name.partition(".")[0]
    return top in _KNOWN or top in sys.stdlib_module_names or top == "__future__"


class _TooDeep:
    """Stands for static data nested too deeply to inspect (counted as foreign)."""


def foreign_classes(treedefs, static_leaves) -> set[type]:
    """The classes from outside crank-jax and the traced libraries in pytrees' structures
    (`PyTreeDef`s: their nodes and the nodes' static data) and static leaves, looking
    inside containers (tuples, lists, sets, dicts) and dataclasses (equinox modules) at
    any depth: a user's object in a static field of one of crank-jax's modules counts."""
    found: set[type] = set()
    seen: set[int] = set()

    def visit(obj, depth=0):
        if depth > _MAX_DEPTH:
            found.add(_TooDeep)
            return
        cls = obj if isinstance(obj, type) else type(obj)
        if not _known(getattr(cls, "__module__", None)):
            found.add(cls)
        if isinstance(obj, type) or id(obj) in seen:
            return
        seen.add(id(obj))
        if isinstance(obj, (tuple, list, set, frozenset)):
            for x in obj:
                visit(x, depth + 1)
        elif isinstance(obj, dict):
            for k, v in obj.items():
                visit(k, depth + 1)
                visit(v, depth + 1)
        elif dataclasses.is_dataclass(obj):
            for f in dataclasses.fields(obj):
                visit(getattr(obj, f.name, None), depth + 1)

    def walk(td):
        node, aux = td.node_data() or (None, None)
        if node is not None:
            visit(node)
            visit(aux)
        for child in td.children():
            walk(child)

    for td in treedefs:
        walk(td)
    for leaf in static_leaves:
        visit(leaf)
    return found
