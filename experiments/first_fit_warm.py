"""The first fit of a record of a new length, in a process that has fitted the scene and
free set before: does it reuse the compiled programs?

In ONE process, lab-rig records (200 Hz, noise 1e-3 rad, free k, c, phi0, dphi0, from
k = 2.4, c = 0.004) of 5 s, 6 s, 5.5 s, 7 s, then 4.8, 5.75, 6.5, 8, 10, 12 and 16 s
(other noise seeds), each fitted once (its first fit) and then `--repeats` times more
(its warm fit: their median by CPU time). Per fit: wall and process CPU time, and how many
programs JAX traced and compiled (`jax.monitoring`'s compile events). The figure of merit
is the ratio of a record's first fit to its own warm fit (target: at most 1.3).

The rows are padded to a ladder of their own length (`identify/segments.py`,
`row_bucket`: 96, ..., 1536, 3072, 6144 samples) and the segments to a row count of their
class (the next power of two). A segment holds about two periods (62-93 samples here,
whatever the record's length), so every record's segments take rows of 96; 4.8-7 s
records (961-1401 samples, 12 or 16 segments) share one single-shooting row (1536) and 16
rows, 8-12 s (24 or 32 segments) the next (3072, 32 rows), 16 s (48 segments) the next.

Run: `python experiments/first_fit_warm.py [--label NAME] [--out FILE]` (run it under
another checkout's `src` on `PYTHONPATH` for that checkout's figures; results are merged
into the file under `label`); `--docs` then writes the table of the labels `before` and
`after` to docs/benchmarks/performance.md (between `<!-- BEGIN buckets -->` and
`<!-- END buckets -->`).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _bench import RESULTS, ROOT, machine, setup_jax, write_json

jax = setup_jax()

import crank_jax as cj  # noqa: E402

#: (record length s, noise seed), in the order they are fitted.
RECORDS = ((5.0, 1), (6.0, 2), (5.5, 3), (7.0, 4), (4.8, 5), (5.75, 6), (6.5, 7), (8.0, 8),
           (10.0, 9), (12.0, 10), (16.0, 11))

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


#: The CLI runs: (record length s, noise seed), fresh processes sharing one program store.
CLI_RUNS = ((5.0, 1), (5.0, 1), (6.0, 2), (6.0, 2))


def cli_runs(start) -> list[dict]:
    """`crank-jax fit` in fresh processes with one program store: the 5 s record cold,
    warm, then the 6 s record (a new length, 16 segments where the 5 s one has 12) first
    and again. Wall and
    CPU time (the child's user + system) per run."""
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        scene = tmp / "start.toml"
        scene.write_text(cj.scene_to_toml(start))
        env = dict(os.environ, CRANK_JAX_CACHE_DIR=str(tmp / "cache"))
        env.pop("CRANK_JAX_NO_CACHE", None)
        for t1, seed in CLI_RUNS:
            rec = tmp / f"rec{t1}.csv"
            if not rec.exists():
                cj.save_data(cj.synthesize(cj.load_scene("lab-rig"), t1=t1, rate=200.0,
                                           noise_std=1e-3, seed=seed), rec)
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            w = time.perf_counter()
            subprocess.run([sys.executable, "-m", "crank_jax", "fit", str(rec), str(scene),
                            "--quiet", "--out", str(tmp / "fit.json")], env=env, check=True,
                           capture_output=True)
            w = time.perf_counter() - w
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
            out.append({"t1_s": t1, "wall_s": round(w, 3), "cpu_s": round(cpu, 3)})
            print(f"CLI {t1} s: {w:.2f} s wall, {cpu:.2f} s CPU", flush=True)
    return out


def _cell(row: dict, fit: str) -> str:
    f = row[fit]
    return f"{f['cpu_s']:.2f} s ({f['wall_s']:.2f} s), {f['compiles']}"


def table(results: dict) -> str:
    """The docs section: per record, the first and warm fit before and after, the CLI
    runs, and how far the estimates moved."""
    m = results["after"]["machine"]
    lines = [
        "## Records of other lengths", "",
        f"`experiments/first_fit_warm.py` ({m['date']}, {m['cores']} cores, {m['cpu']}; "
        "a shared machine, other jobs running: wall times are rough, process CPU times "
        "steadier; results in `experiments/results/first_fit_warm.json`). In one process, "
        "lab-rig records at 200 Hz (free k, c, phi0, dphi0, from k = 2.4, c = 0.004), in "
        "this order, each fitted once and then 5 times more, warm (their median by CPU "
        "time). Cells: process CPU time (wall time), programs compiled. `before`: the code "
        "whose rows were padded to the record's bucket (the main branch at the time), run "
        "just before `after`.", "",
        "| record | before: first fit | before: warm | before: ratio | after: first fit "
        "| after: warm | after: ratio (target <= 1.3) |",
        "|---|---|---|---|---|---|---|"]
    for b, a in zip(results["before"]["records"], results["after"]["records"]):
        lines.append(f"| {a['t1_s']} s ({a['samples']} samples, {_segments(a)}) | "
                     f"{_cell(b, 'first')} | {_cell(b, 'warm')} | {b['ratio_cpu']} | "
                     f"{_cell(a, 'first')} | {_cell(a, 'warm')} | {a['ratio_cpu']} |")
    lines += ["", NOTE, "", _warm_cost(), "", _moved(results)]
    if results["before"].get("cli") and results["after"].get("cli"):
        lines += ["", CLI_NOTE, "", "| `crank-jax fit` | before | after |", "|---|---|---|"]
        names = ("5 s record, empty store", "5 s record, warm",
                 "6 s record (a new length), first", "6 s record, warm")
        for name, b, a in zip(names, results["before"]["cli"]["runs"],
                              results["after"]["cli"]["runs"]):
            lines.append(f"| {name} | {b['cpu_s']:.2f} s ({b['wall_s']:.2f} s) | "
                         f"{a['cpu_s']:.2f} s ({a['wall_s']:.2f} s) |")
    return "\n".join(lines)


def _segments(row: dict) -> str:
    strategy = row["first"]["strategy"]
    return strategy[strategy.find("(") + 1:strategy.find(")")] if "(" in strategy else "1"


def _moved(results: dict) -> str:
    """How far each estimate moved from before to after, relative, over the records."""
    worst, absolute = {}, {}
    for b, a in zip(results["before"]["records"], results["after"]["records"]):
        for k, v in a["first"]["values"].items():
            u = b["first"]["values"][k]
            worst[k] = max(worst.get(k, 0.0), abs(v - u) / max(abs(u), 1e-300))
            absolute[k] = max(absolute.get(k, 0.0), abs(v - u))
    return ("The estimates after against before, largest difference over the records, "
            "relative (absolute, SI): " + ", ".join(
                f"{k} {v:.1e} ({absolute[k]:.1e})" for k, v in worst.items())
            + "; the noise's standard errors are orders of magnitude larger.")


NOTE = (
    "The ratio is CPU time, a record's first fit over its warm fit. The first 5 s record "
    "compiles everything. Before, the 6 s record was the first of the next bucket (1201 "
    "samples padded to 1728 where 1001 pad to 1152) and compiled three programs: the "
    "single-shooting Jacobian (one row of the bucket), the motion start's equation of "
    "motion (its rows padded to a bucket, in the single-shooting problem) and the "
    "multiple-shooting Jacobian (rows as long as the bucket over the class's smallest "
    "segment count). Now a row's length comes from a ladder of its own length "
    "(`identify/segments.py`, `row_bucket`: 3 * 2^k, one size per doubling), of the "
    "longest segment for a multiple-shooting row, of the record for the single-shooting "
    "row and the equation-of-motion rows, and the rows' count from the class of the segment "
    "count (the next power of two). A segment holds about two periods (the segment count "
    "follows the record's duration), 62-93 samples here whatever the record's length, so "
    "every record's segments take rows of 96 samples; the 4.8-7 s records (961-1401 "
    "samples, 12 or 16 segments) share one single-shooting row of 1536 and 16 segment rows, "
    "and the 6 s record compiles nothing. What still compiles, and why: the 8 s record has "
    "24 segments, a new class (32 rows), and 1601 samples, past the single-shooting row of "
    "1536 (3 programs); the 10 and 12 s records then share all of them (24 and 32 "
    "segments; 2001 and 2401 samples, in 3072). The 16 s record has 48 segments (64 rows) "
    "and 3201 samples (past 3072): 3 programs. (It compiled a fourth, its single-shooting "
    "Jacobian at the larger step budget, while padded save times took steps of their own: "
    "its start solve counted 1769 steps in a row of 6144 against 944 unpadded, past the "
    "1638 that raise the budget, a static of the programs; padding now repeats a row's "
    "last save time and takes no step.) Longer records raise it themselves (a start "
    "solve of more than 1638 steps: roughly 25-30 s of this rig) and compile once at "
    "that level. At 200 Hz the single-shooting ladder's edges (7.7 s, 15.4 s) lie near the "
    "lab rig's segment classes' (7.3 s, 14.7 s), so a record across one pays once for "
    "both. Coarser classes were measured and not taken: the 5 s record's 12 segments in 32 "
    "rows instead of 16 cost 1.45-1.8x per multiple-shooting Jacobian (median CPU 0.0124 "
    "and 0.0126 s in 16 rows, 0.0225 and 0.0180 s in 32): the rows are solved side by side "
    "under a `vmap`, and an inactive row steps along with the others.")


def _warm_cost() -> str:
    """The warm fit's cost of the padding, from experiments/results/warm_padding_cost.json."""
    path = RESULTS / "warm_padding_cost.json"
    if not path.exists():
        return ""
    res = json.loads(path.read_text())
    cells = []
    for t in res["records"]:
        runs = {lab: [r["median_cpu_s"][str(t)] for r in res["runs"] if r["label"] == lab]
                for lab in ("before", "after")}
        ratio = statistics.median(runs["after"]) / statistics.median(runs["before"])
        cells.append(f"{t:g} s: {', '.join(f'{x:.3f}' for x in runs['before'])} s before, "
                     f"{', '.join(f'{x:.3f}' for x in runs['after'])} s after "
                     f"({ratio:.2f}x)")
    return (
        "The warm fit's cost of the padding (`experiments/warm_padding_cost.py`, "
        f"{res['machine']['date']}, results in `experiments/results/warm_padding_cost.json`: "
        f"the warm fit's median CPU time over {res.get('repeats', 11)} fits in a fresh "
        "process, the two codes alternated): " + "; ".join(cells) + ". `before`: padded "
        "save times a few nanoseconds past a row's end. The `dopri8-adaptive` solver writes "
        "save times in windows of 4 and shortens a step to its window's end, so every 4 of "
        "them cost one (tiny) step attempt, and a record low in its rung, whose "
        "single-shooting row is mostly padding (8 s: 1601 samples in 3072; 16 s: 3201 in "
        "6144), paid most. `after`: the padding repeats a row's last save time; the solver "
        "stops at the first and the repeats take its value (`solve.adaptive.solve_adaptive`), "
        "so a padded row takes exactly the steps of the unpadded one, and its residuals are "
        "the same to the bit (`tests/test_warm_lengths.py`).")


CLI_NOTE = (
    "The same in fresh processes (`crank-jax fit`, one program store shared by the runs; "
    "CPU time of the process (wall time)): the stored programs' key holds the shapes, so "
    "a record of a fitted shape loads them; before, the 6 s record compiled.")


def write_docs(results: dict) -> None:
    page = ROOT / "docs" / "benchmarks" / "performance.md"
    text = page.read_text()
    begin, end = "<!-- BEGIN buckets -->", "<!-- END buckets -->"
    block = f"{begin}\n{table(results)}\n{end}"
    if begin in text:
        text = re.sub(re.escape(begin) + ".*?" + re.escape(end), lambda _: block, text,
                      flags=re.S)
    else:
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    page.write_text(text)


def in_process(start, repeats: int) -> list[dict]:
    """The records of [`RECORDS`][] fitted in this process, first and warm."""
    jax.monitoring.register_event_duration_secs_listener(_listen)
    lab = cj.load_scene("lab-rig")
    rows = []
    for t1, seed in RECORDS:
        data = cj.synthesize(lab, t1=t1, rate=200.0, noise_std=1e-3, seed=seed)
        first = one_fit(start, data)
        warms = [one_fit(start, data) for _ in range(repeats)]
        warm = dict(sorted(warms, key=lambda f: f["cpu_s"])[len(warms) // 2],
                    cpu_all_s=[f["cpu_s"] for f in warms])
        rows.append({"t1_s": t1, "samples": int(data.n), "first": first, "warm": warm,
                     "ratio_cpu": round(first["cpu_s"] / warm["cpu_s"], 2),
                     "ratio_wall": round(first["wall_s"] / warm["wall_s"], 2)})
        print(f"{t1:4.1f} s ({data.n} samples): first {first['wall_s']:6.2f} s wall "
              f"{first['cpu_s']:6.2f} s CPU ({first['compiles']} compiles); warm "
              f"{warm['wall_s']:5.2f} s wall {warm['cpu_s']:5.2f} s CPU "
              f"({warm['compiles']} compiles); ratio CPU {rows[-1]['ratio_cpu']}",
              flush=True)
    return rows


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", default="after")
    ap.add_argument("--out", type=Path, default=RESULTS / "first_fit_warm.json")
    ap.add_argument("--docs", action="store_true", help="write the docs table and stop")
    ap.add_argument("--repeats", type=int, default=5, help="warm fits a record (median)")
    ap.add_argument("--cli", action="store_true",
                    help="time `crank-jax fit` runs instead (kept beside the label's records)")
    args = ap.parse_args(argv)
    out = json.loads(args.out.read_text()) if args.out.exists() else {}
    if args.docs:
        write_docs(out)
        return out
    lab = cj.load_scene("lab-rig")
    start = cj.Scene(lab.mech.replace(k=2.4, c=0.004), phi0=1.0, name="lab-rig-start")
    entry = out.setdefault(args.label, {})
    if args.cli:
        entry["cli"] = {"machine": machine(), "runs": cli_runs(start)}
    else:
        entry.update(machine=machine(), crank_jax=cj.__file__,
                     records=in_process(start, args.repeats))
    write_json(args.out, out)
    return out


if __name__ == "__main__":
    main()
