"""The tracking tutorial's script (docs/tutorials/tracking-a-drying-guide.md): a rig whose
slider guide dries out, tracked from its log file and alarmed; then a fleet of 1,000
machines, three of them failing, tracked under one `jax.vmap`.

The records come from the equations written by hand in numpy
(`track_independent.accel`), not from crank-jax's model: scipy's DOP853 for the rig,
a vectorised classical Runge-Kutta (10 steps a sample) for the fleet.

    python experiments/track_tutorial.py              # 10 minutes of the rig at 1 kHz
    python experiments/track_tutorial.py --minutes 60 # the full hour (3.6 million samples)
    python experiments/track_tutorial.py --fleet 100  # a smaller fleet

Writes docs/figures/tracking_guide.png, docs/figures/tracking_fleet.png and
experiments/results/track_tutorial.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path

from _bench import FIGURES, RESULTS, machine, rk4, setup_jax

jax = setup_jax()

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402
from track_independent import accel  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.online import (  # noqa: E402
    init_state,
    name_alarms,
    prepare,
    run_filter,
    track_stream,
)

#: The rig: the lab rig with a lubricated slider guide (viscous friction c_s, N*s/m),
#: driven by a programmed two-tone torque (N*m) that is part of the scene.
DRIVE = cj.model.MultiSineLoad(amplitudes=[0.15, 0.1], freqs_hz=[3.1, 5.3], phases=[0.0, 1.0])
LAB = cj.load_scene("lab-rig")
GUIDE = dataclasses.replace(LAB, mech=LAB.mech.replace(c_s=2.0), torque=DRIVE)


def friction(t, T):
    """The guide's friction at `t` of a run of `T` s: 2 N*s/m while lubricated, then
    from half-way it dries out, tripling over the next 30% of the run."""
    x = np.clip((np.asarray(t) - 0.5 * T) / (0.3 * T), 0.0, 1.0)
    return 2.0 * (1.0 + 2.0 * x**2 * (3 - 2 * x))


def drive(t):
    return 0.15 * np.sin(2 * np.pi * 3.1 * t) + 0.1 * np.sin(2 * np.pi * 5.3 * t + 1.0)


def guide_record(T: float, rate: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The drying rig's angle log: times (n,), s, and angles (n,), rad, 1 mrad noise."""
    p = {n: float(v) for n, v in GUIDE.mech.as_dict().items()}
    ts = np.arange(0.0, T, 1 / rate)
    sol = solve_ivp(lambda t, y: [y[1], accel(y[0], y[1], t, p | {"c_s": friction(t, T)},
                                              drive(t))],
                    (0.0, ts[-1]), [0.3, 0.0], method="DOP853", t_eval=ts, rtol=1e-10,
                    atol=1e-12)
    if not sol.success:
        raise RuntimeError(sol.message)
    return ts, sol.y[0] + np.random.default_rng(seed).normal(0.0, 1e-3, ts.size)


#: The parameters' random walks tried on the guide (relative per sqrt(s)): `track`'s
#: default, and ten times it, for a friction that drifts over minutes.
Q_PARAMS = (1e-4, 1e-3)


