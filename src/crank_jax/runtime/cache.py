"""JAX's persistent compilation cache, on by default in a per-user cache directory.

A cold `crank-jax simulate` spends most of its time compiling; with the cache a second
process reuses the compiled executables, and the package's own programs (the fit's, the
linearisation, concrete `simulate` calls) are kept beside it, in `crank-jax-programs/`,
so that a second process need not even trace them (see `persistent.py`). Set
`CRANK_JAX_NO_CACHE=1` to leave JAX's configuration untouched, or `CRANK_JAX_CACHE_DIR`
to choose the directory.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

__all__ = ["enable_compilation_cache", "default_cache_dir"]


def default_cache_dir() -> Path:
    """`$CRANK_JAX_CACHE_DIR`, else `$XDG_CACHE_HOME/crank-jax/jax`, else `~/.cache/...`."""
    if os.environ.get("CRANK_JAX_CACHE_DIR"):
        return Path(os.environ["CRANK_JAX_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "crank-jax" / "jax"


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Point JAX's persistent compilation cache at `path` (default: [`default_cache_dir`][]).

    Does nothing (returns None) if the user already configured a cache directory, if
    `CRANK_JAX_NO_CACHE` is set, or if the directory cannot be created or written.
    """
    if os.environ.get("CRANK_JAX_NO_CACHE") or jax.config.jax_compilation_cache_dir:
        return None
    p = Path(path) if path is not None else default_cache_dir()
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    if not os.access(p, os.W_OK | os.X_OK):
        # A read-only cache (a shared or read-only home) would make JAX warn on every
        # write; run without one instead.
        return None
    jax.config.update("jax_compilation_cache_dir", str(p))
    # Small programs compile in well under JAX's default 1 s threshold, yet together they
    # are most of a cold start; cache them all.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return p
