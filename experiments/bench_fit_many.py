"""Many independent fits: `fit_many` (one vmap-ed Levenberg-Marquardt program per bucket)
against the peer a user would write, scipy `least_squares` over `solve_ivp` DOP853 with a
numba-compiled right-hand side, looped over the records in one process.

    python experiments/bench_fit_many.py              # 100 lab-rig records
    python experiments/bench_fit_many.py --n 1000     # the issue's size
    python experiments/bench_fit_many.py --rig rotating --peer-n 6   # 100 rotating-rig
                                                      # records, two channels (fleet_rot.py)
    python experiments/bench_fit_many.py --table      # rewrite the docs table and stop

Each record: the lab rig with its own k, c (+-10%) and release angle (+-0.2 rad), 5 s at
200 Hz, noise 1e-3 rad; free k, c, phi0, dphi0, started from the nominal scene. Writes
experiments/results/bench_fit_many.json (`--rig rotating`: bench_fit_many_rot.json;
`--smoke`: .smoke.json); `--table` rewrites the
section between `<!-- BEGIN fleet -->` and `<!-- END fleet -->` in
docs/benchmarks/performance.md.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
from _bench import RESULTS, ROOT, machine, setup_jax, write_section

jax = setup_jax()

from peers import HAVE_NUMBA  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.fleet import fit_many  # noqa: E402
from crank_jax.fleet.batch_lm import BATCHES, largest_batch  # noqa: E402

PAGE = ROOT / "docs" / "benchmarks" / "performance.md"
BEGIN, END = "<!-- BEGIN fleet -->", "<!-- END fleet -->"
FREE = ("k", "c", "phi0", "dphi0")
RTOL, ATOL = 1e-8, 1e-10


def records(n: int, seed: int = 0, t1: float = 5.0, rate: float = 200.0):
    """`n` lab-rig records, each its own unit: (Data, its true k, c, phi0)."""
    scene = cj.load_scene("lab-rig")
    rng = np.random.default_rng(seed)
    ts = np.arange(int(round(t1 * rate)) + 1) / rate
    out = []
    for _ in range(n):
        k, c = 2.0 * (1 + 0.1 * rng.uniform(-1, 1)), 0.002 * (1 + 0.1 * rng.uniform(-1, 1))
        phi0 = 1.0 + 0.2 * rng.uniform(-1, 1)
        tr = cj.simulate(scene.mech.replace(k=k, c=c), phi0, 0.0, ts, rtol=RTOL, atol=ATOL)
        phi = np.asarray(tr.phi) + rng.normal(0.0, 1e-3, ts.shape)
        out.append((cj.Data(ts=ts, phi=phi), (k, c, phi0)))
    return scene, out


def peer_fit(scene, data):
    """The peer: scipy least_squares (LM, finite-difference Jacobian) over solve_ivp
    DOP853 with a numba right-hand side. Returns the estimates (k, c, phi0, dphi0)."""
    from peers import PARAM_ORDER, params_of
    from scipy.integrate import solve_ivp
    from scipy.optimize import least_squares

    base = list(params_of(scene.mech))
    ik, ic = PARAM_ORDER.index("k"), PARAM_ORDER.index("c")
    ts, phi = np.asarray(data.ts), np.asarray(data.phi)

    def residuals(x):
        p = base.copy()
        p[ik], p[ic] = x[0], x[1]
        sol = solve_ivp(_RHS, (ts[0], ts[-1]), [x[2], x[3]], method="DOP853", t_eval=ts,
                        rtol=RTOL, atol=ATOL, args=(tuple(p),))
        return sol.y[0] - phi if sol.success else np.full(ts.shape, 10.0)

    x0 = [float(scene.mech.k), float(scene.mech.c), float(phi[0]), 0.0]
    return least_squares(residuals, x0, method="lm", x_scale="jac").x


def _numba_rhs():
    """The peer's right-hand side, compiled by numba (plain Python where numba is missing:
    the results then say so)."""
    from peers import HAVE_NUMBA, acceleration_scalar

    if not HAVE_NUMBA:
        return lambda t, y, p: np.array([y[1], acceleration_scalar(y[0], y[1], p)])
    import numba

    acc = numba.njit(cache=True)(acceleration_scalar)

    @numba.njit(cache=True)
    def rhs(t, y, p):
        return np.array([y[1], acc(y[0], y[1], p)])

    return rhs


def _timings(fleet, n, first, wall, cpu, peer_n, peer_wall, peer_cpu) -> dict:
    """The fields both rigs' results share: the fleet's times and counts, the peer's."""
    return {"first_call_s": first, "warm_s": wall, "warm_cpu_s": cpu,
            "per_record_ms": 1e3 * wall / n,
            "fleet_records": int(sum(a is None for a in fleet.alone)),
            "converged": int(sum(r.converged for r in fleet)),
            "iterations_median": float(np.median([r.iterations for r in fleet])),
            "peer": "scipy least_squares(lm) over solve_ivp DOP853, "
                    + ("numba rhs" if HAVE_NUMBA else "plain Python rhs (numba missing)"),
            "peer_records": peer_n, "peer_per_record_ms": 1e3 * peer_wall,
            "throughput_ratio": peer_wall / (wall / n),
            "peer_per_record_cpu_ms": 1e3 * peer_cpu,
            "throughput_ratio_cpu": peer_cpu / (cpu / n)}


