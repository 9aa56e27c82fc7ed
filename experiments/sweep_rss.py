"""Peak memory (RSS) of `crank-jax sweep` against the number of samples, as a user runs it.

Each size runs the CLI in a fresh child process: the lab rig, k ~ normal(2, 0.1) and
c ~ uniform(0.005, 0.02), the default three outputs (reductions only, nothing saved per
time step), `--t1 0.5 --samples 51`; the child's peak RSS is `ru_maxrss` of
`resource.getrusage(RUSAGE_CHILDREN)` read after each run (children are waited one at a
time, so the maximum so far is the largest child's: sizes run in increasing order).

Run: `python experiments/sweep_rss.py [--sizes 1000,100000,1000000] [--chunk-size 1024]
[--out experiments/results/sweep_rss.json]`. On a GPU host the sweep runs on the GPU (set
`JAX_PLATFORMS=cpu` for the CPU).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def run(n: int, chunk: int, workdir: str) -> dict:
    argv = [sys.executable, "-m", "crank_jax", "sweep", "lab-rig", "--vary",
            "k=normal(2,0.1)", "--vary", "c=uniform(0.005,0.02)", "--n", str(n), "--t1", "0.5",
            "--samples", "51", "--chunk-size", str(chunk), "--quiet", "--out",
            os.path.join(workdir, f"s{n}.npz")]
    env = dict(os.environ, CRANK_JAX_NO_CACHE="1",
               PYTHONPATH=os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")]))
    t = time.perf_counter()
    p = subprocess.run(argv, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if p.returncode != 0:
        raise SystemExit(f"n={n}: exit {p.returncode}: {p.stderr[-2000:]}")
    rss_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return {"n": n, "peak_rss_mb": rss_kb / 1024.0, "wall_s": wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1000,100000,1000000")
    ap.add_argument("--chunk-size", type=int, default=1024)
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results" / "sweep_rss.json"))
    a = ap.parse_args()
    import jax  # its version only: the parent must not take the GPU from the children

    out = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "platform": platform.platform(), "cores": len(os.sched_getaffinity(0)),
           "jax": jax.__version__, "platforms": os.environ.get("JAX_PLATFORMS") or "default",
           "chunk_size": a.chunk_size, "rows": []}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as d:
        for n in sorted(int(s) for s in a.sizes.split(",")):
            out["rows"].append(run(n, a.chunk_size, d))
            print(json.dumps(out["rows"][-1]), flush=True)
            # Written after every size: a long run that is stopped keeps what it measured.
            Path(a.out).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
