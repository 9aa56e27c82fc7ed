"""Rewrite the README's performance section from the results files.

Reads `experiments/results/{work_precision,throughput,gradients,startup}.json` and
replaces the text between `<!-- BEGIN performance (owner: performance) -->` and
`<!-- END performance -->` in README.md. `--print` writes the section to stdout instead.

Run: `python experiments/make_tables.py [--print]`.
"""

from __future__ import annotations

import argparse
import json
import re

from _bench import RESULTS, ROOT

BEGIN = "<!-- BEGIN performance (owner: performance) -->"
END = "<!-- END performance -->"


def _load(name):
    path = RESULTS / f"{name}.json"
    return json.loads(path.read_text()) if path.exists() else None


def _machine(m) -> str:
    v = m["versions"]
    return (f"{m['date']}, {m['cpu']} ({m['cores']} cores), {m['platform']}, "
            f"jax {v['jax']}, diffrax {v['diffrax']}, numba {v['numba']}; {m['note']}")


def _ms(t):
    return "n/a" if t is None else (f"{t * 1e3:.3g} ms" if t < 1 else f"{t:.3g} s")


def _us(t):
    return "n/a" if t is None else f"{t * 1e6:.3g} µs"


def _met(ok):
    return "**met**" if ok else "**not met**"


