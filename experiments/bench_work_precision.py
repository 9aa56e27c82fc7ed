"""Work-precision: run time against the maximum error in phi over 10 s (1001 samples).

Scenes: the lab rig with c = 1e-3 (the issue's target configuration), the torsional and the
near-buckling presets, each with its own phi0. Methods, side by side in one run:

- `crank_jax.simulate` with its default solver (`"auto"`, which picks `"dopri8-adaptive"`;
  `"dopri8-uniform"` by name beside it
  for these non-stiff scenes), and diffrax's adaptive Tsit5, Dopri5, Dopri8 through
  `simulate(solver=...)`, at rtol = 1e-4 .. 1e-12 (atol = rtol / 100);
- scipy `solve_ivp` RK45, DOP853, LSODA and `odeint` with a plain-Python RHS;
- compiled scalar peers in numba (skipped if numba is missing): a Dormand-Prince 5(4) with
  dense output, and DOP853 with scipy's coefficients, controller and dense output.

The error is the max |phi - phi_ref| over the samples. phi_ref is diffrax's Dopri8 at
rtol = 1e-14, cross-checked against scipy's DOP853 at rtol = 1e-13: their difference is
recorded as the error floor. Times are medians. Target (a) is evaluated on the lab rig:
the default solve's time against DOP853's time interpolated (log-log) at the same error.
Issue 9 target 2 compares the default solve (default rtol 1e-8) with the compiled DOP853:
at equal error (interpolated), and against the cheapest compiled-DOP853 run whose error
meets the lab rig's 1e-8 rad.

Run: `python experiments/bench_work_precision.py [--smoke] [--lab-only] [--repeats N]`.
"""

from __future__ import annotations

import argparse

import numpy as np
from _bench import CLOCK, FIGURES, interp_time, median_time, save, setup_jax, use_clock

jax = setup_jax()
import peers  # noqa: E402

import crank_jax as cj  # noqa: E402

T1, SAMPLES = 10.0, 1001


