"""`crank-jax fit` and `crank-jax demo` (parameter identification); `crank-jax synth`, which
writes the records they fit, is `synth_command.py`."""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from .channel_options import (
    add_angle_options,
    add_channel_options,
    parse_sigma,
    read_records,
    read_sensors,
)
from .errors import UserError
from .load_by_option import add_load_by_option, load_by_words
from .options import free_list, seed
from .wording import cli_message


def _warn(msg: str) -> None:
    print(f"crank-jax: warning: {msg}", file=sys.stderr)


# --- fit --------------------------------------------------------------------------------

def _fit_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--free", default="k,c,phi0,dphi0",
                   help="comma-separated free parameters (default k,c,phi0,dphi0): mechanism "
                        "fields, P0, P1, tau0, tau1, phi0, dphi0")
    p.add_argument("--out", help="write the report as JSON to this file")
    p.add_argument("--plot", help="draw data vs fit, residuals and correlations to this PNG")
    p.add_argument("--predictions", metavar="CSV",
                   help="write every sample's time, measurement and the fitted model's "
                        "prediction per channel (SI units) to this CSV (also in --out's "
                        "`predictions`)")
    p.add_argument("--report", metavar="HTML",
                   help="write a self-contained HTML report (estimates, correlations, "
                        "figures, verdicts, provenance) to this file; with --each one "
                        "summary report of the records (in --out DIR when HTML names no "
                        "folder)")
    p.add_argument("--init", default="scene", choices=("scene", "regressor"),
                   help="start values: the scene's, or from the linear regressor form")
    p.add_argument("--method", default="lm", choices=("lm", "optax"),
                   help="lm: Levenberg-Marquardt (default); optax: Adam then L-BFGS")
    p.add_argument("--shooting", choices=("auto", "single", "multiple"),
                   help="auto (default; the demo: single): multiple shooting above 25 "
                        "linearized periods")
    p.add_argument("--segments", type=int, help="number of multiple-shooting segments")
    p.add_argument("--multistart", type=int, default=1, help="number of starts (1)")
    p.add_argument("--seed", type=seed, default=0, help="seed of the multistart (0)")
    p.add_argument("--max-steps", type=int, help="iteration budget per start")
    p.add_argument("--sigma", action="append", metavar="[NAME=]VALUE",
                   help="known noise std: VALUE for the first channel (rad for an angle), or "
                        "NAME=VALUE per channel in its SI unit (repeatable; default: "
                        "estimated from the record and the residuals)")
    p.add_argument("--profile", metavar="NAME", help="profile likelihood of one parameter")
    p.add_argument("--t-start", type=float, dest="fit_t_start",
                   help="fit only samples at or after this time, s (e.g. to trim a release "
                        "transient)")
    p.add_argument("--t-end", type=float, dest="fit_t_end",
                   help="fit only samples at or before this time, s")
    p.add_argument("--scene-out", metavar="FITTED.toml",
                   help="write the fitted mechanism and loads as a complete scene file "
                        "(the first record's; with --per-record, also STEM.recordI.toml "
                        "for each further record); not written for a fit that did not "
                        "converge, unless --scene-out-anyway")
    p.add_argument("--scene-out-anyway", action="store_true",
                   help="write --scene-out even for a fit that did not converge: its last "
                        "iterate, marked in the file ([fit] converged = false), which "
                        "validate refuses without --allow-unconverged")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _fit_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", nargs="?",
                   help="CSV record (t,phi[,P][,tau]); omit both DATA and SCENE to run the "
                        "built-in demo")
    p.add_argument("scene", nargs="?", help="preset name or TOML scene file")
    p.add_argument("records", nargs="*", metavar="...",
                   help="with --each: more records, then the scene (REC1 REC2 ... SCENE)")
    p.add_argument("--each", action="store_true",
                   help="fit each record by itself, side by side in one program; --out DIR "
                        "gets <record stem>.json per record and summary.csv")
    p.add_argument("--more-data", action="append", default=[], metavar="CSV",
                   help="another record of the same mechanism (repeatable): a multi-"
                        "experiment fit, each record with its own initial state and loads")
    p.add_argument("--t-col", default="t", help="name of the time column (t)")
    add_angle_options(p)
    p.add_argument("--load-interp", default="cubic", choices=("cubic", "linear", "zoh"),
                   help="interpolation of the record's P/tau columns: cubic (C2 spline, for "
                        "measured signals; default), linear, or zoh (a held digital command)")
    add_load_by_option(p)
    add_channel_options(p)
    p.add_argument("--per-record", default="", metavar="NAMES",
                   help="comma-separated free parameters that take a separate value in each "
                        "record (with --more-data), e.g. tau_gain or T_c; the rest are shared")
    _fit_options(p)