def section() -> str:
    wp, tp, gr, st, sk = (_load(n) for n in ("work_precision", "throughput", "gradients",
                                             "startup", "structure"))
    out = ["## Performance", "",
           "All numbers below come from the scripts in `experiments/` (rerun them, then "
           "`python experiments/make_tables.py` rewrites this section). Timings are medians "
           "of several runs; comparisons are ratios measured side by side in one run at "
           "equal measured error. The machine was shared with other jobs while these ran, "
           "so absolute times are noisy. No GPU was lent for this work: every number is "
           "CPU-only.", ""]
    out += ["### Where the speed comes from", "",
            "For scenes that are not stiff, with uniform save times and concrete parameters, "
            "`simulate(solver=\"auto\")` now uses `\"dopri8-uniform\"`: an integer number "
            "`m` of equal Dopri8 steps per save interval (diffrax's own Dopri8 tableau, "
            "stages unrolled, the right-hand side written so that XLA fuses each stage into "
            "~3 kernels). `m` is chosen before the solve from the linearised frequency and "
            "the tolerance, then checked: Dopri8's embedded error estimate, summed over all "
            "steps, must stay within `rtol`/`atol`, else `m` grows and the pass repeats. The "
            "sum over-estimates the global error, so this solver lands well below its "
            "tolerance (`tests/test_uniform.py` checks the measured error against the "
            "tolerance on every preset). Traced parameters (inside `jit`, `vmap`, `grad`) "
            "keep diffrax's adaptive solvers unless `solver=\"dopri8-uniform\"` is asked "
            "for. Also, `simulate` called outside any transformation now checks its inputs "
            "on the host instead of with `eqx.error_if`: a program with those callbacks "
            "cannot be stored in JAX's persistent compilation cache, so before this every "
            "CLI call recompiled the solve.", ""]
    if wp:
        out += ["### Work-precision", "", f"*{_machine(wp['machine'])}*", "",
                "![work-precision](docs/figures/work_precision.png)", "",
                "Run time against the max error in phi over 10 s, 1001 samples, rtol = "
                "1e-4..1e-12 (atol = rtol/100). Reference: diffrax Dopri8 at rtol 1e-14; "
                "the grey band is its disagreement with scipy DOP853 at 1e-13:", ""]
        out += ["| scene | error floor (ref vs DOP853) |", "|---|---|"]
        for label, c in wp["cases"].items():
            fl = c["error_floor"]
            out.append(f"| {label} | {'n/a' if fl is None else f'{fl:.1e}'} |")
        out += ["", "Each method at rtol = 1e-8 on the lab rig (c = 1e-3, phi0 = 1 rad):", "",
                "| method | max error (rad) | time | steps / RHS evals |", "|---|---|---|---|"]
        for m, rows in wp["cases"]["lab-rig (c=1e-3)"]["curves"].items():
            r = next((r for r in rows if r["rtol"] == 1e-8), None)
            if r:
                out.append(f"| {m} | {r['error']:.2e} | {_ms(r['time_s'])} | {r['steps']} |")
        out.append("")
    if tp:
        out += ["### Batch throughput", "", f"*{_machine(tp['machine'])}*", "",
                "Lab rig, c = 1e-3, 10 s, 1001 samples, a `jax.vmap`-ed batch over phi0 "
                f"(chunks of {tp['chunk']}), solver `dopri8-uniform`. The numba DP5 column "
                "is its per-trajectory time at the same measured error (interpolated on its "
                "work-precision curve from the same run).", "",
                "| rtol | N | per trajectory | error (member 0) | numba DP5 at equal error "
                "| ratio |", "|---|---|---|---|---|---|"]
        for r in tp["rows"]:
            ratio = "n/a" if r["ratio_to_numba"] is None else f"{r['ratio_to_numba']:.3f}"
            out.append(f"| {r['rtol']:.0e} | {r['N']} | {_us(r['per_traj_s'])} | "
                       f"{r['error_member0']:.1e} | {_us(r['numba_per_traj_s_equal_error'])} "
                       f"| {ratio} |")
        out.append("")
    if gr:
        out += ["### Gradients", "", f"*{_machine(gr['machine'])}*", "",
                f"Full Jacobian d phi(ts)/d theta, shape ({gr['samples']}, "
                f"{len(gr['params'])}), theta = {', '.join(gr['params'])}; lab rig, c = 1e-3, "
                "rtol 1e-8.", "", "| method | time | × one forward solve | compile |",
                "|---|---|---|---|"]
        for r in gr["rows"]:
            comp = "" if r["compile_s"] is None else f"{r['compile_s']:.1f} s"
            out.append(f"| {r['method']} | {_ms(r['time_s'])} | {r['ratio']:.2f} | {comp} |")
        dis = ", ".join(f"{k}: {v:.1e}" for k, v in gr["max_rel_disagreement"].items())
        out += ["", f"Largest disagreement between the Jacobians, relative to each "
                f"parameter's largest sensitivity: {dis}.", ""]
    if st:
        out += ["### Start-up", "", f"*{_machine(st['machine'])}*", "",
                "`crank-jax simulate lab-rig --out x.csv` in a fresh process:", "",
                "| | wall time |", "|---|---|",
                f"| cold (empty compilation cache) | {st['cold_s']:.2f} s |",
                f"| warm (persistent cache filled) | {st['warm_s']:.2f} s |",
                f"| of which `import crank_jax` | {st['import_crank_jax_s']:.2f} s |",
                f"| of which the rest (trace, cache load, run, write) | "
                f"{st['warm_after_import_s']:.2f} s |", ""]
    if sk:
        out += ["### Skip what a scene doesn't need", "", f"*{_machine(sk['machine'])}*", "",
                "The compiled solve (`dopri8-uniform`, 10 s, 1001 samples) of each scene: "
                "instructions in the optimised HLO, XLA's flop estimate, run time.", "",
                "| scene | HLO instructions | flops (XLA estimate) | time | steps |",
                "|---|---|---|---|---|"]
        for r in sk["rows"]:
            out.append(f"| {r['case']} | {r['hlo_instructions']} | {r['flops_estimate']:.3g} "
                       f"| {_ms(r['time_s'])} | {r['steps']} |")
        out.append("")
    out += ["### Targets", ""]
    if wp:
        a = wp["target_a"]
        sp = a["speedup"]
        out.append(f"- (a) one trajectory, default solver, >= 25x faster than scipy DOP853 at "
                   f"equal error: {_met(sp is not None and sp >= 25)}, "
                   f"{'n/a' if sp is None else f'{sp:.2f}x'} (default: error "
                   f"{a['default_error']:.1e} rad in {_ms(a['default_time_s'])}; DOP853 at "
                   f"that error {_ms(a['dop853_time_s_at_equal_error'])}).")
    if tp:
        b = tp["target_b"]
        out.append(f"- (b) per-trajectory cost of a batch of 1e4 <= 0.25x the compiled numba "
                   f"DP5: {_met(b['ratio'] is not None and b['ratio'] <= 0.25)}, "
                   f"{'n/a' if b['ratio'] is None else format(b['ratio'], '.3f') + 'x'} "
                   f"(at error {'n/a' if b['error'] is None else format(b['error'], '.1e')} "
                   "rad).")
    if gr:
        c = gr["target_c"]
        out.append(f"- (c) full Jacobian <= 5x one forward solve: {_met(c['ratio'] <= 5)}, "
                   f"{c['ratio']:.2f}x ({c['best_method']}).")
    if st:
        d = st["target_d"]
        out.append(f"- (d) warm-cache `crank-jax simulate lab-rig` <= 3 s: {_met(d['met'])}, "
                   f"{d['warm_s']:.2f} s.")
    out.append("")
    return "\n".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--print", action="store_true")
    a = ap.parse_args(argv)
    text = section()
    if a.print:
        print(text)
        return
    readme = ROOT / "README.md"
    src = readme.read_text()
    pat = re.compile(re.escape(BEGIN) + ".*?" + re.escape(END), re.S)
    if not pat.search(src):
        raise SystemExit("README.md has no performance section markers")
    readme.write_text(pat.sub(lambda _: f"{BEGIN}\n{text}\n{END}", src))
    print("rewrote the performance section of README.md")


if __name__ == "__main__":
    main()
