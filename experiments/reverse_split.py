"""Where reverse mode's time goes with the CPU flags: the forward pass, and the backward
pass's state part and parameter part. Why the issue-26 goal of grad <= 3x one forward
solve with the flags is not met (bench_reverse.py).

The lab rig as in bench_reverse.py (10 s, 1001 samples, rtol 1e-8, 10 parameters), with
the CPU flags (this script sets them before JAX starts), medians on the process CPU
clock. Rows:

- one forward solve (`simulate` under `jax.jit`);
- the forward pass of the grad: the same solve with its step log (`adjoint.forward`);
- `jax.grad` (the discrete adjoint, one VJP of each step in a loop, the parameters'
  cotangents after it: `adjoint._deferred`);
- **a diagnostic, not a gradient:** a backward loop with each step's VJP taken with
  respect to its start state only (the field's parameters held constant), so the
  parameters' cotangents are never formed (experiments/_reverse_programs.py). Its
  backward pass is what a reverse mode costs that carries the state's cotangent through
  the steps and nothing else.

The backward pass is the grad less the forward pass with its log; its parameter part is
the grad less the diagnostic. Writes experiments/results/reverse_split.json.

Run: `python experiments/reverse_split.py [--smoke]`.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import subprocess
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "src"))
from crank_jax.runtime.xla_flags import backward_program, with_cpu_flags  # noqa: E402

os.environ["XLA_FLAGS"] = with_cpu_flags(os.environ.get("XLA_FLAGS"))

from _bench import median_time, save, setup_jax, use_clock  # noqa: E402

PARAMS = ("L", "b", "s", "m_c", "m_p", "m_s", "I_c", "I_p", "k", "c")


def measure(mode: str, smoke: bool) -> dict:
    """This process's times (s): plain (the forward solve, the forward pass with its log,
    the grad) or the diagnostic (`mode` "state": the grad with `state_only`). One mode per
    process: JAX caches a traced backward pass across `jax.jit`s of the same solve."""
    jax = setup_jax()
    import jax.numpy as jnp

    import crank_jax as cj
    from crank_jax.model import CrankField

    adjoint = importlib.import_module("crank_jax.solve.adjoint")
    if backward_program() != "loop":
        raise SystemExit("the CPU flags did not take: XLA_FLAGS was read before this script")
    t1, samples = (1.0, 101) if smoke else (10.0, 1001)
    mech = cj.load_scene("lab-rig").mech.replace(c=1e-3)
    ts = jnp.linspace(0.0, t1, samples)
    w = jnp.sin(jnp.arange(samples) * 0.7)
    theta0 = jnp.array([float(getattr(mech, n)) for n in PARAMS])
    rtol, atol = 1e-8, 1e-10

    def model(theta):
        return mech.replace(**dict(zip(PARAMS, theta)))

    def phi(theta):
        return cj.simulate(model(theta), 1.0, 0.0, ts, rtol=rtol, atol=atol).phi

    def logged(theta):
        field = CrankField(model(theta), cj.NoLoad(), cj.NoLoad()).packed()
        return adjoint.forward(field, (jnp.array(1.0), jnp.array(0.0)), ts, jnp.array(rtol),
                               jnp.array(atol), max_steps=200_000)[0]

    grad = jax.jit(jax.grad(lambda theta: jnp.sum(w * phi(theta))))
    if mode == "state":
        from _reverse_programs import per_step
        adjoint._deferred = per_step(params=False)
        # No parameter cotangent is formed: the diagnostic's "gradient" is zero.
        assert float(jnp.max(jnp.abs(grad(theta0)))) == 0.0
        fns = {"grad, state cotangents only (diagnostic)": grad}
    else:
        assert float(jnp.max(jnp.abs(grad(theta0)))) > 0.0
        fns = {"forward solve": jax.jit(phi), "forward pass with its log": jax.jit(logged),
               "grad": grad}
    times = {}
    for label, fn in fns.items():
        times[label] = median_time(lambda fn=fn: jax.block_until_ready(fn(theta0)),
                                   3 if smoke else 31)
    return times


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--clock", choices=("wall", "cpu"), default="cpu",
                    help="time on the process CPU clock (default: a shared machine) or wall")
    ap.add_argument("--mode", choices=("plain", "state"), help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    use_clock(a.clock)
    if a.mode is not None:  # a child: one mode, its times as JSON on the last line
        print(json.dumps(measure(a.mode, a.smoke)))
        return
    times = {}
    for mode in ("plain", "state"):
        cmd = [sys.executable, __file__, "--mode", mode, "--clock", a.clock]
        out = subprocess.run(cmd + (["--smoke"] if a.smoke else []), check=True,
                             capture_output=True, text=True).stdout
        times.update(json.loads(out.strip().splitlines()[-1]))
    for label, t in times.items():
        print(f"{label}: {t * 1e3:.3f} ms")
    fwd, log = times["forward solve"], times["forward pass with its log"]
    diag = times["grad, state cotangents only (diagnostic)"]
    back, state = times["grad"] - log, diag - log
    split = {"backward_s": back, "backward_state_part_s": state,
             "backward_parameter_part_s": back - state,
             "grad_ratio": times["grad"] / fwd, "state_only_ratio": diag / fwd}
    print({k: round(v, 6) for k, v in split.items()})
    save("reverse_split", {"t1": 1.0 if a.smoke else 10.0, "samples": 101 if a.smoke else 1001,
                           "params": PARAMS, "times_s": times, **split}, a.smoke)


if __name__ == "__main__":
    main()
