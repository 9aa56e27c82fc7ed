"""Where a cold fit's time goes: `crank-jax fit` with an empty cache and the first `cj.fit`
in a fresh Python process, split into import, tracing (jaxpr), lowering (to MLIR), XLA's
compile per program, and the rest (running the programs, the host's work).

Each run is a fresh interpreter (`--child`) that registers `jax.monitoring` listeners for
JAX's own compile events (`/jax/core/compile/*_duration`, with the function's name) before
anything is traced; the CLI child runs `crank_jax.cli.entry` as `crank-jax` does (its
`configure_cpu` flags, a fresh `CRANK_JAX_CACHE_DIR`), the library child `cj.fit` under
XLA's defaults with no cache (as a library user's first fit).

Run: `python experiments/compile_breakdown.py [--runs N] [--tag NAME]`; writes
`experiments/results/compile_breakdown[_TAG].json`.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

EVENTS = {"/jax/core/compile/jaxpr_trace_duration": "trace",
          "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
          "/jax/core/compile/backend_compile_duration": "compile"}


def child(mode: str, start: str, rec: str, out: str) -> None:
    """One cold run in this (fresh) process; writes its breakdown as JSON to `out`."""
    t0 = time.perf_counter()
    import jax
    from jax import monitoring

    per = defaultdict(lambda: defaultdict(float))

    def listen(event, secs, fun_name="?", **_):
        if event in EVENTS:
            per[fun_name][EVENTS[event]] += secs

    monitoring.register_event_duration_secs_listener(listen)
    t_jax = time.perf_counter()
    if mode == "cli":
        import importlib

        cli_main = importlib.import_module("crank_jax.cli.main")
        t_imp = time.perf_counter()
        # `crank-jax`'s entry point without its final `os._exit`
        sys.argv = ["crank-jax", "fit", rec, start, "--quiet", "--out", out + ".fit.json"]
        cli_main.configure_cpu()
        cli_main._quiet_runtime_logs()
        assert cli_main.main() == 0
    else:
        jax.config.update("jax_enable_x64", True)
        import crank_jax as cj

        t_imp = time.perf_counter()
        r = cj.fit(cj.load_scene(start), cj.load_data(rec), progress=False, warn=False)
        assert r.converged
    t_end = time.perf_counter()
    tot = {k: sum(v[k] for v in per.values()) for k in ("trace", "lower", "compile")}
    Path(out).write_text(json.dumps({
        "mode": mode, "total_s": t_end - t0, "import_jax_s": t_jax - t0,
        "import_crank_jax_s": t_imp - t_jax, "after_import_s": t_end - t_imp, **{
            f"{k}_s": v for k, v in tot.items()},
        "rest_s": t_end - t_imp - sum(tot.values()),
        "programs": {k: dict(v) for k, v in sorted(
            per.items(), key=lambda kv: -sum(kv[1].values()))}}))


def run(mode: str, start: Path, rec: Path, tmp: Path, i: int) -> dict:
    out = tmp / f"{mode}{i}.json"
    env = {k: v for k, v in os.environ.items() if k not in ("CRANK_JAX_NO_CACHE", "XLA_FLAGS")}
    if mode == "cli":
        env["CRANK_JAX_CACHE_DIR"] = str(tmp / f"cache{i}")
    else:
        env["CRANK_JAX_NO_CACHE"] = "1"
    t = time.perf_counter()
    subprocess.run([sys.executable, __file__, "--child", mode, str(start), str(rec), str(out)],
                   env=env, check=True, capture_output=True)
    res = json.loads(out.read_text())
    res["wall_s"] = time.perf_counter() - t
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--child", nargs=4)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--tag", default="")
    ap.add_argument("--modes", default="cli,lib")
    a = ap.parse_args(argv)
    if a.child:
        return child(*a.child)
    import numpy as np
    from _bench import machine, save, setup_jax

    setup_jax()
    import crank_jax as cj

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        lab = cj.load_scene("lab-rig")
        start, rec = tmp / "start.toml", tmp / "rec.csv"
        start.write_text(cj.scene_to_toml(cj.Scene(lab.mech.replace(k=2.4, c=0.004), phi0=1.0,
                                                   name="lab-rig-start")))
        cj.save_data(cj.synthesize(lab, t1=5.0, rate=200.0, noise_std=1e-3, seed=1), rec)
        load0 = os.getloadavg()
        runs = {m: [] for m in a.modes.split(",")}
        for i in range(a.runs):  # the modes interleaved: the machine's load drifts
            for m in runs:
                runs[m].append(run(m, start, rec, tmp, i))
        load1 = os.getloadavg()
    res = {"machine": machine(), "load_before": load0, "load_after": load1,
           "record": "lab-rig free decay, 1 mrad noise, 200 Hz, 5 s; k,c,phi0,dphi0 from "
                     "k=2.4, c=0.004"}
    for m, rs in runs.items():
        keys = [k for k in rs[0] if k.endswith("_s")]
        res[m] = {"medians": {k: float(np.median([r[k] for r in rs])) for k in keys},
                  "runs": rs}
        print(m, {k: round(v, 2) for k, v in res[m]["medians"].items()})
        for name, d in list(rs[0]["programs"].items())[:12]:
            print(f"   {name[:60]:60s}", {k: round(v, 2) for k, v in d.items()})
    save("compile_breakdown" + (f"_{a.tag}" if a.tag else ""), res, False)


if __name__ == "__main__":
    main()
