"""Batch throughput: cost per trajectory of a `jax.vmap`-ed batch, N = 1 .. 1e5.

The lab rig with c = 1e-3, 10 s, 1001 samples; the batch varies phi0 over [0.9, 1.1] rad
(member 0 is the target configuration, phi0 = 1). Solver `"dopri8-uniform"` at rtol 1e-6
(the cheapest setting whose measured error is <= 1e-8 rad) and at the default rtol 1e-8.
Batches above `CHUNK` run in chunks of `CHUNK`. The peer is the compiled numba DP5 at
equal error: its time is interpolated (log-log) along its own work-precision curve,
measured in the same run, at member 0's measured error. Target (b): per-trajectory cost
of the N = 1e4 batch <= 0.25x numba's.

Run: `python experiments/bench_throughput.py [--smoke]`.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _bench import interp_time, median_time, save, setup_jax

jax = setup_jax()
import jax.numpy as jnp  # noqa: E402
import peers  # noqa: E402

import crank_jax as cj  # noqa: E402

CHUNK = 10_000


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true")
    smoke = ap.parse_args(argv).smoke
    sizes = [1, 100] if smoke else [1, 100, 1000, 10_000, 100_000]
    rtols = [1e-6] if smoke else [1e-6, 1e-8]
    t1, samples = (1.0, 101) if smoke else (10.0, 1001)
    mech = cj.load_scene("lab-rig").mech.replace(c=1e-3)
    ts = jnp.linspace(0.0, t1, samples)
    ref = np.asarray(cj.simulate(mech, 1.0, 0.0, ts, solver="dopri8", rtol=1e-14, atol=1e-16,
                                 max_steps=10**7).phi)
    p = peers.params_of(mech)

    # numba's work-precision curve on member 0, for the equal-error comparison.
    numba_curve = []
    if peers.HAVE_NUMBA:
        peers.dp5_numba(p, (1.0, 0.0), np.asarray(ts), 1e-6, 1e-8)
        for rtol in ([1e-7, 1e-9] if smoke else [10.0**-e for e in range(7, 15)]):
            ys, ns = peers.dp5_numba(p, (1.0, 0.0), np.asarray(ts), rtol, rtol * 1e-2)
            t = median_time(lambda rtol=rtol: peers.dp5_numba(p, (1.0, 0.0), np.asarray(ts),
                                                              rtol, rtol * 1e-2), 5)
            numba_curve.append({"rtol": rtol, "error": float(np.max(np.abs(ys[:, 0] - ref))),
                                "time_s": t, "steps": ns})
            print("numba", numba_curve[-1], flush=True)

    rows = []
    for rtol in rtols:
        @jax.jit
        def batch(phi0s, rtol=rtol):
            return jax.vmap(lambda a: cj.simulate(mech, a, 0.0, ts, solver="dopri8-uniform",
                                                  rtol=rtol, atol=rtol * 1e-2).phi)(phi0s)

        for n in sizes:
            if rtol != 1e-6 and n not in (1, 10_000):
                continue
            chunk = min(n, CHUNK)
            # Member 0 is the target phi0 = 1; the rest spread over [0.9, 1.1].
            phi0s = jnp.concatenate([jnp.ones(1), jnp.linspace(0.9, 1.1, chunk)[1:]])
            first = batch(phi0s)
            err = float(np.max(np.abs(np.asarray(first[0]) - ref)))
            nchunks = n // chunk

            def run(phi0s=phi0s, nchunks=nchunks):
                for _ in range(nchunks):
                    out = batch(phi0s)
                return jax.block_until_ready(out)

            t0 = time.perf_counter()
            t = median_time(run, repeats=1 if n >= 100_000 else (3 if n >= 10_000 else 5),
                            warmup=0 if n >= 10_000 else 1)
            per = t / n
            t_nb = (interp_time([r["error"] for r in numba_curve],
                                [r["time_s"] for r in numba_curve], err)
                    if numba_curve else None)
            rows.append({"rtol": rtol, "N": n, "chunk": chunk, "time_s": t, "per_traj_s": per,
                         "error_member0": err, "numba_per_traj_s_equal_error": t_nb,
                         "ratio_to_numba": None if t_nb is None else per / t_nb})
            print(rows[-1], f"({time.perf_counter() - t0:.1f} s)", flush=True)

    tgt = next((r for r in rows if r["N"] == 10_000 and r["rtol"] == 1e-6), None)
    target = {"goal": 0.25, "ratio": None if tgt is None else tgt["ratio_to_numba"],
              "error": None if tgt is None else tgt["error_member0"]}
    print("target (b):", target)
    save("throughput", {"t1": t1, "samples": samples, "chunk": CHUNK, "rows": rows,
                        "numba_curve": numba_curve, "target_b": target}, smoke)


if __name__ == "__main__":
    main()
