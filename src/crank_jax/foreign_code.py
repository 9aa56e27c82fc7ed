"""The code from outside crank-jax that a stored program holds (a user's `AbstractLoad`
subclass, a force module of their own), for the program store's key (`persistent.py`).

A compiled program holds the code of every class in its inputs, but the store's key
covers crank-jax's own source and the versions of the libraries it traces. A user's
class edited between two runs would load the executable compiled from the old code: a
wrong number with exit 0. So the key also holds the source of every such class: the files
of the modules that define it and its bases, and of the user modules those import
(transitively; an installed package counts by its version instead). A class without a
source file (defined in `python -c`, a notebook or an `exec`), or whose source changed
after this process started (the running code may be the old one), gives no key: its
program runs compiled in memory only, never stored.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import os
import site
import sys
import sysconfig
import time
from importlib import metadata
from pathlib import Path

__all__ = ["foreign_classes", "source_digest"]

# Modules whose code is covered by the key already (crank-jax's source, the traced
# libraries' versions) or that trace nothing into a program (Python's own, NumPy's types).
_KNOWN = frozenset({"crank_jax", "builtins", "jax", "jaxlib", "equinox", "diffrax",
                    "optimistix", "lineax", "optax", "numpy", "jaxtyping"})

_MAX_MODULES = 200  # more user modules than this: not stored (scanning would cost)

# When this module was imported: crank-jax is imported before any class that subclasses
# its own, and a source file changed after that may not be the code that runs.
_STARTED = time.time()


def _known(module_name: str) -> bool:
    top = module_name.partition(".")[0]
    return top in _KNOWN or top in sys.stdlib_module_names or top == "__future__"


def foreign_classes(treedefs, static_leaves) -> set[type]:
    """The classes from outside crank-jax and the traced libraries in pytrees' structures
    (`PyTreeDef`s: their nodes and the nodes' static data) and static leaves."""
    found: set[type] = set()

    def visit(obj, depth=0):
        if depth > 8:
            return
        cls = obj if isinstance(obj, type) else type(obj)
        if not _known(cls.__module__):
            found.add(cls)
        if isinstance(obj, (tuple, list)):
            for x in obj:
                visit(x, depth + 1)

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


def source_digest(classes: frozenset[type]) -> str | None:
    """A digest of the source of `classes` (their modules and bases' modules, and the
    user modules those import), or None when some has no source file, or one changed
    after this process started (checked at every call: an edit after the first use,
    e.g. a notebook's autoreload, makes the running code differ from either version)."""
    found = _sources(classes)
    if found is None:
        return None
    digest, files = found
    try:
        if any(os.stat(f).st_mtime >= _STARTED for f in files):
            return None
    except OSError:
        return None
    return digest


@functools.cache
def _sources(classes: frozenset[type]) -> tuple[str, tuple[str, ...]] | None:
    """(the digest, the user source files it covers) of `classes`, once per process."""
    names = set()
    for cls in classes:
        for c in inspect.getmro(cls):
            if not _known(c.__module__):
                names.add(c.__module__)
    h, seen, todo, files = hashlib.sha256(), set(), sorted(names), []
    while todo:
        name = todo.pop()
        if name in seen or _known(name):
            continue
        seen.add(name)
        module = sys.modules.get(name)
        file = getattr(module, "__file__", None)
        if module is None or not file or len(seen) > _MAX_MODULES:
            return None
        version = _installed_version(name, file)
        if version is not None:  # an installed package: its version stands for its code
            h.update(f"{name}={version}\n".encode())
            continue
        try:
            h.update(f"{name}\n".encode() + Path(file).read_bytes())
        except OSError:
            return None
        files.append(file)
        todo.extend(_imports(module))
    return h.hexdigest(), tuple(files)


def _imports(module) -> list[str]:
    """The modules whose objects (modules, functions, classes) `module` names."""
    out = []
    for v in list(vars(module).values()):
        name = v.__name__ if inspect.ismodule(v) else getattr(v, "__module__", None)
        if isinstance(name, str) and not _known(name):
            out.append(name)
    return out


def _installed_version(name: str, file: str) -> str | None:
    """The version of the installed distribution that provides module `name`, or None
    (user code: not under an installation's package directories)."""
    resolved = Path(file).resolve()
    if not any(resolved.is_relative_to(d) for d in _site_dirs()):
        return None
    dists = _distributions().get(name.partition(".")[0], [])
    versions = sorted(f"{d}={metadata.version(d)}" for d in dists)
    return ",".join(versions) or None


@functools.cache
def _site_dirs() -> tuple[Path, ...]:
    dirs = set(site.getsitepackages()) | {site.getusersitepackages()}
    dirs |= {sysconfig.get_path(k) for k in ("purelib", "platlib")}
    return tuple(Path(d).resolve() for d in dirs if d)


@functools.cache
def _distributions():
    return metadata.packages_distributions()
