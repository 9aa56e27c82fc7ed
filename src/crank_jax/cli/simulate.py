"""`crank-jax simulate`, `linearize` and `scenes`: the model's command group."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from .errors import UserError

__all__ = ["COMMANDS"]


def _scene_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="preset name (see `crank-jax scenes`) or a TOML scene file")


def _load(source: str):
    from ..scene import load_scene

    return load_scene(source)


# --- simulate ---------------------------------------------------------------------------

def _simulate_args(p: argparse.ArgumentParser) -> None:
    _scene_args(p)
    p.add_argument("--t1", type=float, help="end time, s (default: the scene's, else 10)")
    p.add_argument("--samples", type=int, help="number of uniform samples on [0, t1]")
    p.add_argument("--phi0", type=float, help="initial crank angle, rad")
    p.add_argument("--dphi0", type=float, help="initial crank rate, rad/s")
    p.add_argument("--solver", help="auto, tsit5, dopri5, dopri8 or kvaerno5")
    p.add_argument("--rtol", type=float, help="relative tolerance")
    p.add_argument("--atol", type=float, help="absolute tolerance")
    p.add_argument("--extras", help="comma-separated derived outputs to add as columns "
                   "(ddphi, delta, slider, energy, loads, reactions); default: the scene's")
    p.add_argument("--out", required=True, help="output CSV file (t,phi,dphi,...)")
    p.add_argument("--plot", help="also draw phi(t) and dphi(t) to this PNG file")


def _simulate_run(a: argparse.Namespace) -> int:
    from ..io import atomic_write, check_not_input
    from ..solve.policy import SOLVERS
    from ..solve.simulate import output_columns

    scene = _load(a.scene)
    check_not_input(a.out, [a.scene])
    if a.plot:
        check_not_input(a.plot, [a.scene])
    t1 = scene.t1 if a.t1 is None else a.t1
    samples = scene.samples if a.samples is None else a.samples
    if not (np.isfinite(t1) and t1 > 0):
        raise UserError(f"--t1 must be a finite time > 0 s, got {t1}")
    if samples < 2:
        raise UserError(f"--samples must be >= 2, got {samples}")
    if a.solver is not None and a.solver not in SOLVERS:
        raise UserError(f"--solver {a.solver!r} is unknown; choose from {', '.join(SOLVERS)}")
    for name in ("rtol", "atol"):
        v = getattr(a, name)
        if v is not None and not (np.isfinite(v) and v > 0):
            raise UserError(f"--{name} must be a positive number, got {v}")
    kw = {}
    for name in ("phi0", "dphi0", "solver", "rtol", "atol"):
        if getattr(a, name) is not None:
            kw[name] = getattr(a, name)
    if a.extras is not None:
        kw["outputs"] = tuple(x.strip() for x in a.extras.split(",") if x.strip())
        output_columns(kw["outputs"])  # raises ValueError naming an unknown output
    for name in ("phi0", "dphi0"):
        if name in kw and not np.isfinite(kw[name]):
            raise UserError(f"--{name} must be finite, got {kw[name]}")
    traj = scene.simulate(scene.ts(t1, samples), **kw)
    cols = traj.columns()
    data = np.column_stack([np.asarray(v) for v in cols.values()])
    with atomic_write(a.out) as f:
        f.write(",".join(cols) + "\n")
        np.savetxt(f, data, delimiter=",", fmt="%.17g")
    if a.plot:
        from ..plot import plot_trajectory

        plot_trajectory(traj, a.plot, title=f"{scene.name}: {scene.description}")
    print(f"wrote {a.out}: {samples} samples of {', '.join(cols)} over [0, {t1:g}] s "
          f"({int(traj.num_steps)} solver steps)", file=sys.stderr)
    return 0


# --- linearize --------------------------------------------------------------------------

def _linearize_args(p: argparse.ArgumentParser) -> None:
    _scene_args(p)
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")


def _linearize_run(a: argparse.Namespace) -> int:
    from ..model.linear import coulomb_note, linearize

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
    ("linearize", "linearise a scene about phi = 0", _linearize_args, _linearize_run),
    ("scenes", "list the preset scenes", _scenes_args, _scenes_run),
]
