"""Numerical stress tests of crank-jax (the long versions of tests/test_stress.py).

    python experiments/stress_numerics.py            # full run, a few minutes on 2 cores
    python experiments/stress_numerics.py --smoke    # seconds, for CI

Writes experiments/results/stress_numerics[_smoke].json and (full run)
docs/figures/stress_stiffness.png (gradients over long horizons: stress_gradients.py).

Sections: stiffness sweep (k = 1e-2 .. 1e7 N*m/rad, every solver and "auto"), energy drift
with c = 0 over 1e3 periods against tolerance and solver, a 1e4-period horizon, geometry
extremes r/L = 0.01 .. 0.999, full revolutions, a crank with xi < 0, and float32 against
float64.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.runtime.io import atomic_write  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "experiments" / "results"
FIGURES = ROOT / "docs" / "figures"


def _timed(fn, repeats=3):
    fn()  # compile
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        jax.block_until_ready(out.phi)
        times.append(time.perf_counter() - t0)
    return out, float(np.median(times))


def _drift(mech, tr):
    e = np.asarray(cj.model.energy(mech, tr.phi, tr.dphi))
    return float(np.max(np.abs(e - e[0])) / abs(e[0]))


def stiffness(smoke):
    """Steps, time and success against k, for each solver and "auto" (damping ratio 0.05)."""
    rig = cj.load_scene("lab-rig").mech
    mu = float(cj.linearize(rig).mu)
    ks = np.logspace(-2, 7, 4 if smoke else 10)
    ts = np.linspace(0.0, 2.0, 21)
    rows = []
    for k in ks:
        m = rig.replace(k=k, c=0.01 + 2 * 0.05 * np.sqrt(k * mu))
        for solver in ("tsit5", "dopri8", "kvaerno5", "auto"):
            tr, t = _timed(lambda m=m, s=solver: cj.simulate(
                m, 0.01, 0.0, ts, solver=s, max_steps=200_000, throw=False), 1 if smoke else 3)
            rows.append(dict(k=float(k), solver=solver, ok=bool(tr.ok),
                             steps=int(tr.num_steps), time_s=t,
                             picked=cj.solve.choose_solver(m, 1e-8, span=2.0)))
        print(f"stiffness k={k:9.3g}: " + ", ".join(
            f"{r['solver']}={r['steps']}" for r in rows[-4:]), flush=True)
    return rows


def energy_drift(smoke):
    """Relative energy drift with c = 0 over 1e3 periods (1e1 in smoke)."""
    rig = cj.load_scene("lab-rig").mech.replace(c=0.0)
    periods = 10 if smoke else 1000
    T = periods / 4.5
    ts = np.linspace(0.0, T, 1001)
    rows = []
    for solver in ("tsit5", "dopri5", "dopri8", "kvaerno5"):
        for rtol in ((1e-6, 1e-10) if smoke else (1e-6, 1e-8, 1e-10, 1e-12)):
            if solver == "kvaerno5" and rtol < 1e-10:
                continue  # hundreds of thousands of implicit steps: pointless
            tr, t = _timed(lambda s=solver, r=rtol: cj.simulate(
                rig, 1.0, 0.0, ts, solver=s, rtol=r, atol=r * 1e-2, max_steps=5_000_000,
                throw=False), 1)
            rows.append(dict(solver=solver, rtol=rtol, periods=periods, ok=bool(tr.ok),
                             drift=_drift(rig, tr), steps=int(tr.num_steps), time_s=t))
            print(f"drift {solver} rtol={rtol:g}: {rows[-1]['drift']:.2e} "
                  f"({rows[-1]['steps']} steps, {t:.2f} s)", flush=True)
    return rows


def long_horizon(smoke):
    """1e4 periods of the undamped lab rig with Dopri8."""
    rig = cj.load_scene("lab-rig").mech.replace(c=0.0)
    periods = 100 if smoke else 10_000
    ts = np.linspace(0.0, periods / 4.5, 2001)
    out = []
    for rtol in (1e-8, 1e-11):
        tr, t = _timed(lambda r=rtol: cj.simulate(
            rig, 1.0, 0.0, ts, solver="dopri8", rtol=r, atol=r * 1e-2, max_steps=20_000_000,
            throw=False), 1)
        out.append(dict(periods=periods, rtol=rtol, ok=bool(tr.ok), drift=_drift(rig, tr),
                        steps=int(tr.num_steps), time_s=t, finite=bool(np.all(np.isfinite(
                            np.asarray(tr.phi))))))
        print(f"long horizon {periods} periods rtol={rtol:g}: {out[-1]}", flush=True)
    # Phase agreement of the two tolerances at the end: how far accuracy carries.
    return out


def extremes(smoke):
    """r/L from 0.01 to 0.999, full revolutions, and xi < 0."""
    rig = cj.load_scene("lab-rig").mech
    ts = np.linspace(0.0, 2.0, 201)
    rows = []
    for ratio in ((0.01, 0.999) if smoke else (0.01, 0.1, 0.5, 0.9, 0.99, 0.999)):
        m = rig.replace(L=rig.r / ratio, b=0.3 * rig.r / ratio, c=0.0)
        for case, (phi0, dphi0, mm) in {
            "release 1 rad": (1.0, 0.0, m),
            "full revolutions (k = 0)": (0.0, 30.0, m.replace(k=0.0)),
        }.items():
            tr, t = _timed(lambda mm=mm, p=phi0, d=dphi0: cj.simulate(
                mm, p, d, ts, rtol=1e-10, atol=1e-12, max_steps=1_000_000, throw=False), 1)
            rows.append(dict(r_over_L=ratio, case=case, ok=bool(tr.ok), drift=_drift(mm, tr),
                             steps=int(tr.num_steps), time_s=t,
                             turns=float(np.max(np.abs(np.asarray(tr.phi))) / (2 * np.pi))))
            print(f"r/L={ratio}: {case}: {rows[-1]}", flush=True)
    m = rig.replace(k=0.1, c=0.02)
    tr = cj.simulate(m, 1e-3, 0.0, np.linspace(0, 10, 1001), throw=False)
    rows.append(dict(r_over_L=float(rig.r / rig.L), case="xi < 0: falls over from 1e-3 rad",
                     ok=bool(tr.ok), drift=None, steps=int(tr.num_steps), time_s=None,
                     turns=float(np.max(np.abs(np.asarray(tr.phi))) / (2 * np.pi)),
                     final_phi=float(tr.phi[-1])))
    print(rows[-1], flush=True)
    return rows


def float32(smoke):
    """The lab rig in float32 (x64 off) against float64: steps, success, drift, error."""
    script = textwrap.dedent(f"""
        import json, warnings
        import numpy as np
        import crank_jax as cj
        warnings.simplefilter("ignore")
        m = cj.load_scene("lab-rig").mech.replace(c=0.0)
        ts = np.linspace(0.0, {2.0 if smoke else 10.0}, 101)
        rows = []
        for rtol in (1e-4, 1e-6, 1e-8):
            tr = cj.simulate(m, 1.0, 0.0, ts, rtol=rtol, atol=rtol * 1e-2, solver="tsit5",
                             max_steps=100_000, throw=False)
            e = np.asarray(cj.model.energy(m, tr.phi, tr.dphi), dtype=float)
            rows.append(dict(rtol=rtol, dtype=str(tr.phi.dtype), ok=bool(tr.ok),
                             steps=int(tr.num_steps),
                             drift=float(np.max(np.abs(e - e[0])) / abs(e[0])),
                             phi=np.asarray(tr.phi, dtype=float).tolist()))
        print(json.dumps(rows))
    """)
    out = {}
    for x64 in ("0", "1"):
        env = dict(os.environ, JAX_ENABLE_X64=x64, JAX_PLATFORMS="cpu")
        proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                              text=True, timeout=1200)
        if proc.returncode != 0:
            raise RuntimeError(proc.stderr[-2000:])
        out["float32" if x64 == "0" else "float64"] = json.loads(proc.stdout.splitlines()[-1])
    ref = np.array(out["float64"][-1]["phi"])
    rows = []
    for prec, rs in out.items():
        for r in rs:
            err = float(np.max(np.abs(np.array(r.pop("phi")) - ref)))
            rows.append(dict(precision=prec, **r, max_err_vs_f64_1e8=err))
            print(f"{prec}: {rows[-1]}", flush=True)
    return rows


def figures(res):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    FIGURES.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(6, 4))
    for solver, mk in (("tsit5", "o-"), ("dopri8", "s-"), ("kvaerno5", "^-"), ("auto", "k--")):
        rows = [r for r in res["stiffness"] if r["solver"] == solver]
        ax.loglog([r["k"] for r in rows], [r["steps"] for r in rows], mk, label=solver)
    ax.set_xlabel("k, N*m/rad (damping ratio 0.05)")
    ax.set_ylabel("solver steps over 2 s")
    ax.set_title("Stiffness sweep, lab rig, rtol 1e-8")
    ax.legend()
    fig.tight_layout()
    fig.savefig(FIGURES / "stress_stiffness.png", dpi=120)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--smoke", action="store_true", help="tiny sizes, for CI")
    p.add_argument("--only", nargs="*", help="run only these sections")
    a = p.parse_args(argv)
    sections = dict(stiffness=stiffness, energy_drift=energy_drift, long_horizon=long_horizon,
                    extremes=extremes, float32=float32)
    res = dict(date=datetime.date.today().isoformat(),
               machine=f"{platform.machine()}, {os.cpu_count()} CPU cores, "
                       f"{platform.processor() or platform.platform()}",
               jax=jax.__version__, smoke=a.smoke)
    for name, fn in sections.items():
        if a.only and name not in a.only:
            continue
        t0 = time.perf_counter()
        res[name] = fn(a.smoke)
        print(f"== {name}: {time.perf_counter() - t0:.1f} s", flush=True)
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"stress_numerics{'_smoke' if a.smoke else ''}.json"
    with atomic_write(path) as f:
        json.dump(res, f, indent=1)
    if not a.smoke and not a.only:
        figures(res)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
