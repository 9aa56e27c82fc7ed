"""The `crank-jax` command line.

Every subcommand is a tuple `(name, help, add_arguments, run)` in the `COMMANDS` list of
its command group (`simulate`, `identify`, `sweep`).

The contract with the user: a mistake on their side (bad file, bad value, unknown option)
prints one line on stderr and exits with status 2; a run that could not finish (a failed
solve, an internal error, no memory) prints one line and exits with status 1; no traceback
reaches the user unless asked for with `--debug` or `CRANK_JAX_DEBUG=1`. Every option is
checked before any work. Outputs are written atomically and never over an input file, and
SIGINT, SIGTERM and SIGHUP remove the temporary files of unfinished outputs (exit 130, 143,
129).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading
import traceback
import warnings
from collections.abc import Iterator

from ..runtime.io import DISK_FULL, Terminated, disk_full, note_signal, raise_if_terminated
from ..runtime.xla_flags import configure_cpu
from . import (
    bayes,
    identify,
    sweep,
    vibration,
)
from . import (
    simulate_command as simulate,
)
from . import (
    synth_command as synth,
)
from . import (
    track_command as track,
)
from . import (
    validate_command as validate,
)
from .errors import EXIT_FAILURE, EXIT_USAGE, UserError
from .wording import cli_message

__all__ = ["main", "entry", "build_parser", "Terminated", "ENV_DEBUG"]

#: Set to a non-empty value other than "0" to see tracebacks (like `--debug`).
ENV_DEBUG = "CRANK_JAX_DEBUG"


class _Parser(argparse.ArgumentParser):
    # argparse prints the whole usage block before its error; one line is kinder in
    # scripts and logs, and `--help` still shows the usage.
    def error(self, message: str):
        raise UserError(f"{self.prog}: {message} (see --help)")


def _setup_jax() -> None:
    import jax

    from ..runtime.cache import enable_compilation_cache

    jax.config.update("jax_enable_x64", True)
    # Keep JAX's own frames in tracebacks: they tell a failure inside JAX (ours to fix,
    # exit 1) from a value crank-jax refused (the user's, exit 2); see `_raised_inside_jax`.
    jax.config.update("jax_traceback_filtering", "off")
    # The CLI is a program, not a library: it may configure JAX, and every call after the
    # first reuses the compiled programs from the persistent cache.
    enable_compilation_cache()


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="crank-jax", description="Slider-crank simulation and identification.")
    parser.add_argument("--debug", action="store_true",
                        help=f"show the traceback of any error (also: {ENV_DEBUG}=1)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name, help_, add, run in (simulate.COMMANDS + synth.COMMANDS + identify.COMMANDS
                               + sweep.COMMANDS + validate.COMMANDS + bayes.COMMANDS
                               + vibration.COMMANDS + track.COMMANDS):
        p = sub.add_parser(name, help=help_, description=help_)
        add(p)
        p.set_defaults(_run=run)
    return parser


@contextlib.contextmanager
def _signals_raise() -> Iterator[None]:
    """Turn SIGTERM and SIGHUP into [`Terminated`][] (and SIGINT into KeyboardInterrupt)
    while the CLI runs (main thread only).

    The default action of SIGTERM kills the process without unwinding, so a temporary
    output file would survive it. Python runs the handler between bytecodes: a compiled
    computation finishes its current call first, which is why long simulations run in
    bounded chunks. Python drops an exception raised while a garbage-collector callback
    runs (JAX has one), so the signal is also noted for the writers to check before they
    commit (see `io.note_signal`), and the dropped exception is not reported.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        note_signal(signum)
        raise KeyboardInterrupt if signum == signal.SIGINT else Terminated(signum)

    def unraisable(info):
        if not isinstance(info.exc_value, (Terminated, KeyboardInterrupt)):
            old_hook(info)

    sigs = [s for s in (getattr(signal, n, None) for n in ("SIGTERM", "SIGHUP", "SIGINT")) if s]
    old = {s: signal.getsignal(s) for s in sigs}
    old_hook, sys.unraisablehook = sys.unraisablehook, unraisable
    note_signal(None)
    for s in sigs:
        if old[s] is not signal.SIG_IGN:  # nohup ignores SIGHUP: keep it ignored
            signal.signal(s, handler)
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        sys.unraisablehook = old_hook
        note_signal(None)


