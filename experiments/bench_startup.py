"""Start-up: wall time of `crank-jax simulate lab-rig --out x.csv` in a fresh process,
cold (empty persistent compilation cache) and warm (the cache filled by a previous run),
with a breakdown: the bare interpreter, `import crank_jax`, and the rest (tracing and
lowering the solve, loading or compiling it, running it, writing the CSV).

Each cold run uses a new empty cache directory (`CRANK_JAX_CACHE_DIR`); warm runs reuse
one. Medians of several runs. Target (d): warm <= 3 s.

Run: `python experiments/bench_startup.py [--smoke]`.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
from _bench import save, setup_jax, wall

setup_jax()

CLI = [sys.executable, "-m", "crank_jax"]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true")
    smoke = ap.parse_args(argv).smoke
    n = 1 if smoke else 5
    env = {k: v for k, v in os.environ.items() if k != "CRANK_JAX_NO_CACHE"}
    with tempfile.TemporaryDirectory() as tmp:
        out = str(Path(tmp) / "x.csv")
        cmd = CLI + ["simulate", "lab-rig", "--out", out]
        cold = []
        for i in range(n if not smoke else 1):
            e = dict(env, CRANK_JAX_CACHE_DIR=str(Path(tmp) / f"cold{i}"))
            cold.append(wall(cmd, e))
        warm_env = dict(env, CRANK_JAX_CACHE_DIR=str(Path(tmp) / "cold0"))
        warm = [wall(cmd, warm_env) for _ in range(n)]
        bare = [wall([sys.executable, "-c", "pass"], env) for _ in range(n)]
        imp = [wall([sys.executable, "-c", "import crank_jax.cli, crank_jax"], warm_env)
               for _ in range(n)]
        cache_files = len(list((Path(tmp) / "cold0").iterdir()))
    med = {k: float(np.median(v)) for k, v in
           {"cold": cold, "warm": warm, "python": bare, "import": imp}.items()}
    res = {
        "command": "crank-jax simulate lab-rig --out x.csv",
        "cold_s": med["cold"], "warm_s": med["warm"], "cold_runs": cold, "warm_runs": warm,
        "python_s": med["python"], "import_crank_jax_s": med["import"],
        "warm_after_import_s": med["warm"] - med["import"], "cache_entries": cache_files,
        "target_d": {"goal_s": 3.0, "warm_s": med["warm"], "met": med["warm"] <= 3.0},
    }
    print(res)
    save("startup", res, smoke)


if __name__ == "__main__":
    main()