def single_fits(scene, data, fleet, free, **kw) -> dict:
    """The issue's criterion: each fleet estimate against its record's single fit
    (`cj.fit`, the same options), over the single fit's standard error; the first
    `len(data)` records."""
    diff = []
    for d, res in zip(data, fleet):
        one = cj.fit(scene, d, free, progress=False, warn=False, **kw)
        diff.append([abs(res.values[k] - one.values[k]) / one.stderr[k] for k in free])
    diff = np.asarray(diff)
    return {"single_records": len(data), "single_max_diff_over_stderr": float(diff.max()),
            "single_max_diff_by_param": dict(zip(free, diff.max(axis=0).tolist()))}


def run(n: int, peer_n: int, smoke: bool, rig: str = "lab") -> dict:
    if rig == "rotating":
        return run_rot(n, peer_n, smoke)
    scene, recs = records(n)
    data = [d for d, _ in recs]
    t = time.perf_counter()
    # The same call first: it compiles (or loads) the programs of every batch the timed
    # call runs (the records' groups, by shooting, cut into batches of largest_batch()
    # and the rest, each padded to a size of BATCHES), so the timed call compiles nothing.
    fit_many(scene, data, FREE, progress=False, warn=False)
    first = time.perf_counter() - t
    t, c = time.perf_counter(), time.process_time()
    fleet = fit_many(scene, data, FREE, progress=False, warn=False)
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    est = np.array([[r.values[k] for k in FREE] for r in fleet])
    se = np.array([[r.stderr[k] or math.nan for k in FREE] for r in fleet])
    truth = np.array([[k, c_, p0] for _, (k, c_, p0) in recs])
    z = (est[:, :3] - truth) / se[:, :3]
    global _RHS
    _RHS = _numba_rhs()
    peer_fit(scene, data[0])  # numba's compile
    t, c = time.perf_counter(), time.process_time()
    peer = np.array([peer_fit(scene, d) for d in data[:peer_n]])
    peer_wall = (time.perf_counter() - t) / peer_n
    peer_cpu = (time.process_time() - c) / peer_n
    diff = np.abs(peer - est[:peer_n]) / se[:peer_n]
    return {"smoke": smoke, "machine": machine(), "n": n, "samples": 1001,
            "free": list(FREE), **_timings(fleet, n, first, wall, cpu, peer_n, peer_wall,
                                            peer_cpu),
            "z_truth_rms": float(np.sqrt(np.nanmean(z**2))),
            **single_fits(scene, data[:peer_n], fleet, FREE),
            "peer_max_diff_over_stderr": float(np.nanmax(diff)),
            "batch_sizes": [b for b in BATCHES if b <= largest_batch()],
            "shooting": {s: int(sum(r.strategy == s for r in fleet))
                         for s in sorted({r.strategy for r in fleet})}}


