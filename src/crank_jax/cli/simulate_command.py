"""`crank-jax simulate`, `linearize` and `scenes`: the model's command group."""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

from ..runtime.progress import progress_bar
from ..solve.names import SOLVERS
from .errors import UserError
from .scene_inputs import refuse_input_loads

__all__ = ["COMMANDS"]


def _scene_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="preset name (see `crank-jax scenes`) or a TOML scene file")


def _load(source: str):
    from ..scene import load_scene

    return load_scene(source)


# --- simulate ---------------------------------------------------------------------------

#: Samples simulated, checked and written per chunk: memory stays near
#: `CHUNK_SAMPLES * columns * 8` bytes (plus the solver's fixed overhead) for any --samples.
CHUNK_SAMPLES = 65536
#: The most samples `simulate` writes (1e9 rows of t,phi,dphi are about 60 GB of CSV).
MAX_SAMPLES = 10**9
#: Typical bytes one value takes in the CSV (`%.17g` and a separator), for the disk check.
CSV_BYTES_PER_VALUE = 20
#: Most points drawn by --plot: longer runs are decimated evenly.
PLOT_POINTS = 20001
#: `simulate --max-steps`: the default (the library's) and the largest budget (an int32
#: step counter).
DEFAULT_MAX_STEPS = 200_000
MAX_STEPS = 2**31 - 1


