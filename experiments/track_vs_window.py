"""The tracker's filter against the other estimator a user would build: a sliding-window
batch fit (`crank_jax.fit` of the same model on the last `W` seconds of the record, every
`S` seconds, free `k`, `c`, `phi0`, `dphi0`), on the independent-model records of
`track_independent.py` (the lab rig under its two-tone torque, 200 Hz, 60 s, made by
hand-written equations under scipy's DOP853): `k` 5% down at 30 s, and no change.

Compared side by side: `k`'s error at 29 s and at 59 s and whether its 95% interval covers
the truth there; when the change is found (the filter: its first alarm naming `k`; the
windows: the end of the first window whose `k` differs from the first window's by more
than the two-sided 5% z-test, Bonferroni-corrected over the windows, so that both tests
have a stated false-alarm rate over the record); false alarms; the compute per second of
record (warm: each is run once before it is timed).

    python experiments/track_vs_window.py [--window 5] [--stride 1] [--seed 0]
    python experiments/track_vs_window.py --table   # rewrite the docs table and stop

Writes experiments/results/track_vs_window.json and the table between
`<!-- BEGIN track-vs-window -->` and `<!-- END track-vs-window -->` in
docs/guide/tracking.md.
"""

from __future__ import annotations

import argparse
import json
import time

from _bench import RESULTS, machine, setup_jax, write_section

setup_jax()

import numpy as np  # noqa: E402
from scipy.stats import norm  # noqa: E402
from track_independent import LAB, PAGE, T_CHANGE, T, record  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.online import track  # noqa: E402
from crank_jax.runtime.io import atomic_write  # noqa: E402

BEGIN, END = "<!-- BEGIN track-vs-window -->", "<!-- END track-vs-window -->"
OUT = RESULTS / "track_vs_window.json"
FREE = ("k", "c", "phi0", "dphi0")
ALPHA = 0.05


def windows(window: float, stride: float) -> list[tuple[float, float]]:
    """(t0, t1) of each window, s: the last `window` seconds at every `stride`."""
    ends = np.arange(window, T + 1e-9, stride)
    return [(float(e - window), float(min(e, T - 1e-9))) for e in ends]


def by_windows(data, window: float, stride: float) -> dict:
    """k (and its standard error) of a fit of each window, with the time it took."""
    rows = []
    t_all = time.perf_counter()
    for t0, t1 in windows(window, stride):
        res = cj.fit(LAB, data, free=FREE, window=(t0, t1), progress=False, warn=False)
        rows.append({"t0": t0, "t1": t1, "k": res.values["k"], "se": res.stderr["k"],
                     "converged": bool(res.converged), "iterations": int(res.iterations)})
    return {"rows": rows, "seconds": time.perf_counter() - t_all}


def judge_windows(win: dict, change: float) -> dict:
    """The windows' figures, judged as the filter's are (see the module)."""
    k0 = float(LAB.mech.k)
    rows = win["rows"]
    z = norm.ppf(1 - ALPHA / 2 / len(rows))
    ref = rows[0]
    found = [r for r in rows[1:] if r["se"] and ref["se"]
             and abs(r["k"] - ref["k"]) > z * np.hypot(r["se"], ref["se"])]
    early = [r for r in found if r["t1"] < T_CHANGE] if change else found
    late = [r for r in found if r["t1"] >= T_CHANGE]

    def at(t):  # the last window that ends by t
        r = max((r for r in rows if r["t1"] <= t + 1e-9), key=lambda r: r["t1"])
        truth = k0 * (1 + change) if change and t >= T_CHANGE else k0
        se = r["se"] or float("nan")
        return {"error_pct": 100 * (r["k"] / truth - 1),
                "covers": bool(abs(r["k"] - truth) <= 1.96 * se)}

    return {"false_alarms": len(early),
            "delay_s": (late[0]["t1"] - T_CHANGE) if change and late else None,
            "at": {"29": at(29.0), "59": at(59.0)},
            "converged": sum(r["converged"] for r in rows), "windows": len(rows),
            "seconds_per_record_second": win["seconds"] / T}