def _outputs_ok(a: argparse.Namespace, inputs: list) -> None:
    from ..runtime.io import check_distinct_outputs, check_figure_format, check_output

    outs = [(path, option) for path, option in (
        (a.out, "--out"), (a.plot, "--plot"), (getattr(a, "scene_out", None), "--scene-out"),
        (a.report, "--report"), (getattr(a, "predictions", None), "--predictions")) if path]
    outs += [(path, f"--scene-out's record {i} scene")
             for i, path in enumerate(_record_scenes(a)[1:], start=1)]
    for path, option in outs:
        check_output(path, inputs, option)
    if getattr(a, "scene_out_anyway", False) and not getattr(a, "scene_out", None):
        raise UserError("--scene-out-anyway needs --scene-out FITTED.toml (the file to write)")
    if a.plot:
        check_figure_format(a.plot, "--plot")
    # Every output its own file (./fit.json is fit.json, a link its target), so none is
    # written over another, whatever order they are written in.
    check_distinct_outputs(outs)


#: Where a fit message's advice has a form of its own on the command line.
_START_VALUES = re.compile(r"choose other start values\b(?! \()")


def cli_words(text: str) -> str:
    """A fit message with the library's argument names replaced by the command's options
    (`cli_message`), and its "choose other start values" saying where the command takes
    them."""
    return _START_VALUES.sub("choose other start values (in the scene file, or --init "
                             "regressor)", cli_message(text))


def _in_cli_words(res):
    return res._replace(message=cli_words(res.message),
                        warnings=[cli_words(w) for w in res.warnings])


def _write_json(res, path) -> None:
    """A fit's `fit.json` (the CLI's words in its messages), written atomically."""
    from ..runtime.io import atomic_write

    text = json.dumps(_in_cli_words(res).to_json(), indent=2)  # one write, not one a token
    with atomic_write(path) as f:
        f.write(text + "\n")


def _report(res, a: argparse.Namespace, truth: dict | None = None, title: str = "") -> int:
    res = _in_cli_words(res)
    print(cli_words(res.summary()))  # its termination's words too
    if truth:
        print("truth: " + ", ".join(f"{k} = {v:g}" for k, v in truth.items()))
    if res.profile is not None:
        lo, hi = res.profile.ci95
        print(f"profile-likelihood 95% interval of {res.profile.name}: "
              f"[{'-' if lo is None else f'{lo:.6g}'}, {'-' if hi is None else f'{hi:.6g}'}]")
    for w in res.warnings:
        _warn(w)
    if a.out:
        _write_json(res, a.out)
        print(f"wrote {a.out}", file=sys.stderr)
    if getattr(a, "predictions", None):
        from ..identify.predictions import write_predictions_csv

        write_predictions_csv(a.predictions, res.predictions())
        print(f"wrote {a.predictions}", file=sys.stderr)
    if a.plot:
        from ..report.fit_plot import plot_fit

        plot_fit(res, a.plot, title)
        print(f"wrote {a.plot}", file=sys.stderr)
    if a.report:
        res.report(a.report, scene=a.fitted_scene, command=getattr(a, "_argv", None),
                   title=title)
        print(f"wrote {a.report}", file=sys.stderr)
    withheld = bool(getattr(a, "scene_out", None)) and not (
        res.converged or getattr(a, "scene_out_anyway", False))
    if getattr(a, "scene_out", None) and not withheld:
        _write_scene(res, a)
        print(f"wrote {a.scene_out}" + ("" if res.converged else " (marked NOT converged: "
                                        "the last iterate)"), file=sys.stderr)
    if (res.termination or {}).get("verdict") == "refused":
        # Nothing was fitted: the records cannot tell (a constant channel, no motion above
        # the noise, an absurd start). That is the input's to fix, as any bad input: exit
        # 2, after the outputs asked for are written (they hold the verdict and why).
        raise UserError(f"nothing was fitted: {res.message}")
    if withheld:
        # The last iterate of a fit that did not converge is no fitted scene: the output
        # asked for is not there, so the run did not finish what it was asked.
        raise RuntimeError(f"--scene-out {a.scene_out} not written: the fit did not "
                           "converge, so there is no fitted scene; fix the fit, or pass "
                           "--scene-out-anyway for its last iterate, marked unconverged")
    # Not identifiable or not converged is a result, reported in full: exit 0.
    return 0


