"""`crank-jax validate`: predict a second record (open loop, or k steps ahead with
`--horizon`) and score the prediction."""

from __future__ import annotations

import argparse
import json
import math
import sys

from .channel_options import add_angle_options, add_channel_options, read_records
from .errors import UserError
from .load_by_option import add_load_by_option, load_by_words
from .wording import cli_message

__all__ = ["COMMANDS", "LOAD_INTERP"]

#: Interpolation kinds of sampled load columns: a cubic spline, straight lines, or a
#: zero-order hold (a digital controller's command).
LOAD_INTERP = ("cubic", "linear", "zoh")


def _validate_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="the fitted scene: preset name or TOML scene file")
    p.add_argument("data", help="the validation record, CSV (t,phi[,P][,tau])")
    p.add_argument("--t-start", type=float, help="start of the window to use, s (default: "
                   "the record's first sample; trim a start-up transient with it)")
    p.add_argument("--t-end", type=float, help="end of the window, s (default: the last sample)")
    p.add_argument("--init-window", type=float, metavar="S",
                   help="seconds at the window's start used to estimate the initial state "
                        "(default: one revolution at the record's mean speed for a crank "
                        "that turns, at least 30 samples; else about one linearized period; "
                        "at most half the record)")
    p.add_argument("--horizon", type=float, metavar="S",
                   help="predict S seconds ahead: after the initial-state window, cut the "
                        "record into windows of S s, estimate each window's state from its "
                        "first samples (max(5, a tenth of it)) and score the rest of it "
                        "(default: the whole record open loop). One revolution suits a "
                        "driven rig; a free decay is judged open loop")
    p.add_argument("--init-free", metavar="NAMES", default="",
                   help="comma-separated parameters estimated with the state on the "
                        "initial-state window and then held, e.g. tau0 (the record's own "
                        "drive level) or phi_offset")
    p.add_argument("--load-interp", metavar="KIND",
                   help=f"interpolation of the record's load columns: {', '.join(LOAD_INTERP)}")
    p.add_argument("--scene-loads", action="store_true",
                   help="the scene's loads serve where the record has no P/tau column: "
                        "the default, as in fit (kept for old command lines)")
    add_load_by_option(p)
    p.add_argument("--t-col", default="t", help="name of the time column (t)")
    add_angle_options(p)
    add_channel_options(p)
    p.add_argument("--out", required=True, help="write the scores as JSON to this file")
    p.add_argument("--plot", help="draw data, prediction and error to this PNG")
    p.add_argument("--predictions", metavar="CSV",
                   help="write every sample's time, measurement and prediction per channel "
                        "(SI units) to this CSV (also in --out's `predictions`)")
    p.add_argument("--report", metavar="HTML",
                   help="write a self-contained HTML report (scores, figures, provenance)")
    p.add_argument("--allow-unconverged", action="store_true",
                   help="validate a scene marked as the last iterate of a fit that did not "
                        "converge ([fit] converged = false, from fit --scene-out-anyway); "
                        "refused by default")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _check_numbers(a: argparse.Namespace) -> None:
    for flag, v in (("--t-start", a.t_start), ("--t-end", a.t_end)):
        if v is not None and not math.isfinite(v):
            raise UserError(f"{flag} must be a finite time, s, got {v}")
    if a.t_start is not None and a.t_end is not None and not a.t_start < a.t_end:
        raise UserError(f"--t-start ({a.t_start:g} s) must be below --t-end ({a.t_end:g} s)")
    if a.init_window is not None and not (math.isfinite(a.init_window) and a.init_window > 0):
        raise UserError(f"--init-window must be a time > 0 s, got {a.init_window}")
    if a.horizon is not None and not (math.isfinite(a.horizon) and a.horizon > 0):
        raise UserError(f"--horizon must be a time > 0 s, got {a.horizon}")
    _init_free(a)
    if a.load_interp is not None and a.load_interp not in LOAD_INTERP:
        raise UserError(f"--load-interp {a.load_interp!r} is unknown; choose from "
                        f"{', '.join(LOAD_INTERP)}")