def cases(smoke: bool, lab_only: bool = False):
    lab = cj.load_scene("lab-rig")
    out = [("lab-rig (c=1e-3)", lab.mech.replace(c=1e-3), 1.0)]
    if not (smoke or lab_only):
        for name in ("torsional", "near-buckling"):
            s = cj.load_scene(name)
            out.append((name, s.mech, float(s.phi0)))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                    help="time on the wall clock or the process CPU clock (shared machines)")
    ap.add_argument("--tag", default="", help="suffix of the results file (e.g. _before)")
    ap.add_argument("--smoke", action="store_true", help="tiny run for CI")
    ap.add_argument("--lab-only", action="store_true", help="only the lab-rig scene")
    ap.add_argument("--repeats", type=int, default=5, help="timing repeats (median)")
    a = ap.parse_args(argv)
    use_clock(a.clock)
    smoke = a.smoke
    rtols = [1e-5, 1e-8] if smoke else [10.0**-e for e in range(4, 13)]
    repeats = 1 if smoke else a.repeats
    ts = np.linspace(0.0, T1, SAMPLES)
    tsj = jax.numpy.asarray(ts)
    results = {}
    for label, mech, phi0 in cases(smoke, a.lab_only):
        p = peers.params_of(mech)
        y0 = (phi0, 0.0)
        ref = np.asarray(cj.simulate(mech, phi0, 0.0, tsj, solver="dopri8", rtol=1e-14,
                                     atol=1e-16, max_steps=10**7).phi)
        if smoke:
            floor = None
        else:
            chk, _ = peers.scipy_solve("DOP853", p, y0, ts, 1e-13, 1e-15)
            floor = float(np.max(np.abs(chk - ref)))
        curves: dict[str, list[dict]] = {}

        def record(method, rtol, phi, t, steps=None):
            err = float(np.max(np.abs(np.asarray(phi) - ref)))
            curves.setdefault(method, []).append(
                {"rtol": rtol, "error": err, "time_s": t, "steps": steps})
            print(f"{label:>18} {method:>26} rtol={rtol:.0e} err={err:.2e} t={t * 1e3:9.3f} ms",
                  flush=True)

        jax_methods = {"crank_jax default (auto)": None,
                       "crank_jax dopri8-uniform": "dopri8-uniform", "diffrax Tsit5": "tsit5",
                       "diffrax Dopri5": "dopri5", "diffrax Dopri8": "dopri8"}
        if smoke:
            jax_methods = {"crank_jax default (auto)": None, "diffrax Dopri8": "dopri8"}
        for method, solver in jax_methods.items():
            kw = {} if solver is None else {"solver": solver}
            for rtol in rtols:
                def run(rtol=rtol, kw=kw):
                    tr = cj.simulate(mech, phi0, 0.0, tsj, rtol=rtol, atol=rtol * 1e-2,
                                     max_steps=10**6, **kw)
                    return jax.block_until_ready(tr)
                tr = run()
                record(method, rtol, tr.phi, median_time(run, repeats), int(tr.num_steps))

        scipy_methods = ["DOP853"] if smoke else ["RK45", "DOP853", "LSODA", "odeint"]
        for method in scipy_methods:
            for rtol in rtols:
                # RK45/LSODA at very tight tolerances take minutes on the torsional scene.
                if method != "DOP853" and rtol < 1e-10:
                    continue
                if method == "odeint":
                    def run(rtol=rtol):
                        return peers.odeint_solve(p, y0, ts, rtol, rtol * 1e-2)
                else:
                    def run(rtol=rtol, method=method):
                        return peers.scipy_solve(method, p, y0, ts, rtol, rtol * 1e-2)
                phi, nfev = run()
                record(f"scipy {method}", rtol, phi, median_time(run, repeats if not smoke else 1,
                                                                 warmup=0, budget_s=10.0), nfev)
        if peers.HAVE_NUMBA:
            nb_rtols = rtols if smoke else rtols + [1e-13]
            for name, fn in (("numba DP5 (compiled)", peers.dp5_numba),
                             ("numba DOP853 (compiled)", peers.dop853_numba)):
                fn(p, y0, ts, 1e-6, 1e-8)  # compile
                for rtol in nb_rtols:
                    def run(rtol=rtol, fn=fn):
                        return fn(p, y0, ts, rtol, rtol * 1e-2)
                    ys, ns = run()
                    record(name, rtol, ys[:, 0], median_time(run, repeats), ns)
        else:
            print("numba is not installed: skipping the compiled DP5 peer")
        results[label] = {"phi0": phi0, "error_floor": floor, "curves": curves}

    # Target (a): default solver vs scipy DOP853 at equal error, on the lab rig.
    lab = results["lab-rig (c=1e-3)"]["curves"]
    default = next(r for r in lab["crank_jax default (auto)"] if r["rtol"] == 1e-8)
    dop = lab["scipy DOP853"]
    t_dop = interp_time([r["error"] for r in dop], [r["time_s"] for r in dop], default["error"])
    target = {
        "default_error": default["error"], "default_time_s": default["time_s"],
        "dop853_time_s_at_equal_error": t_dop,
        "speedup": None if t_dop is None else t_dop / default["time_s"],
        "goal": 25.0,
    }
    print("target (a):", target)
    # Issue 9 target 2 at equal measured error <= 1e-8 rad: the default's cheapest run
    # meeting it (rtol 1e-8 lands just above 1e-8 with the adaptive default).
    meeting = [r for r in lab["crank_jax default (auto)"] if r["error"] <= 1e-8]
    target2 = target_2(lab, min(meeting, key=lambda r: r["time_s"]) if meeting else default)
    if target2 is not None and not smoke:
        target2["paired"] = paired_ratio(lab, target2, tsj, ts)
    print("issue 9 target 2:", target2)
    save("work_precision" + a.tag, {"t1": T1, "samples": SAMPLES, "cases": results,
                                    "target_a": target, "target_2": target2}, smoke)
    plot(results, smoke, a.tag)


