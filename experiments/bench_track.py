"""Tracking's speed: the filter's warm cost on a 12,000-sample record, a fleet of records
under one `jax.vmap` against one record, and the per-sample cost of the peer a user would
write: a plain numpy extended Kalman filter stepping the same model (the same
Runge-Kutta substeps and equations, its Jacobians by central differences, the model's
acceleration a compiled function called from Python).

    python experiments/bench_track.py [--fleet 64] [--peer-samples 2000] [--clock cpu]
    python experiments/bench_track.py --smoke        # tiny; bench_track.smoke.json
    python experiments/bench_track.py --table        # rewrite the docs table and stop

Writes experiments/results/bench_track.json; `--table` rewrites the section between
`<!-- BEGIN tracking -->` and `<!-- END tracking -->` in docs/benchmarks/performance.md.
"""

from __future__ import annotations

import argparse
import json
import time

from _bench import RESULTS, ROOT, median_time, save, setup_jax, use_clock, write_section

jax = setup_jax()

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.online import prepare, run_filter, track  # noqa: E402

LAB = cj.load_scene("lab-rig")
PAGE = ROOT / "docs" / "benchmarks" / "performance.md"
BEGIN, END = "<!-- BEGIN tracking -->", "<!-- END tracking -->"


def record(n: int, seed: int = 0, rate: float = 200.0) -> cj.Data:
    """The lab rig under a measured two-tone torque, `n` samples at `rate` Hz, 1 mrad."""
    ts = np.arange(n) / rate
    tau = 0.15 * np.sin(2 * np.pi * 3.1 * ts) + 0.1 * np.sin(2 * np.pi * 5.3 * ts + 1.0)
    torque = cj.SampledLoad(ts, tau)
    phi = np.asarray(cj.simulate(LAB.mech, 0.3, 0.0, ts, torque=torque, rtol=1e-10,
                                 atol=1e-12).phi)
    phi = phi + np.random.default_rng(seed).normal(0.0, 1e-3, n)
    return cj.Data(ts, phi, torque=torque, source=f"seed {seed}")


def numpy_ekf(model, settings, state, ts, ys) -> np.ndarray:
    """The peer: the same filter in numpy, one sample at a time (central differences)."""
    acc = jax.jit(lambda z, phi, dphi, t: cj.model.acceleration(
        model.mech_at(z), phi, dphi, t, model.load, model.torque))

    def propagate(x, t, dt):
        z, y, h = x[2:], x[:2].copy(), dt / model.substeps
        f = lambda s, y: np.array([y[1], float(acc(z, y[0], y[1], s))])  # noqa: E731
        for k in range(model.substeps):
            s = t + k * h
            k1 = f(s, y)
            k2 = f(s + h / 2, y + h / 2 * k1)
            k3 = f(s + h / 2, y + h / 2 * k2)
            k4 = f(s + h, y + h * k3)
            y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        return np.concatenate([y, z])

    x, P, tp = np.asarray(state.x), np.asarray(state.P), float(state.t)
    R = np.diag(np.asarray(settings.R))
    q = np.concatenate([[0.0, float(settings.q_accel)], np.asarray(settings.q_param)])
    out = []
    for t, y in zip(ts, ys):
        dt = t - tp
        xp = propagate(x, tp, dt)
        F = np.stack([(propagate(x + e, tp, dt) - propagate(x - e, tp, dt)) / (2 * e.sum())
                      for e in np.eye(x.size) * 1e-7 * np.maximum(1, np.abs(x))], axis=1)
        P = F @ P @ F.T + np.diag(q) * dt
        H = np.zeros((1, x.size))
        H[0, 0] = 1.0  # the angle channel
        S = H @ P @ H.T + R
        K = P @ H.T @ np.linalg.inv(S)
        x = xp + K @ (y - xp[:1])
        IKH = np.eye(x.size) - K @ H
        P = IKH @ P @ IKH.T + K @ R @ K.T
        tp = t
        out.append(x)
    return np.array(out)


