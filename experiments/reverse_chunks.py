"""Reverse mode with the CPU flags: the backward program before 2026-11-28 (one VJP per
step with the parameters too) beside `adjoint._deferred` at several chunk sizes
(`adjoint._CHUNK`; 0: the old program), compiled ahead in one process and timed in
interleaved rounds (a shared machine's load moves between rounds), each ratio to the
forward solve of the same rounds. Lab rig as in bench_reverse.py (10 s, 1001 samples,
rtol 1e-8, 10 parameters). Prints its rows (and the load average); writes nothing.

Run: `python experiments/reverse_chunks.py [--chunks 0,64,128] [--clock cpu|wall]`.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "src"))
from crank_jax.runtime.xla_flags import with_cpu_flags  # noqa: E402

os.environ["XLA_FLAGS"] = with_cpu_flags(os.environ.get("XLA_FLAGS"))

import numpy as np  # noqa: E402
from _bench import median_time, setup_jax, use_clock  # noqa: E402
from _reverse_programs import per_step  # noqa: E402

PARAMS = ("L", "b", "s", "m_c", "m_p", "m_s", "I_c", "I_p", "k", "c")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--chunks", default="0,64")
    ap.add_argument("--clock", choices=("wall", "cpu"), default="cpu")
    a = ap.parse_args(argv)
    jax = setup_jax()
    import jax.numpy as jnp

    import crank_jax as cj
    from crank_jax.runtime.xla_flags import backward_program
    from crank_jax.solve import adjoint

    if backward_program() != "loop":
        raise SystemExit("the CPU flags did not take")
    mech = cj.load_scene("lab-rig").mech.replace(c=1e-3)
    ts = jnp.linspace(0.0, 10.0, 1001)
    w = jnp.sin(jnp.arange(1001) * 0.7)
    theta0 = jnp.array([float(getattr(mech, n)) for n in PARAMS])

    def crank(theta):
        m = mech.replace(**dict(zip(PARAMS, theta)))
        return cj.simulate(m, 1.0, 0.0, ts, rtol=1e-8, atol=1e-10).phi

    fns = {"forward solve": jax.jit(crank).lower(theta0).compile()}
    grads, new = {}, adjoint._deferred
    for chunk in (int(c) for c in a.chunks.split(",")):
        label = "one VJP per step (before)" if chunk == 0 else f"deferred, chunk {chunk}"
        adjoint._deferred, adjoint._CHUNK = (per_step() if chunk == 0 else new), chunk or 64
        jax.clear_caches()  # a fresh trace of the backward pass
        t0 = time.perf_counter()
        fns[label] = jax.jit(jax.grad(lambda th: jnp.sum(w * crank(th)))).lower(theta0).compile()
        grads[label] = np.asarray(fns[label](theta0))
        print(f"{label}: compiled in {time.perf_counter() - t0:.0f} s", flush=True)
    adjoint._deferred, adjoint._CHUNK = new, 64
    ref = next(iter(grads.values()))
    use_clock(a.clock)
    times = {}
    for _ in range(3):
        for label, fn in fns.items():
            times.setdefault(label, []).append(
                median_time(lambda fn=fn: jax.block_until_ready(fn(theta0)), 11))
    fwd = np.median(times["forward solve"])
    for label, t in times.items():
        d = np.max(np.abs(grads[label] - ref)) / np.max(np.abs(ref)) if label in grads else None
        rel = "" if d is None else f", grad vs the first {d:.1e}"
        print(f"{label}: {np.median(t) * 1e3:.3f} ms, {np.median(t) / fwd:.2f}x{rel}")
    print(f"{a.clock} clock, load average {os.getloadavg()}")


if __name__ == "__main__":
    main()
