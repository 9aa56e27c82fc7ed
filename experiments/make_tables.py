"""Rewrite the docs site's performance page from the results files.

Reads `experiments/results/{work_precision,throughput,gradients,startup,fusion}.json` and
replaces the text between `<!-- BEGIN performance (owner: performance) -->` and
`<!-- END performance -->` in docs/benchmarks/performance.md (figure links made relative
to that page). `--print` writes the section to stdout instead.

Run: `python experiments/make_tables.py [--print]`.
"""

from __future__ import annotations

import argparse
import json
import re

import numpy as np
from _bench import FIGURES, RESULTS, ROOT, interp_time

BEGIN = "<!-- BEGIN performance (owner: performance) -->"
END = "<!-- END performance -->"


def _load(name):
    path = RESULTS / f"{name}.json"
    return json.loads(path.read_text()) if path.exists() else None


def reverse_table() -> list[str]:
    """The Reverse mode section (experiments/bench_reverse.py's two results files), or
    nothing before its first run."""
    runs = {tag: _load("gradients_reverse" + tag) for tag in ("", "_cpu_flags")}
    if not all(runs.values()):
        return []
    base, flags = runs[""], runs["_cpu_flags"]
    out = ["### Reverse mode", "", f"*{_machine(base['machine'])}*", "",
           f"`jax.grad` of `sum(w * phi(ts))` over {len(base['params'])} parameters "
           f"({', '.join(base['params'])}); lab rig, c = 1e-3, {base['samples']} samples, "
           "rtol 1e-8 (`experiments/bench_reverse.py`, one process per setting, each "
           f"ratio to that process's forward solve; {base.get('clock', 'wall')} clock, "
           "medians).", "",
           "| | XLA defaults | × its forward solve | CPU flags | × its forward solve |",
           "|---|---|---|---|---|"]
    by = {r["method"]: r for r in base["rows"]}
    for b in flags["rows"]:  # the flags' run also has the program of before 2026-11-28
        a = by.get(b["method"])
        cells = f"{_ms(a['time_s'])} | {a['ratio']:.2f}" if a else "(not this setting's) |"
        out.append(f"| {b['method']} | {cells} | {_ms(b['time_s'])} | {b['ratio']:.2f} |")
    comp = " / ".join(f"{r['rows'][1]['compile_s']:.0f} s" for r in (base, flags))
    other = "wall" if base.get("clock", "wall") == "cpu" else "process CPU"
    if "other_clock_ratio" in base["rows"][1]:
        out += ["", f"On the {other} clock, in the same runs, the crank-jax grad took "
                f"{base['rows'][1]['other_clock_ratio']:.2f}x its forward solve under the "
                f"defaults and {flags['rows'][1]['other_clock_ratio']:.2f}x with the flags "
                f"(plain diffrax: {base['rows'][-1]['other_clock_ratio']:.0f}x and "
                f"{flags['rows'][-1]['other_clock_ratio']:.0f}x). Under the defaults XLA runs "
                "the backward blocks' large kernels on both cores: the process CPU clock "
                "counts that time twice, a user's wall clock once."]
    if "grad_vs_per_step_rel" in flags:
        old = flags["rows"][2]
        out += ["", f"With the flags the parameters' cotangents are formed after each block's "
                "step loop, from the stages' points and cotangents, by VJPs of the field over "
                "64 points at a time (`adjoint._deferred`, issue 40): the grad took "
                f"{flags['rows'][1]['ratio']:.2f}x its forward solve against "
                f"{old['ratio']:.2f}x for the program before it (one VJP per step with the "
                "parameters too), compiled and measured in the same process (load average "
                f"{flags['load_avg'][0]:.1f}); the two gradients agree to "
                f"{flags['grad_vs_per_step_rel']:.1e}. These rows are timed one after the other "
                "(the load moves between them); timed in interleaved rounds in one process "
                "(`experiments/reverse_chunks.py`, 2026-11-28 01:35-01:43 UTC, load ~15, "
                "cpu clock) the new program took 3.67x its forward solve against 4.78x "
                "(64 points a chunk; 128: 3.92x; in an earlier run at load ~12-19, 8: 3.39x, "
                "16: 3.44x, 32: 3.33x, 64: 3.12x, old 3.77x). One VJP over all the block's 3584 "
                "points at once was as slow as the old program (4.04x against 4.0x, one run "
                "at load ~12): XLA:CPU runs its ~440 kernels one after another over the "
                "whole block."]
    out += ["", f"Goals (issue 40): the crank-jax grad <= {base['goal']['ratio']:g}x under "
            f"the defaults ({_met(base['goal']['met'])}), <= {flags['goal']['ratio']:g}x "
            f"with the flags ({_met(flags['goal']['met'])}). The ratios move between runs "
            "on one machine: on 2026-11-28 between 10:44 and 10:50 UTC three runs gave "
            "2.53x, 3.79x and 3.72x with the flags and 5.01x, 5.55x and 4.52x under the "
            "defaults (cpu clock), against 2.54x and 4.24x at 01:57 UTC; the table is "
            "a rerun at 20:14 UTC, after the field's acceleration was traced once per "
            "program (`model/dynamics.py`). That change does not move the grad: six "
            "alternated runs with the flags that evening, the code before it (e2cb2f3) and "
            "after, gave 4.51x, 3.88x, 5.02x before and 5.05x, 3.97x, 4.78x after "
            "(`bench_reverse.py --setting cpu_flags`, cpu clock; the forward solve "
            "0.85-1.13 ms). Its first call (compilation) "
            f"took {comp}. It agrees with plain diffrax's gradient to "
            f"{base['grad_vs_plain_diffrax_rel']:.1e} (relative to the largest component: "
            "two solutions at the tolerance). Before issue 26 the grad differentiated a "
            "diffrax Dopri8 re-solve: 51.8 ms (68x) under the defaults, 4.35 ms (12x) with "
            "the flags. The backward pass differs by setting (`solve/adjoint.py`): with "
            "the flags one VJP per step in a loop that XLA compiles into one function "
            "(the parameters' part after it, above); "
            "under the defaults, where that loop would dispatch each of a step's ~600 "
            "kernels (90x), blocks of 256 steps with a hand-written adjoint of the stage "
            "recursion (the stages recomputed in one scan with the field's state "
            "Jacobians, then one parameter VJP over the block's stage points), whose field "
            "evaluations over the block's points take sin, cos and 1/sqrt as arithmetic "
            "that XLA:CPU vectorises (`trig.traced_as(field, 'arithmetic')`, as the "
            "lockstep batch does; "
            "2026-11-27: 9.8 -> 5.8 ms, 9.4x -> 5.5x, on the same machine). With the flags "
            "those blocks took 3.3 ms against 2.5 ms for the loop of one VJP per step "
            "(2026-11-27), so the flags keep the loop. The step "
            "loop logs accepted steps to a 32-step buffer that the outer loop copies out, "
            "so the loop's buffers stay small enough for XLA:CPU to run it inline. "
            "Compile times are wall-clock.", ""]
    return out + _reverse_split()


