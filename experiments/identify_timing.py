"""Fit time against record length, for Levenberg-Marquardt and for optax (Adam + L-BFGS).

The demo experiment (lab rig, known harmonic torque, 200 Hz, 1 mrad noise, k, c, phi0,
dphi0 free, the same start) at several record lengths. For each length and method: the
first fit (compilation included) and the median of three more fits on fresh noise (warm),
the iterations, whether it converged, and how far the optax estimate is from LM's in
units of LM's standard error.

    python experiments/identify_timing.py [--lengths 1 2 5 10] [--optax-steps 600]

Writes experiments/results/identify_timing.json and docs/figures/identify_timing.png.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.identify import DEMO, demo_record  # noqa: E402
from crank_jax.report.plotting import pyplot, save_figure  # noqa: E402
from crank_jax.runtime.io import atomic_write  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FREE = ("k", "c", "phi0", "dphi0")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lengths", type=float, nargs="+", default=[1.0, 2.0, 5.0, 10.0])
    ap.add_argument("--optax-steps", type=int, default=600)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    scene0, _ = demo_record(seed=0)
    rows = []
    jobs = [(t1, m) for t1 in args.lengths for m in ("lm", "optax")]
    for t1, method in tqdm(jobs, desc="lengths x methods"):
        scene = cj.Scene(scene0.mech, torque=scene0.torque, phi0=scene0.phi0, t1=t1)
        times, its, conv, fits = [], [], [], []
        for rep in range(1 + args.repeats):
            data = cj.synthesize(scene, rate=DEMO["rate"], noise_std=DEMO["noise_std"],
                                 seed=100 + rep)
            kw = dict(method=method, max_steps=args.optax_steps) if method == "optax" else {}
            t = time.perf_counter()
            res = cj.fit(scene, data, free=FREE, init=dict(DEMO["start"]), progress=False,
                         warn=False, **kw)
            times.append(time.perf_counter() - t)
            its.append(res.iterations)
            conv.append(res.converged)
            fits.append(res)
        rows.append({"t1": t1, "samples": fits[0].n_samples, "method": method,
                     "shooting": fits[0].shooting, "first_seconds": times[0],
                     "warm_seconds_median": float(np.median(times[1:])),
                     "iterations_median": float(np.median(its[1:])),
                     "converged": int(sum(conv[1:])), "repeats": args.repeats,
                     "values": [f.values for f in fits[1:]],
                     "stderr": [f.stderr for f in fits[1:]]})
    # optax vs LM on the same records, in LM standard errors.
    by = {(r["t1"], r["method"]): r for r in rows}
    for t1 in args.lengths:
        lm, ox = by[(t1, "lm")], by[(t1, "optax")]
        dev = [max(abs(o[n] - lm_v[n]) / lm_s[n] for n in FREE if lm_s[n])
               for o, lm_v, lm_s in zip(ox["values"], lm["values"], lm["stderr"])]
        ox["max_deviation_from_lm_in_stderr"] = float(max(dev))
    doc = {"rows": rows, "date": time.strftime("%Y-%m-%d"),
           "machine": f"{platform.machine()} CPU, shared 2-core VM (noisy)",
           "note": "first = including JIT compilation; warm = median over fresh-noise repeats"}
    out = ROOT / "experiments" / "results" / "identify_timing.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(out) as f:
        json.dump(doc, f, indent=1)
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    for method, style in (("lm", "o-"), ("optax", "s--")):
        rs = [r for r in rows if r["method"] == method]
        ax.plot([r["t1"] for r in rs], [r["warm_seconds_median"] for r in rs], style,
                label=f"{method} (warm)")
        ax.plot([r["t1"] for r in rs], [r["first_seconds"] for r in rs], style, alpha=0.35,
                label=f"{method} (first, with compilation)")
    ax.set_xlabel("record length [s] (200 Hz)")
    ax.set_ylabel("fit time [s]")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    (ROOT / "docs" / "figures").mkdir(parents=True, exist_ok=True)
    save_figure(fig, ROOT / "docs" / "figures" / "identify_timing.png")
    for r in rows:
        print(f"{r['t1']:5g} s {r['method']:6} {r['shooting']:28} "
              f"first {r['first_seconds']:6.1f} s"
              f"  warm {r['warm_seconds_median']:6.2f} s  iters {r['iterations_median']:5.0f}"
              f"  converged {r['converged']}/{r['repeats']}"
              + (f"  |optax-lm| <= {r['max_deviation_from_lm_in_stderr']:.2g} se"
                 if "max_deviation_from_lm_in_stderr" in r else ""))


if __name__ == "__main__":
    main()
