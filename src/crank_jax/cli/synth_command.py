"""`crank-jax synth`: simulate a scene and write a synthetic record with what real rigs
add (noise, quantisation, jitter, lost samples, a start-up transient; see
[`synthesize`][crank_jax.records.synth.synthesize])."""

from __future__ import annotations

import argparse
import sys

import numpy as np

from .channel_options import parse_sigma
from .errors import UserError
from .options import seed
from .scene_inputs import refuse_input_loads


def _synth_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="preset name or TOML scene file")
    p.add_argument("--t1", type=float, help="end of the record, s (default: the scene's t1)")
    p.add_argument("--rate", type=float, default=200.0, help="sampling rate, Hz (200)")
    p.add_argument("--noise-std", action="append", metavar="[NAME=]STD",
                   help="standard deviation of Gaussian noise: STD for the angle, rad (0), or "
                        "NAME=STD for a scene sensor's channel in its SI unit (repeatable)")
    p.add_argument("--quantization", type=int,
                   help="encoder counts per revolution (default: no quantisation)")
    p.add_argument("--jitter-std", type=float, default=0.0,
                   help="standard deviation of the sampling instants, s (0)")
    p.add_argument("--drop", type=float, default=0.0,
                   help="probability that a sample is lost (0)")
    p.add_argument("--t-start", type=float, default=0.0,
                   help="time of the first sample, s (0; the scene's state is at t = 0)")
    p.add_argument("--transient", type=float, default=0.0, metavar="RAD",
                   help="amplitude of a start-up transient (a hand release), rad (0: none)")
    p.add_argument("--transient-time", type=float, default=0.1, metavar="S",
                   help="its decay time, s (0.1)")
    p.add_argument("--seed", type=seed, default=0, help="noise seed (0)")
    p.add_argument("--out", required=True, help="output CSV (t,phi[,P][,tau])")
    # As every command takes it: a script passes --quiet to each; synth shows no
    # progress bar, so it changes nothing.
    p.add_argument("--quiet", action="store_true", help="no progress bar (synth has none)")


def _check_record_size(a: argparse.Namespace, scene) -> None:
    from ..records.table import MAX_RECORD_SAMPLES

    t1 = scene.t1 if a.t1 is None else a.t1
    n = (t1 - a.t_start) * a.rate  # NaN or inf (a bad option) is synthesize's to name
    if np.isfinite(n) and n >= MAX_RECORD_SAMPLES:
        raise UserError(f"--rate {a.rate:g} Hz over {t1 - a.t_start:g} s (--t-start to --t1) "
                        f"is {n:.3g} samples; a record holds at most {MAX_RECORD_SAMPLES}: "
                        "lower --rate or shorten the record (--t1)")


def _synth_run(a: argparse.Namespace) -> int:
    from ..records.data import save_data
    from ..records.synth import synthesize
    from ..runtime.io import check_output
    from ..scene import load_scene

    check_output(a.out, [a.scene], "--out")
    scene = load_scene(a.scene)
    refuse_input_loads(scene, a.scene, "synth")
    _check_record_size(a, scene)
    noise = parse_sigma(a.noise_std, "--noise-std", zero=True)
    data = synthesize(scene, t1=a.t1, rate=a.rate, noise_std=0.0 if noise is None else noise,
                      quantization=a.quantization, jitter_std=a.jitter_std, drop=a.drop,
                      t_start=a.t_start, seed=a.seed, transient=a.transient,
                      transient_time=a.transient_time)
    comment = (f"crank-jax synth {a.scene}: t1={a.t1 if a.t1 is not None else scene.t1} "
               f"rate={a.rate} noise_std={noise or 0.0} quantization={a.quantization} "
               f"jitter_std={a.jitter_std} drop={a.drop} t_start={a.t_start} seed={a.seed}")
    save_data(data, a.out, comment)
    print(f"wrote {a.out}: {data.n} samples of {', '.join(data.columns())} over "
          f"[{data.ts[0]:g}, {data.ts[-1]:g}] s", file=sys.stderr)
    return 0


#: Subcommands added to `crank-jax` (see `cli.COMMANDS` for the tuple layout).
COMMANDS: list = [
    ("synth", "simulate a scene and write noisy synthetic data (CSV)", _synth_args, _synth_run),
]