def _reverse_split() -> list[str]:
    """Why the flags' goal is not met (experiments/reverse_split.py), or nothing before
    its first run."""
    r = _load("reverse_split")
    if r is None:
        return []
    t = r["times_s"]
    return [f"Where the time went with the flags ({r['machine']['date']}, "
            f"`experiments/reverse_split.py`, {r.get('clock', 'wall')} clock): one forward "
            f"solve {_ms(t['forward solve'])}; the grad's forward pass, the same solve with "
            f"its step log, {_ms(t['forward pass with its log'])}; its backward pass "
            f"{_ms(r['backward_s'])}, of which {_ms(r['backward_state_part_s'])} carries "
            f"the state's cotangent through the steps and {_ms(r['backward_parameter_part_s'])}"
            " forms the parameters' cotangents (measured as the difference with a "
            "diagnostic run whose step VJPs leave the parameters out). Without the "
            f"parameters' cotangents the grad took {r['state_only_ratio']:.1f}x one forward "
            f"solve, with them {r['grad_ratio']:.1f}x (the grad's program of the run's date). "
            "Tried and slower (2026-11-27): that part as one VJP of the step's 14 field "
            "evaluations side by side, inside the loop (grad 5.4-6.7 ms against 2.5-3.0 "
            "ms); the vectorised blocks (above).", ""]


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
    wp, tp, gr, st, sk, ee, fu = (_load(n) for n in (
        "work_precision", "throughput", "gradients", "startup", "structure", "end_to_end",
        "fusion"))
    out = ["## Performance", "",
           "All numbers below come from the scripts in `experiments/` (rerun them, then "
           "`python experiments/make_tables.py` rewrites this section). Timings are medians "
           "of several runs; comparisons are ratios measured side by side in one run at "
           "equal measured error. The machine was shared with other jobs while these ran, "
           "so absolute times are noisy. No GPU was lent for this work: every number is "
           "CPU-only.", ""]
    out += ["### Where the speed comes from", "",
            "For scenes that are not stiff and have no sampled load, `simulate(solver="
            "\"auto\")` uses `\"dopri8-adaptive\"` (`solve/adaptive.py`): diffrax's Dopri8 "
            "tableau, error norm and integral controller, with the stages unrolled into "
            "straight-line code that XLA fuses (`FusedERK`), the first stage taken from the "
            "previous step's last, and the dense output evaluated once per block of step "
            "attempts for the save times the block covers. The step loop writes a chunk "
            "of 28 save times to a 512-byte buffer that an outer loop copies out: XLA's "
            "CPU runtime runs a loop body's kernels one after another in the calling "
            "thread only while its buffers are that small, and the step loop that carried "
            "all the outputs paid ~0.8 us more per step (1.6x the solve). Its step count "
            "follows the motion, not the save grid "
            "(907 steps on the lab rig at rtol 1e-8, as diffrax's Dopri8). Under `jax.vmap` "
            "a `custom_vmap` rule (`solve/lockstep.py`) steps the whole batch with one step "
            "size that every member's error allows, so the batch is plain SIMD arithmetic "
            "(no per-member scatter or select); reverse mode goes through a `custom_vjp` "
            "whose backward pass is the discrete adjoint of the solve's steps "
            "(`solve/adjoint.py`; the Reverse mode table). "
            "Forward mode (`adjoint=\"forward\"`: `jax.jacfwd`, the fits' Jacobians) "
            "steps the variational equation beside the solution, with steps that also meet "
            "the tolerance on the sensitivities (`solve/variational.py`, since 2026-11-28: "
            "more steps than the solution alone, e.g. 242 -> 321 on the lab rig without "
            "friction, 748 -> 1099 with it; the Gradients table was measured before): the "
            "sensitivity matrix is part of the state, each "
            "stage takes one reverse pass of the field with respect to the state and the "
            "packed coefficients, and a constant matrix d coefficients / d theta, formed "
            "outside the loop, carries them to the parameters. Any number of tangents then "
            "costs one pass with a column per differentiated parameter, instead of JAX's "
            "tangents through the fused steps, whose code XLA:CPU handles poorly (the "
            "Gradients table has both). "
            "The solvers step `CrankField.packed()`: the parameter parts of M, K, q "
            "(`m_p r b`, `g m_s`, ...) formed once, outside the step loop, in one array, so "
            "that a solve with traced parameters (every compiled one) compiles to the loop "
            "XLA makes for constants (the fusion table). "
            "`simulate` called outside any transformation checks its inputs on the host "
            "instead of with `eqx.error_if`, so that JAX's persistent compilation cache can "
            "store the program, and dispatches one `jax.jit` of its array leaves.", "",
            "`\"dopri8-uniform\"` (by name) takes an integer number of equal Dopri8 steps "
            "per save interval with a summed error budget; it lands 10-1000x below its "
            "tolerance. JAX differentiates its loop: its own derivative rules (the "
            "Jacobian rows below, where measured before 2026-11-26) were slower than "
            "diffrax's Dopri8 and were removed (issue 26).", "",
            "**XLA's CPU flags, and CPU devices.** XLA's CPU runtime (jax >= 0.7) runs a "
            "program as a sequence of kernels dispatched one by one, a loop body's once per "
            "iteration; a loop whose iteration touches fewer than 1024 bytes it compiles into "
            "one function instead. A Dopri8 step touches more (13 stages, each reading the "
            "packed coefficients), so by default each step pays ~30 dispatches. The "
            "`crank-jax` program raises that threshold to 1 MiB in `XLA_FLAGS` before JAX "
            "starts, and on a CPU with AVX-512 asks for 512-bit vectors (`crank_jax."
            "runtime.xla_flags`; a value the user set wins). The library cannot and does not: the "
            "settings are process-wide, read when JAX starts, and `jax.jit`'s "
            "`compiler_options` cannot reach the threshold; a Python program sets them the "
            "same way, `cj.configure_cpu(devices=1)`, before its first JAX computation. "
            "Likewise a program that asks "
            "JAX for several CPU devices (`jax_num_cpu_devices`; JAX's default is one) gets a "
            "`vmap`-ed lockstep batch's groups spread over them, one core each "
            "(`solve/lockstep.py`), and a sweep's chunks (`sweep/run.py`). "
            "`cj.configure_cpu()` does both, a device per core; the `crank-jax` program calls "
            "it. The tables below are measured with XLA's defaults and one "
            "device unless they say otherwise; \"With the CPU flags\" repeats the targets' "
            "measurements with them.", ""]
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
        out += ["", "The default solver against the best of diffrax's Tsit5, Dopri5 and Dopri8 "
                "at the default's measured error (log-log interpolation along each diffrax "
                "curve; \"n/a\" where no diffrax run reached that error):", "",
                "| scene | rtol | default error | default time | best diffrax at equal error "
                "| default faster by |", "|---|---|---|---|---|---|"]
        slower = []
        for label, c in wp["cases"].items():
            cur = c["curves"]
            for r in sorted(cur.get("crank_jax default (auto)", []), key=lambda r: -r["rtol"]):
                best = None
                for m in ("diffrax Tsit5", "diffrax Dopri5", "diffrax Dopri8"):
                    if m in cur:
                        t = interp_time([x["error"] for x in cur[m]],
                                        [x["time_s"] for x in cur[m]], r["error"])
                        if t is not None and (best is None or t < best[1]):
                            best = (m, t)
                ratio = None if best is None else best[1] / r["time_s"]
                if ratio is not None and ratio < 1:
                    slower.append(f"{label} at rtol {r['rtol']:.0e} ({best[0]}, {ratio:.2f}x)")
                if best is not None:
                    bt = f"{_ms(best[1])} ({best[0][8:]})"
                else:
                    # Below every diffrax run: name the most accurate one instead.
                    runs = [(x["error"], x["time_s"], m[8:]) for m in
                            ("diffrax Tsit5", "diffrax Dopri5", "diffrax Dopri8")
                            for x in cur.get(m, [])]
                    e, t, m = min(runs) if runs else (None, None, None)
                    bt = ("n/a" if e is None else
                          f"n/a (most accurate diffrax: {e:.1e} in {_ms(t)}, {m})")
                out.append(f"| {label} | {r['rtol']:.0e} | {r['error']:.1e} | "
                           f"{_ms(r['time_s'])} | {bt} | "
                           f"{'n/a' if ratio is None else f'{ratio:.2f}x'} |")
        out += ["", ("Where a diffrax solver is faster at equal error: " + "; ".join(slower)
                     + "." if slower else "Wherever both reach the same error, the default "
                     "is the fastest of these.") + " A concrete `simulate` call pays a "
                "fixed host cost (input checks, the linearisation for the solver policy, "
                "dispatch; the Gradients table below measures a concrete call against the "
                "same solve under `jit`), so at loose "
                "tolerances, where the solve itself is short, a lower-order diffrax solver "
                "can be as fast; inside a user's `jit` that cost is paid once at tracing "
                "(see the batch table's N = 1 row)."]
        cheap = []
        for label, c in wp["cases"].items():
            cur = c["curves"]
            d = min(cur.get("crank_jax default (auto)", []), key=lambda r: r["time_s"],
                    default=None)
            runs = [(x["time_s"], x["error"], m[8:]) for m in
                    ("diffrax Tsit5", "diffrax Dopri5", "diffrax Dopri8") for x in cur.get(m, [])]
            if d and runs and min(runs)[0] < d["time_s"]:
                t, e, m = min(runs)
                cheap.append(f"{label}: diffrax {m} in {_ms(t)} (error {e:.1e}) against the "
                             f"default's cheapest {_ms(d['time_s'])} (error {d['error']:.1e})")
        if cheap:
            out += ["", "Where a diffrax solver is cheaper in absolute terms (at a larger error "
                    "than the default ever returns): " + "; ".join(cheap) + "."]
        out += ["", "Each method at rtol = 1e-8 on the lab rig (c = 1e-3, phi0 = 1 rad):", "",
                "| method | max error (rad) | time | steps / RHS evals |", "|---|---|---|---|"]
        for m, rows in wp["cases"]["lab-rig (c=1e-3)"]["curves"].items():
            r = next((r for r in rows if r["rtol"] == 1e-8), None)
            if r:
                out.append(f"| {m} | {r['error']:.2e} | {_ms(r['time_s'])} | {r['steps']} |")
        out.append("")
    if tp:
        out += ["### Batch throughput", "", f"*{_machine(tp['machine'])}*", "",
                "Lab rig, c = 1e-3, phi0 = 1 rad, 10 s, 1001 samples: `jax.jit(jax.vmap(...))` "
                f"over mechanisms (k within +-10%, chunks of {tp['chunk']}): k is traced, "
                "the other parameters are constants of the program (the solver steps the "
                "packed coefficients either way, so a whole traced `SliderCrank` costs the "
                "same: see the fusion table). The error is the largest of 4 members against a "
                "tight reference; the numba columns are a single compiled trajectory's time at "
                "that error (interpolated on its work-precision curve from the same run).", "",
                "| method | rtol | N | per trajectory | max error | numba DP5 | numba DOP853 "
                "| ratio to DOP853 |", "|---|---|---|---|---|---|---|---|"]
        for r in tp["rows"]:
            dop = r.get("numba DOP853_s_equal_error")
            ratio = r.get("ratio_to_numba DOP853_equal_error")
            out.append(f"| {r['method']} | {r['rtol']:.0e} | {r['N']} | "
                       f"{_us(r['per_traj_s'])} | {r['max_error']:.1e} | "
                       f"{_us(r.get('numba DP5_s_equal_error'))} | {_us(dop)} | "
                       f"{'n/a' if ratio is None else format(ratio, '.3f')} |")
        out.append("")
    if fu:
        out += ["### Traced parameters cost what constants do", "", f"*{_machine(fu['machine'])}*",
                "", "The step loop of `solve_adaptive` inside `jit` (10 s, "
                f"{fu['samples']} saves, rtol {fu['rtol']:.0e}; experiments/bench_fusion.py): "
                "its kernels and their operands per step, the loop-carried values, the time. "
                "`CrankField` forms the parameter parts of M, K, q inside the loop, where XLA "
                "hoists each one as a scalar of its own; `simulate` steps `CrankField.packed()`"
                ", which forms them once in one array (model/coefficients.py).", "",
                "| scene | field | kernels | kernel operands | loop-carried | time |",
                "|---|---|---|---|---|---|"]
        for r in fu["rows"]:
            out.append(f"| {r['case']} | {r['field']} | {r['kernels']} | "
                       f"{r['kernel_operands']} | {r['loop_carried']} | {_ms(r['time_s'])} |")
        out.append("")
        if fu.get("elementwise"):
            out += ["float64 cost per element on XLA:CPU (a loop over 10^4 values): JAX's own "
                    "functions against trig.py's arithmetic forms, which a lockstep batch "
                    "uses because XLA vectorises them over a batch.", "",
                    "| function | JAX | trig.py |", "|---|---|---|"]
            out += [f"| {r['function']} | {r['jax_ns']:.2f} ns | {r['trig_ns']:.2f} ns |"
                    for r in fu["elementwise"]]
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
                f"parameter's largest sensitivity: {dis}.", "",
                "The ratios are to the forward solve as the Jacobians run it (the same "
                "function of theta under `jit`). Before 2026-11-24 they were to a concrete "
                "`simulate` call, whose host-side checks made them look smaller by the "
                "concrete row's factor. The row \"stages in a loop\" is the fit's solver "
                "(`AdaptiveDopri8(loop_stages=True)`, set by `pick_solver`): its variational "
                "stages in a `fori_loop` instead of unrolled, so the field (a reverse pass "
                "per state component) is traced once: about half the compile time for a "
                "Jacobian about 1.1-1.2x dearer. A fit calls its Jacobian tens of times but "
                "compiles it in every new process; a user's `jax.jacfwd` keeps the unrolled "
                "stages.", ""]
    out += reverse_table()
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
                "| scene | HLO instructions | flops (XLA estimate) | time | steps | time per "
                "step |", "|---|---|---|---|---|---|"]
        for r in sk["rows"]:
            out.append(f"| {r['case']} | {r['hlo_instructions']} | {r['flops_estimate']:.3g} "
                       f"| {_ms(r['time_s'])} | {r['steps']} | "
                       f"{r['time_s'] / r['steps'] * 1e6:.2f} µs |")
        out += ["", "Times are medians of 31 runs. The loaded scene evaluates two harmonic "
                "loads (a `sin` each) in every stage, so its steps cost more. An earlier "
                "7-run median of 16.5 ms for it (6.2 ms for the lab rig) did not reproduce "
                "with 31 runs: it was noise from other jobs on the machine."]
        out.append("")
    if ee:
        out += _end_to_end(ee)
    out += _cpu_flags(wp2_of(wp), tp, gr)
    out += ["### Targets", ""]
    if wp:
        a = wp["target_a"]
        sp = a["speedup"]
        out.append(f"- (a) one trajectory, default solver, >= 25x faster than scipy DOP853 at "
                   f"equal error: {_met(sp is not None and sp >= 25)}, "
                   f"{'n/a' if sp is None else f'{sp:.2f}x'} (default: error "
                   f"{a['default_error']:.1e} rad in {_ms(a['default_time_s'])}; DOP853 at "
                   f"that error {_ms(a['dop853_time_s_at_equal_error'])}).")
    # The lab-rig run with the compiled DOP853 peer (`--lab-only --tag _after`) where the
    # three-scene run predates that peer.
    wp2 = wp2_of(wp)
    if wp2 and wp2.get("target_2"):
        t2 = wp2["target_2"]
        r2 = t2["ratio_at_equal_error"]
        out.append(f"- (issue 9, 2) one trajectory, default solver, <= 3.0x the compiled DOP853:"
                   f" {_met(r2 is not None and r2 <= 3.0)}, "
                   f"{'n/a' if r2 is None else f'{r2:.2f}x'} at equal error "
                   f"({t2['default_error']:.1e} rad; {wp2['machine']['date']}); "
                   f"{t2['ratio_vs_cheapest_meeting_1e-8'] or float('nan'):.2f}x against "
                   "DOP853's cheapest run meeting 1e-8 rad" + _paired(t2.get("paired"))
                   + _with_flags("work_precision", "target_2", "ratio_at_equal_error", 3.0)
                   + ".")
    if tp and tp.get("target_3"):
        t3 = tp["target_3"]
        r3 = t3["ratio_equal_error"]
        out.append(f"- (issue 9, 3) batch of 1e4 in jit+vmap, default solver, <= 0.15x the "
                   f"compiled DOP853 per trajectory: {_met(r3 is not None and r3 <= 0.15)}, "
                   f"{'n/a' if r3 is None else f'{r3:.3f}x'} at equal error "
                   f"({t3['max_error']:.1e} rad); "
                   f"{t3['ratio_vs_cheapest_meeting_1e-8'] or float('nan'):.3f}x against "
                   "DOP853's cheapest run meeting 1e-8 rad"
                   + _with_flags("throughput", "target_3", "ratio_equal_error", 0.15)
                   + _with_flags("throughput", "target_3", "ratio_equal_error", 0.15,
                                 "_cpu_flags_two_devices", "with them and two CPU devices")
                   + ".")
    if gr:
        c = gr["target_c"]
        out.append(f"- (c) full Jacobian <= 5x one forward solve: {_met(c['ratio'] <= 5)}, "
                   f"{c['ratio']:.2f}x ({c['best_method']})"
                   + _with_flags("gradients", "target_c", "ratio", 5.0) + ".")
        if gr.get("target_4"):
            t4 = gr["target_4"]
            out.append(f"- (issue 9, 4) forward-sensitivity Jacobian (10 parameters, "
                       f"{gr['samples']} samples) <= 4x one forward solve: "
                       f"{_met(t4['ratio'] <= 4)}, {t4['ratio']:.2f}x ({t4['method']})"
                       + _with_flags("gradients", "target_4", "ratio", 4.0) + ".")
    if ee:
        m, t = ee["medians"], ee["targets_met"]
        out.append(f"- (issue 9, 1) `crank-jax fit` warm <= 2 s and <= half the scipy script: "
                   f"{_met(t['warm_fit_le_2s'] and t['warm_fit_le_half_scipy'])}, "
                   f"{m['cli_fit_warm_s']:.2f} s against scipy's {m['scipy_peer_s']:.2f} s "
                   f"({m['cli_fit_warm_s'] / m['scipy_peer_s']:.2f}x); other records "
                   f"{m['cli_fit_warm_other_records_s']:.2f} s; cold <= 10 s: "
                   f"{_met(t['cold_fit_le_10s'])}, {m['cli_fit_cold_s']:.2f} s; demo warm "
                   f"<= 3 s: {_met(t['demo_warm_le_3s'])}, {m['demo_warm_s']:.2f} s; first "
                   f"fit in a process <= 8 s: {_met(t['first_fit_in_process_le_8s'])}, "
                   f"{m['first_fit_in_process_s']:.2f} s.")
        if "cold_fit_le_5s" in t:
            cold = m["cli_fit_cold_s"]
            out.append(f"- (issue 40) `crank-jax fit` cold <= 5 s: {_met(t['cold_fit_le_5s'])}, "
                       f"{cold:.2f} s ({cold / m['scipy_peer_s']:.2f}x the scipy script of "
                       f"the same run, {m['scipy_peer_s']:.2f} s); warm <= 1 s: "
                       f"{_met(t['warm_fit_le_1s'])}, {m['cli_fit_warm_s']:.2f} s; the first "
                       "`cj.fit` in a process <= 5 s: "
                       f"{_met(t['first_fit_in_process_le_5s'])}, "
                       f"{m['first_fit_in_process_s']:.2f} s.")
    if st:
        d = st["target_d"]
        out.append(f"- (d) warm-cache `crank-jax simulate lab-rig` <= 3 s: {_met(d['met'])}, "
                   f"{d['warm_s']:.2f} s.")
    out.append("")
    return "\n".join(out)