def run_rot(n: int, peer_n: int, smoke: bool) -> dict:
    """The rotating rig with two channels (experiments/fleet_rot.py), both channels weighted
    by their known noise in the fleet and in the peer."""
    import fleet_rot as fr

    scene, recs = fr.records(n)
    data = [d for d, _ in recs]
    kw = dict(sigma=dict(fr.NOISE), progress=False, warn=False)
    t = time.perf_counter()
    fit_many(scene, data, fr.FREE, **kw)  # the same call first: it compiles
    first = time.perf_counter() - t
    t, c = time.perf_counter(), time.process_time()
    fleet = fit_many(scene, data, fr.FREE, **kw)
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    est = np.array([[r.values[k] for k in fr.FREE] for r in fleet])
    se = np.array([[r.stderr[k] or math.nan for k in fr.FREE] for r in fleet])
    truth = np.array([t_ for _, t_ in recs])
    z = (est[:, :2] - truth[:, :2]) / se[:, :2]
    rhs = fr.numba_rhs()
    fr.peer_fit(rhs, scene, data[0])  # numba's compile
    t, c = time.perf_counter(), time.process_time()
    peer = [fr.peer_fit(rhs, scene, d) for d in data[:peer_n]]
    peer_wall = (time.perf_counter() - t) / peer_n
    peer_cpu = (time.process_time() - c) / peer_n
    # The peer again, started at the fleet's estimate: does it stay there (the same
    # minimum, within a twentieth of a standard error)? It also gives the fleet
    # estimate's cost under the peer's model (the peer's cost at its start).
    again = [fr.peer_fit(rhs, scene, d, list(x)) for d, x in zip(data, est[:peer_n])]
    diff = np.abs(np.array([p[0] for p in peer]) - est[:peer_n]) / se[:peer_n]
    diff_again = np.abs(np.array([p[0] for p in again]) - est[:peer_n]) / se[:peer_n]
    same = diff.max(axis=1) <= 0.05
    return {"smoke": smoke, "rig": "rotating", "machine": machine(), "n": n,
            "samples": int(data[0].ts.size), "channels": list(fr.NOISE),
            "noise": dict(fr.NOISE), "free": list(fr.FREE),
            **_timings(fleet, n, first, wall, cpu, peer_n, peer_wall, peer_cpu),
            "alone_reasons": sorted({a for a in fleet.alone if a is not None}),
            "z_truth_rms_tau0_c": float(np.sqrt(np.nanmean(z**2))),
            **single_fits(scene, data[:peer_n], fleet, fr.FREE, sigma=dict(fr.NOISE)),
            "peer_tolerances": [fr.PEER_RTOL, fr.PEER_ATOL], "diff_step": fr.DIFF_STEP,
            "peer_start": "nominal tau0, c; phi0, dphi0 from the record's first 5 samples",
            "peer_same_minimum": int(same.sum()),
            "peer_worse_minimum": int(sum(p[1] > a[2] + 1.0 for p, a in zip(peer, again))),
            "peer_cost": [p[1] for p in peer], "fleet_cost_under_peer": [a[2] for a in again],
            "peer_max_diff_over_stderr": float(np.nanmax(diff)),
            "peer_max_diff_same_minimum": (float(np.nanmax(diff[same])) if same.any()
                                           else None),
            "peer_from_fleet_max_diff_over_stderr": float(np.nanmax(diff_again)),
            "peer_from_fleet_max_diff_by_param": dict(zip(
                fr.FREE, np.nanmax(diff_again, axis=0).tolist())),
            "shooting": {s: int(sum(r.strategy == s for r in fleet))
                         for s in sorted({r.strategy for r in fleet})}}


def cli(n: int) -> dict:
    """`crank-jax fit REC1.csv ... lab-rig --each --out DIR` on `n` records, in a fresh
    process twice (the second warm: its programs stored by the first); wall and CPU time
    of the whole process, import included."""
    import resource
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    _, recs = records(n)
    with tempfile.TemporaryDirectory() as tmp:
        files = []
        for i, (d, _) in enumerate(recs):
            files.append(str(Path(tmp) / f"rec{i:04d}.csv"))
            cj.save_data(d, files[-1])
        cmd = [sys.executable, "-m", "crank_jax", "fit", *files, "lab-rig", "--each",
               "--out", str(Path(tmp) / "out"), "--quiet"]
        times = []
        for _ in range(2):
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            t = time.perf_counter()
            subprocess.run(cmd, check=True, capture_output=True)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            times.append((time.perf_counter() - t, (after.ru_utime + after.ru_stime)
                          - (before.ru_utime + before.ru_stime)))
    return {"cli_records": n, "cli_first_s": times[0][0], "cli_warm_s": times[1][0],
            "cli_warm_cpu_s": times[1][1]}


