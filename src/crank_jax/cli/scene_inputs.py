"""Commands that take no record (`synth`, `simulate`, `sweep`, `design`) refuse a scene
whose load is driven by a record's column (`[torque] input = "volts"`), in the CLI's
words and before any work: the library's "give InputLoad a signal" came only after the
work (a long one in `design`)."""

from __future__ import annotations

from .errors import UserError

__all__ = ["refuse_input_loads"]


def refuse_input_loads(scene, source: str, command: str) -> None:
    """[`UserError`][] naming the scene, its table and the column when a load of `scene`
    (loaded from `source`) reads a record's input column: `command` has no record."""
    from ..model.sampled import InputLoad

    for side, what in (("load", "slider force"), ("torque", "crank torque")):
        x = getattr(scene, side)
        if isinstance(x, InputLoad) and x.signal is None:
            raise UserError(
                f"{source}: its {what} [{side}] is driven by the record column {x.column!r} "
                f"(input = \"{x.column}\"), and `crank-jax {command}` reads no record: the "
                f"scene needs a record with a {x.column!r} column (fit, validate); for "
                f"{command}, give [{side}] a kind without input (constant, harmonic, ...)")
