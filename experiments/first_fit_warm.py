"""The first fit of a record of a new length, in a process that has fitted the scene and
free set before: does it reuse the compiled programs?

In ONE process, lab-rig records (200 Hz, noise 1e-3 rad, free k, c, phi0, dphi0, from
k = 2.4, c = 0.004) of 5 s, then the same 5 s record again (the warm fit), then 6 s,
5.5 s and 7 s records (other noise seeds), each fitted twice in a row: its first fit, then
its warm fit. Per fit: wall and process CPU time, and how many programs JAX traced and
compiled (`jax.monitoring`'s compile events). The figure of merit is the ratio of a
record's first fit to its own warm fit (target: at most 1.3).

Record lengths are padded to buckets (`identify/segments.py`): 1001 and 1101 samples
(5 s, 5.5 s) share one, 1201 and 1401 (6 s, 7 s) the next, so the 6 s record is the first
of its bucket and compiles, and the 5.5 s and 7 s records are new lengths in fitted
buckets.

Run: `python experiments/first_fit_warm.py [--label NAME] [--out FILE]` (run it under
another checkout's `src` on `PYTHONPATH` for that checkout's figures; results are merged
into the file under `label`).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from _bench import RESULTS, machine, setup_jax

jax = setup_jax()

import crank_jax as cj  # noqa: E402

#: (record length s, noise seed), in the order they are fitted.
RECORDS = ((5.0, 1), (6.0, 2), (5.5, 3), (7.0, 4))

_EVENTS = {"/jax/core/compile/jaxpr_trace_duration": "traces",
           "/jax/core/compile/backend_compile_duration": "compiles"}
_COUNTS = {"traces": 0, "compiles": 0}


def _listen(event: str, duration: float, **_) -> None:
    name = _EVENTS.get(event)
    if name is not None:
        _COUNTS[name] += 1


def one_fit(start, data) -> dict:
    """Fit `data` from `start`: wall s, process CPU s, traces, compiles, values."""
    before = dict(_COUNTS)
    w, c = time.perf_counter(), time.process_time()
    res = cj.fit(start, data, progress=False)
    w, c = time.perf_counter() - w, time.process_time() - c
    return {"wall_s": round(w, 3), "cpu_s": round(c, 3),
            **{k: _COUNTS[k] - before[k] for k in _COUNTS},
            "converged": bool(res.converged), "strategy": res.strategy,
            "values": {k: float(v) for k, v in res.values.items()}}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", default="after")
    ap.add_argument("--out", type=Path, default=RESULTS / "first_fit_warm.json")
    args = ap.parse_args(argv)
    jax.monitoring.register_event_duration_secs_listener(_listen)
    lab = cj.load_scene("lab-rig")
    start = cj.Scene(lab.mech.replace(k=2.4, c=0.004), phi0=1.0, name="lab-rig-start")
    rows = []
    for t1, seed in RECORDS:
        data = cj.synthesize(lab, t1=t1, rate=200.0, noise_std=1e-3, seed=seed)
        first, warm = one_fit(start, data), one_fit(start, data)
        rows.append({"t1_s": t1, "samples": int(data.n), "first": first, "warm": warm,
                     "ratio_cpu": round(first["cpu_s"] / warm["cpu_s"], 2),
                     "ratio_wall": round(first["wall_s"] / warm["wall_s"], 2)})
        print(f"{t1:4.1f} s ({data.n} samples): first {first['wall_s']:6.2f} s wall "
              f"{first['cpu_s']:6.2f} s CPU ({first['compiles']} compiles); warm "
              f"{warm['wall_s']:5.2f} s wall {warm['cpu_s']:5.2f} s CPU "
              f"({warm['compiles']} compiles); ratio CPU {rows[-1]['ratio_cpu']}",
              flush=True)
    out = json.loads(args.out.read_text()) if args.out.exists() else {}
    out[args.label] = {"machine": machine(), "crank_jax": cj.__file__, "records": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(out, indent=1) + "\n")
    tmp.replace(args.out)
    return out


if __name__ == "__main__":
    main()
