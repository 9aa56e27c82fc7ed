"""The fit's two Jacobian programs (the single-shooting start solve and the multiple-shooting
one, lab-rig free decay, 5 s at 200 Hz, 12 segments) traced, lowered and compiled in one
process under several per-program XLA compile options, with each executable's run time:
what a compile option buys a cold fit, and what it costs each call.

Run: `python experiments/fit_programs_options.py [--repeats N]`; writes
`experiments/results/fit_programs_options.json`. Under XLA's defaults unless `XLA_FLAGS`
says otherwise (`--cpu-flags` adds crank-jax's).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

OPTIONS = {
    "default": {},
    # XLA's default, named: a compile of its own (JAX caches executables in memory by
    # their options, and the start solve has compiled the single-shooting one with none)
    "default_named": {"xla_cpu_use_fusion_emitters": True},
    "llvm_no_expensive": {"xla_llvm_disable_expensive_passes": True},
    "backend_opt_1": {"xla_backend_optimization_level": 1},
    "backend_opt_0": {"xla_backend_optimization_level": 0},
    "split_1": {"xla_cpu_parallel_codegen_split_count": 1},
    "no_fusion_emitters": {"xla_cpu_use_fusion_emitters": False},
    "fast_compile": {"xla_cpu_opt_preset": "CPU_OPT_PRESET_FAST_COMPILE"},
    "fast_compile_no_emitters": {"xla_cpu_opt_preset": "CPU_OPT_PRESET_FAST_COMPILE",
                                 "xla_cpu_use_fusion_emitters": False},
}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--cpu-flags", action="store_true")
    ap.add_argument("--options", default=",".join(OPTIONS))
    ap.add_argument("--programs", default="single,multiple")
    ap.add_argument("--tag", default="")
    a = ap.parse_args(argv)
    if a.cpu_flags:
        from crank_jax.runtime.xla_flags import with_cpu_flags

        os.environ["XLA_FLAGS"] = with_cpu_flags(os.environ.get("XLA_FLAGS"))
    os.environ["CRANK_JAX_NO_CACHE"] = "1"
    import jax
    import jax.numpy as jnp
    import numpy as np
    from _bench import save, setup_jax

    setup_jax()
    import crank_jax as cj
    from crank_jax.identify.fit_plan import make_plan
    from crank_jax.identify.programs import jacobian_at
    from crank_jax.identify.request import normalize

    lab = cj.load_scene("lab-rig")
    start = cj.Scene(lab.mech.replace(k=2.4, c=0.004), phi0=1.0, name="lab-rig-start")
    data = cj.synthesize(lab, t1=5.0, rate=200.0, noise_std=1e-3, seed=1)
    req = normalize(
        start, data, ("k", "c", "phi0", "dphi0"), init="scene", method="lm",
        shooting="auto", segments=None, multistart=1, seed=0, max_steps=None, tol=1e-8,
        sigma=None, profile=None, window=None, progress=False, warn=False)
    plan = make_plan(req)  # compiles the start solve once (not timed)
    progs = {"single": (plan.single, plan.z0[:plan.single.p]), "multiple": (plan.shoot, plan.z0)}
    res = {"load_before": os.getloadavg(), "xla_flags": os.environ.get("XLA_FLAGS"),
           "programs": {}}
    for name, (prob, z) in progs.items():
        if name not in a.programs.split(","):
            continue
        z = jnp.asarray(z)
        t = time.perf_counter()
        lowered = jacobian_at.lower(prob, z)
        t_lower = time.perf_counter() - t
        out = {"trace_and_lower_s": t_lower, "options": {}}
        ref = None
        for opt in a.options.split(","):
            t = time.perf_counter()
            comp = lowered.compile(compiler_options=OPTIONS[opt])
            t_comp = time.perf_counter() - t
            call = lambda: jax.block_until_ready(comp(prob, z))  # noqa: E731
            vals = call()
            if ref is None:
                ref = vals
            diff = max(float(np.max(np.abs(np.asarray(x, float) - np.asarray(y, float))))
                       for x, y in zip(jax.tree.leaves(vals), jax.tree.leaves(ref)))
            ts = []
            for _ in range(a.repeats):
                t = time.perf_counter()
                call()
                ts.append(time.perf_counter() - t)
            out["options"][opt] = {"compile_s": t_comp, "run_ms": 1e3 * float(np.median(ts)),
                                   "max_abs_diff_vs_default": diff}
            print(name, opt, {k: round(v, 4) if isinstance(v, float) else v
                              for k, v in out["options"][opt].items()}, flush=True)
        print(name, "trace+lower", round(t_lower, 2), flush=True)
        res["programs"][name] = out
    res["load_after"] = os.getloadavg()
    save("fit_programs_options" + ("_cpu_flags" if a.cpu_flags else "")
         + (f"_{a.tag}" if a.tag else ""), res, False)


if __name__ == "__main__":
    sys.exit(main())