@contextlib.contextmanager
def _warnings_one_line() -> Iterator[None]:
    """Show each warning as one line `crank-jax: warning: ...` (not file, line and source);
    the warning filters themselves are left alone."""
    old = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        print(f"crank-jax: warning: {cli_message(_one_line(message))}", file=sys.stderr)

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = old


def _one_line(e: BaseException | Warning | str) -> str:
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    msg = lines[0] if lines else type(e).__name__
    return msg if len(msg) <= 500 else msg[:497] + "..."


#: What diffrax advises when a solve runs out of steps: `max_steps` is a library argument,
#: so the CLI names what its user can change instead.
_MAX_STEPS_ADVICE = "Try increasing `max_steps`."


def _solver_advice(msg: str, args: argparse.Namespace | None) -> str:
    """`msg` with diffrax's "Try increasing `max_steps`" replaced by what this command's
    user can change (only `simulate` has an ODE step budget option)."""
    if _MAX_STEPS_ADVICE not in msg:
        return msg
    command = getattr(args, "command", None)
    if command == "simulate":
        fix = ("raise --max-steps (the budget per chunk of samples), or shorten the run "
               "(--t1)")
    else:
        fix = ("shorten the run (--t1 or the record) or check that the scene's values are in "
               "SI units; `crank-jax simulate SCENE --max-steps N` shows how many steps the "
               "scene needs")
    return msg.replace(_MAX_STEPS_ADVICE, f"The solve ran out of steps: {fix}.")


def _debug(argv: list[str]) -> bool:
    return "--debug" in argv or os.environ.get(ENV_DEBUG, "") not in ("", "0")


def _fail(code: int, msg: str, debug: bool) -> int:
    if debug:
        traceback.print_exc()
    # The library names its arguments (`warmup=`); the user typed options (--warmup).
    print(f"crank-jax: error: {cli_message(msg)}", file=sys.stderr)
    return code


def _internal(e: BaseException) -> str:
    return (f"internal error: {type(e).__name__}: {_one_line(e)} (please report it; run "
            f"with --debug or {ENV_DEBUG}=1 for the traceback)")


#: Packages whose ValueErrors are never the user's: crank-jax checks its inputs before it
#: hands them on, so one of these raising means a bug of ours (e.g. a sharding mismatch).
_INTERNAL_PACKAGES = ("jax", "jaxlib", "equinox", "lineax", "diffrax", "optimistix")


def _raised_inside_jax(e: BaseException) -> bool:
    tb = e.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    module = tb.tb_frame.f_globals.get("__name__", "") if tb is not None else ""
    return module.split(".")[0] in _INTERNAL_PACKAGES