def table(doc: dict) -> str:
    """The docs section from a results document."""
    m = doc["machine"]
    return "\n".join([
        "## Tracking", "",
        f"`experiments/bench_track.py` ({m['date']}, {m['cores']} cores, {m['cpu']}; a "
        "shared machine, other jobs running: wall times are rough; results in "
        "`experiments/results/bench_track.json`). The lab rig under a measured two-tone "
        f"torque, {doc['samples']} samples at 200 Hz, free `k` and `c`, "
        f"{doc['substeps']} Runge-Kutta substep(s) a sample.", "",
        "| what | time | target |", "|---|---|---|",
        f"| the filter, warm, {doc['samples']} samples | {doc['warm_filter_s']:.3g} s "
        f"({doc['per_sample_us']:.3g} µs a sample) | |",
        f"| a warm `track()` call (record read, start, filter, alarms) | "
        f"{doc['warm_track_call_s']:.3g} s | <= 1 s |",
        f"| the first `track()` call in a process (compilation) | "
        f"{doc['first_track_call_s']:.3g} s | |",
        f"| {doc['fleet']} records under one `vmap`, against one record | "
        f"{doc['fleet_over_one']:.3g}x | <= 8x |",
        f"| a plain numpy EKF on the same model (peer), per sample | "
        f"{doc['peer_per_sample_us']:.3g} µs ({doc['peer_over_ours_per_sample']:.3g}x "
        f"ours; parameters equal to {doc['peer_parameter_max_abs_difference']:.1g}) | |"])


def write_table(doc: dict) -> None:
    write_section(PAGE, BEGIN, END, table(doc), "tracking")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=12_000)
    ap.add_argument("--fleet", type=int, default=64)
    ap.add_argument("--peer-samples", type=int, default=2_000)
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall")
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--table", action="store_true",
                    help="rewrite the docs table from bench_track.json and stop")
    a = ap.parse_args()
    if a.table:
        write_table(json.loads((RESULTS / "bench_track.json").read_text()))
        return
    use_clock(a.clock)
    if a.smoke:
        a.samples, a.fleet, a.peer_samples = 1_000, 4, 50
    data = record(a.samples)
    t = time.perf_counter()
    track(LAB, data, free=("k", "c"), start="scene", progress=False)
    first = time.perf_counter() - t
    model, settings, state = prepare(LAB, data, free=("k", "c"), start="scene",
                                     progress=False)[:3]
    n = a.samples
    ts, ys = jnp.asarray(data.ts), jnp.asarray(data.phi)[:, None]
    ok = jnp.ones(n, bool)
    one = median_time(lambda: jax.block_until_ready(run_filter(model, settings, state, ts,
                                                                ys, ok)), repeats=5)
    api = median_time(lambda: track(LAB, data, free=("k", "c"), start="scene",
                                    progress=False), repeats=3)
    fleet = jnp.stack([jnp.asarray(record(n, seed=s).phi)[:, None] for s in range(a.fleet)])
    batch = jax.jit(jax.vmap(lambda y: run_filter(model, settings, state, ts, y, ok)))
    many = median_time(lambda: jax.block_until_ready(batch(fleet)), repeats=3)
    m = a.peer_samples
    t = time.perf_counter()
    ref = numpy_ekf(model, settings, state, np.asarray(ts[:m]), np.asarray(ys[:m]))
    peer = (time.perf_counter() - t) / m
    _, ours = run_filter(model, settings, state, ts, ys, ok)
    agree = float(np.max(np.abs(ref[:, 2:] - np.asarray(ours.x)[:m, 2:])))
    rows = {"samples": n, "substeps": model.substeps, "first_track_call_s": first,
            "warm_filter_s": one, "warm_track_call_s": api,
            "per_sample_us": one / n * 1e6, "fleet": a.fleet, "fleet_s": many,
            "fleet_over_one": many / one, "peer_per_sample_us": peer * 1e6,
            "peer_over_ours_per_sample": peer / (one / n),
            "peer_parameter_max_abs_difference": agree}
    for k, v in rows.items():
        print(f"{k}: {v:.4g}" if isinstance(v, float) else f"{k}: {v}")
    save("bench_track", rows, a.smoke)


if __name__ == "__main__":
    main()
