"""`crank-jax backbone`, `response` and `stability`: the nonlinear-vibration commands
(crank_jax.vibration). Each writes one JSON file atomically, and `--plot` a figure."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from .errors import RunFailed, UserError

__all__ = ["COMMANDS"]

#: The most backbone amplitudes, continuation points and chart grid side a command takes.
MAX_AMPLITUDES = 10_000
MAX_POINTS = 100_000


def _range(text: str, option: str, with_n: bool, lo_ok_zero: bool = False):
    """`A0:A1` or, with `with_n`, `A0:A1[:N]` -> (a0, a1, n or None)."""
    parts = text.split(":")
    if len(parts) not in ((2, 3) if with_n else (2,)):
        form = "A0:A1[:N]" if with_n else "A0:A1"
        raise UserError(f"{option} {text!r} must be {form}, e.g. {option} "
                        f"{'0.01:1.0:20' if with_n else '3:5.5'}")
    try:
        a0, a1 = float(parts[0]), float(parts[1])
        n = int(parts[2]) if len(parts) == 3 else None
    except ValueError:
        raise UserError(f"{option} {text!r}: numbers expected, e.g. "
                        f"{option} {'0.01:1.0:20' if with_n else '3:5.5'}") from None
    if not (math.isfinite(a0) and math.isfinite(a1)) or not (
            (a0 >= 0 if lo_ok_zero else a0 > 0) and a1 > a0):
        low = ">= 0" if lo_ok_zero else "> 0"
        raise UserError(f"{option} {text!r}: need {low} start below the end")
    if n is not None and not 1 <= n <= MAX_AMPLITUDES:
        raise UserError(f"{option} {text!r}: N must be from 1 to {MAX_AMPLITUDES}")
    return a0, a1, n


def _outputs(a, *inputs) -> None:
    from ..runtime.io import check_distinct_outputs, check_figure_format, check_output

    try:
        check_output(a.out, inputs, "--out")
        if getattr(a, "plot", None):
            check_output(a.plot, inputs, "--plot")
            check_figure_format(a.plot, "--plot")
            check_distinct_outputs([(a.out, "--out"), (a.plot, "--plot")])
    except ValueError as e:
        raise UserError(str(e)) from None


def _write(path: str, doc: dict) -> None:
    from ..runtime.io import atomic_write

    with atomic_write(path) as f:
        json.dump(doc, f, indent=1, allow_nan=False)
        f.write("\n")


def _clean(x):
    """NaN -> None (JSON has no NaN), recursively."""
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _load(source: str):
    from ..scene import load_scene

    return load_scene(source)


# --- backbone ---------------------------------------------------------------------------

def _backbone_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="preset name or TOML scene file (its mechanism is used; "
                   "damping, friction and loads are left out)")
    p.add_argument("--amplitudes", required=True, metavar="A0:A1[:N]",
                   help="swing amplitudes (phi_max - phi_min)/2, rad: N (default 20) "
                   "evenly spaced from A0 > 0 to A1")
    p.add_argument("--out", required=True, help="JSON file to write")


def _backbone_run(a: argparse.Namespace) -> int:
    a0, a1, n = _range(a.amplitudes, "--amplitudes", with_n=True)
    _outputs(a, a.scene)
    scene = _load(a.scene)
    from ..vibration.backbone import backbone

    bb = backbone(scene.mech, np.linspace(a0, a1, n or 20))
    ok = np.asarray(bb.ok)
    doc = {"scene": scene.name, "linear_frequency_hz": float(bb.linear_frequency_hz),
           "points": [{"amplitude": float(bb.amplitude[i]), "phi_max": float(bb.phi_max[i]),
                       "phi_min": float(bb.phi_min[i]),
                       "frequency_hz": float(bb.frequency_hz[i]),
                       "period": float(bb.period[i])} for i in np.flatnonzero(ok)]}
    partial = None
    if not ok.all():
        partial = _backbone_stop(scene.mech, float(bb.amplitude[int(np.argmin(ok))]), doc)
    if not ok.any():
        raise RunFailed(f"no backbone point was found: {doc['stopped']}; nothing written")
    _write(a.out, _clean(doc))
    print(f"wrote {int(ok.sum())} backbone points to {a.out} (linear frequency "
          f"{doc['linear_frequency_hz']:.6g} Hz)")
    if partial:  # written, but short of what was asked where swings exist
        raise RunFailed(f"partial: {doc['stopped']}")
    return 0


def _backbone_stop(mech, first: float, doc: dict) -> bool:
    """Say in `doc["stopped"]` why no swing of amplitude `first` (rad) or more was found;
    True if it is a failure (swings that large exist) rather than the physics."""
    from ..vibration.backbone import conservative
    from ..vibration.rest import largest_swing, stable_rest

    mech = conservative(mech)
    top = largest_swing(mech, stable_rest(mech)[0])
    doc["largest_swing"] = top
    if first >= top:
        doc["stopped"] = (f"no swing of amplitude {first:g} rad or more exists: beyond "
                          f"{top:.6g} rad the crank goes over the top and rotates")
        print(f"note: {doc['stopped']}")
        return False
    doc["stopped"] = (f"no swing of amplitude {first:g} rad or more was found, although "
                      f"swings up to {top:.6g} rad exist: the solve failed there; ask for "
                      "more closely spaced amplitudes")
    return True


# --- response ---------------------------------------------------------------------------

def _response_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="preset name or TOML scene file with a harmonic [torque] "
                   "(tau1) or [load] (P1): the drive, whose frequency is continued")
    p.add_argument("--freq", required=True, metavar="F0:F1", help="frequency range, Hz")
    p.add_argument("--out", required=True, help="JSON file to write")
    p.add_argument("--plot", help="figure to write (PNG, SVG, PDF...)")
    p.add_argument("--max-points", type=int, default=400,
                   help="most orbits on the curve (default 400)")


def _response_run(a: argparse.Namespace) -> int:
    f0, f1, _ = _range(a.freq, "--freq", with_n=False)
    if not 2 <= a.max_points <= MAX_POINTS:
        raise UserError(f"--max-points must be from 2 to {MAX_POINTS}, got {a.max_points}")
    _outputs(a, a.scene)
    scene = _load(a.scene)
    from ..vibration import forced_response

    resp = forced_response(scene, (f0, f1), max_points=a.max_points,
                           backbone_points=30 if a.plot else 0)
    _write(a.out, _clean(resp.to_dict()))
    if a.plot:
        from ..vibration.plots import plot_response

        plot_response(resp, a.plot, title=f"{scene.name}: forced response")
    n = sum(len(b.freq_hz) for b in resp.branches)
    print(f"wrote {n} orbits, {len(resp.folds)} folds to {a.out} ({resp.stopped})")
    if not resp.complete:  # written (marked "complete": false), but not a finished run
        raise RunFailed(f"{resp.stopped}; {a.out} holds the partial curve")
    return 0


# --- stability --------------------------------------------------------------------------

def _stability_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="preset name or TOML scene file (no offset, no crank "
                   "torque); its mean slider force P0 is kept")
    p.add_argument("--load-amplitude", required=True, metavar="P1_LO:P1_HI",
                   help="slider-force amplitudes P1, N")
    p.add_argument("--freq", required=True, metavar="F0:F1", help="frequencies, Hz")
    p.add_argument("--grid", type=int, default=40, help="points on each axis (default 40)")
    p.add_argument("--out", required=True, help="JSON file to write")
    p.add_argument("--plot", help="figure to write (PNG, SVG, PDF...)")


def _stability_run(a: argparse.Namespace) -> int:
    from ..vibration.chart import MAX_GRID

    p0, p1, _ = _range(a.load_amplitude, "--load-amplitude", with_n=False, lo_ok_zero=True)
    f0, f1, _ = _range(a.freq, "--freq", with_n=False)
    if not 2 <= a.grid <= MAX_GRID:
        raise UserError(f"--grid must be from 2 to {MAX_GRID}, got {a.grid}")
    _outputs(a, a.scene)
    scene = _load(a.scene)
    from ..vibration import stability_chart

    chart = stability_chart(scene, (p0, p1), (f0, f1), grid=a.grid)
    _write(a.out, _clean(chart.to_dict()))
    if a.plot:
        from ..vibration.plots import plot_chart

        plot_chart(chart, a.plot, title=f"{scene.name}: stability of the rest position")
    ok = np.asarray(chart.ok)
    rest = "" if chart.rest == 0 else f", about the rest at phi = {chart.rest:.6g} rad"
    print(f"wrote a {a.grid} x {a.grid} chart to {a.out} ("
          f"{100 * float(np.mean(chart.unstable)):.0f}% unstable, "
          f"{100 * float(np.mean(np.asarray(chart.stable))):.0f}% stable{rest})")
    if not ok.all():  # written (null multipliers, "ok": false), but not a finished run
        bad = np.argwhere(~ok)[0]
        raise RunFailed(f"partial: {int((~ok).sum())} of {ok.size} points failed (their "
                        f"monodromy solve did not finish; the first at P1 = "
                        f"{chart.amplitude[bad[0]]:g} N, {chart.freq_hz[bad[1]]:g} Hz): "
                        "they are neither stable nor unstable (each is a solve over one "
                        "forcing period: a low frequency or a tight rtol needs more steps)")
    return 0


#: (name, help, add_arguments, run) for every subcommand.
COMMANDS = [
    ("backbone", "backbone curve: free-swing frequency against amplitude", _backbone_args,
     _backbone_run),
    ("response", "forced response curve by continuation, with Floquet stability",
     _response_args, _response_run),
    ("stability", "parametric-resonance chart of the rest position under a harmonic "
     "slider force", _stability_args, _stability_run),
]
