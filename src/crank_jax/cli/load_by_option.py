"""`--load-by time|angle` for the commands that read a record's load columns (`fit`,
`validate`, `posterior`), and the library's words about it in the command's."""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Iterator

from ..records.load_by import LOAD_BY
from .errors import UserError
from .wording import cli_message

__all__ = ["add_load_by_option", "load_by_words"]

def add_load_by_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--load-by", default="time", choices=LOAD_BY,
                   help="what the record's P/tau columns follow: time (interpolated in time; "
                        "default) or angle (tabled by the record's own angle channel, which "
                        "must turn one way, and evaluated at the model's angle: a force that "
                        "follows the crank; held at its end values beyond the record's "
                        "angles)")


@contextlib.contextmanager
def load_by_words() -> Iterator[None]:
    """Re-raise a library `ValueError` about `load_by` as a [`UserError`][] (exit 2) that
    names the command's options."""
    try:
        yield
    except ValueError as e:
        text = str(e)
        if "`load_by=" not in text:
            raise
        raise UserError(cli_message(text)) from None