def _with_flags(name, target, key, goal, tag="_cpu_flags",
                label="with the CPU flags") -> str:
    """"; with the CPU flags: ..." from the run tagged `tag`, if any."""
    x = _load(f"{name}{tag}")
    r = x and (x.get(target) or {}).get(key)
    if r is None:
        return ""
    return f"; {label}: {_met(r <= goal)}, {r:.3g}x"


def wp2_of(wp):
    """The work-precision run with the compiled DOP853 peer (target 2): the three-scene run
    if it has one, else the lab-rig run `--lab-only --tag _after`."""
    return wp if wp and wp.get("target_2") else _load("work_precision_after")


def _cpu_flags(wp2, tp, gr) -> list[str]:
    """Issue 9's targets 2-4 measured again in processes with crank-jax's CPU flags
    (`XLA_FLAGS` from `crank_jax.configure_cpu`; runs tagged `_cpu_flags`), and the batch
    also with two CPU devices (`_cpu_flags_two_devices`), beside the runs with XLA's
    defaults. Each ratio is to a peer measured in the same run."""
    fwp, ftp, fgr, ftp2 = (_load(n) for n in (
        "work_precision_cpu_flags", "throughput_cpu_flags", "gradients_cpu_flags",
        "throughput_cpu_flags_two_devices"))
    if not (fwp or ftp or fgr or ftp2):
        return []
    flags = next(x["machine"].get("xla_flags") for x in (fwp, ftp, fgr, ftp2) if x)
    out = ["### With the CPU flags", "",
           f"`XLA_FLAGS=\"{flags}\"` (what `crank-jax` sets on this machine; "
           "`cj.configure_cpu`), and for the batch also two CPU devices, one per core "
           "(`JAX_NUM_CPU_DEVICES=2`, i.e. `jax.config.update(\"jax_num_cpu_devices\", 2)` "
           "before JAX starts), over which a lockstep batch spreads its groups of members. "
           "Each ratio is to a peer measured in the same run (the compiled numba DOP853 at "
           "equal error, or the forward solve); the first column repeats the tables above.",
           "", "| measurement | XLA defaults | CPU flags | CPU flags, two CPU devices | goal |",
           "|---|---|---|---|---|"]

    def when(x):
        return x["machine"]["date"][5:16]

    def t2(w):
        t = w and w.get("target_2")
        if not t or t["ratio_at_equal_error"] is None:
            return "n/a"
        return (f"{_ms(t['default_time_s'])} at {t['default_error']:.1e} rad: "
                f"**{t['ratio_at_equal_error']:.2f}x** ({when(w)})")

    def t3(x):
        t = x and x.get("target_3")
        if not t:
            return "n/a"
        r = next(r for r in x["rows"] if r["N"] == 10_000 and r["method"] == "default (auto)"
                 and r["max_error"] == t["max_error"])
        return (f"{_us(r['per_traj_s'])} per trajectory: **{t['ratio_equal_error']:.3f}x** "
                f"({when(x)})")

    def one(x):
        r = x and next((r for r in x["rows"] if r["N"] == 1 and r["rtol"] == 1e-9
                        and r["method"] == "default (auto)"), None)
        return "n/a" if not r else (f"{_us(r['per_traj_s'])}: "
                                    f"{r['ratio_to_numba DOP853_equal_error']:.2f}x")

    def t4(g):
        if not g or not g.get("target_4"):
            return "n/a"
        fwd = g["rows"][0]["time_s"]
        jac = next(r for r in g["rows"] if r["method"] == g["target_4"]["method"])
        return (f"{_ms(jac['time_s'])} against {_ms(fwd)}: **{g['target_4']['ratio']:.2f}x** "
                f"({when(g)})")

    out += [f"| (2) `simulate`, one trajectory, against DOP853 | {t2(wp2)} | {t2(fwp)} | "
            "(one device's work) | <= 3.0x |",
            f"| one trajectory in `jit(vmap)` (N = 1, rtol 1e-9), against DOP853 | {one(tp)} "
            f"| {one(ftp)} | {one(ftp2)} | |",
            f"| (3) batch of 1e4 in `jit(vmap)`, against DOP853 per trajectory | {t3(tp)} | "
            f"{t3(ftp)} | {t3(ftp2)} | <= 0.15x |",
            f"| (4) forward Jacobian (10 parameters) against one forward solve | {t4(gr)} | "
            f"{t4(fgr)} | (one device's work) | <= 4x |", "",
            "What each setting changes: the small-loop threshold takes the dispatch cost out "
            "of the step loops, so a single trajectory gets ~2x cheaper and the Jacobian "
            "~8x: its loop carries the sensitivities and a reverse pass of the field per "
            "stage, ~230 kernels per step that XLA's defaults dispatch one by one (the "
            "former tangents through the steps, ~160 kernels, gained ~3x); 512-bit vectors "
            "make the "
            "batch's SIMD arithmetic cheaper; a second CPU device runs half of the batch's "
            "groups on the second core. The batch's ratio also moves with the peer's own "
            "time, which varies between runs on this shared machine.", ""]
    sd = _load("sweep_devices")
    if sd:
        one, many = sd["rows"][0], sd["rows"][-1]
        out += [f"Sweeps over one CPU device per core (`experiments/bench_sweep_devices.py`, "
                f"{when(sd)}, XLA's defaults): a warm `cj.sweep` of {sd['n']} lab rigs (k and "
                f"c varied, default outputs) took {one['warm_s']:.2f} s on one device and "
                f"{many['warm_s']:.2f} s on {many['devices']} "
                f"({one['warm_s'] / many['warm_s']:.2f}x), with "
                + ("the same results." if sd["same_results"] else "DIFFERENT results."), ""]
    if fwp and (FIGURES / "work_precision_cpu_flags.png").exists():
        out += ["The lab rig's work-precision figure from the run with the CPU flags:", "",
                "![work-precision, CPU flags](docs/figures/work_precision_cpu_flags.png)", ""]
    return out


