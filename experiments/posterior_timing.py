"""Time a 4-parameter lab-rig posterior (k, c, phi0, dphi0; 1000 draws x 4 chains after
500 warm-up steps) and compare it with the fit's Laplace intervals.

Run: `python experiments/posterior_timing.py [t1] [draws] [--no-cpu-flags]`; writes
`experiments/results/posterior_timing.json` (`--no-cpu-flags`: XLA's defaults, one CPU
device, as a library user who does not call `configure_cpu` gets; the file then gets a
`_defaults` suffix). By default the script calls `crank_jax.configure_cpu()` as the
`crank-jax` program does: the CPU flags and a JAX device per core, over which the chains
are shared. Gradient evaluations (leapfrog steps, warm-up and sampling, all chains) do
not depend on the machine's load; the seconds do (the load average is recorded). The time
of the sampler excludes the fit; the first call also compiles the chunked NUTS program, so
the script runs twice (a small first run compiles: the same program serves both).
"""

import json
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import crank_jax as cj  # noqa: E402
from crank_jax.runtime.io import atomic_write  # noqa: E402

FLAGS = "--no-cpu-flags" not in sys.argv
if FLAGS:
    cj.configure_cpu()


def main() -> None:
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    t1 = float(args[0]) if args else 5.0
    draws = int(args[1]) if len(args) > 1 else 1000
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
           "cpu_flags": FLAGS, "jax_devices": len(jax.devices()),
           "load_average": os.getloadavg(), "first_call_s (fit + compile, 4 draws)": first,
           "sampling_s (warm-up + draws)": post.seconds, "total_s (fit + sampling)": total,
           "cpu_s (fit + sampling, all threads)": cpu,
           "gradient_evaluations": post.gradient_evaluations,
           "ms_per_gradient_evaluation (wall, per chain)":
               1e3 * post.seconds * len(jax.devices()) / post.gradient_evaluations,
           "mean_tree_steps": post.mean_tree_steps, "divergences": post.divergences,
           "step_size": post.step_size.tolist(), "summary": post.summary(),
           "laplace": {n: {"value": post.fit.values[n], "stderr": post.fit.stderr[n]}
                       for n in post.names}}
    os.makedirs("experiments/results", exist_ok=True)
    name = "posterior_timing" + ("" if FLAGS else "_defaults")
    with atomic_write(f"experiments/results/{name}.json") as f:
        json.dump(out, f, indent=1)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
