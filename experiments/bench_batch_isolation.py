"""What batch-member isolation costs: a uniform `jax.vmap`-ed batch of lab rigs before and
after every member got its own step control (issue 26, item 3), both in one run.

The lab rig with c = 1e-3, phi0 = 1 rad, 10 s, 1001 samples, the batch varying k over
+-10% (as bench_throughput.py), `simulate`'s default solver at rtol 1e-8 / atol 1e-10.
"before" is the source tree at `--before` (default 2a7668c, the last commit with one
shared step size per lockstep group), extracted with `git archive`; "after" is this
checkout. Each measurement runs in a fresh process with that tree first on PYTHONPATH,
the two alternating, `--rounds` times; the file records every round's median wall and CPU
(process) time per trajectory, the latter less disturbed by other jobs on a shared
machine, and the member error against a tight reference (diffrax Dopri8, rtol 1e-14).

Run: `python experiments/bench_batch_isolation.py [--sizes 1000,10000] [--rounds 2]`.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from _bench import ROOT, save

CHILD = r"""
import json, sys, time
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import crank_jax as cj
n = int(sys.argv[1])
mech = cj.load_scene("lab-rig").mech.replace(c=1e-3)
ts = jnp.linspace(0.0, 10.0, 1001)
ks = float(mech.k) * jnp.linspace(0.9, 1.1, n)
run = jax.jit(jax.vmap(lambda k: cj.simulate(mech.replace(k=k), 1.0, 0.0, ts).phi))
jax.block_until_ready(run(ks))
times, cpu = [], []
for _ in range(3):
    t, c = time.perf_counter(), time.process_time()
    out = jax.block_until_ready(run(ks))
    times.append(time.perf_counter() - t)
    cpu.append(time.process_time() - c)
ref = np.asarray(cj.simulate(mech.replace(k=ks[-1]), 1.0, 0.0, ts, solver="dopri8",
                             rtol=1e-14, atol=1e-16, max_steps=10**7).phi)
err = float(np.max(np.abs(np.asarray(out[-1]) - ref)))
print(json.dumps({"us_per_trajectory": float(np.median(times)) / n * 1e6,
                  "cpu_us_per_trajectory": float(np.median(cpu)) / n * 1e6,
                  "error_rad": err}))
"""


def _measure(src: Path, n: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(src), CRANK_JAX_NO_CACHE="1")
    out = subprocess.run([sys.executable, "-c", CHILD, str(n)], env=env, check=True,
                         capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", default="2a7668c", help="git revision of the 'before' tree")
    ap.add_argument("--sizes", default="1000,10000")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--smoke", action="store_true", help="one small batch, one round")
    a = ap.parse_args(argv)
    sizes = [64] if a.smoke else [int(x) for x in a.sizes.split(",")]
    rounds = 1 if a.smoke else a.rounds
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", a.before, "src"],
                                 check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
        trees = {"before": Path(tmp) / "src", "after": ROOT / "src"}
        for n in sizes:
            runs = {"before": [], "after": []}
            for _ in range(rounds):
                for name, src in trees.items():
                    runs[name].append(_measure(src, n))
                    print(n, name, runs[name][-1], flush=True)
            med = {k: float(np.median([r["us_per_trajectory"] for r in v]))
                   for k, v in runs.items()}
            cpu = {k: float(np.median([r["cpu_us_per_trajectory"] for r in v]))
                   for k, v in runs.items()}
            rows.append({"batch": n, "runs": runs, "median_us": med, "median_cpu_us": cpu,
                         "after_over_before": med["after"] / med["before"],
                         "after_over_before_cpu": cpu["after"] / cpu["before"]})
    save("batch_isolation", {"before": a.before, "rows": rows}, a.smoke)


if __name__ == "__main__":
    main()