def judge_filter(res, change: float, seconds: float) -> dict:
    k0 = float(LAB.mech.k)
    t = res.t
    truth = np.where((t >= T_CHANGE) & bool(change), k0 * (1 + change), k0)
    lo, hi = res.band("k")
    k_alarms = [a for a in res.alarms if "k" in a["parameters"]]
    early = [a for a in res.alarms if a["t"] < T_CHANGE] if change else list(res.alarms)

    def at(when):
        i = int(np.argmin(np.abs(t - when)))
        return {"error_pct": 100 * (res.values["k"][i] / truth[i] - 1),
                "covers": bool(lo[i] <= truth[i] <= hi[i])}

    late = [a for a in k_alarms if a["t"] >= T_CHANGE]
    return {"false_alarms": len(early),
            "delay_s": (late[0]["t"] - T_CHANGE) if change and late else None,
            "at": {"29": at(29.0), "59": at(59.0)},
            "seconds_per_record_second": seconds / T}


def run(window: float, stride: float, seed: int) -> dict:
    out = []
    for label, change in (("k -5% at 30 s", -0.05), ("no change", 0.0)):
        data = record("k" if change else None, change, "phi", seed)
        track(LAB, data, free=("k", "c"), progress=False)  # warm
        t0 = time.perf_counter()
        res = track(LAB, data, free=("k", "c"), progress=False)
        filt = judge_filter(res, change, time.perf_counter() - t0)
        by_windows(data, window, stride * 20)  # warm: the same programs, fewer windows
        win = judge_windows(by_windows(data, window, stride), change)
        out.append({"case": label, "filter": filt, "windows": win})
        print(json.dumps(out[-1]), flush=True)
    return {"machine": machine(), "window_s": window, "stride_s": stride, "seed": seed,
            "rows": out}


def table(doc: dict) -> str:
    m = doc["machine"]
    lines = [
        f"`experiments/track_vs_window.py` ({m['date']}, {m['cpu']}; a shared machine: "
        f"times are rough). Windows of {doc['window_s']:g} s every {doc['stride_s']:g} s, "
        "each a default `crank_jax.fit` (free k, c, phi0, dphi0); the filter a default "
        "`track` (free k, c). Delay: from the change to the alarm (filter) or to the end of "
        "the first window whose k differs (windows).", "",
        "| record | estimator | k error at 29 s / 59 s | 95% covers at 29 / 59 s | "
        "change found after | false alarms | compute per second of record |",
        "|---|---|---|---|---|---|---|"]
    for row in doc["rows"]:
        for name, key in (("filter (EKF)", "filter"), ("sliding windows", "windows")):
            r = row[key]
            a, b = r["at"]["29"], r["at"]["59"]
            delay = ("-" if row["case"] == "no change" else
                     "not found" if r["delay_s"] is None else f"{r['delay_s']:.2f} s")
            lines.append(
                f"| {row['case']} | {name} | {a['error_pct']:+.2f}% / {b['error_pct']:+.2f}% "
                f"| {'yes' if a['covers'] else 'no'} / {'yes' if b['covers'] else 'no'} "
                f"| {delay} | {r['false_alarms']} "
                f"| {1e3 * r['seconds_per_record_second']:.1f} ms |")
    return "\n".join(lines)


def write_table(doc: dict) -> None:
    write_section(PAGE, BEGIN, END, table(doc), "sliding-window")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--window", type=float, default=5.0)
    ap.add_argument("--stride", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--table", action="store_true")
    a = ap.parse_args()
    if a.table:
        write_table(json.loads(OUT.read_text()))
        return
    doc = run(a.window, a.stride, a.seed)
    with atomic_write(OUT) as f:
        f.write(json.dumps(doc, indent=1))
    write_table(doc)


if __name__ == "__main__":
    main()