#: What a scene needs for a load parameter of each role to be free (`--free`).
_LOAD_FIX = {
    "mean": "give the scene a constant or harmonic {side} ([{side}] kind = \"constant\")",
    "amp": "give the scene a harmonic {side} ([{side}] kind = \"harmonic\")",
    "gain": ("drive the scene's {side} by a record column ([{side}] input = \"COLUMN\", "
             "gain = ...) and fit a record that has that column"),
}


def _check_free(free: tuple[str, ...], a: argparse.Namespace, scene, n_records: int) -> None:
    """Check --free and --profile against the names a fit knows and the scene's loads,
    before any record is read (a long record takes seconds to read)."""
    from ..identify.request import LOAD_NAMES, free_names, load_param, reported_names

    unknown = [n for n in free if n not in free_names()]
    if unknown:
        raise UserError(f"--free: unknown free parameter(s) {', '.join(unknown)}; choose from "
                        f"{', '.join(free_names())}")
    for n in free:
        if n in LOAD_NAMES:
            side, role = LOAD_NAMES[n]
            if load_param(getattr(scene, "load" if side == "load" else "torque"), role) is None:
                raise UserError(f"--free: {n} cannot be free: the scene's {side} has no {n}; "
                                f"{_LOAD_FIX[role].format(side=side)}")
    per_record = tuple(n for n in _per_record(a) if n in free) if n_records > 1 else ()
    names = reported_names(tuple(dict.fromkeys(free)), n_records, per_record)
    if a.profile is not None and a.profile not in names:
        raise UserError(f"--profile {a.profile!r} is not a free parameter; choose from "
                        f"{', '.join(names)}")


def _per_record(a: argparse.Namespace) -> tuple[str, ...]:
    """The names of `--per-record` (none for the demo, which has no such option)."""
    return tuple(dict.fromkeys(x.strip() for x in getattr(a, "per_record", "").split(",")
                               if x.strip()))


def _fit_kwargs(a: argparse.Namespace, scene=None, n_records: int = 1) -> dict:
    """The keyword arguments of `fit` from the options, every one checked (with `scene`,
    the free names against it too)."""
    from ..identify.fit_options import MAX_ITERATIONS

    free = free_list(a.free)
    if scene is not None:
        _check_free(free, a, scene, n_records)
    shooting = a.shooting or "auto"
    if shooting == "single" and a.segments is not None and a.segments > 1:
        raise UserError(f"--segments {a.segments} needs --shooting multiple or auto")
    if a.multistart < 1:
        raise UserError(f"--multistart must be >= 1, got {a.multistart}")
    if a.segments is not None and a.segments < 1:
        raise UserError(f"--segments must be >= 1, got {a.segments}")
    if a.max_steps is not None and not 1 <= a.max_steps <= MAX_ITERATIONS:
        raise UserError(f"--max-steps must be an integer from 1 to {MAX_ITERATIONS}, got "
                        f"{a.max_steps}")
    sigma = parse_sigma(a.sigma)
    per_record = _per_record(a)
    bad = [n for n in per_record if n not in free]
    if bad:
        raise UserError(f"--per-record names {', '.join(bad)}, which is not free; add it to "
                        "--free or leave it out of --per-record")
    if per_record and n_records < 2:
        raise UserError(f"--per-record {','.join(per_record)} needs several records "
                        "(--more-data): with one record every free parameter is already its "
                        "own; leave --per-record out")
    lo, hi = getattr(a, "fit_t_start", None), getattr(a, "fit_t_end", None)
    if lo is not None and hi is not None and not lo < hi:
        raise UserError(f"--t-start ({lo:g}) must be before --t-end ({hi:g})")
    window = None if lo is None and hi is None else (lo, hi)
    return dict(free=free, init=a.init, method=a.method, shooting=shooting,
                segments=a.segments, multistart=a.multistart, seed=a.seed,
                max_steps=a.max_steps, sigma=sigma, profile=a.profile, window=window,
                progress=not a.quiet, warn=False, per_record=per_record,
                load_by=getattr(a, "load_by", "time"))