def _simulate_args(p: argparse.ArgumentParser) -> None:
    _scene_args(p)
    p.add_argument("--t1", type=float, help="end time, s (default: the scene's, else 10)")
    p.add_argument("--samples", type=int,
                   help=f"number of uniform samples on [0, t1] (2 to {MAX_SAMPLES:.0e}; runs "
                        f"longer than {CHUNK_SAMPLES} are streamed in chunks with progress)")
    p.add_argument("--phi0", type=float, help="initial crank angle, rad")
    p.add_argument("--dphi0", type=float, help="initial crank rate, rad/s")
    p.add_argument("--solver", help=f"one of {', '.join(SOLVERS)} (default: the scene's)")
    p.add_argument("--rtol", type=float, help="relative tolerance (at most 1e-2)")
    p.add_argument("--atol", type=float, help="absolute tolerance, rad and rad/s (at most 1e-3)")
    p.add_argument("--max-steps", type=int, metavar="N",
                   help=f"solver step budget per chunk of {CHUNK_SAMPLES} samples "
                        f"({DEFAULT_MAX_STEPS}; 1 to {MAX_STEPS})")
    p.add_argument("--extras", help="comma-separated derived outputs to add as columns "
                   "(ddphi, delta, slider, energy, loads, reactions); default: the scene's")
    p.add_argument("--out", required=True, help="output CSV file (t,phi,dphi,...)")
    p.add_argument("--plot", help="also draw phi(t) and dphi(t) to this image file (.png, "
                   ".pdf, .svg, ...)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _check_options(a: argparse.Namespace) -> dict:
    """Check every option that needs no scene, before any work; return simulate's kwargs."""
    from ..runtime.io import check_distinct_outputs, check_figure_format, check_output
    from ..solve.inputs import MAX_ATOL, MAX_RTOL, MIN_RTOL
    from ..solve.trajectory import output_columns

    if a.t1 is not None and not (np.isfinite(a.t1) and a.t1 > 0):
        raise UserError(f"--t1 must be a finite time > 0 s, got {a.t1}")
    if a.samples is not None and not 2 <= a.samples <= MAX_SAMPLES:
        raise UserError(f"--samples must be >= 2 and <= {MAX_SAMPLES}, got {a.samples}")
    if a.solver is not None and a.solver not in SOLVERS:
        raise UserError(f"--solver {a.solver!r} is unknown; choose from {', '.join(SOLVERS)}")
    for name in ("rtol", "atol"):
        v = getattr(a, name)
        if v is not None and not (np.isfinite(v) and v > 0):
            raise UserError(f"--{name} must be a positive number, got {v}")
    if a.rtol is not None and a.rtol > MAX_RTOL:
        raise UserError(f"--rtol must be at most {MAX_RTOL:g}, got {a.rtol:g}: a looser "
                        "tolerance no longer bounds the solver's error")
    if a.rtol is not None and a.rtol < MIN_RTOL:
        raise UserError(f"--rtol must be at least {MIN_RTOL:g}, got {a.rtol:g}: float64 "
                        "cannot resolve a tighter one")
    if a.atol is not None and a.atol > MAX_ATOL:
        raise UserError(f"--atol must be at most {MAX_ATOL:g} (rad, rad/s), got {a.atol:g}: "
                        "a looser tolerance lets every step err by more")
    if a.max_steps is not None and not 1 <= a.max_steps <= MAX_STEPS:
        raise UserError(f"--max-steps must be from 1 to {MAX_STEPS}, got {a.max_steps}")
    for name in ("phi0", "dphi0"):
        v = getattr(a, name)
        if v is not None and not np.isfinite(v):
            raise UserError(f"--{name} must be finite, got {v}")
    kw = {name: getattr(a, name) for name in ("phi0", "dphi0", "solver", "rtol", "atol",
                                              "max_steps") if getattr(a, name) is not None}
    if a.extras is not None:
        kw["outputs"] = tuple(x.strip() for x in a.extras.split(",") if x.strip())
        try:
            output_columns(kw["outputs"])
        except ValueError as e:
            raise UserError(f"--extras: {e}") from None
    check_output(a.out, [a.scene], "--out")
    if a.plot:
        check_output(a.plot, [a.scene], "--plot")
        check_figure_format(a.plot, "--plot")
        check_distinct_outputs([(a.out, "--out"), (a.plot, "--plot")])
    return kw


def _check_size(a: argparse.Namespace, t1: float, samples: int, ncols: int) -> None:
    """Refuse, before any work, a run whose samples cannot be resolved or stored."""
    src = "--samples" if a.samples is not None else "the scene's [output] samples"
    if not 2 <= samples <= MAX_SAMPLES:
        raise UserError(f"{src} must be >= 2 and <= {MAX_SAMPLES}, got {samples}")
    dt = t1 / (samples - 1)
    if not (dt > 0 and np.isfinite(dt) and dt >= 4 * np.spacing(t1)):
        raise UserError(f"t1 = {t1:g} s is too short for {samples} samples: their times "
                        "cannot be told apart in float64; use fewer samples")
    out = Path(a.out)
    if out.exists() and not out.is_file():
        return  # a device such as /dev/null
    need = samples * ncols * CSV_BYTES_PER_VALUE
    free = shutil.disk_usage(out.resolve().parent).free
    if need > free:
        raise UserError(f"{samples} samples of {ncols} columns need about {need / 1e9:.3g} GB "
                        f"for {a.out}, but its file system has {free / 1e9:.3g} GB free; ask "
                        "for fewer --samples")


def _grid(t1: float, samples: int, lo: int, hi: int) -> np.ndarray:
    """Sample times `lo..hi-1` of the uniform grid of `samples` points on [0, t1], s."""
    ts = np.arange(lo, hi, dtype=np.float64) * (t1 / (samples - 1))
    if hi == samples:
        ts[-1] = t1  # exactly t1, as linspace gives
    return ts


def _write_rows(f, cols: dict) -> None:
    data = np.column_stack([np.asarray(v, dtype=np.float64) for v in cols.values()])
    if not np.all(np.isfinite(data)):
        i, j = np.argwhere(~np.isfinite(data))[0]
        raise RuntimeError(f"column {list(cols)[j]!r} is not finite at t = {data[i, 0]:g} s; "
                           "the run is not written")
    # One %-format of the whole chunk is ~3x faster than np.savetxt's loop over rows.
    row = ",".join(["%.17g"] * data.shape[1]) + "\n"
    f.write((row * data.shape[0]) % tuple(data.ravel().tolist()))


def _stream(scene, t1: float, samples: int, kw: dict, f, plot_stride: int, quiet: bool):
    """Simulate chunk by chunk, each starting from the last state of the one before, and
    write the CSV rows to `f`. Returns (column names, solver steps, decimated ts/phi/dphi)."""
    chunks = max(1, -(-(samples - 1) // CHUNK_SAMPLES))
    kw = dict(kw)
    steps, names, keep = 0, None, ([], [], [])
    with progress_bar(samples, "simulate", not quiet and chunks > 1, unit="sample",
                      unit_scale=True) as bar:
        for k in range(chunks):
            lo = k * CHUNK_SAMPLES
            hi = samples if k == chunks - 1 else lo + CHUNK_SAMPLES + 1
            ts = _grid(t1, samples, lo, hi)
            traj = scene.simulate(ts, **kw)
            kw["phi0"], kw["dphi0"] = float(traj.phi[-1]), float(traj.dphi[-1])
            cols = traj.columns()
            first = 0 if k == 0 else 1  # row `lo` was the last row of the chunk before
            cols = {c: np.asarray(v)[first:] for c, v in cols.items()}
            if names is None:
                names = list(cols)
                f.write(",".join(names) + "\n")
            _write_rows(f, cols)
            steps += int(traj.num_steps)
            idx = np.arange(lo + first, hi)
            sel = (idx % plot_stride == 0) | (idx == samples - 1)
            for lst, c in zip(keep, ("t", "phi", "dphi")):
                lst.append(cols[c][sel])
            bar.update(hi - lo - first)
    return names, steps, [np.concatenate(x) for x in keep]


def _simulate_run(a: argparse.Namespace) -> int:
    from ..runtime.io import atomic_write
    from ..solve.trajectory import output_columns

    kw = _check_options(a)
    scene = _load(a.scene)
    refuse_input_loads(scene, a.scene, "simulate")
    t1 = scene.t1 if a.t1 is None else a.t1
    samples = scene.samples if a.samples is None else a.samples
    ncols = 3 + len(output_columns(kw.get("outputs", scene.outputs)))
    _check_size(a, t1, samples, ncols)
    stride = max(1, -(-samples // PLOT_POINTS))
    with atomic_write(a.out) as f:
        names, steps, (ts, phi, dphi) = _stream(scene, t1, samples, kw, f, stride, a.quiet)
    if a.plot:
        from types import SimpleNamespace

        from ..report.plotting import plot_trajectory

        plot_trajectory(SimpleNamespace(ts=ts, phi=phi, dphi=dphi), a.plot,
                        title=f"{scene.name}: {scene.description}")
    print(f"wrote {a.out}: {samples} samples of {', '.join(names)} over [0, {t1:g}] s "
          f"({steps} solver steps)", file=sys.stderr)
    return 0


# --- linearize --------------------------------------------------------------------------

def _linearize_args(p: argparse.ArgumentParser) -> None:
    _scene_args(p)
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")


def _linearize_run(a: argparse.Namespace) -> int:
    from ..model.linear import coulomb_note
    from ..simulation import linearize

    scene = _load(a.scene)
    lin = linearize(scene.mech, scene.load, scene.torque)
    out = {}
    for key in ("mu", "chi", "xi", "omega_n", "zeta", "stable", "k_crit", "phi_eq"):
        v = np.asarray(getattr(lin, key))
        if key == "stable":
            out[key] = bool(v)
        else:
            out[key] = float(v) if np.isfinite(v) else None
    if a.json:
        print(json.dumps(out))
    else:
        units = {"mu": "kg m^2", "chi": "N m s/rad", "xi": "N m/rad", "omega_n": "rad/s",
                 "zeta": "", "stable": "", "k_crit": "N m/rad", "phi_eq": "rad"}
        for key, v in out.items():
            print(f"{key:>8} = {v}  {units[key]}".rstrip())
        if out["omega_n"] is not None:
            print(f"{'f_n':>8} = {out['omega_n'] / (2 * np.pi):.6g}  Hz")
        note = coulomb_note(scene.mech)
        if note:
            print(note)
    return 0


# --- scenes -----------------------------------------------------------------------------

def _scenes_args(p: argparse.ArgumentParser) -> None:
    pass


def _scenes_run(a: argparse.Namespace) -> int:
    from ..scene import presets

    for name, desc in presets().items():
        print(f"{name:<14} {desc}")
    return 0


#: (name, help, add_arguments, run) for every subcommand.
COMMANDS = [
    ("simulate", "simulate a scene and write a CSV", _simulate_args, _simulate_run),
    ("linearize", "linearize a scene about its static equilibrium phi_eq", _linearize_args,
     _linearize_run),
    ("scenes", "list the preset scenes", _scenes_args, _scenes_run),
]