def table(doc: dict, more: list[dict] = ()) -> str:
    """The docs table of a 100-record run `doc`, with a row for each larger run of `more`
    (`--n N`, results in bench_fit_many_nN.json)."""
    m = doc["machine"]
    n = doc["n"]
    return "\n".join([
        "## Many fits at once", "",
        f"`experiments/bench_fit_many.py --n {n}` ({m['date']}, {m['cores']} cores, "
        f"{m['cpu']}; a shared machine, other jobs running: wall times are rough; results in "
        "`experiments/results/bench_fit_many.json`). Lab-rig records, each its own unit "
        "(k, c +-10%, release +-0.2 rad), 5 s at 200 Hz, noise 1e-3 rad, free k, c, phi0, "
        "dphi0, fitted by `crank_jax.fleet.fit_many` (one vmap-ed LM program) against "
        f"the peer: {doc['peer']}, looped over {doc['peer_records']} of the records. Where "
        "the time went, 2026-12-02: the fleet's LM now starts undamped, with the "
        "Gauss-Newton step, and damps after a rejected step (Nielsen's start, 1e-3 of the "
        "scaled normal matrix's diagonal cut by at most 3 an accepted step, throttled the "
        "weak directions: 12 iterations a record at the median on the rotating rig below, "
        "now 4); `fit_many` plans the next records on the calling thread while a worker "
        "fits the batches planned (planning is host work, about a quarter of the time), "
        "in batches of at most 16 on the CPU. Before these, on this machine: 100 "
        "lab-rig records in 6.18 s (28.4x the peer), 1000 in 59.0 s, the command on 100 "
        "in 9.4 s, the rotating rig at 14.4x.", "",
        "| what | figure | target |", "|---|---|---|",
        f"| {n} records, warm (wall) | {doc['warm_s']:.3g} s ({doc['per_record_ms']:.3g} ms "
        f"a record; {doc['warm_cpu_s']:.3g} s of CPU) | 1000 records <= 60 s |",
        f"| the peer, per record | {doc['peer_per_record_ms']:.3g} ms "
        f"({doc.get('peer_per_record_cpu_ms', math.nan):.3g} ms of CPU) | |",
        f"| throughput, ours over the peer's | {doc['throughput_ratio']:.3g}x (wall), "
        f"{doc.get('throughput_ratio_cpu', math.nan):.3g}x (CPU time) | >= 20x |",
        *[f"| {d['n']} records, warm (wall; {d['machine']['date']}) | {d['warm_s']:.3g} s "
          f"({d['per_record_ms']:.3g} ms a record; {d['warm_cpu_s']:.3g} s of CPU; "
          f"{d['throughput_ratio']:.3g}x the peer's wall throughput, "
          f"{d['throughput_ratio_cpu']:.3g}x CPU, the peer on {d['peer_records']} records) "
          f"| <= 60 s, >= 20x |" for d in more],
        f"| records fitted by the fleet / converged | {doc['fleet_records']} / "
        f"{doc['converged']} of {n} | |",
        *_single_row(doc),
        f"| largest difference from the peer's estimate | "
        f"{doc['peer_max_diff_over_stderr']:.2g} standard errors (the peer stops at its own "
        "test, on a finite-difference Jacobian) | |",
        f"| the same call before it (compiling its programs) | "
        f"{doc['first_call_s']:.3g} s | |"] + ([
        f"| `crank-jax fit` of {doc['cli_records']} records `--each`, warm, the process "
        f"included | {doc['cli_warm_s']:.3g} s wall ({doc['cli_warm_cpu_s']:.3g} s of CPU; "
        f"the run before it: {doc['cli_first_s']:.3g} s) | 100 records <= 10 s |"]
        if "cli_warm_s" in doc else []) + ([
        "| the records' shooting | " + ", ".join(f"{v} {k}" for k, v in
                                               doc["shooting"].items()) + " | |"]
        if "shooting" in doc else []))


def _single_row(doc: dict) -> list[str]:
    """The row of the issue's criterion: the fleet against each record's single fit."""
    if "single_max_diff_over_stderr" not in doc:
        return []
    return [f"| largest difference from the record's single fit (`cj.fit`, "
            f"{doc['single_records']} records) | {doc['single_max_diff_over_stderr']:.2g} "
            "standard errors | <= 0.05 |"]


