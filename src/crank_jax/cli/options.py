"""Argument types shared by the command groups (a leaf module, like `errors`): argparse
names the option in front of the message they raise (`argument --seed: ...`)."""

from __future__ import annotations

import argparse

from ..sweep.distributions import MAX_SEED
from .errors import UserError

__all__ = ["seed", "MAX_SEED", "free_list"]


def seed(text: str) -> int:
    """A random seed: an integer from 0 to [`MAX_SEED`][] (numpy's generators refuse a
    negative one, with a message that names no option)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer seed from 0 to {MAX_SEED}, "
                                         f"got {text!r}") from None
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"a seed must be an integer from 0 to {MAX_SEED}, "
                                         f"got {value}")
    return value


def free_list(text: str) -> tuple[str, ...]:
    """`--free a,b,c` -> ("a", "b", "c"), blanks dropped; [`UserError`][] when it names
    nothing."""
    free = tuple(x.strip() for x in text.split(",") if x.strip())
    if not free:
        raise UserError("--free is empty; name at least one parameter")
    return free