def _paired(pr) -> str:
    """Target 2 measured in pairs (one call of each in every round), if recorded."""
    if not pr:
        return ""
    q1, q3 = pr["ratio_quartiles"]
    return (f"; measured in {pr['rounds']} paired rounds (one call of each per round, on a "
            f"machine whose speed drifts): median {pr['ratio_median']:.2f}x, quartiles "
            f"{q1:.2f}-{q3:.2f}x")


def _strategy(ee) -> str:
    """The main fit's strategy and the others', as recorded."""
    st = ee.get("strategies")
    if not st:
        return "this start needs multiple shooting"
    same = all(x == st[0] for x in st)
    st = [x.replace(" (", ", ").replace(")", "") for x in st]
    return (f"{st[0]}; " + ("the same for the other records" if same
                            else "the others: " + "; ".join(st[1:])))


def _end_to_end(ee) -> list[str]:
    m = ee["medians"]
    rows = [("`crank-jax fit`, empty cache (compiles and stores its programs)", "cli_fit_cold_s"),
            ("`crank-jax fit`, warm (loads them)", "cli_fit_warm_s"),
            ("`crank-jax fit` of other records (length, noise, start values), warm",
             "cli_fit_warm_other_records_s"),
            ("`crank-jax fit` of a record in the next length bucket (compiles once)",
             "cli_fit_warm_new_bucket_s"),
            ("`crank-jax demo`, empty cache", "demo_cold_s"),
            ("`crank-jax demo`, warm", "demo_warm_s"),
            ("first fit inside a fresh Python process, no cache", "first_fit_in_process_s"),
            ("first fit inside a fresh Python process, `enable_compilation_cache()` warm",
             "first_fit_in_process_stored_programs_s"),
            ("the scipy script (`least_squares` + DOP853, Python right-hand side)",
             "scipy_peer_s")]
    out = ["### End to end", "", f"*{_machine(ee['machine'])}*", "",
           f"Fresh processes, as a user runs them: a fit of {ee['free']} to "
           f"{ee['record']} from k = {ee['start']['k']}, c = {ee['start']['c']} "
           "(`experiments/bench_end_to_end.py`, medians). Warm runs load the stored programs "
           "(`persistent.py`); what is left is importing JAX, loading the executables and "
           f"the fit itself ({_strategy(ee)}; MINPACK's LM on the host, one call of the "
           "compiled residuals-and-Jacobian program a point). The `crank-jax` runs use the "
           "CPU flags and the device per core that the program sets (`configure_cpu`, see "
           "above"
           + ("" if ee.get("cli_xla_flags") else "; this run predates it") + "); "
           "the fits inside a Python process use XLA's defaults, as a library user's do. "
           "The third column is each time over the scipy script's in the same run: the "
           "machine's speed moves between runs (the scipy script, single-threaded Python, "
           "took 5.44 s on 2026-11-27 03:27 UTC, 13.18 s on 2026-11-28 09:40 UTC and "
           "9.3-13.3 s within the run of 10:21, all on this project's 2-core VMs), the "
           "ratios less; a median of three runs still moves by 10-20%.",
           "", "| run | wall time | × the scipy script |", "|---|---|---|"]
    peer = m.get("scipy_peer_s")
    out += [f"| {label} | {m[key]:.2f} s | "
            + (f"{m[key] / peer:.2f} |" if peer else "|") for label, key in rows if key in m]
    other = ee["runs"].get("other", [])
    if len(other) >= 2:
        a, b = (float(np.median(other[i::2])) for i in (0, 1))
        starts = ee.get("other_starts") or [{"k": "?", "c": "?"}] * 2
        sa, sb = (f"from k = {s['k']}, c = {s['c']}" for s in starts)
        out += ["", f"The other records, each run after the first fit filled the store: "
                f"1.03x as long, {sa}: {a:.2f} s; 0.9x as long, {sb}: {b:.2f} s. Their "
                "lengths share the first's bucket and their segment count comes from the "
                "record alone, so they load its programs. Record lengths are padded to "
                "72, 108, 144, 216, ..., 1152, 1728, ... samples (9 * 2^k and 27 * 2^k, so "
                "that N + 1 samples of a round duration at a round rate sit ~15% below an "
                "edge) and multiple-shooting segment counts rounded to 2, 3, 4, 6, 8, 12, "
                "...; a record 1.2x as long lands in the next bucket and compiles its "
                "programs once (the row above), after which they are stored."]
    out += ["", "History: the fit's solves moved to `simulate`'s solve core in commit 32c3754 "
            "(issue 26), whose multiple-shooting Jacobian (the variational equation, unrolled "
            "stages, batched over the segments) took 3.5 s to trace and 3.6 s to compile: "
            "a run on 2026-11-27 00:41 UTC measured 15.6 s cold, 2.23 s warm and 14.4 s for "
            "the first fit in a process (7.56 s, 1.69 s and 7.35 s before). Since then the "
            "fit's solver steps those stages in a loop (`loop_stages`: trace 1.0 s, compile "
            "1.7-1.9 s; `experiments/fit_solver_tradeoff.py`) and the no-motion check takes "
            "its F quantile from `scipy.special` (importing `scipy.stats` had cost 1.0 s of "
            "every fit).",
            "", "2026-11-28 (issue 40): `import crank_jax` no longer loads `scipy.optimize` "
            "(2.75 -> 2.1 s on the slow machine of the table above, medians of 6), and the "
            "default solver's Dopri8 tableau is diffrax's numbers copied "
            "(`solve/dopri8_tableau.py`, tested bit for bit against diffrax's): reading "
            "`diffrax.Dopri8.tableau` imported diffrax, lineax and optimistix, 0.6-1.0 s "
            "of every warm fit, which runs nothing else of diffrax (a warm `crank-jax fit` "
            "3.77 -> 3.11 s, medians of 5). What is left of a warm fit (cProfile, 5.0 s "
            "under the profiler): importing JAX 1.1 s and equinox 0.4 s, `scipy.optimize` "
            "for MINPACK 0.8 s (0.37 s of it scipy parsing its own docstrings), loading the "
            "three stored programs 0.5 s, the fit's own work about 1.5 s. Where a cold "
            "fit's time goes, on the same machine: the multiple-shooting Jacobian takes "
            "2.6-3.0 s to trace and 4.0-4.5 s to compile, the single-shooting one 1.0-1.5 s "
            "and 3.4-3.7 s; 2 s of the first trace is JAX's batching interpreter walking the "
            "solver under the segments' `vmap` (each segment has its own save times, so the "
            "lockstep rule fell back to a plain `vmap`; no longer, below). Tried and not "
            "kept (2026-11-28): "
            "compiling the two Jacobian programs in two threads (11.25 and 12.27 s in "
            "sequence, 10.69 and 11.47 s side by side: XLA's compile already uses both "
            "cores and the traces hold the GIL), and tracing the segment solve once and "
            "replaying its jaxpr under the `vmap` (the trace under cProfile 5.8 -> 4.7 s: "
            "the batching of the replayed jaxpr costs what the batching of the traced solve "
            "did; not worth a second form of the solve).",
            "", "2026-11-28, later (issue 40): the segments step in lockstep with their own "
            "save times (`solve/lockstep.py`), so the multiple-shooting Jacobian traces "
            "without the batching interpreter (its trace 2.9 -> 1.9 s, a second fit in the "
            "same process 0.30 -> 0.21 s), and the fit puts its host data on the device "
            "with no compiled program (`runtime/arrays.py`; a cold fit compiled 32 "
            "programs, now 15, and a warm CLI fit looks up 7 instead of 24). Measured "
            "paired, the code before (62b344e) and after in turn on the same record, 5 "
            "pairs each on a loaded machine: `crank-jax fit` cold 19.49 -> 18.19 s (0.95x), "
            "warm 4.34 -> 3.92 s (0.91x, 9 pairs), the first `cj.fit` in a process 0.94x "
            "(20.08 s before; medians of the pairs' ratios in brackets); the table above "
            "is the run after, whose run before gave 19.76 s cold and 4.57 s warm against "
            "the scipy script's 13.84 s. Where a cold "
            "fit in a process goes now (11.7 s on a quieter moment of the same machine): "
            "importing 1.4 s, the linearisation that picks the solver 1.0 s, the "
            "single-shooting Jacobian 1.5 s to trace and 3.0 s to compile, the "
            "multiple-shooting one 1.9 s and 2.6 s, the rest under 1 s. Tried and not kept: "
            "the segments in a `lax.map` instead of a batch (trace 4.9 -> 6.8 s: the "
            "Jacobian's directions batch the loop anyway; a warm fit 0.30 -> 0.33 s), and "
            "more compile options on the two Jacobians "
            "(`experiments/fit_programs_options.py`, results `_probe3`: XLA's backend "
            "optimisation level 1 or 0 and LLVM's expensive passes off took 3.5-3.6 s "
            "instead of 3.8 s for the single-shooting one, and its calls 1.3-2.2x as long). "
            "A cold fit under 5 s needs one Jacobian program fewer, or much smaller ones: "
            "not done."]
    return out + _trace_once() + _blas_threads() + [""]