def _fit_run(a: argparse.Namespace) -> int:
    records = getattr(a, "records", [])
    if getattr(a, "each", False):
        from .fit_each import fit_each

        files = [x for x in (a.data, a.scene, *records) if x is not None]
        if len(files) < 2:
            raise UserError("--each needs records and a scene: REC1.csv [REC2.csv ...] SCENE")
        a.scene = files[-1]
        return fit_each(a, files[:-1], _write_json, _fit_kwargs)
    if records:
        raise UserError(f"fit takes one DATA and one SCENE, got {2 + len(records)} paths; "
                        "--each fits each record by itself, --more-data fits them jointly")
    if a.data is None and a.scene is None:
        if a.more_data:
            raise UserError("--more-data needs DATA and SCENE")
        return _demo(a)
    if a.scene is None:
        raise UserError("give both DATA and SCENE (or neither, for the built-in demo)")
    from ..identify.fit import fit
    from ..runtime.io import check_input
    from ..scene import load_scene

    files = [a.data] + list(a.more_data)
    scene = load_scene(a.scene)
    kwargs = _fit_kwargs(a, scene, len(files))  # every option before any record is read
    for path, option in zip(files, ["DATA"] + ["--more-data"] * len(a.more_data)):
        check_input(path, option)  # unopened: a FIFO with no writer would block the read
    _outputs_ok(a, files + [a.scene])
    records = read_records(a, scene, files)
    # What each record was read through: its fitted scene (--scene-out) keeps it.
    a.record_sensors = [read_sensors(a, scene, f) for f in files]
    with load_by_words():
        res = fit(scene, records if len(records) > 1 else records[0], **kwargs)
    a.fitted_scene = scene
    return _report(res, a, title=f"{', '.join(files)} with {a.scene}")


def _record_scenes(a: argparse.Namespace) -> list[str]:
    """The fitted scene files: `--scene-out` (the first record's), and with `--per-record`
    and `--more-data` one more per further record, `STEM.recordI.toml` beside it."""
    out = getattr(a, "scene_out", None)
    if not out:
        return []
    n = 1 + len(getattr(a, "more_data", None) or [])
    if n == 1 or not getattr(a, "per_record", "").strip():
        return [out]
    p = Path(out)
    return [out] + [str(p.with_name(f"{p.stem}.record{i}{p.suffix or '.toml'}"))
                    for i in range(1, n)]


def _write_scene(res, a: argparse.Namespace) -> None:
    """The fitted mechanism (and fitted load amplitudes) as a complete scene file, with the
    first record's fitted initial state and per-record values; with `--per-record`, one
    scene per record (see `_record_scenes`), each a scene `synth`, `fit` and `validate`
    take. Written atomically, never over an input; the last iterate of a fit that did not
    converge only with --scene-out-anyway, marked in the file."""
    from ..identify.fitted import save_fitted_scene

    paths = _record_scenes(a)
    for i, path in enumerate(paths):
        read = getattr(a, "record_sensors", None)  # what record i was read through
        save_fitted_scene(a.fitted_scene, res, path, record=i,
                          sensors=read[i] if read else None,
                          anyway=getattr(a, "scene_out_anyway", False))
        if i:
            print(f"wrote {path} (record {i}'s fitted scene)", file=sys.stderr)


# --- demo -------------------------------------------------------------------------------

def _demo_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--noise-seed", type=seed, default=1,
                   help="seed of the synthetic noise (1)")
    _fit_options(p)


def _demo(a: argparse.Namespace) -> int:
    from ..identify.demo import DEMO, demo_record
    from ..identify.fit import fit

    _outputs_ok(a, [])
    if getattr(a, "data", None) is not None or getattr(a, "more_data", None):
        raise UserError("the demo takes no data")
    seed = getattr(a, "noise_seed", 1)
    if a.shooting is None and not (a.segments or 0) > 1:
        a.shooting = DEMO["shooting"]  # the demo's own choice (see DEMO), not a warning
    kw = _fit_kwargs(a)  # every option before the record is synthesised
    scene, data = demo_record(seed)
    _check_free(kw["free"], a, scene, 1)
    truth_mech = scene.mech.as_dict()
    print(f"demo: {scene.description}; tau(t) = {DEMO['tau1']} sin(2 pi {DEMO['freq_hz']} t) "
          f"N*m; {DEMO['t1']:g} s at {DEMO['rate']:g} Hz with {DEMO['noise_std']:g} rad noise "
          f"(seed {seed})", file=sys.stderr)
    if a.init == "scene":
        start = {k: v for k, v in DEMO["start"].items() if k in kw["free"]}
        kw["init"] = start
    res = fit(scene, data, **kw)
    a.fitted_scene = scene
    truth = {n: truth_mech[n] for n in res.names if n in truth_mech}
    truth.update({n: v for n, v in (("phi0", DEMO["phi0"]), ("dphi0", 0.0)) if n in res.names})
    return _report(res, a, truth, title="demo: lab rig with a known harmonic torque")


#: Subcommands added to `crank-jax` (see `cli.COMMANDS` for the tuple layout).
COMMANDS: list = [
    ("fit", "fit parameters to a record, with uncertainty and identifiability (no arguments: "
            "the built-in demo)", _fit_args, _fit_run),
    ("demo", "synthesize lab-rig data under a known torque, fit k, c, phi0, dphi0 and print "
             "the estimates with 95%% intervals", _demo_args, _demo),
]
