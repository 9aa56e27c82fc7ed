"""Code from outside crank-jax in a program's inputs (a user's `AbstractLoad` subclass, a
force module of their own), which the program store (`persistent.py`) never stores. A
host question (where a class's files lie), so it is the runtime's: the core decides
its own cached trace on the objects alone (`model/loads.py`, `only_own_loads`).

A stored program is loaded without tracing, so its key must hold every input of the
trace. For crank-jax's own classes it does (the package's source, the traced libraries'
versions, the static structure). For a user's class it cannot: its `__call__` may read a
module global, a closure cell, a configuration file, an environment variable, none of
which is in its source or in the arguments. Keyed on its source (as the store once was), a
load reading `GAIN` gave the first run's trajectory after `GAIN` changed, two classes
from one factory shared one program, and `fit(force=...)` returned wrong, "converged"
values. So a program with any class from outside crank-jax in its inputs is never
stored: it is traced in every process (that is what tracing is for), and JAX's own
persistent cache, keyed on the traced program, still spares the compilation.

Which code is the library's own is decided by where its files lie, never by a module's
name: a class counts only if its module's file, and the file of every function its body
defines, is in crank-jax's package, a pinned library's installed package or the
interpreter's standard library (a user's `profile.py`, a "torque profile", is named like
the standard library's profiler but lies elsewhere).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.util
import os
import sys
import sysconfig
import types
import weakref

__all__ = ["foreign_classes"]

# Packages whose code is covered by the key already (crank-jax's source, the traced
# libraries' versions, which `persistent.py` keys on) or that trace nothing into a
# program (Python's own standard library, NumPy's types). Trusted by where their files
# lie, never by a module's name: a user's `profile.py` is named like the standard
# library's profiler but is not it.
_PINNED = ("jax", "jaxlib", "equinox", "diffrax", "optimistix", "lineax", "optax", "numpy",
           "jaxtyping")

_MAX_DEPTH = 32  # deeper static data than this counts as foreign (not stored)


def _real(path: str) -> str:
    return os.path.normcase(os.path.realpath(path))


@functools.cache
def _trusted_roots() -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(trusted directories, directories inside them that are not trusted): crank-jax's
    package, each pinned library's installed package, and the interpreter's standard
    library without the site-packages an installation may keep inside it."""
    roots = [os.path.dirname(os.path.dirname(_real(__file__)))]
    for name in _PINNED:
        spec = importlib.util.find_spec(name)
        roots += [_real(d) for d in (spec.submodule_search_locations or ())] if spec else []
    stdlib = {_real(sysconfig.get_paths()["stdlib"]), _real(os.path.dirname(os.__file__))}
    roots += sorted(stdlib)
    excluded = [os.path.join(d, sub) for d in stdlib
                for sub in ("site-packages", "dist-packages")]
    return tuple(roots), tuple(excluded)


def _inside(path: str, dirs) -> bool:
    return any(path == d or path.startswith(d + os.sep) for d in dirs)


def _trusted_file(path) -> bool:
    """Whether a source or extension file lies in a trusted package directory."""
    if not isinstance(path, str) or not os.path.isabs(path):
        return False
    roots, excluded = _trusted_roots()
    real = _real(path)
    return _inside(real, roots) and not _inside(real, excluded)


def _module_file(module_name: str):
    """The file of the module a class names, or of its nearest enclosing package with one
    (an extension's submodule, e.g. `jaxlib._jax.pytree`, has none); None for a module
    that is not loaded, or has no file anywhere up its name."""
    name = module_name
    while name:
        module = sys.modules.get(name)
        if module is None:
            return None
        path = getattr(module, "__file__", None)
        if path:
            return path
        name = name.rpartition(".")[0]
    return None


def _functions(cls):
    """The code objects of the functions a class body defines (methods, static and class
    methods, properties' accessors, wrapped methods)."""
    for value in list(vars(cls).values()):
        try:
            fns = (value, getattr(value, "__func__", None), getattr(value, "fget", None),
                   getattr(value, "method", None), getattr(value, "__wrapped__", None))
        except Exception:  # noqa: BLE001 (an attribute whose lookup runs code)
            fns = (value,)
        for fn in fns:
            code = getattr(fn, "__code__", None)
            if isinstance(code, types.CodeType):
                yield code


_VERDICTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _known_class(cls) -> bool:
    """Whether a class is trusted code: its module is a built-in one or its file lies in a
    trusted directory, and so does every function its body defines that has a file
    (a generated `__init__` has none: its filename is "<string>")."""
    module_name = getattr(cls, "__module__", None)
    if not isinstance(module_name, str):
        return False
    if module_name in sys.builtin_module_names:
        return True
    if not _trusted_file(_module_file(module_name)):
        return False
    return all(_trusted_file(c.co_filename) or not os.path.isabs(c.co_filename)
               for c in _functions(cls))


def _known(cls) -> bool:
    try:
        return _VERDICTS[cls]
    except (KeyError, TypeError):
        pass
    verdict = _known_class(cls)
    try:
        _VERDICTS[cls] = verdict
    except TypeError:  # a class that takes no weak reference is judged every time
        pass
    return verdict


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
        if not _known(cls):
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
