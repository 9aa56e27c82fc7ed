"""Time a 4-parameter lab-rig posterior (k, c, phi0, dphi0; 1000 draws x 4 chains after
500 warm-up steps) and compare it with the fit's Laplace intervals.

Run: `python experiments/posterior_timing.py [t1] [draws]`; writes
`experiments/results/posterior_timing.json`. The time of the sampler excludes the fit;
the first call also compiles the chunked NUTS program, so the script runs twice (a small
first run compiles: the same program serves both).
"""

import json
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import crank_jax as cj  # noqa: E402


def main() -> None:
    t1 = float(sys.argv[1]) if len(sys.argv) > 1 else 5.0
    draws = int(sys.argv[2]) if len(sys.argv) > 2 else 1000
    scene = cj.load_scene("lab-rig")
    data = cj.synthesize(scene, t1=t1, rate=200, noise_std=1e-3, seed=1)
    free = ("k", "c", "phi0", "dphi0")
    t = time.perf_counter()
    cj.posterior(scene, data, free, draws=4, chains=4, warmup=0, progress=False)
    first = time.perf_counter() - t
    t, cpu = time.perf_counter(), time.process_time()
    post = cj.posterior(scene, data, free, draws=draws, chains=4, warmup=500, progress=False)
    total, cpu = time.perf_counter() - t, time.process_time() - cpu
    out = {"record": f"lab-rig, {t1:g} s at 200 Hz, 1 mrad noise", "free": free,
           "draws": draws, "chains": 4, "warmup": 500, "cpus": os.cpu_count(),
           "load_average": os.getloadavg(), "first_call_s (fit + compile, 4 draws)": first,
           "sampling_s (warm-up + draws)": post.seconds, "total_s (fit + sampling)": total,
           "cpu_s (fit + sampling, all threads)": cpu,
           "mean_tree_steps": post.mean_tree_steps, "divergences": post.divergences,
           "step_size": post.step_size.tolist(), "summary": post.summary(),
           "laplace": {n: {"value": post.fit.values[n], "stderr": post.fit.stderr[n]}
                       for n in post.names}}
    os.makedirs("experiments/results", exist_ok=True)
    with cj.atomic_write("experiments/results/posterior_timing.json") as f:
        json.dump(out, f, indent=1)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
