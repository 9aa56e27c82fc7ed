"""`crank-jax fit REC1.csv REC2.csv ... SCENE --each --out DIR`: each record fitted by
itself, side by side ([`fit_many`][crank_jax.fleet.many.fit_many]); DIR gets
`<record stem>.json` per record (a single fit's `fit.json`) and `summary.csv`, and with
`--report HTML` one summary report (in DIR where HTML names no folder)."""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

from .errors import UserError

__all__ = ["fit_each", "SUMMARY"]

#: The summary table's file name in `--out DIR`.
SUMMARY = "summary.csv"

#: Options of `fit` that a fit of each record by itself does not take, and their defaults.
_NOT_EACH = (("more_data", [], "--more-data"), ("plot", None, "--plot"),
             ("predictions", None, "--predictions"),
             ("scene_out", None, "--scene-out"), ("profile", None, "--profile"),
             ("multistart", 1, "--multistart"), ("per_record", "", "--per-record"),
             ("method", "lm", "--method"), ("shooting", None, "--shooting"),
             ("segments", None, "--segments"))


def report_path(a: argparse.Namespace) -> Path | None:
    """Where `--report` goes with `--each`: in `--out DIR` when it names no folder."""
    if not a.report:
        return None
    p = Path(a.report)
    return Path(a.out) / p if p.parent == Path(".") else p


def _outputs(a: argparse.Namespace, files: list[str]) -> tuple[Path, dict[str, Path]]:
    """The output directory and each record's JSON file, checked before any work: one
    stem per record, DIR not a file, no output over an input (nor the report over one)."""
    from ..runtime.io import check_output

    if not a.out:
        raise UserError("--each needs --out DIR (the directory of the records' results)")
    out = Path(a.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {a.out!r} is a file; with --each name a directory")
    stems: dict[str, str] = {}
    for f in files:
        stem = Path(f).stem
        if stem in stems:
            raise UserError(f"--each: records {stems[stem]} and {f} would both write "
                            f"{stem}.json in {a.out}; rename one")
        stems[stem] = f
    out.mkdir(parents=True, exist_ok=True)
    paths = {f: out / f"{Path(f).stem}.json" for f in files}
    report = report_path(a)
    if report is not None and (report.suffix.lower() == ".json" or report.name == SUMMARY):
        raise UserError(f"--report {a.report!r} would clash with the results in {a.out}; "
                        "name an .html file")
    try:
        for p in [*paths.values(), out / SUMMARY] + ([report] if report else []):
            check_output(p, files + [a.scene], "--out")
    except ValueError as e:
        raise UserError(str(e)) from None
    return out, paths


def _check_options(a: argparse.Namespace) -> None:
    for attr, default, option in _NOT_EACH:
        if getattr(a, attr, default) not in (default, None) or (
                attr == "shooting" and a.shooting not in (None, "auto")):
            raise UserError(f"{option} is not taken with --each (each record is fitted by "
                            "itself); leave it out, or fit that record alone")


def fit_each(a: argparse.Namespace, files: list[str], write_json, fit_kwargs) -> int:
    """Run `fit --each`: `files` the records, `a.scene` the scene; `write_json(res, path)`
    writes a record's `fit.json`, `fit_kwargs(a, scene, n_records)` gives `fit`'s options
    (the fit command's own). Exit 0 when every record was fitted (a fit that did not
    converge is a result, as for one record); a record refused before any fit (no motion,
    an absurd start) is the input's to fix: exit 2, after every output is written."""
    from ..fleet import fit_many
    from ..runtime.io import atomic_write, check_input
    from ..scene import load_scene
    from .channel_options import read_records
    from .load_by_option import load_by_words

    _check_options(a)
    scene = load_scene(a.scene)
    kw = fit_kwargs(a, scene, 1)
    for path in files:
        check_input(path, "DATA")
    out, paths = _outputs(a, files)
    records = read_records(a, scene, files)
    keep = ("free", "init", "max_steps", "sigma", "window", "progress", "load_by")
    with load_by_words():
        fleet = fit_many(scene, records, warn=False, **{k: kw[k] for k in keep})
    for f, res in zip(files, fleet):
        write_json(res, paths[f])
    rows = fleet.rows([Path(f).name for f in files])
    names = list(dict.fromkeys(k for row in rows for k in row))
    with atomic_write(out / SUMMARY) as fh:
        w = csv.DictWriter(fh, fieldnames=names, lineterminator="\n")
        w.writeheader()
        w.writerows({k: "" if v is None else v for k, v in row.items()} for row in rows)
    if a.report:
        from ..report import write_fleet_report

        write_fleet_report(fleet, report_path(a), labels=files, scene=scene)
    alone = sum(x is not None for x in fleet.alone)
    ok = sum(r.converged for r in fleet)
    print(f"fitted {len(files)} records ({len(files) - alone} side by side, {alone} by "
          f"themselves), {ok} converged, in {fleet.seconds:.1f} s; wrote {len(files)} JSON "
          f"files and {SUMMARY} in {out}" + (f"; the report {report_path(a)}" if a.report
                                               else ""), file=sys.stderr)
    refused = [f for f, res in zip(files, fleet)
               if (res.termination or {}).get("verdict") == "refused"]
    if refused:
        # As for one record: nothing fitted is the input's to fix (exit 2), after the
        # outputs are written (they say why).
        raise UserError(f"nothing was fitted for {', '.join(refused)}: see their JSON files")
    return 0
