"""LM iterations and wall time of fits under defaults on real-record-like cases (issue 25,
item 7): the rotating-rig tutorial's two records, the rotating rig's fit with each channel
configuration (both, slide only, angle only) on a few noise seeds, and the lab-rig demo
(which must still converge, k near 2).

Iterations do not depend on the machine's load; wall times do (the machine these numbers
come from is shared: read them with the iterations beside them). Each case is run twice
in one process and the second, warm run is reported (the first compiles).

Run: `python experiments/fit_speed.py --label before --out experiments/results/fit_speed.json`
(a few minutes on a laptop's CPU); `--label` names the run inside the results file, whose
other runs are kept.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, os.path.dirname(__file__))

import rotating_rig as rr  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.identify import DEMO, demo_record  # noqa: E402
from crank_jax.runtime.io import atomic_write  # noqa: E402


def _tutorial():
    """The tutorial's fit (docs/tutorials/rotating_rig.py): records at 6 V and 9 V."""
    sensors = rr.CONFIGS["both"]
    recs = [rr.record(6.0, sensors, 1), rr.record(9.0, sensors, 2)]
    start = rr.rig(None, sensors, gain=rr.START["tau_gain"], c=rr.START["c"],
                   T_c=rr.START["T_c"])
    return cj.fit(start, recs, free=rr.FREE, progress=False, warn=False)


def _demo():
    scene, data = demo_record(1)
    return cj.fit(scene, data, free=("k", "c", "phi0", "dphi0"), init=dict(DEMO["start"]),
                  progress=False, warn=False)


CASES = {"tutorial": _tutorial, "demo": _demo,
         **{f"rig-both-seed{s}": (lambda s=s: rr.fit_config(rr.CONFIGS["both"], seed=s))
            for s in (1000, 1001, 1002)},
         **{f"rig-slide-seed{s}": (lambda s=s: rr.fit_config(rr.CONFIGS["slide"], seed=s))
            for s in (1000, 1001, 1002)},
         **{f"rig-angle-seed{s}": (lambda s=s: rr.fit_config(rr.CONFIGS["angle"], seed=s))
            for s in (1000, 1001, 1002)}}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--label", required=True, help="name of this run in the results file")
    p.add_argument("--out", default="experiments/results/fit_speed.json")
    p.add_argument("--cases", default=",".join(CASES), help="comma-separated cases")
    a = p.parse_args()
    names = [c for c in a.cases.split(",") if c]
    bad = [c for c in names if c not in CASES]
    if bad:
        raise SystemExit(f"--cases: unknown case {bad[0]!r}; choose from {', '.join(CASES)}")
    rows = {}
    for name in names:
        for _ in range(2):  # the second run is warm
            t = time.perf_counter()
            res = CASES[name]()
            wall = time.perf_counter() - t
        rows[name] = {"iterations": res.iterations, "seconds": round(wall, 2),
                      "converged": res.converged, "strategy": res.strategy,
                      "rms": res.rms_residual,
                      "values": {n: res.values[n] for n in res.names if "[" not in n}}
        print(name, json.dumps(rows[name]), flush=True)
    doc = {}
    if os.path.exists(a.out):
        with open(a.out) as f:
            doc = json.load(f)
    doc[a.label] = {"cases": rows, "cpu": os.cpu_count(),
                    "note": "warm runs; the machine was shared (2 cores, several users)"}
    with atomic_write(a.out) as f:
        json.dump(doc, f, indent=2)
        f.write("\n")


if __name__ == "__main__":
    main()