def paired_ratio(lab: dict, t2: dict, tsj, ts, rounds: int = 41) -> dict | None:
    """Target 2 measured in pairs, for a machine whose speed drifts from second to second
    (seen: the compiled DOP853 alone at 0.9-1.3 ms within a minute): each round times one
    concrete default `simulate` call and the compiled DOP853 at the two rtols whose errors
    bracket the default's, interpolates DOP853's time (log-log) at the default's error,
    and takes the ratio; the median over the rounds is reported. The same solves as the
    curves, so the same errors."""
    dop = lab["numba DOP853 (compiled)"]
    r_def = next(r["rtol"] for r in lab["crank_jax default (auto)"]
                 if r["error"] == t2["default_error"])
    e = t2["default_error"]
    lo = [r for r in dop if r["error"] <= e]
    hi = [r for r in dop if r["error"] >= e]
    if not lo or not hi:
        return None
    lo, hi = max(lo, key=lambda r: r["error"]), min(hi, key=lambda r: r["error"])
    mech, phi0 = next((m, p0) for label, m, p0 in cases(False, True) if label.startswith("lab"))
    p = peers.params_of(mech)

    def ours():
        return jax.block_until_ready(cj.simulate(mech, phi0, 0.0, tsj, rtol=r_def,
                                                 atol=r_def * 1e-2, max_steps=10**6))

    def peer(rtol):
        return peers.dop853_numba(p, (phi0, 0.0), ts, rtol, rtol * 1e-2)

    def clock(fn, *a):
        now = CLOCK["fn"]
        t = now()
        fn(*a)
        return now() - t

    ratios = []
    for _ in range(rounds):
        t_ours = clock(ours)
        t_lo, t_hi = clock(peer, lo["rtol"]), clock(peer, hi["rtol"])
        t_dop = interp_time([lo["error"], hi["error"]], [t_lo, t_hi], e) if lo is not hi \
            else t_lo
        ratios.append(t_ours / t_dop)
    return {"rounds": rounds, "default_rtol": r_def, "dop853_rtols": [lo["rtol"], hi["rtol"]],
            "ratio_median": float(np.median(ratios)),
            "ratio_quartiles": [float(np.percentile(ratios, 25)),
                                float(np.percentile(ratios, 75))]}


def target_2(lab: dict, default: dict) -> dict | None:
    """A default solve against the compiled DOP853: at equal error, and against its cheapest
    run that meets the lab rig's 1e-8 rad."""
    dop = lab.get("numba DOP853 (compiled)")
    if not dop:
        return None
    t_eq = interp_time([r["error"] for r in dop], [r["time_s"] for r in dop], default["error"])
    meets = [r for r in dop if r["error"] <= 1e-8]
    t_meet = min((r["time_s"] for r in meets), default=None)
    return {"goal": 3.0, "default_error": default["error"], "default_time_s": default["time_s"],
            "dop853_time_s_at_equal_error": t_eq,
            "ratio_at_equal_error": None if t_eq is None else default["time_s"] / t_eq,
            "dop853_cheapest_time_s_error_le_1e-8": t_meet,
            "ratio_vs_cheapest_meeting_1e-8": (None if t_meet is None
                                               else default["time_s"] / t_meet)}


STYLE = {
    "crank_jax default (auto)": dict(color="k", lw=2.5, marker="o"),
    "crank_jax dopri8-uniform": dict(color="0.5", lw=1.5, marker="o"),
    "diffrax Tsit5": dict(color="C0", marker="."),
    "diffrax Dopri5": dict(color="C9", marker="."),
    "diffrax Dopri8": dict(color="C1", marker="."),
    "scipy RK45": dict(color="C2", ls="--", marker="x"),
    "scipy DOP853": dict(color="C3", ls="--", marker="x"),
    "scipy LSODA": dict(color="C4", ls="--", marker="x"),
    "scipy odeint": dict(color="C5", ls="--", marker="x"),
    "numba DP5 (compiled)": dict(color="C6", ls=":", marker="s"),
    "numba DOP853 (compiled)": dict(color="C7", ls=":", marker="D"),
}


def plot(results, smoke, tag=""):
    from crank_jax.report.plotting import pyplot, save_figure

    plt = pyplot()
    fig, axes = plt.subplots(1, len(results), figsize=(5.2 * len(results), 4.6), squeeze=False)
    for ax, (label, res) in zip(axes[0], results.items()):
        for method, rows in res["curves"].items():
            rows = sorted(rows, key=lambda r: r["error"])
            ax.loglog([r["error"] for r in rows], [r["time_s"] for r in rows], label=method,
                      ms=4, **STYLE.get(method, {}))
        if res["error_floor"]:
            ax.axvspan(1e-16, res["error_floor"], color="0.9", zorder=0)
            ax.set_xlim(left=res["error_floor"] / 3)
        ax.set_title(f"{label}, phi0 = {res['phi0']:g} rad, 10 s", fontsize=10)
        ax.set_xlabel("max |phi - phi_ref| (rad)")
        ax.grid(alpha=0.3, which="both")
    clock = "process CPU time" if CLOCK["name"] == "cpu" else "run time"
    axes[0][0].set_ylabel(f"{clock} (s), median")
    axes[0][-1].legend(fontsize=7, loc="upper right")
    fig.suptitle("Work-precision (grey: below the reference's own uncertainty)", fontsize=10)
    FIGURES.mkdir(parents=True, exist_ok=True)
    path = FIGURES / (f"work_precision{tag}.smoke.png" if smoke else f"work_precision{tag}.png")
    save_figure(fig, path)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