def _init_free(a: argparse.Namespace) -> tuple[str, ...]:
    """The names of --init-free, each checked (before any record is read)."""
    from ..validation.kstep import init_free_names

    try:
        return init_free_names(tuple(x.strip() for x in a.init_free.split(",") if x.strip()))
    except ValueError as e:  # the library's words name the option as the CLI spells it
        raise UserError(cli_message(str(e))) from None


def _unconverged(a: argparse.Namespace) -> str | None:
    """Refuse a scene marked as the last iterate of a fit that did not converge (`[fit]
    converged = false`) unless --allow-unconverged; with it, the warning to give."""
    from ..identify.fitted import fit_mark

    mark = fit_mark(a.scene)
    if mark is None or mark["converged"]:
        return None
    why = mark.get("message") or "no reason given"
    if not a.allow_unconverged:
        raise UserError(f"{a.scene} is marked as the last iterate of a fit that did not "
                        f"converge ([fit] converged = false: {why}); fit again until it "
                        "converges, or pass --allow-unconverged to validate it anyway")
    return (f"{a.scene} is the last iterate of a fit that did not converge ({why}): its "
            "scores judge that iterate, not a fitted model")


def _read(a: argparse.Namespace, scene):
    return read_records(a, scene, [a.data])[0]  # as fit reads its records


def _validate_run(a: argparse.Namespace) -> int:
    from ..report.validation_plot import plot_validation
    from ..runtime.io import (
        atomic_write,
        check_distinct_outputs,
        check_figure_format,
        check_input,
        check_output,
    )
    from ..scene import load_scene
    from ..validation.kstep import validate

    _check_numbers(a)
    check_input(a.data, "DATA")  # at once: a FIFO with no writer would block the read
    # Every output checked before the record is read (not when writing, after the work).
    for path, option in ((a.out, "--out"), (a.plot, "--plot"), (a.predictions, "--predictions")):
        if path:
            check_output(path, [a.data, a.scene], option)
    if a.plot:
        check_figure_format(a.plot, "--plot")
    if a.report:
        check_output(a.report, [a.data, a.scene], "--report")
    check_distinct_outputs([(a.out, "--out"), (a.plot, "--plot"), (a.report, "--report"),
                            (a.predictions, "--predictions")])
    scene = load_scene(a.scene)
    unconverged = _unconverged(a)
    data = _read(a, scene)
    with load_by_words():
        val = validate(scene, data, t_start=a.t_start, t_end=a.t_end,
                       init_window=a.init_window, progress=not a.quiet, horizon=a.horizon,
                       init_free=_init_free(a), load_by=a.load_by)
    if unconverged:
        val.warnings.insert(0, unconverged)
    print(cli_message(val.summary()))
    for w in val.warnings:
        print(f"crank-jax: warning: {cli_message(w)}", file=sys.stderr)
    with atomic_write(a.out) as f:
        json.dump(val.to_json(), f, indent=2)
        f.write("\n")
    print(f"wrote {a.out}", file=sys.stderr)
    if a.predictions:
        from ..identify.predictions import write_predictions_csv

        write_predictions_csv(a.predictions, [val.predictions()])
        print(f"wrote {a.predictions}", file=sys.stderr)
    if a.plot:
        plot_validation(val, a.plot, title=f"{a.data} predicted by {a.scene}")
        print(f"wrote {a.plot}", file=sys.stderr)
    if a.report:
        val.report(a.report, scene=scene, command=getattr(a, "_argv", None),
                   title=f"{a.data} predicted by {a.scene}")
        print(f"wrote {a.report}", file=sys.stderr)
    return 0


#: Subcommands added to `crank-jax` (see `cli.main` for the tuple layout).
COMMANDS: list = [
    ("validate", "predict a record the model was not fitted to (initial state from its "
                 "start, the rest open-loop, or --horizon S seconds ahead) and report rms, "
                 "max error and fit percent",
     _validate_args, _validate_run),
]
