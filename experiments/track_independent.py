"""Tracking checked on records crank-jax did not make: the slider-crank equations written
out by hand in numpy (DESIGN.md section 1: M(phi), K(phi), q with the crank torque) and
integrated by scipy's `solve_ivp` (DOP853, rtol 1e-11), a parameter changed part-way by
restarting the solve from the state at the change. The lab rig driven by a measured
two-tone torque, 200 Hz, 60 s; the tracker starts from its default batch fit of the
first 5 s and knows nothing of the change.

The issue's criteria (case `k -5%` on `phi`): one alarm naming `k` within 3 s of the
change at 30 s and none before it; `k` within 0.5% of the truth at 29 s and at 59 s, each
95% band covering it. The same record with no change: no alarm, `k`'s band covering the
truth at >= 85% of the samples after the first 5 s. Tried beyond them, and reported as
they come: other seeds, other change sizes, a damping change, the slider's position as
the only channel.

    python experiments/track_independent.py [--seeds 2] [--quick]
    python experiments/track_independent.py --table   # rewrite the docs table and stop

Writes experiments/results/track_independent.json and the table between
`<!-- BEGIN track-independent -->` and `<!-- END track-independent -->` in
docs/guide/tracking.md.
"""

from __future__ import annotations

import argparse
import json
import time

from _bench import RESULTS, ROOT, machine, setup_jax, write_section

setup_jax()

import numpy as np  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.online import track  # noqa: E402

LAB = cj.load_scene("lab-rig")
RATE, T, T_CHANGE = 200.0, 60.0, 30.0
PAGE = ROOT / "docs" / "guide" / "tracking.md"
BEGIN, END = "<!-- BEGIN track-independent -->", "<!-- END track-independent -->"
#: (label, changed parameter or None, relative change, channel, free set)
CASES = [("no change", None, 0.0, "phi", ("k", "c")),
         ("k -5%", "k", -0.05, "phi", ("k", "c")),
         ("k -2%", "k", -0.02, "phi", ("k", "c")),
         ("k -10%", "k", -0.10, "phi", ("k", "c")),
         ("c +30%", "c", 0.30, "phi", ("k", "c")),
         ("no change, x_s", None, 0.0, "x_s", ("k", "c")),
         ("k -5%, x_s", "k", -0.05, "x_s", ("k", "c"))]
#: Noise of each channel: 1 mrad on the angle; on the slider's position, the 50 um a
#: 1 mrad error of the crank (r = 50 mm) makes at its largest.
NOISE = {"phi": 1e-3, "x_s": 5e-5}


def torque(t):
    """The measured two-tone crank torque, N*m."""
    return 0.15 * np.sin(2 * np.pi * 3.1 * t) + 0.1 * np.sin(2 * np.pi * 5.3 * t + 1.0)


def accel(phi, dphi, t, p, tau=None):
    """phi'' of DESIGN.md's minimal form, by hand: (q - K phi'^2) / M, with the crank
    torque `tau` (N*m; default the two-tone `torque(t)`) and the slider guide's viscous
    friction `p["c_s"]` (N*s/m, optional); gravity along -x, no offset. rad/s^2. Scalars
    or arrays (a fleet, elementwise)."""
    r, L, b, s, m_c, m_p, m_s = p["r"], p["L"], p["b"], p["s"], p["m_c"], p["m_p"], p["m_s"]
    I_c, I_p, k, c, g = p["I_c"], p["I_p"], p["k"], p["c"], p["g"]
    sp, cp = np.sin(phi), np.cos(phi)
    sd = r / L * sp
    cd = np.sqrt(1.0 - sd * sd)
    d1 = r / L * cp / cd
    d2 = r / L * (d1 * cp * sd - sp * cd) / cd**2
    cpd = cp * cd - sp * sd
    spd = sp * cd + cp * sd
    lever = r * sp + L * d1 * sd
    M = (m_c * s**2 + I_c + m_p * (r**2 - 2 * r * b * d1 * cpd + b**2 * d1**2)
         + I_p * d1**2 + m_s * lever**2)
    K = (m_p * (r * b * (d1 * (1 + d1) * spd - d2 * cpd) + b**2 * d1 * d2) + I_p * d1 * d2
         + m_s * lever * (r * cp + L * (d2 * sd + d1**2 * cd)))
    q = (g * (m_c * s * sp + m_p * (r * sp + b * d1 * sd) + m_s * lever) - k * phi
         - c * dphi - p.get("c_s", 0.0) * lever**2 * dphi
         + (torque(t) if tau is None else tau))
    return (q - K * dphi**2) / M