def table_rot(doc: dict) -> str:
    """The docs sub-table of a rotating-rig run `doc` (bench_fit_many_rot.json)."""
    m, n = doc["machine"], doc["n"]
    alone = doc["n"] - doc["fleet_records"]
    gap = [p - f for p, f in zip(doc["peer_cost"], doc["fleet_cost_under_peer"])]
    return "\n".join([
        "### The rotating rig, two channels", "",
        f"`experiments/bench_fit_many.py --rig rotating --n {n} --peer-n "
        f"{doc['peer_records']}` ({m['date']}, {m['cores']} cores, {m['cpu']}; a shared "
        "machine, other jobs running: wall times are rough, CPU times beside them; results "
        "in `experiments/results/bench_fit_many_rot.json`). The rotating rig "
        "of `misfit_bench.py` (`experiments/fleet_rot.py`: offset slider-crank, tilted "
        "mount, constant torque tau0 against damping c), each record its own unit (tau0, c "
        "+-5%, any start angle, 3-7 rad/s), 3 s at 200 Hz (about nine turns), two channels: "
        "crank angle `phi` (noise 2e-3 rad) and slide position `x_s` (5e-5 m), both "
        "weighted by their noise; free tau0, c, phi0, dphi0 from the nominal scene. The "
        f"peer: {doc['peer']}, both channels' residuals over their noise, a "
        "finite-difference step of 1e-6 (the default, 1.5e-8, is below the ODE's error and "
        "left it in false minima) and rtol 1e-10, atol 1e-12 (at the fleet's 1e-8 its "
        "Jacobian was noisy enough to stop it up to a standard error short of the minimum, "
        "at about the same time per fit), started from the nominal tau0, c and the record's first "
        f"samples, looped over {doc['peer_records']} of the records.", "",
        "| what | figure | target |", "|---|---|---|",
        f"| {n} records, warm (wall) | {doc['warm_s']:.3g} s ({doc['per_record_ms']:.3g} ms "
        f"a record; {doc['warm_cpu_s']:.3g} s of CPU) | |",
        f"| the peer, per record | {doc['peer_per_record_ms']:.3g} ms "
        f"({doc['peer_per_record_cpu_ms']:.3g} ms of CPU) | |",
        f"| throughput, ours over the peer's | {doc['throughput_ratio']:.3g}x (wall), "
        f"{doc['throughput_ratio_cpu']:.3g}x (CPU time) | >= 20x |",
        f"| records fitted by the fleet / converged | {doc['fleet_records']} / "
        f"{doc['converged']} of {n}" + (f" ({alone} by `fit`: "
                                        + "; ".join(doc["alone_reasons"]) + ")"
                                        if alone else "") + " | |",
        f"| the peer's fits at the fleet's minimum (within 0.05 standard errors) | "
        f"{doc['peer_same_minimum']} of {doc['peer_records']} (in a worse minimum: "
        f"{doc['peer_worse_minimum']}); stopped above the fleet estimate's cost under the "
        f"peer's own model: {sum(g > 0 for g in gap)} of {doc['peer_records']} (by at most "
        f"{max(gap):.2g} "
        "in half the sum of squares) | |",
        *_single_row(doc),
        f"| largest difference from the peer's estimate | "
        f"{doc['peer_max_diff_over_stderr']:.2g} standard errors; the peer restarted at the "
        f"fleet's estimate: {doc['peer_from_fleet_max_diff_over_stderr']:.2g} | |",
        f"| the same call before it (compiling its programs) | "
        f"{doc['first_call_s']:.3g} s | |",
        "| the records' shooting | " + ", ".join(f"{v} {k}" for k, v in
                                               doc["shooting"].items()) + " | |"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100, help="records (100)")
    ap.add_argument("--peer-n", type=int, default=10, help="records the peer fits (10)")
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--rig", choices=("lab", "rotating"), default="lab",
                    help="lab (default) or rotating: the rotating rig with two channels")
    ap.add_argument("--cli", type=int, default=0, metavar="N",
                    help="also time the warm `crank-jax fit ... --each` command on N records")
    ap.add_argument("--table", action="store_true",
                    help="rewrite the docs table from bench_fit_many.json and stop")
    a = ap.parse_args()
    name = RESULTS / "bench_fit_many.json"
    if a.table:
        more = sorted(RESULTS.glob("bench_fit_many_n*.json"))
        text = table(json.loads(name.read_text()), [json.loads(p.read_text()) for p in more])
        rot = RESULTS / "bench_fit_many_rot.json"
        if rot.exists():
            text += "\n\n" + table_rot(json.loads(rot.read_text()))
        write_section(PAGE, BEGIN, END, text, "fleet")
        return
    if a.smoke:
        a.n, a.peer_n = 4, 1
    if a.rig == "rotating":
        name = RESULTS / "bench_fit_many_rot.json"
    doc = run(a.n, min(a.peer_n, a.n), a.smoke, a.rig)
    if a.cli:
        doc.update(cli(a.cli))
    out = (name.with_suffix(".smoke.json") if a.smoke else name if a.n == 100
           else name.with_name(f"bench_fit_many_n{a.n}.json"))
    out.write_text(json.dumps(doc, indent=2) + "\n")
    print(json.dumps({k: v for k, v in doc.items() if k != "machine"}, indent=2))


_RHS = None

if __name__ == "__main__":
    main()
