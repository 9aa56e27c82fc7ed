"""The acceleration traced once per program (`model/dynamics.py`, `_traced_once`) against
traced at every site of the solver, on the first fit in a fresh Python process.

A solver evaluates its field at several places of one program (the first stage, the
initial step, the stage loop, the variational equation's reverse passes), and each was a
fresh trace of the same jnp arithmetic. The two arms run alternately in fresh
interpreters (no compilation cache), on the lab record of `bench_end_to_end.py` (5 s at
200 Hz from k = 2.4: single shooting at the start, then multiple shooting in 12
segments): the whole first fit, and JAX's own log of the time it spent tracing, lowering
and compiling each program. The "every site" arm sets `_traced_once` back to the plain
acceleration in its subprocess before the fit.

Run: `python experiments/trace_once.py [--smoke] [--pairs N]`.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

import numpy as np
from _bench import child_json, save, setup_jax
from bench_end_to_end import records

setup_jax()

# Runs in a fresh interpreter: `sys.argv[1:]` = arm, start scene, record.
CHILD = r'''
import json, logging, re, sys, time
t0 = time.perf_counter()
import jax
jax.config.update("jax_enable_x64", True)
log = []
class Grab(logging.Handler):
    def emit(self, rec):
        m = re.match(r"Finished (tracing|jaxpr to MLIR module conversion|XLA compilation)"
                     r" (?:of )?(?:for jit|jit)?\(?(\w+)\)? .*in ([0-9.e-]+) sec",
                     rec.getMessage())
        if m:
            log.append((m.group(1).split()[0], m.group(2), float(m.group(3))))
logging.getLogger("jax").addHandler(Grab())
logging.getLogger("jax").setLevel(logging.DEBUG)
jax.config.update("jax_log_compiles", True)
import crank_jax as cj
if sys.argv[1] == "every-site":
    from crank_jax.model import dynamics
    dynamics._traced_once = dynamics._acceleration
r = cj.fit(cj.load_scene(sys.argv[2]), cj.load_data(sys.argv[3]), progress=False)
total = time.perf_counter() - t0
assert r.converged
jac = [(k, s) for k, name, s in log if name == "jacobian"]
print(json.dumps(dict(total=total, strategy=r.strategy,
                      k=r.values["k"], iterations=r.iterations,
                      trace=[s for k, s in jac if k == "tracing"],
                      lower=[s for k, s in jac if k == "jaxpr"],
                      compile=[s for k, s in jac if k == "XLA"],
                      all_tracing=sum(s for k, _, s in log if k == "tracing"))))
'''


def run(arm: str, start: Path, rec: Path) -> dict:
    return child_json(CHILD, (arm, start, rec), dict(os.environ, CRANK_JAX_NO_CACHE="1"))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--pairs", type=int, default=3)
    args = ap.parse_args(argv)
    pairs = 1 if args.smoke else args.pairs
    runs = {"once": [], "every-site": []}
    with tempfile.TemporaryDirectory() as tmp:
        starts, recs = records(Path(tmp), args.smoke)
        for i in range(pairs):  # alternated, the order swapped every other pair
            for arm in (("every-site", "once") if i % 2 else ("once", "every-site")):
                runs[arm].append(run(arm, starts[0], recs[0]))
                print(arm, json.dumps(runs[arm][-1]), flush=True)

    def med(arm, key, i=None):
        vals = [r[key] if i is None else r[key][i] for r in runs[arm]]
        return float(np.median(vals))

    summary = {}
    for arm in runs:
        n_prog = min(len(r["trace"]) for r in runs[arm])
        summary[arm] = dict(
            first_fit_s=med(arm, "total"), all_tracing_s=med(arm, "all_tracing"),
            jacobian_trace_s=[med(arm, "trace", i) for i in range(n_prog)],
            jacobian_lower_s=[med(arm, "lower", i) for i in range(n_prog)],
            jacobian_compile_s=[med(arm, "compile", i) for i in range(n_prog)])
    same = all(r["k"] == runs["once"][0]["k"] for arm in runs for r in runs[arm])
    save("trace_once", {
        "record": "lab-rig free decay, 1 mrad noise, 200 Hz, " + ("2 s" if args.smoke else "5 s"),
        "start": {"k": 2.4, "c": 0.004}, "strategy": runs["once"][0]["strategy"],
        "same_estimate_every_run": same, "medians": summary, "runs": runs,
        "note": "jacobian_* lists: the single-shooting Jacobian program, then the "
                "multiple-shooting one (JAX's compile log, seconds)"}, args.smoke)
    for arm, s in summary.items():
        print(f"{arm:10s} first fit {s['first_fit_s']:.2f} s, tracing {s['all_tracing_s']:.2f} s,"
              f" Jacobians traced in {s['jacobian_trace_s']}")


if __name__ == "__main__":
    main()
