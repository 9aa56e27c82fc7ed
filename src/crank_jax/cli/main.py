"""The `crank-jax` command line.

Every subcommand is a tuple `(name, help, add_arguments, run)` in the `COMMANDS` list of
its command group (`simulate`, `identify`, `sweep`). A user mistake (bad file, bad value,
unknown option) prints one line on stderr and exits with status 2; outputs are written
atomically and never over an input file.
"""

from __future__ import annotations

import argparse
import sys

from . import identify, simulate, sweep, validate
from .errors import EXIT_USAGE, UserError

__all__ = ["main", "build_parser"]


class _Parser(argparse.ArgumentParser):
    # argparse prints the whole usage block before its error; one line is kinder in
    # scripts and logs, and `--help` still shows the usage.
    def error(self, message: str):
        raise UserError(f"{self.prog}: {message} (see --help)")


def _setup_jax() -> None:
    import jax

    from ..cache import enable_compilation_cache

    jax.config.update("jax_enable_x64", True)
    # The CLI is a program, not a library: it may configure JAX, and every call after the
    # first reuses the compiled programs from the persistent cache.
    enable_compilation_cache()


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="crank-jax", description="Slider-crank simulation and identification.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name, help_, add, run in (simulate.COMMANDS + identify.COMMANDS + sweep.COMMANDS
                               + validate.COMMANDS):
        p = sub.add_parser(name, help=help_, description=help_)
        add(p)
        p.set_defaults(_run=run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of `crank-jax`; returns the exit status."""
    try:
        args = build_parser().parse_args(argv)
        _setup_jax()
        return int(args._run(args) or 0)
    except UserError as e:
        print(f"crank-jax: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except (ValueError, OSError) as e:
        # SceneError, data errors and bad values are ValueErrors with a message that names
        # the field and the fix; file problems are OSErrors. Either is the user's to fix.
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        print(f"crank-jax: error: {msg}", file=sys.stderr)
        return EXIT_USAGE
    except RuntimeError as e:
        # A solve that failed (e.g. hit max_steps) or a value rejected inside jit by
        # eqx.error_if: not a crash of ours, so no traceback, but not a success either.
        lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
        print(f"crank-jax: error: {lines[0] if lines else type(e).__name__}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("crank-jax: interrupted", file=sys.stderr)
        return 130
