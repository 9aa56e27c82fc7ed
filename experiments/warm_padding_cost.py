"""The warm fit's cost of the rows' padding: the same records fitted warm under two
checkouts, alternated in fresh processes.

A record's rows are padded to a ladder of lengths (`identify/segments.py`), so a warm fit
of a record solves and differentiates more save times than the record holds. Here the
warm fit of lab-rig records at 200 Hz (free k, c, phi0, dphi0, from k = 2.4, c = 0.004)
is timed under a `before` checkout's `src` and an `after` one's, alternated (before,
after, before, after, ...) in fresh processes, each process fitting every record once
(to compile) and then `--repeats` times (process CPU time per fit; the median).

Run: `python experiments/warm_padding_cost.py --before PATH/src --after PATH/src
[--rounds 2] [--repeats 11]` -> experiments/results/warm_padding_cost.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from _bench import RESULTS, machine, setup_jax, write_json

#: (record length s, noise seed)
RECORDS = ((5.0, 1), (8.0, 8), (10.0, 9), (16.0, 16))


def child(repeats: int) -> None:
    """In a child process: each record's warm fits, CPU s, as JSON on stdout."""
    setup_jax()
    import crank_jax as cj

    lab = cj.load_scene("lab-rig")
    start = cj.Scene(lab.mech.replace(k=2.4, c=0.004), phi0=1.0, name="lab-rig-start")
    out = {}
    for t1, seed in RECORDS:
        data = cj.synthesize(lab, t1=t1, rate=200.0, noise_std=1e-3, seed=seed)
        cj.fit(start, data, progress=False)
        cpu = []
        for _ in range(repeats):
            c = time.process_time()
            cj.fit(start, data, progress=False)
            cpu.append(round(time.process_time() - c, 4))
        out[str(t1)] = cpu
    print(json.dumps(out))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", type=Path, required=True, help="the before checkout's src")
    ap.add_argument("--after", type=Path, required=True, help="the after checkout's src")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=11)
    ap.add_argument("--out", type=Path, default=RESULTS / "warm_padding_cost.json")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(args.repeats)
        return {}
    runs = []
    for r in range(args.rounds):
        for label, src in (("before", args.before), ("after", args.after)):
            env = dict(os.environ, PYTHONPATH=str(src.resolve()), CRANK_JAX_NO_CACHE="1")
            done = subprocess.run([sys.executable, __file__, "--child", "--before", ".",
                                   "--after", ".", "--repeats", str(args.repeats)],
                                  env=env, check=True, capture_output=True, text=True)
            cpu = json.loads(done.stdout.strip().splitlines()[-1])
            med = {t: sorted(v)[len(v) // 2] for t, v in cpu.items()}
            runs.append({"label": label, "round": r, "cpu_s": cpu, "median_cpu_s": med})
            print(label, r, med, flush=True)
    out = {"machine": machine(), "records": [t for t, _ in RECORDS], "runs": runs,
           "repeats": args.repeats, "before": str(args.before), "after": str(args.after)}
    write_json(args.out, out)
    return out


if __name__ == "__main__":
    main()
