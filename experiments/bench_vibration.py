"""Nonlinear vibration analysis, measured (issue 41): accuracy and time of a forced
response curve (continuation with Floquet stability) against brute-force time stepping
swept up and down at equal accuracy, the time of a stability chart, the backbone's
small-amplitude limit, the chart's tongue edges against Mathieu theory, and a figure of
each kind.

The brute force uses the same integrator (the library's `"dopri8-adaptive"` at the same
tolerances) and the same refined extremes, so the comparison is of the methods: at each
frequency it holds the drive for n periods from the previous frequency's final state (a
sweep up, then a sweep down) and reads the amplitude over the last period. Its error is
the transient left after n periods, measured against the exact orbit through its final
state (`periodic_orbit`); n is raised until that error is at most the target.

Run: python experiments/bench_vibration.py [--smoke]
"""

from __future__ import annotations

import sys
import time

from _bench import FIGURES, median_time, save, setup_jax, use_clock

jax = setup_jax()

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.vibration import mathieu_tongue, periodic_orbit  # noqa: E402
from crank_jax.vibration.chart import floquet_max  # noqa: E402
from crank_jax.vibration.drive import field_at  # noqa: E402
from crank_jax.vibration.flow import flow  # noqa: E402
from crank_jax.vibration.orbit import extremes  # noqa: E402
from crank_jax.vibration.plots import plot_chart, plot_response  # noqa: E402

SMOKE = "--smoke" in sys.argv
TARGET = 1e-6  # relative amplitude error asked of both methods
F0, F1 = 3.0, 5.5


def driven():
    sc = cj.load_scene("lab-rig")
    return eqx.tree_at(lambda s: s.torque, sc, cj.HarmonicLoad(0.0, 0.05, 4.0))


@eqx.filter_jit
def _hold(scene, structure, f, y0, n):
    """Hold frequency f for n periods from y0: (final state, amplitude over the last)."""
    field = field_at(scene, "torque", f, structure)
    T = 1.0 / f
    y = flow(field, y0, (n - 1) * T, rtol=scene.rtol, atol=scene.atol)
    pmax, pmin = extremes(field, y, T, rtol=scene.rtol, atol=scene.atol)
    return flow(field, y, T, rtol=scene.rtol, atol=scene.atol), (pmax - pmin) / 2


def brute_sweep(scene, freqs, n):
    structure = scene.structure
    y = jnp.zeros(2)
    out = []
    for f in list(freqs) + list(freqs[::-1]):
        y, a = _hold(scene, structure, jnp.asarray(f), y, jnp.asarray(float(n)))
        out.append((float(f), float(a), np.asarray(y)))
    return out