def slider(phi, p):
    """The slider's position x_s = r cos(phi) + L cos(delta), m."""
    sd = p["r"] / p["L"] * np.sin(phi)
    return p["r"] * np.cos(phi) + p["L"] * np.sqrt(1 - sd**2)


def simulate(p, ts, name, change, y0=(0.3, 0.0)):
    """phi at `ts`, with `name` changed by the factor `1 + change` from T_CHANGE on."""
    def solve(q, t0, t1, y, at):
        sol = solve_ivp(lambda t, y: [y[1], accel(y[0], y[1], t, q)], (t0, t1), list(y),
                        method="DOP853", t_eval=at, rtol=1e-11, atol=1e-12, dense_output=True)
        if not sol.success:
            raise RuntimeError(sol.message)
        return sol
    if name is None:
        return solve(p, ts[0], ts[-1], y0, ts).y[0]
    a = ts[ts < T_CHANGE]
    first = solve(p, ts[0], T_CHANGE, y0, a)
    later = ts[ts >= T_CHANGE]
    after = p | {name: p[name] * (1 + change)}
    second = solve(after, T_CHANGE, ts[-1], first.sol(T_CHANGE), later)
    return np.concatenate([first.y[0], second.y[0]])


def record(name, change, channel, seed):
    ts = np.arange(0.0, T, 1 / RATE)
    p = LAB.mech.as_dict()
    phi = simulate({n: float(v) for n, v in p.items()}, ts, name, change)
    rng = np.random.default_rng(seed)
    tau = cj.SampledLoad(ts, torque(ts))
    if channel == "phi":
        return cj.Data(ts, phi + rng.normal(0, NOISE["phi"], ts.size), torque=tau,
                       source=f"independent seed {seed}")
    xs = slider(phi, {n: float(v) for n, v in p.items()}) + rng.normal(0, NOISE["x_s"], ts.size)
    return cj.Data(ts, channels={"x_s": xs}, torque=tau, source=f"independent seed {seed}")


def judge(res, name, change, free):
    """The criteria's figures for one tracked record."""
    truth0 = {n: float(getattr(LAB.mech, n)) for n in free}
    watch = name or "k"
    t = res.t
    true_path = np.full(t.size, truth0[watch])
    if name is not None:
        true_path[t >= T_CHANGE] *= 1 + change
    lo, hi = res.band(watch)
    cover = (lo <= true_path) & (true_path <= hi)
    settled = t >= 5.0
    pre = settled & ((t < T_CHANGE) if name else True)
    at = {}
    for when in (29.0, 59.0):
        i = int(np.argmin(np.abs(t - when)))
        at[when] = {"error_pct": 100 * (res.values[watch][i] / true_path[i] - 1),
                    "covers": bool(cover[i])}
    alarms = [{"t": a["t"], "parameters": a["parameters"], "t_change": a["t_change"]}
              for a in res.alarms]
    early = [a for a in alarms if a["t"] < T_CHANGE] if name else alarms
    hit = [a for a in alarms if name and T_CHANGE <= a["t"] <= T_CHANGE + 3.0
           and a["parameters"][0] == name]
    # The band's honesty: the rms of the error over its standard error (1 when honest).
    z = (res.values[watch] - true_path) / res.stderr[watch]
    return {"watch": watch, "alarms": alarms, "false_alarms": len(early),
            "z_rms_pre": float(np.sqrt(np.mean(z[pre] ** 2))),
            "detected": bool(hit), "delay_s": hit[0]["t"] - T_CHANGE if hit else None,
            "coverage_pre": float(np.mean(cover[pre])),
            "coverage_after_5s": float(np.mean(cover[settled])), "at": at,
            "start": res.settings["start"]}


