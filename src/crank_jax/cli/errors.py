"""The CLI's error type, a leaf module: every command group raises it, none imports another."""

from __future__ import annotations

__all__ = ["UserError", "RunFailed", "EXIT_USAGE", "EXIT_FAILURE"]

#: Exit status of a user mistake (bad file, bad value, unknown option).
EXIT_USAGE = 2
#: Exit status of a run that could not finish (a failed solve, an internal error).
EXIT_FAILURE = 1


class UserError(Exception):
    """A mistake on the user's side: reported in one line, exit status 2."""


class RunFailed(RuntimeError):
    """A run that did not finish (a partial result, written and marked so): reported in one
    line, exit status 1, as a failed solve is."""