def main(argv: list[str] | None = None) -> int:
    """Entry point of `crank-jax`; returns the exit status (0, 1 or 2; 128 + the signal's
    number when interrupted). Never raises, except `SystemExit` from `--help`'s exit 0,
    which it returns as 0."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = _debug(argv)
    args = None
    try:
        with _signals_raise(), _warnings_one_line():
            # --debug is accepted anywhere on the line, not only before the command.
            args = build_parser().parse_args([a for a in argv if a != "--debug"])
            args._argv = ["crank-jax"] + argv  # the command line, for reports
            _setup_jax()
            code = int(args._run(args) or 0)
            raise_if_terminated()  # a signal whose exception was dropped: still its exit
            return code
    except SystemExit as e:  # --help
        return e.code if isinstance(e.code, int) else (0 if e.code is None else EXIT_USAGE)
    except UserError as e:
        return _fail(EXIT_USAGE, _one_line(e), debug)
    except (ValueError, OSError) as e:
        # SceneError, data errors and bad values are ValueErrors with a message that names
        # the field and the fix; file problems are OSErrors. Either is the user's to fix,
        # unless JAX or a library under it raised it: that is a failure of ours.
        if isinstance(e, ValueError) and _raised_inside_jax(e):
            return _fail(EXIT_FAILURE, _internal(e), debug)
        if isinstance(e, OSError) and e.errno in DISK_FULL and "could not write" not in str(e):
            # A write outside the atomic writers (which name their file themselves).
            return _fail(EXIT_USAGE, _one_line(disk_full(e.filename, e)), debug)
        if isinstance(e, BrokenPipeError):  # `crank-jax ... | head`: not an error
            with contextlib.suppress(OSError):
                sys.stdout = open(os.devnull, "w")  # noqa: SIM115 (silence the exit flush)
            return EXIT_FAILURE
        return _fail(EXIT_USAGE, _one_line(e), debug)
    except RuntimeError as e:
        # A solve that failed (e.g. hit max_steps) or a value rejected inside jit by
        # eqx.error_if: not a crash of ours, so no traceback, but not a success either.
        return _fail(EXIT_FAILURE, _solver_advice(_one_line(e), args), debug)
    except MemoryError:
        return _fail(EXIT_FAILURE, "out of memory; ask for fewer samples or a shorter run",
                     debug)
    except KeyboardInterrupt:
        print("crank-jax: interrupted", file=sys.stderr)
        return 128 + signal.SIGINT
    except Terminated as e:
        print(f"crank-jax: terminated by {signal.Signals(e.signum).name}", file=sys.stderr)
        return 128 + e.signum
    except Exception as e:  # any other class is a bug of ours: say so in one line
        return _fail(EXIT_FAILURE, _internal(e), debug)




def _quiet_runtime_logs() -> None:
    """Keep XLA's C++ log lines (and JAX's logger records) off a command's stderr.

    XLA logs through absl at its own level: a stored program that fails to parse, say,
    prints `E... wire_format_lite.cc:578] String field ... contains invalid UTF-8 data`
    although the command recovers (it recompiles) and succeeds. A command's stderr holds
    its own one-line messages only, and its failures reach the user as exceptions, so only
    fatal records are kept: JAX's `jax_logging_level` sets absl's minimum level at run
    time (`TF_CPP_MIN_LOG_LEVEL` is read only when jaxlib loads, which importing the
    package has done). A level the user set, `JAX_LOGGING_LEVEL` or a
    `TF_CPP_MIN_LOG_LEVEL` other than the "1" that `import jax` puts there by default,
    is kept, and so is every log under `--debug`.
    """
    if os.environ.get("JAX_LOGGING_LEVEL") or os.environ.get("TF_CPP_MIN_LOG_LEVEL",
                                                              "1") != "1":
        return
    import jax

    jax.config.update("jax_logging_level", "CRITICAL")


def entry() -> None:
    """The `crank-jax` program (console script and `python -m crank_jax`): [`main`][],
    then leave without the interpreter's teardown.

    Tearing down JAX's runtime and the imported modules takes a noticeable part of a warm
    fit (docs/benchmarks/design-figures.md, Start-up), and does nothing a finished command
    needs: every output is written
    atomically and closed before `main` returns, so only the standard streams are flushed.
    (`main` itself returns, for callers in a running interpreter.)

    Before JAX starts, it adds crank-jax's CPU flags to `XLA_FLAGS` (XLA's small-loop
    threshold, and 512-bit vectors on AVX-512 CPUs) and asks for one JAX CPU device per
    core (sweeps and batches spread over them), keeping what the user set: see
    `crank_jax.runtime.xla_flags.configure_cpu`; and it keeps the runtime's log lines off stderr
    (`_quiet_runtime_logs`). Only here: `main` may run inside a host program whose JAX is
    configured.
    """
    configure_cpu()
    if not _debug(sys.argv[1:]):
        _quiet_runtime_logs()
    code = main()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)
