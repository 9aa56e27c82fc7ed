"""`crank-jax track`: follow a running machine's parameters through a record, with bands
and change alarms."""

from __future__ import annotations

import argparse
import json
import sys

from .channel_options import add_angle_options, add_channel_options, read_records
from .errors import UserError
from .load_by_option import add_load_by_option, load_by_words
from .wording import cli_message

__all__ = ["COMMANDS"]


def _track_args(p: argparse.ArgumentParser) -> None:
    from ..online.tracking import STARTS

    p.add_argument("data", help="the record, CSV (t and its channels, measured P/tau columns)")
    p.add_argument("scene", help="the scene: preset name or TOML scene file (its values are "
                                 "the fixed ones, and the start with --start scene)")
    p.add_argument("--free", required=True, metavar="NAMES",
                   help="comma-separated mechanism fields to follow, e.g. k,c")
    p.add_argument("--start", choices=STARTS, default="batch",
                   help="start from a batch fit of the record's first seconds (default) or "
                        "from the scene's values")
    p.add_argument("--start-seconds", type=float, default=5.0, metavar="S",
                   help="seconds of the batch fit that starts the filter (5)")
    p.add_argument("--false-alarm-rate", type=float, default=1.0, metavar="PER_HOUR",
                   help="alarms per hour of record allowed on a machine that does not "
                        "change (an upper bound; default 1)")
    p.add_argument("--change-ratio", type=float, default=4.0, metavar="R",
                   help="the growth of the innovations' variance the change test looks for (4)")
    p.add_argument("--settle", type=float, default=5.0, metavar="S",
                   help="seconds after an alarm at which the new values are read (5)")
    p.add_argument("--every", type=int, default=1, metavar="N",
                   help="keep every N-th sample in track.json (a long record; default 1)")
    p.add_argument("--t-col", default="t", help="name of the time column (t)")
    add_load_by_option(p)
    add_angle_options(p)
    add_channel_options(p)
    p.add_argument("--out", required=True, help="write the paths and alarms as JSON here")
    p.add_argument("--report", metavar="HTML",
                   help="write a self-contained HTML report (paths with bands, innovations, "
                        "alarms)")
    p.add_argument("--quiet", action="store_true", help="no progress")


def _free(a: argparse.Namespace) -> tuple[str, ...]:
    return tuple(x.strip() for x in a.free.split(",") if x.strip())


def _track_run(a: argparse.Namespace) -> int:
    from ..online.tracking import track
    from ..runtime.io import atomic_write, check_distinct_outputs, check_input, check_output
    from ..scene import load_scene

    free = _free(a)
    check_input(a.data, "DATA")
    check_output(a.out, [a.data, a.scene], "--out")
    if a.report:
        check_output(a.report, [a.data, a.scene], "--report")
    check_distinct_outputs([(a.out, "--out"), (a.report, "--report")])
    scene = load_scene(a.scene)
    data = read_records(a, scene, [a.data])[0]
    try:
        with load_by_words():
            res = track(scene, data, free=free, start=a.start,
                        start_seconds=a.start_seconds, false_alarm_rate=a.false_alarm_rate,
                        change_ratio=a.change_ratio, settle=a.settle, every=a.every,
                        load_by=a.load_by, progress=not a.quiet)
    except ValueError as e:  # its checks (before any work) are the command's: its words
        raise UserError(cli_message(str(e))) from None
    print(cli_message(res.summary()))
    with atomic_write(a.out) as f:
        json.dump(res.to_json(), f, indent=1)
        f.write("\n")
    print(f"wrote {a.out}", file=sys.stderr)
    if a.report:
        from ..report import write_track_report

        write_track_report(res, a.report, scene=scene, command=getattr(a, "_argv", None),
                           title=f"{a.data} tracked with {a.scene}")
        print(f"wrote {a.report}", file=sys.stderr)
    return 0


#: Subcommands added to `crank-jax` (see `cli.main` for the tuple layout).
COMMANDS: list = [
    ("track", "follow the free parameters through a record sample by sample (an extended "
              "Kalman filter), with 95%% bands and change alarms",
     _track_args, _track_run),
]
