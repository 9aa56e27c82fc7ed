"""Posterior coverage: over synthetic lab-rig records (k, c, phi0, dphi0 free; 2 s at
100 Hz, 2 mrad noise), how often the 95% credible interval of each parameter covers the
truth, beside the fit's Laplace 95% intervals on the same records.

Run: `python experiments/posterior_coverage.py [records] [draws]`; writes
`experiments/results/posterior_coverage.json`, rewritten after every record (so a run cut
short keeps what it did; `records` says how many). Expect coverage near 0.95 with a
binomial standard error of sqrt(0.95 * 0.05 / records). It calls
`crank_jax.configure_cpu()` as the `crank-jax` program does (the two chains run on two
CPU devices).
"""

import json
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import crank_jax as cj  # noqa: E402
from crank_jax.runtime.io import atomic_write  # noqa: E402

cj.configure_cpu()

FREE = ("k", "c", "phi0", "dphi0")


def main() -> None:
    records = int(sys.argv[1]) if len(sys.argv) > 1 else 40
    draws = int(sys.argv[2]) if len(sys.argv) > 2 else 300
    scene = cj.load_scene("lab-rig")
    truth = {"k": 2.0, "c": 0.002, "phi0": 1.0, "dphi0": 0.0}
    hits = {n: 0 for n in FREE}
    laplace = {n: 0 for n in FREE}
    rows = []
    t0 = time.perf_counter()
    for seed in range(records):
        data = cj.synthesize(scene, t1=2.0, rate=100.0, noise_std=2e-3, seed=1000 + seed)
        post = cj.posterior(scene, data, FREE, draws=draws, chains=2, warmup=300,
                            seed=seed, progress=False)
        s = post.summary()
        row = {"seed": seed, "divergences": post.divergences}
        for n in FREE:
            inside = s[n]["q2.5"] <= truth[n] <= s[n]["q97.5"]
            hits[n] += inside
            ci = post.fit.ci95[n]
            laplace[n] += bool(ci and ci[0] <= truth[n] <= ci[1])
            row[n] = {"q2.5": s[n]["q2.5"], "q97.5": s[n]["q97.5"], "rhat": s[n]["rhat"],
                      "laplace_ci95": ci}
        rows.append(row)
        out = _write(rows, hits, laplace, draws, time.perf_counter() - t0)
    print(json.dumps({k: v for k, v in out.items() if k != "rows"}, indent=1))


def _write(rows, hits, laplace, draws, seconds):
    m = len(rows)
    out = {"records": m, "draws": draws, "chains": 2, "warmup": 300,
           "seconds": seconds, "cpu_s": time.process_time(), "load_average": os.getloadavg(),
           "divergences": sum(r["divergences"] for r in rows),
           "max_rhat": max(r[n]["rhat"] for r in rows for n in FREE),
           "posterior_coverage": {n: hits[n] / m for n in FREE},
           "laplace_coverage": {n: laplace[n] / m for n in FREE},
           "binomial_se": (0.95 * 0.05 / m) ** 0.5, "rows": rows}
    os.makedirs("experiments/results", exist_ok=True)
    with atomic_write("experiments/results/posterior_coverage.json") as f:
        json.dump(out, f, indent=1)
    return out


if __name__ == "__main__":
    main()