def passes(row) -> bool:
    """The issue's criteria, applied to every case (a change case: detection; both: no
    alarm before, 0.5% and covering at 29 s and 59 s; no-change: >= 85% coverage)."""
    ok = row["false_alarms"] == 0 and all(
        abs(a["error_pct"]) <= 0.5 and a["covers"] for a in row["at"].values())
    if row["change"]:
        return ok and row["detected"] and len(row["alarms"]) == 1
    return ok and row["coverage_after_5s"] >= 0.85


def run(seeds: int, quick: bool) -> dict:
    rows = []
    cases = CASES[:2] if quick else CASES
    for label, name, change, channel, free in cases:
        for seed in range(seeds):
            data = record(name, change, channel, seed)
            t0 = time.perf_counter()
            res = track(LAB, data, free=free, progress=False)
            row = {"case": label, "seed": seed, "channel": channel, "change": name,
                   "size": change, "seconds": time.perf_counter() - t0}
            row |= judge(res, name, change, free)
            row["pass"] = passes(row)
            rows.append(row)
            print(json.dumps(row), flush=True)
    return {"machine": machine(), "seeds": seeds, "rows": rows}


def table(doc: dict) -> str:
    def cell(a):
        return f"{a['error_pct']:+.2f}% {'yes' if a['covers'] else 'NO'}"
    lines = [f"`experiments/track_independent.py` ({doc['machine']['date']}; records from "
             "scipy's DOP853 on the equations written by hand in numpy, not crank-jax's "
             "model; the tracker starts from its batch fit of the first 5 s). The error "
             "and cover columns are the watched parameter's (the changed one, else `k`) "
             "at 29 s and 59 s; coverage is of its 95% band over the samples after 5 s "
             "(before the change, for a change case); z rms is the rms of the error over "
             "its standard error over the same samples (1 for an honest band; below 1, "
             "a band wider than the errors).", "",
             "| case | seed | alarms (t s: named) | delay | at 29 s: error, covered | "
             "at 59 s | coverage | z rms | criteria |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in doc["rows"]:
        al = "; ".join(f"{a['t']:.2f}: {','.join(a['parameters'])}" for a in r["alarms"])
        d = f"{r['delay_s']:.2f} s" if r["delay_s"] is not None else "-"
        cov = r["coverage_pre"] if r["change"] else r["coverage_after_5s"]
        lines.append(f"| {r['case']} | {r['seed']} | {al or 'none'} | {d} | "
                     f"{cell(r['at'][29.0] if 29.0 in r['at'] else r['at']['29.0'])} | "
                     f"{cell(r['at'][59.0] if 59.0 in r['at'] else r['at']['59.0'])} | "
                     f"{100 * cov:.1f}% | {r.get('z_rms_pre', float('nan')):.2f} | "
                     f"{'pass' if r['pass'] else 'FAIL'} |")
    n = sum(r["pass"] for r in doc["rows"])
    lines += ["", f"{n} of {len(doc['rows'])} tracked records meet the criteria."]
    return "\n".join(lines)


def write_table(doc: dict) -> None:
    write_section(PAGE, BEGIN, END, table(doc), "independent-check")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="the first two cases only")
    ap.add_argument("--table", action="store_true")
    a = ap.parse_args()
    out = RESULTS / "track_independent.json"
    if a.table:
        write_table(json.loads(out.read_text()))
        return
    doc = run(a.seeds, a.quick)
    RESULTS.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1))
    print(table(doc))


if __name__ == "__main__":
    main()
