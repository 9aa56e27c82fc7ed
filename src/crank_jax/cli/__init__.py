"""The `crank-jax` command line: one module per command group, `errors` a leaf."""

from .main import build_parser, main

__all__ = ["main", "build_parser"]
