"""A motor-driven, rotating offset slider-crank, as real rigs are: fit it under defaults
from generic start values, validate it on a record at another voltage, and (slow) check
the coverage of the 95% intervals per channel configuration.

The rig (synthesised, every number below is the truth the fit does not see):

- an offset slider line (`e` = 8 mm) on a mount tilted by 0.35 rad (`gravity_angle`);
- a DC motor at constant voltage: torque `gain * volts` (`[torque] input = "volts"`),
  its back-EMF in the crank damping `c`;
- Coulomb friction in the crank bearing (`T_c`);
- an encoder on the crank (4096 counts per revolution, counting the other way, with an
  unknown zero) and a linear sensor on the slider (mm, counting towards the crank, with
  its own zero), logged at 50 Hz by a loop that jitters by 3 ms and writes the actual
  time of each sample.

A crank that turns one way cannot tell Coulomb friction from a constant torque: two
records at different voltages separate them (a multi-record fit, the motor's gain shared).
The fit frees `tau_gain`, `c`, `T_c` and each record's state; the masses and geometry
are known (weighed and measured). It starts from generic values: the gain and damping
half and twice their truth, no friction.

Run:

- `python experiments/rotating_rig.py` fits both channels, prints the estimates with
  their intervals, the per-channel fit, and the validation on a third record at another
  voltage (a few minutes on a laptop's CPU, most of it compiling).
- `python experiments/rotating_rig.py --coverage N --out results.json` (slow) repeats the
  fit over N noise seeds for each channel configuration (angle only, slide only, both)
  and writes how often each 95% interval holds the truth. `--configs angle` picks
  configurations, `--first-seed K` starts at seed K, and `--plain` synthesises records
  without jitter or quantisation (a control: Gaussian noise only).
"""

from __future__ import annotations

import argparse
import json
import math
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.model import InputLoad  # noqa: E402
from crank_jax.runtime.io import atomic_write  # noqa: E402

TRUTH = dict(tau_gain=0.03, c=0.01, T_c=0.02)
#: Generic start values: the motor's gain and damping off by 2x, no friction.
START = dict(tau_gain=0.015, c=0.02, T_c=0.0)
FREE = ("tau_gain", "c", "T_c", "phi0", "dphi0")
RATE, JITTER, T1 = 50.0, 3e-3, 3.0
VOLTS_FIT, VOLTS_VALIDATE = (6.0, 9.0), 7.5
ENCODER = cj.Sensor("phi", "wheel_deg", "deg", scale=-1.0, offset=-3.083)
SLIDE = cj.Sensor("x_s", "slide_mm", "mm", scale=-1.0, offset=0.2948)
NOISE = {"phi": 2e-3, "x_s": 5e-5}  # rad, m (besides the encoder's quantisation)
CONFIGS = {"angle": (ENCODER,), "slide": (SLIDE,), "both": (ENCODER, SLIDE)}


def mechanism(**values) -> cj.SliderCrank:
    m = dict(r=0.05, L=0.2, b=0.1, s=0.01, m_c=0.1, m_p=0.05, m_s=0.1, I_c=2e-3, I_p=2e-4,
             k=0.0, c=TRUTH["c"], g=9.81, e=0.008, T_c=TRUTH["T_c"], w_c=0.05,
             gravity_angle=0.35)
    m.update(values)
    return cj.SliderCrank(**m)


def rig(volts: float | None, sensors, gain: float = TRUTH["tau_gain"], **mech) -> cj.Scene:
    """The rig at constant `volts` (None: the record supplies them), started at rest."""
    torque = InputLoad(gain=gain, column="volts")
    if volts is not None:
        torque = torque.bind([0.0, T1 + 1.0], [volts, volts], interp="linear")
    return cj.Scene(mechanism(**mech), torque=torque, phi0=0.0, dphi0=5.0, t1=T1,
                    sensors=tuple(sensors), name="rotating-rig")


def record(volts: float, sensors, seed: int, plain: bool = False) -> cj.Data:
    """One synthetic record: the motor started 0.5 s earlier (its start-up not logged).
    `plain`: Gaussian noise only (no loop jitter, no encoder quantisation), a control."""
    noise = {s.name: NOISE[s.name] for s in sensors}
    return cj.synthesize(rig(volts, sensors), t_start=0.5, rate=RATE,
                         jitter_std=0.0 if plain else JITTER,
                         quantization=None if plain else 4096, noise_std=noise, seed=seed,
                         sensors=sensors, timestamps="actual")


