"""Tracking's speed: the filter's warm cost on a 12,000-sample record, a fleet of records
under one `jax.vmap` against one record, and the per-sample cost of the peer a user would
write: a plain numpy extended Kalman filter stepping the same model (the same
Runge-Kutta substeps and equations, its Jacobians by central differences, the model's
acceleration a compiled function called from Python).

    python experiments/bench_track.py [--fleet 64] [--peer-samples 2000] [--clock cpu]
    python experiments/bench_track.py --smoke        # tiny; bench_track.smoke.json
    python experiments/bench_track.py --table        # rewrite the docs table and stop
    python experiments/bench_track.py --stream [--stream-samples 10000000]
        # a long record tracked from its .npy file: time and peak memory
        # (bench_track_stream.json; --table adds its row when that file is there)

Writes experiments/results/bench_track.json; `--table` rewrites the section between
`<!-- BEGIN tracking -->` and `<!-- END tracking -->` in docs/benchmarks/performance.md.
"""

from __future__ import annotations

import argparse
import json
import time

from _bench import RESULTS, ROOT, median_time, rk4, save, setup_jax, use_clock, write_section

jax = setup_jax()

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.online import prepare, run_filter, track, track_stream  # noqa: E402

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
        return np.concatenate([rk4(f, t, y, h, model.substeps), z])

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


def peak_mb() -> float:
    """This process's peak resident memory so far (VmHWM), MB."""
    with open("/proc/self/status") as f:
        return next(int(ln.split()[1]) / 1024 for ln in f if ln.startswith("VmHWM:"))


def stream(n: int, every: int, smoke: bool) -> None:
    """Track an `n`-sample record (1 kHz: a free decay, then the rig at rest, 1 mrad noise)
    from its .npy file with `track_stream`, keeping every `every`-th sample: the time,
    and the peak memory over a warm call's."""
    import tempfile
    from pathlib import Path

    rate = 1000.0
    head = 20_000
    ts = np.arange(head) / rate
    phi = np.asarray(cj.simulate(LAB.mech, 1.0, 0.0, ts).phi)
    kw = dict(free=("k", "c"), start="scene", progress=False, every=every)
    with tempfile.TemporaryDirectory() as tmp:
        short, long_ = Path(tmp) / "short.npy", Path(tmp) / "long.npy"
        rng = np.random.default_rng(0)
        np.save(short, np.stack([ts, phi + rng.normal(0, 1e-3, head)], 1))
        # The long file is written a block at a time by plain writes (never whole in
        # memory here, and no memory map whose pages would count in this process's peak).
        with open(long_, "wb") as f:
            np.lib.format.write_array_header_1_0(
                f, {"descr": "<f8", "fortran_order": False, "shape": (n, 2)})
            for lo in range(0, n, 1_000_000):
                hi = min(lo + 1_000_000, n)
                t = np.arange(lo, hi) / rate
                y = np.zeros(hi - lo)
                y[:max(0, min(hi, head) - lo)] = phi[lo:min(hi, head)]
                np.stack([t, y + rng.normal(0, 1e-3, hi - lo)], 1).tofile(f)
        track_stream(LAB, short, **kw)
        before = peak_mb()
        t0 = time.perf_counter()
        res = track_stream(LAB, long_, **kw)
        took = time.perf_counter() - t0
        after = peak_mb()
    outputs_mb = n * (2 * (2 + 2) + 4) * 8 / 2**20  # state, se, innovation, g, alarm, run
    rows = {"samples": n, "rate_hz": rate, "every": every, "kept": int(res.t.size),
            "seconds": took, "per_sample_us": took / n * 1e6, "peak_before_mb": before,
            "peak_after_mb": after, "peak_growth_mb": after - before,
            "full_outputs_mb": outputs_mb, "record_mb": n * 2 * 8 / 2**20,
            "alarms": len(res.alarms)}
    for k, v in rows.items():
        print(f"{k}: {v:.4g}" if isinstance(v, float) else f"{k}: {v}")
    save("bench_track_stream", rows, smoke)


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
        f"ours; parameters equal to {doc['peer_parameter_max_abs_difference']:.1g}) | |"]
        + _stream_rows())


def _stream_rows() -> list[str]:
    """The streamed record's rows, when `bench_track_stream.json` is there."""
    path = RESULTS / "bench_track_stream.json"
    if not path.exists():
        return []
    s = json.loads(path.read_text())
    return ["", f"A long record streamed from its `.npy` file (`--stream`, "
            f"{s['machine']['date']}): `track_stream` on {s['samples']:.3g} samples at "
            f"{s['rate_hz']:g} Hz keeping every {s['every']}-th (the lab rig's free decay, "
            "then the rig at rest, 1 mrad noise; free `k` and `c`). The machine was shared "
            "with a load of about 10 on its 2 cores: the time a sample is not comparable "
            "with the in-memory row above; the memory is the point.", "",
            "| what | figure |", "|---|---|",
            f"| time | {s['seconds']:.0f} s ({s['per_sample_us']:.3g} µs a sample) |",
            f"| peak memory, growth over a warm short call | {s['peak_growth_mb']:.0f} MB "
            f"(peak {s['peak_after_mb']:.0f} MB) |",
            f"| the per-sample outputs it did not keep / the record itself | "
            f"{s['full_outputs_mb']:.0f} MB / {s['record_mb']:.0f} MB |"]


def write_table(doc: dict) -> None:
    write_section(PAGE, BEGIN, END, table(doc), "tracking")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=12_000)
    ap.add_argument("--fleet", type=int, default=64)
    ap.add_argument("--peer-samples", type=int, default=2_000)
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall")
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--stream", action="store_true",
                    help="time a long record tracked from its file (track_stream) and stop")
    ap.add_argument("--stream-samples", type=int, default=10_000_000)
    ap.add_argument("--stream-every", type=int, default=1000)
    ap.add_argument("--table", action="store_true",
                    help="rewrite the docs table from bench_track.json and stop")
    a = ap.parse_args()
    if a.table:
        write_table(json.loads((RESULTS / "bench_track.json").read_text()))
        return
    use_clock(a.clock)
    if a.stream:
        stream(100_000 if a.smoke else a.stream_samples, a.stream_every, a.smoke)
        return
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