def part_guide(minutes: float, rate: float) -> dict:
    T = 60.0 * minutes
    t0 = time.perf_counter()
    ts, phi = guide_record(T, rate)
    made = time.perf_counter() - t0
    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "guide.npy"
        np.save(path, np.stack([ts, phi], axis=1))
        del ts, phi
        for q in Q_PARAMS:
            t0 = time.perf_counter()
            res = track_stream(GUIDE, path, free=("k", "c_s"), every=max(1, int(rate) // 20),
                               false_alarm_rate=0.1, settle=10.0, q_param=q, progress=True)
            print(res.summary())
            runs[q] = (res, time.perf_counter() - t0)
    truth = friction(runs[Q_PARAMS[0]][0].t, T)
    _figure_guide(runs, truth, T)
    return {"minutes": minutes, "rate_hz": rate, "simulate_s": made,
            "drying_starts_s": 0.5 * T, "drying_ends_s": 0.8 * T,
            "c_s_true_end": float(truth[-1]),
            "runs": [_guide_figures(q, res, took, truth) for q, (res, took) in runs.items()]}


def _guide_figures(q, res, took, truth) -> dict:
    lo, hi = res.band("c_s")
    cover = (lo <= truth) & (truth <= hi)
    z = (res.values["c_s"] - truth) / res.stderr["c_s"]
    late = res.t > 30.0
    return {"q_param": q, "samples": res.settings["stream"]["samples"], "track_s": took,
            "alarms": [{k: a[k] for k in ("t", "t_change", "parameters", "before", "after")}
                       for a in res.alarms],
            "c_s_coverage": float(np.mean(cover[late])),
            "c_s_z_rms": float(np.sqrt(np.mean(z[late] ** 2))),
            "c_s_end": float(res.values["c_s"][-1]), "c_s_end_se": float(res.stderr["c_s"][-1]),
            "k_end": float(res.values["k"][-1])}


def _figure_guide(runs, truth, T) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for c, (q, (res, _)) in enumerate(runs.items()):
        m = res.t / 60
        lo, hi = res.band("c_s")
        ax[0].fill_between(m, lo, hi, color=f"C{c}", alpha=0.3)
        ax[0].plot(m, res.values["c_s"], f"C{c}", lw=1, label=f"tracked, q_param {q:g}")
        ax[1].semilogy(m, np.maximum(res.statistic, 1e-3), f"C{c}", lw=0.8,
                       label=f"CUSUM, q_param {q:g}")
        for a in res.alarms:
            for x in ax:
                x.axvline(a["t"] / 60, color=f"C{c}", ls=":", lw=1)
    ax[0].plot(runs[Q_PARAMS[0]][0].t / 60, truth, "k--", lw=1, label="truth")
    ax[0].set_ylabel("guide friction c_s (N s/m)")
    ax[0].set_ylim(0, 1.3 * truth.max())
    ax[1].axhline(runs[Q_PARAMS[0]][0].settings["threshold"], color="r", lw=1,
                  label="threshold")
    ax[1].set_xlabel("time (min)")
    ax[1].set_ylabel("change statistic")
    for x in ax:
        x.legend(loc="upper left", fontsize=8)
    fig.suptitle(f"A slider guide drying out: {T / 60:g} min at 1 kHz, tracked from its log "
                 "(bands 95%, alarms dotted)")
    fig.tight_layout()
    FIGURES.mkdir(parents=True, exist_ok=True)
    fig.savefig(FIGURES / "tracking_guide.png", dpi=110)
    plt.close(fig)


#: The fleet's failing machines: index -> (parameter, relative change) at FAIL_AT s.
FAILING = {137: ("k", -0.05), 512: ("c", 0.5), 901: ("k", -0.03)}
FLEET_T, FLEET_RATE, FAIL_AT = 20.0, 200.0, 10.0


def fleet_records(n: int, seed: int = 1):
    """`n` machines' angle logs (n, samples), rad: the lab rig's stiffness and damping
    spread by 1% and 5% between machines, each from its own start, 1 mrad noise; the
    machines of `FAILING` (those < n) change at `FAIL_AT`. A vectorised RK4."""
    rng = np.random.default_rng(seed)
    p = {k: float(v) for k, v in LAB.mech.as_dict().items()}
    k = p["k"] * (1 + 0.01 * rng.standard_normal(n))
    c = p["c"] * (1 + 0.05 * rng.standard_normal(n))
    y = np.stack([rng.uniform(0.1, 0.4, n), np.zeros(n)])
    sub, dt = 10, 1 / FLEET_RATE
    h = dt / sub
    ts = np.arange(0.0, FLEET_T, dt)
    out = np.empty((n, ts.size))
    for i, t in enumerate(ts):
        out[:, i] = y[0]
        if t >= FAIL_AT - 1e-12 and t < FAIL_AT + dt / 2:
            for j, (name, d) in FAILING.items():
                if j < n:
                    (k if name == "k" else c)[j] *= 1 + d
        q = p | {"k": k, "c": c}
        f = lambda tt, yy: np.stack([yy[1], accel(yy[0], yy[1], tt, q)])  # noqa: E731
        y = rk4(f, t, y, h, sub)
    return ts, out + rng.normal(0.0, 1e-3, out.shape)


def part_fleet(n: int) -> dict:
    t0 = time.perf_counter()
    ts, phis = fleet_records(n)
    made = time.perf_counter() - t0
    scene = dataclasses.replace(LAB, torque=DRIVE)
    # One machine sets the filter up (the fleet shares the scene, its noise and step);
    # each machine starts from its own first two samples at the scene's values: the
    # speed a difference of two samples (0.3 rad/s of noise, and the acceleration's bias),
    # given 0.5 rad/s of standard deviation.
    p = prepare(scene, cj.Data(ts, phis[0]), free=("k", "c"), start="scene",
                false_alarm_rate=0.1, progress=False)
    dphi0 = (phis[:, 1] - phis[:, 0]) / (ts[1] - ts[0])
    P0 = p.state.P.at[1, 1].set(0.5**2)
    states = jax.vmap(lambda x0, v0: init_state(
        p.state.x.at[0].set(x0).at[1].set(v0), P0, ts[0]))(
        jnp.asarray(phis[:, 0]), jnp.asarray(dphi0))
    tj, ok = jnp.asarray(ts), jnp.ones(ts.size, bool)
    fleet = jax.jit(jax.vmap(lambda st, y: run_filter(p.model, p.settings, st, tj, y[:, None],
                                                      ok)))
    t0 = time.perf_counter()
    _, steps = jax.block_until_ready(fleet(states, jnp.asarray(phis)))
    took = time.perf_counter() - t0
    alarmed, named = [], {}
    for i in np.flatnonzero(np.asarray(steps.alarm).any(axis=1)):
        one = jax.tree.map(lambda a: np.asarray(a[i]), steps)
        ev = [(int(j), int(j - one.run[j]), float(ts[j]), float(ts[max(j - one.run[j], 0)]),
               float(one.g[j])) for j in np.flatnonzero(one.alarm)]
        named[int(i)] = name_alarms(one, ev, p.free, p.log, 5.0, 1, float(ts[1] - ts[0]),
                                    ts.size)
        alarmed.append(int(i))
    failing = [j for j in FAILING if j < n]
    found = [j for j in failing if j in named]
    false = [j for j in alarmed if j not in FAILING]
    _figure_fleet(np.asarray(steps.g).max(axis=1), float(p.settings.threshold), failing)
    return {"machines": n, "seconds": FLEET_T, "rate_hz": FLEET_RATE, "simulate_s": made,
            "vmap_track_s": took, "failing": {str(j): FAILING[j] for j in failing},
            "found": found, "false_alarm_machines": false,
            "alarms": {str(i): [{k: a[k] for k in ("t", "parameters", "before", "after")}
                                for a in v] for i, v in named.items()}}


def _figure_fleet(gmax, threshold, failing) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.5))
    idx = np.arange(gmax.size)
    ax.semilogy(idx, np.maximum(gmax, 1e-2), ".", ms=3, color="C0", label="machine")
    ax.semilogy(failing, np.maximum(gmax[failing], 1e-2), "o", ms=7, mfc="none", color="C3",
                label="failing (k or c changed)")
    ax.axhline(threshold, color="r", lw=1, label="alarm threshold")
    ax.set_xlabel("machine")
    ax.set_ylabel("largest change statistic")
    ax.set_title(f"A fleet of {gmax.size} machines under one vmap")
    ax.legend(fontsize=8, loc="lower center", ncol=3)
    fig.tight_layout()
    FIGURES.mkdir(parents=True, exist_ok=True)
    fig.savefig(FIGURES / "tracking_fleet.png", dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--fleet", type=int, default=1000)
    ap.add_argument("--skip-guide", action="store_true")
    ap.add_argument("--skip-fleet", action="store_true")
    a = ap.parse_args()
    out = RESULTS / "track_tutorial.json"
    # A part not run keeps its results from the file.
    doc = json.loads(out.read_text()) if out.exists() else {}
    doc["machine"] = machine()
    if not a.skip_guide:
        doc["guide"] = part_guide(a.minutes, a.rate)
        print(json.dumps(doc["guide"], indent=1), flush=True)
    if not a.skip_fleet:
        doc["fleet"] = part_fleet(a.fleet)
        print(json.dumps(doc["fleet"], indent=1))
    RESULTS.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