def main():
    use_clock("cpu")  # the machine is shared: CPU time is less distorted than wall time
    scene = driven()
    res = {}

    # --- forced response curve -----------------------------------------------------------
    t = time.process_time()
    resp = cj.forced_response(scene, (F0, F1), backbone_points=30)
    res["response_first_call_cpu_s"] = time.process_time() - t
    t_curve = median_time(lambda: cj.forced_response(scene, (F0, F1)), repeats=3, warmup=0)
    (b,) = resp.branches
    res["response"] = {"points": len(b.freq_hz), "folds": resp.folds,
                       "unstable_points": int((~b.stable).sum()), "cpu_s": t_curve}
    # The curve's accuracy: its orbits against orbits at a 100x tighter solver tolerance.
    tight = eqx.tree_at(lambda s: (s.rtol, s.atol), scene, (jnp.asarray(1e-10),
                                                             jnp.asarray(1e-12)))
    idx = np.linspace(0, len(b.freq_hz) - 1, 4 if SMOKE else 12).astype(int)
    errs = []
    for i in idx:
        o = periodic_orbit(tight, b.freq_hz[i], guess=jnp.asarray([b.phi0[i], b.dphi0[i]]))
        errs.append(abs(float(o.amplitude) - b.amplitude[i]) / b.amplitude[i])
    res["response"]["max_rel_error_vs_tighter"] = float(np.max(errs))

    # --- brute force, swept up and down ---------------------------------------------------
    nf = 20 if SMOKE else len(b.freq_hz) // 2
    freqs = np.linspace(F0, F1, nf)
    brute = {}
    for n in ((50, 100) if SMOKE else (50, 100, 200, 400)):
        brute_sweep(scene, freqs[:2], n)  # compile
        t = time.process_time()
        sweep = brute_sweep(scene, freqs, n)
        cpu = time.process_time() - t
        err = []
        for f, a, y in sweep:
            o = periodic_orbit(scene, f, guess=jnp.asarray(y))
            err.append(abs(a - float(o.amplitude)) / float(o.amplitude))
        brute[n] = {"cpu_s": cpu, "max_rel_error": float(np.max(err)),
                    "steady_states": len(sweep)}
        print(f"brute n={n}: {cpu:.2f} s, max rel error {np.max(err):.2e}")
        if np.max(err) <= TARGET:
            break
    res["brute_force"] = {"frequencies_each_way": nf, "target_rel_error": TARGET,
                          "by_periods": brute}
    ok = [n for n, v in brute.items() if v["max_rel_error"] <= TARGET]
    if ok:
        res["speedup_at_equal_accuracy"] = brute[min(ok)]["cpu_s"] / t_curve

    # Three frequencies, one inside the hysteresis region (both stable branches).
    checks = []
    structure = scene.structure
    for f, sweep in ((3.5, [3.5]), (4.0, [4.0]), (4.0, [4.3, 4.0]), (5.0, [5.0])):
        y = jnp.zeros(2)
        for fs in sweep:
            y, a = _hold(scene, structure, jnp.asarray(fs), y, jnp.asarray(400.0))
        o = periodic_orbit(scene, f, guess=y)
        checks.append({"freq_hz": f, "sweep": sweep, "brute_amplitude": float(a),
                       "orbit_amplitude": float(o.amplitude), "stable": bool(o.stable),
                       "rel_diff": abs(float(a) - float(o.amplitude)) / float(o.amplitude)})
    res["three_frequencies"] = checks

    # --- backbone ---------------------------------------------------------------------------
    bb = cj.backbone(scene.mech, [1e-4, 2e-4])
    f = np.asarray(bb.frequency_hz)
    f_lin = float(bb.linear_frequency_hz)
    res["backbone_small_amplitude"] = {
        "rel_error_at_1e-4_rad": abs(f[0] - f_lin) / f_lin,
        "rel_error_extrapolated_to_0": abs((4 * f[0] - f[1]) / 3 - f_lin) / f_lin}

    # --- stability chart --------------------------------------------------------------------
    lin = cj.linearize(scene.mech)
    f_n = float(lin.omega_n) / (2 * np.pi)
    base = cj.load_scene("lab-rig")
    grid = 8 if SMOKE else 40
    t = time.process_time()
    chart = cj.stability_chart(base, (0.0, 25.0), (0.5 * f_n, 2.5 * f_n), grid=grid)
    res["chart_first_call_cpu_s"] = time.process_time() - t
    res["chart"] = {"grid": grid, "cpu_s": median_time(
        lambda: cj.stability_chart(base, (0.0, 25.0), (0.5 * f_n, 2.5 * f_n), grid=grid),
        repeats=3, warmup=0)}
    # Tongue edges against first-order Mathieu theory.
    xi_P = float(cj.linearize(base.mech, cj.ConstantLoad(1.0)).xi) - float(lin.xi)
    fq = jnp.linspace(1.8 * f_n, 2.2 * f_n, 801)
    fm = jax.jit(jax.vmap(lambda a, q: floquet_max(base, a, q), (None, 0)))
    edges = []
    for h in (0.4, 0.2, 0.1):
        P1 = h * float(lin.xi) / abs(xi_P)
        m = np.asarray(fm(P1, fq)) - 1
        cross = np.flatnonzero(np.diff(np.sign(m)) != 0)
        num = [float(fq[i] - m[i] * (fq[i + 1] - fq[i]) / (m[i + 1] - m[i])) for i in cross]
        th = mathieu_tongue(base, P1)
        edges.append({"h": h, "P1": P1, "chart_edges_hz": num, "theory_edges_hz": th})
    res["tongue_edges"] = edges

    if not SMOKE:
        FIGURES.mkdir(parents=True, exist_ok=True)
        plot_response(resp, FIGURES / "vibration_response.png",
                      title="lab rig, tau = 0.05 sin(2 pi f t) N*m: forced response")
        plot_chart(chart, FIGURES / "vibration_chart.png",
                   title="lab rig: rest position under P = P1 cos(2 pi f t)")
    save("vibration", res, SMOKE)


if __name__ == "__main__":
    main()
