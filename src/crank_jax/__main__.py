"""`python -m crank_jax ...` is `crank-jax ...`."""

from .cli import entry

entry()