def fit_config(sensors, seed: int, progress: bool = False, plain: bool = False):
    """Fit the two records at `VOLTS_FIT` from the generic start. **Returns:** the fit."""
    recs = [record(v, sensors, seed * 10 + i, plain) for i, v in enumerate(VOLTS_FIT)]
    start = rig(None, sensors, gain=START["tau_gain"], c=START["c"], T_c=START["T_c"])
    return cj.fit(start, recs, free=FREE, progress=progress, warn=False)


def covered(res) -> dict[str, bool | None]:
    """Whether each mechanism/load estimate's 95% interval holds the truth (None: no
    interval)."""
    out = {}
    for name, want in TRUTH.items():
        ci = res.ci95.get(name)
        out[name] = None if ci is None else bool(ci[0] <= want <= ci[1])
    return out


def demo() -> None:
    t = time.perf_counter()
    res = fit_config(CONFIGS["both"], seed=0, progress=True)
    print(res.summary())
    print(f"wall time {time.perf_counter() - t:.1f} s, {res.iterations} LM iterations")
    for n, want in TRUTH.items():
        print(f"{n}: estimate {res.values[n]:.5g}, truth {want:g}, 95% CI {res.ci95[n]}")
    fitted = cj.identify.fitted_scene(rig(None, CONFIGS["both"]), res)
    val = cj.validate(fitted, record(VOLTS_VALIDATE, CONFIGS["both"], seed=99),
                      init_window=0.5)
    print(val.summary())


def coverage(n_seeds: int, out: str, configs=tuple(CONFIGS), first_seed: int = 0,
             plain: bool = False) -> None:
    """Fit `n_seeds` seeds (from `first_seed`) per configuration, seed by seed across the
    configurations; the results file is rewritten after every fit, so a run cut short
    keeps what it did. `plain`: records without jitter or quantisation (a control)."""
    rows = {name: [] for name in configs}
    for seed in range(first_seed, first_seed + n_seeds):
        for name in configs:
            t = time.perf_counter()
            res = fit_config(CONFIGS[name], seed=1000 + seed, plain=plain)
            rows[name].append({"seed": seed, "converged": res.converged,
                               "message": res.message, "iterations": res.iterations,
                               "seconds": time.perf_counter() - t,
                               "values": {n: res.values[n] for n in TRUTH},
                               "covered": covered(res)})
            print(name, seed, res.converged, covered(res), flush=True)
            summary = _summary(rows)
            with atomic_write(out) as f:
                json.dump({"truth": TRUTH, "start": START, "seeds": n_seeds,
                           "first_seed": first_seed, "plain": plain, "summary": summary,
                           "fits": rows}, f, indent=1)
                f.write("\n")
    print(json.dumps(summary, indent=2))


def _summary(rows: dict) -> dict:
    summary = {}
    for name, rs in rows.items():
        per = {}
        for p in TRUTH:
            hits = [r["covered"][p] for r in rs if r["converged"] and r["covered"][p] is not None]
            err = [abs(r["values"][p] / TRUTH[p] - 1) for r in rs if r["converged"]]
            per[p] = {"coverage": (sum(hits) / len(hits)) if hits else None,
                      "n": len(hits), "median_relative_error": (float(np.median(err)) if err
                                                                 else None)}
        summary[name] = {"converged": sum(r["converged"] for r in rs), "fits": len(rs),
                         "parameters": per,
                         "median_iterations": (float(np.median([r["iterations"] for r in rs]))
                                               if rs else None),
                         "median_seconds": (float(np.median([r["seconds"] for r in rs]))
                                            if rs else None)}
    return summary


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--coverage", type=int, metavar="N",
                   help="repeat over N seeds per channel configuration (slow)")
    p.add_argument("--out", default="experiments/results/rotating_rig_coverage.json",
                   help="results file of --coverage")
    p.add_argument("--configs", default=",".join(CONFIGS),
                   help="channel configurations of --coverage, comma-separated")
    p.add_argument("--first-seed", type=int, default=0, help="first seed of --coverage")
    p.add_argument("--plain", action="store_true",
                   help="--coverage on records without jitter or quantisation (a control)")
    a = p.parse_args()
    if a.coverage:
        if not (a.coverage > 0 and math.isfinite(a.coverage)):
            raise SystemExit("--coverage must be a positive number of seeds")
        configs = tuple(c for c in a.configs.split(",") if c)
        if not configs or any(c not in CONFIGS for c in configs):
            raise SystemExit(f"--configs takes names from {', '.join(CONFIGS)}")
        if a.first_seed < 0:
            raise SystemExit("--first-seed must be >= 0")
        coverage(a.coverage, a.out, configs, a.first_seed, a.plain)
    else:
        demo()


if __name__ == "__main__":
    main()
