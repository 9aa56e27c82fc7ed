"""`crank-jax sweep` (Monte Carlo sweeps)."""

from __future__ import annotations

#: Subcommands added to `crank-jax` (see `cli.COMMANDS` for the tuple layout).
COMMANDS: list = []
