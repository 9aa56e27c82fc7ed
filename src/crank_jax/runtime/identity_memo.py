"""A small memo of the last few results, keyed by the identity of the JAX arrays they were
computed from (and the values of scalars): the front door's `simulate` keeps its host
plans here (`crank_jax/simulation.py`), so that a repeated concrete call skips its checks
and the linearisation.

Why identity and not value: hashing the arrays' values would cost what the memo saves
(a plan is a sizeable part of a fast lab-rig solve: docs/benchmarks/design-figures.md). A
JAX array is
immutable, and the key holds it, so its `id` cannot be reused while the entry lives; a
NumPy array (mutable) or a tracer gives no key, and such calls are not memoised. Thread-
safe (a lock around each change); the solver core knows nothing of it.
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable, Hashable
from typing import Any

import jax
import numpy as np

__all__ = ["IdentityMemo"]


class _Identity:
    """Hashes and compares a tuple of JAX arrays by identity (and scalars by value),
    keeping the arrays alive while it is a key."""

    __slots__ = ("parts", "_hash")

    def __init__(self, parts: tuple):
        self.parts = parts
        self._hash = hash(tuple(p if isinstance(p, tuple) else id(p) for p in parts))

    def __hash__(self):
        return self._hash

    def __eq__(self, other):
        return (isinstance(other, _Identity) and len(self.parts) == len(other.parts)
                and all(a is b if not isinstance(a, tuple) else a == b
                        for a, b in zip(self.parts, other.parts)))


class IdentityMemo:
    """The last `kept` results of `make()`, oldest first, by [`key`][]. A `make` that
    raises keeps nothing."""

    def __init__(self, kept: int):
        self.kept = kept
        self._items: collections.OrderedDict = collections.OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._items)

    @staticmethod
    def key(tree, *static: Hashable) -> Hashable | None:
        """A key for the arrays of `tree` (by identity) and `static` (by value), or None
        (no memo) unless every leaf is a JAX array or a Python or NumPy scalar."""
        leaves, treedef = jax.tree_util.tree_flatten(tree)
        parts = []
        for x in leaves:
            if isinstance(x, jax.core.Tracer):
                return None
            if isinstance(x, jax.Array):
                parts.append(x)
            elif isinstance(x, (float, int, bool, np.generic)):
                parts.append((type(x), x))
            else:  # a mutable array (NumPy's) or anything else: no memo
                return None
        return (_Identity(tuple(parts)), treedef, *static)

    def get(self, key: Hashable | None, make: Callable[[], Any]) -> Any:
        """The result kept under `key`, else `make()` (kept under `key` unless it is None)."""
        value = self._items.get(key) if key is not None else None
        if value is None:
            value = make()
            if key is not None:
                with self._lock:
                    self._items[key] = value
                    while len(self._items) > self.kept:
                        self._items.popitem(last=False)
        return value
