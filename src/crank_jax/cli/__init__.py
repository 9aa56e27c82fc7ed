"""The `crank-jax` command line: one module per command group, `errors` a leaf."""

from .main import build_parser, entry, main

__all__ = ["main", "entry", "build_parser"]