def _trace_once() -> list[str]:
    """The acceleration traced once per program (model/dynamics.py), from trace_once.json."""
    tr = _load("trace_once")
    if tr is None:
        return []
    once, every = tr["medians"]["once"], tr["medians"]["every-site"]
    n = len(tr["runs"]["once"])

    def secs(xs):
        return " and ".join(f"{x:.2f}" for x in xs)

    return ["", "2026-11-28, evening (issue 40): a solver evaluates its field at several "
            "places of one program (the first stage, the initial step's two, the stage "
            "loop, the variational equation's reverse passes), and each traced the same "
            "jnp arithmetic again (~50 ms a time: jnp's operators cost ~0.25 ms each to "
            "trace, 5x `lax`'s). The acceleration is now a jitted call, traced once per "
            "input shape, whose trace, JVP and transpose JAX caches; XLA inlines it before "
            "optimising, so the compiled programs are the same (normalised optimised HLO "
            "compared, tests/test_field_trace.py). A user's load or force class is traced "
            "afresh at every site (its code may read state the cache does not see). "
            f"On the first fit in a fresh process ({_machine(tr['machine'])}; "
            f"`experiments/trace_once.py`, {n} alternated pairs, medians): the two "
            f"Jacobians traced in {secs(once['jacobian_trace_s'])} s instead of "
            f"{secs(every['jacobian_trace_s'])} s, all tracing {once['all_tracing_s']:.2f} s "
            f"instead of {every['all_tracing_s']:.2f} s, the whole first fit "
            f"{once['first_fit_s']:.2f} s instead of {every['first_fit_s']:.2f} s (the same "
            "estimate in every run). The linearisation's program compiles with XLA's older "
            "emitters (`FAST_COMPILE`): 0.31 s instead of 0.62-0.71 s, the same bits on 960 "
            "mechanisms of the preset scenes. What a cold fit is left with is XLA compiling "
            "the two Jacobian programs, 2-3.5 s each."]


