"""The host's BLAS threads in a fit: one thread (what `cj.fit` runs with, see
`crank_jax/runtime/blas.py`) against OpenBLAS's default (a thread per core).

Two measurements, each with 0, 1 and 2 busy processes beside it (a shared machine, or a
user's other work):

1. NumPy's SVD of a matrix shaped as the lab record's multiple-shooting Jacobian
   (1318 x 26), the Gauss-Newton step's factorisation: median and worst of 30;
2. a warm fit of the lab record (k, c, phi0, dphi0 from k = 2.4; multiple shooting, 12
   segments) in this process: `cj.fit` (one BLAS thread) against `cj.fit.__wrapped__`
   (the same function without the limit), alternated, 4 each.

    python experiments/fit_blas_threads.py [--smoke]

Writes experiments/results/fit_blas_threads.json.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

from _bench import RESULTS, machine, setup_jax

jax = setup_jax()
import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.runtime.io import atomic_write  # noqa: E402


def _hogs(n: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def _stats(times: list[float]) -> dict:
    return {"median_s": float(np.median(times)), "max_s": float(np.max(times)),
            "n": len(times)}


def _svd_times(J: np.ndarray, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        np.linalg.svd(J, full_matrices=False)
        out.append(time.perf_counter() - t)
    return out


def _lab_record():
    """The main record of experiments/bench_end_to_end.py: the lab rig, 5 s at 200 Hz,
    1 mrad of noise (seed 1), and its start scene (k = 2.4, c = 0.004)."""
    lab = cj.load_scene("lab-rig")
    start = cj.Scene(lab.mech.replace(k=2.4, c=0.004), phi0=1.0, name="lab-rig-start")
    return start, cj.synthesize(lab, t1=5.0, rate=200.0, noise_std=1e-3, seed=1)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--smoke", action="store_true", help="fewer repeats, no file written")
    smoke = ap.parse_args(argv).smoke
    repeats, fits = (5, 1) if smoke else (30, 4)
    J = np.random.default_rng(0).standard_normal((1318, 26))
    scene, data = _lab_record()
    first = cj.fit(scene, data, progress=False, warn=False)  # compile once
    print(f"the fit: {first.strategy}, {first.iterations} iterations, k = "
          f"{first.values['k']:.6g}")
    rows = {}
    for load in (0, 1, 2):
        hogs = _hogs(load)
        time.sleep(0.5)
        try:
            default = _svd_times(J, repeats)
            with threadpool_limits(limits=1, user_api="blas"):
                one = _svd_times(J, repeats)
            f_one, f_default = [], []
            for _ in range(fits):
                for fn, into in ((cj.fit, f_one), (cj.fit.__wrapped__, f_default)):
                    t = time.perf_counter()
                    fn(scene, data, progress=False, warn=False)
                    into.append(time.perf_counter() - t)
        finally:
            for h in hogs:
                h.kill()
        rows[f"{load} busy"] = {"svd_default": _stats(default), "svd_one_thread": _stats(one),
                                "fit_default": _stats(f_default),
                                "fit_one_thread": _stats(f_one)}
        print(f"{load} busy: SVD {np.median(default) * 1e3:.2f} ms (worst "
              f"{max(default) * 1e3:.1f}) default, {np.median(one) * 1e3:.2f} ms (worst "
              f"{max(one) * 1e3:.1f}) one thread; warm fit {np.median(f_default):.3f} s "
              f"default, {np.median(f_one):.3f} s one thread")
    if not smoke:
        out = RESULTS / "fit_blas_threads.json"
        with atomic_write(out) as f:
            json.dump({"machine": machine(), "rows": rows}, f, indent=1)
        print(f"wrote {out}")


if __name__ == "__main__":
    main()
