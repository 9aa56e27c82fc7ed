"""`crank-jax synth` and `crank-jax fit` (parameter identification)."""

from __future__ import annotations

#: Subcommands added to `crank-jax` (see `cli.COMMANDS` for the tuple layout).
COMMANDS: list = []