def _blas_threads() -> list[str]:
    """The fit's host BLAS on one thread (runtime/blas.py), from fit_blas_threads.json."""
    bt = _load("fit_blas_threads")
    if bt is None:
        return []
    out = ["", f"The fit's host linear algebra on one BLAS thread (`runtime/blas.py`; "
           f"{_machine(bt['machine'])}; `experiments/fit_blas_threads.py`): NumPy's SVD of "
           "a 1318 x 26 matrix (the lab record's multiple-shooting Jacobian) 30 times, "
           "and the warm lab fit 4 times, alternated, with busy processes beside them:", "",
           "| busy processes | SVD, OpenBLAS's default threads: median (worst) | one thread "
           "| warm fit, default threads | one thread |", "|---|---|---|---|---|"]
    for name, row in bt["rows"].items():
        sd, so = row["svd_default"], row["svd_one_thread"]
        out.append(f"| {name.split()[0]} | {_ms(sd['median_s'])} ({_ms(sd['max_s'])}) | "
                   f"{_ms(so['median_s'])} ({_ms(so['max_s'])}) | "
                   f"{row['fit_default']['median_s']:.3f} s | "
                   f"{row['fit_one_thread']['median_s']:.3f} s |")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--print", action="store_true")
    a = ap.parse_args(argv)
    text = section()
    if a.print:
        print(text)
        return
    page = ROOT / "docs" / "benchmarks" / "performance.md"
    src = page.read_text()
    pat = re.compile(re.escape(BEGIN) + ".*?" + re.escape(END), re.S)
    if not pat.search(src):
        raise SystemExit(f"{page} has no performance section markers")
    text = text.replace("](docs/figures/", "](../figures/")  # relative to the page
    page.write_text(pat.sub(lambda _: f"{BEGIN}\n{text}\n{END}", src))
    print(f"rewrote the performance section of {page.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
