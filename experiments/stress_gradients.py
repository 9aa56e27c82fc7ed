"""Gradients over long horizons: where single shooting breaks and multiple shooting does not.

    python experiments/stress_gradients.py            # full run, ~1-2 min on 2 cores
    python experiments/stress_gradients.py --smoke    # seconds, for CI

Writes experiments/results/stress_gradients[_smoke].json and (full run)
docs/figures/stress_gradients.png.

The problem: fit the spring stiffness k of the lab rig (1 rad release, truth k = 2 N*m/rad)
to a noise-free synthetic record phi_d(t) sampled 20 times per period, by the mean squared
error L(k) = mean_i (phi(t_i; k) - phi_d(t_i))^2 (rad^2) over a horizon of N periods, with
the shaft undamped (c = 0) and lightly damped (c = 1e-3 N*m*s/rad, damping ratio ~0.011).

- Single shooting integrates the whole horizon from the known initial state. The
  sensitivities d phi/d theta for theta = (k, c, phi0) come from one forward-mode solve
  (`adjoint="forward"`, `jax.jacfwd`); the gradient dL/dk from them by the chain rule, and
  independently from reverse mode (`jax.jacrev`, the default adjoint) and from central
  finite differences of a tight-tolerance (rtol 1e-12) solve.
- Multiple shooting cuts the horizon into one-period segments, each started from the
  record's state at its first sample (a fitter makes these states free parameters; here
  they sit at their converged values), with the continuity defect of the rate at each
  segment's end, scaled by 1/omega to radians, as an extra residual. The segments are
  `jax.vmap`-ed.

Every horizon's loss is a prefix of the longest record: the trajectory on [0, T] does not
depend on where the record ends, so one solve over the longest horizon serves them all (and
one compiled program per quantity, rather than one per horizon).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.runtime.io import atomic_write  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "experiments" / "results"
FIGURES = ROOT / "docs" / "figures"

SPP = 20  # samples per period of the record
SOLVER = "dopri8"  # explicit: the lab rig is not stiff, and "auto" needs concrete params
TIGHT = 1e-12  # rtol of the reference solves (atol = rtol * 1e-2 throughout)
REL_DK = 0.01  # the gradient is taken 1% above the truth (at the truth it is 0)


def _machine() -> dict:
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return dict(platform=platform.platform(), machine=platform.machine(), cpu=cpu,
                cores=os.cpu_count())


def _say(msg: str, t0: float) -> None:
    print(f"[{time.perf_counter() - t0:6.1f} s] {msg}", flush=True)


def measured_period(mech: cj.SliderCrank, phi0: float) -> float:
    """Period (s) of the undamped free swing released from `phi0` rad, from the mean spacing
    of the zero crossings of a tight solve (the swing is nonlinear: not 2 pi / omega_n)."""
    omega = float(cj.linearize(mech).omega_n)
    ts = np.linspace(0.0, 20 * 2 * np.pi / omega, 4001)
    phi = np.asarray(cj.simulate(mech.replace(c=0.0), phi0, 0.0, ts, solver=SOLVER,
                                 rtol=TIGHT, atol=TIGHT * 1e-2).phi)
    i = np.nonzero(np.sign(phi[:-1]) != np.sign(phi[1:]))[0]
    tz = ts[i] - phi[i] * (ts[i + 1] - ts[i]) / (phi[i + 1] - phi[i])  # linear interpolation
    return float(2 * np.mean(np.diff(tz)))


def local_minima(y: np.ndarray) -> int:
    """Interior strict local minima of a sampled curve."""
    return int(np.sum((y[1:-1] < y[:-2]) & (y[1:-1] < y[2:])))


def basin(ks: np.ndarray, y: np.ndarray, k_true: float) -> tuple[float, float]:
    """Relative extent (below, above the truth) over which the sampled loss falls
    monotonically towards its minimum nearest the truth: where gradient descent from a
    start guess still reaches the truth. A bound of the grid means "at least this"."""
    i0 = int(np.argmin(np.abs(ks - k_true)))
    lo = i0
    while lo > 0 and y[lo - 1] > y[lo]:
        lo -= 1
    hi = i0
    while hi < len(y) - 1 and y[hi + 1] > y[hi]:
        hi += 1
    return float((k_true - ks[lo]) / k_true), float((ks[hi] - k_true) / k_true)


def run(smoke: bool) -> dict:
    t0 = time.perf_counter()
    scene = cj.load_scene("lab-rig")
    phi0 = float(scene.phi0)
    k_true = float(scene.mech.k)
    period = measured_period(scene.mech, phi0)
    omega = 2 * np.pi / period
    horizons = (1, 3, 10) if smoke else (1, 3, 10, 30, 100, 300)
    dampings = (0.0,) if smoke else (0.0, 1e-3)
    n_max = horizons[-1] * SPP + 1
    ts = jnp.asarray(np.linspace(0.0, horizons[-1] * period, n_max))
    counts = np.array([n * SPP + 1 for n in horizons])  # samples in each horizon's record
    _say(f"period at {phi0} rad: {period:.5f} s; horizons {horizons} periods", t0)

    def traj(theta, rtol, adjoint="forward"):
        """phi (n_max,), rad, for theta = (k, c, phi0) (N*m/rad, N*m*s/rad, rad)."""
        k, c, p0 = theta
        return cj.simulate(scene.mech.replace(k=k, c=c), p0, 0.0, ts, solver=SOLVER,
                           rtol=rtol, atol=rtol * 1e-2, adjoint=adjoint,
                           max_steps=5_000_000).phi

    # One forward-mode solve gives phi and all three sensitivity columns: (n_max,), (n_max, 3).
    traj_jac = jax.jit(lambda th, rtol: (traj(th, rtol), jax.jacfwd(traj)(th, rtol)))
    traj_only = jax.jit(traj)
    batch = jax.jit(jax.vmap(traj, in_axes=(0, None)))  # landscapes: (n_k, n_max)
    mask = jnp.asarray(np.arange(n_max)[None, :] < counts[:, None], dtype=float)

    def prefix_losses(k, c, phi_d, rtol):
        """L_N(k) for every horizon N, rad^2: (len(horizons),), by reverse mode's adjoint."""
        phi = traj(jnp.stack([k, c, phi0]), rtol, adjoint="reverse")
        return mask @ (phi - phi_d) ** 2 / counts

    rev_grad = jax.jit(jax.jacrev(prefix_losses))

    # --- multiple shooting: one-period segments, vmapped; segment j covers samples
    # j*SPP .. (j+1)*SPP of the record.
    ts_seg = ts[: SPP + 1]

    def segment(k, c, x0, rtol):
        """phi, dphi (SPP+1,) of one segment started at the state x0 = (phi, dphi)."""
        tr = cj.simulate(scene.mech.replace(k=k, c=c), x0[0], x0[1], ts_seg, solver=SOLVER,
                         rtol=rtol, atol=rtol * 1e-2, adjoint="forward")
        return tr.phi, tr.dphi

    def seg_loss(k, c, x0, phi_seg, dphi_end, rtol):
        """Sum of squared residuals of one segment, rad^2: the record misfit at its SPP
        samples after the start, plus the rate's continuity defect at its end in rad."""
        phi, dphi = segment(k, c, x0, rtol)
        return jnp.sum((phi[1:] - phi_seg[1:]) ** 2) + ((dphi[-1] - dphi_end) / omega) ** 2

    def seg_val_grad1(k, *a):
        # Forward mode (one tangent): the segments were solved with ForwardMode.
        return jax.jvp(lambda kk: seg_loss(kk, *a), (k,), (jnp.ones_like(k),))

    seg_val_grad = jax.jit(jax.vmap(seg_val_grad1, in_axes=(None, None, 0, 0, 0, None)))
    seg_landscape = jax.jit(jax.vmap(lambda k, *a: jnp.sum(jax.vmap(
        seg_loss, in_axes=(None, None, 0, 0, 0, None))(k, *a)), in_axes=(0,) + (None,) * 5))

    out = dict(period_s=period, phi0=phi0, k_true=k_true, samples_per_period=SPP,
               horizons_periods=list(horizons), k0=k_true * (1 + REL_DK), single=[],
               multiple=[], accuracy=[], landscape={})
    k0 = k_true * (1 + REL_DK)
    n_grid = 41 if smoke else 401
    ks = k_true * np.linspace(0.95, 1.05, n_grid)
    for c in dampings:
        truth = cj.simulate(scene.mech.replace(c=c), phi0, 0.0, ts, solver=SOLVER, rtol=TIGHT,
                            atol=TIGHT * 1e-2, max_steps=5_000_000)
        phi_d, dphi_d = truth.phi, truth.dphi
        jc = float(c)

        # Sensitivities at the truth: RMS over each horizon of d phi / d(k, c, phi0).
        _, J = traj_jac(jnp.array([k_true, jc, phi0]), 1e-8)
        J = np.asarray(J)
        # Gradient at k0 = truth + 1%: forward mode at three tolerances (1e-12 is the
        # reference), reverse mode, and finite differences of tight solves.
        fwd = {}
        for rtol in (1e-6, 1e-8, TIGHT):
            phi, Jk = traj_jac(jnp.array([k0, jc, phi0]), rtol)
            res = np.asarray(phi - phi_d)
            fwd[rtol] = np.array([2 * np.mean(res[:n] * np.asarray(Jk)[:n, 0])
                                  for n in counts])
            if rtol == TIGHT:
                loss0 = np.array([np.mean(res[:n] ** 2) for n in counts])
        rev = np.asarray(rev_grad(jnp.asarray(k0), jnp.asarray(jc), phi_d, 1e-8))
        fd = {}
        for h in (1e-4, 1e-6):
            for rtol in (TIGHT, 1e-8):
                lp = [np.asarray(traj_only(jnp.array([k0 * (1 + s * h), jc, phi0]), rtol)
                                 - phi_d) for s in (1, -1)]
                lpm = [np.array([np.mean(r[:n] ** 2) for n in counts]) for r in lp]
                fd[(h, rtol)] = (lpm[0] - lpm[1]) / (2 * k0 * h)
        _say(f"c = {c:g}: single-shooting sensitivities and gradients", t0)

        # Multiple shooting at k0: per-segment values and gradients, all segments at once.
        S = horizons[-1]
        starts = np.arange(S) * SPP
        x0s = jnp.stack([phi_d[starts], dphi_d[starts]], axis=1)
        phis = jnp.stack([phi_d[s:s + SPP + 1] for s in starts])
        dends = dphi_d[starts + SPP]
        vals, grads = seg_val_grad(jnp.asarray(k0), jnp.asarray(jc), x0s, phis, dends, 1e-10)
        vals, grads = np.asarray(vals), np.asarray(grads)
        _say(f"c = {c:g}: multiple shooting ({S} segments)", t0)

        ref = fwd[TIGHT]
        for i, N in enumerate(horizons):
            n = counts[i]
            out["single"].append(dict(
                c=c, periods=N, loss_at_k0=float(loss0[i]), grad_k_at_k0=float(ref[i]),
                rms_dphi_dk=float(np.sqrt(np.mean(J[:n, 0] ** 2))),
                rms_dphi_dc=float(np.sqrt(np.mean(J[:n, 1] ** 2))),
                rms_dphi_dphi0=float(np.sqrt(np.mean(J[:n, 2] ** 2))),
                final_abs_dphi_dk=float(abs(J[n - 1, 0]))))
            out["multiple"].append(dict(
                c=c, periods=N, segments=N, loss_at_k0=float(np.sum(vals[:N]) / n),
                grad_k_at_k0=float(np.sum(grads[:N]) / n),
                max_abs_segment_grad_per_sample=float(np.max(np.abs(grads[:N])) / SPP)))
            rel = {f"forward_rtol_{r:g}": float(abs(fwd[r][i] - ref[i]) / abs(ref[i]))
                   for r in (1e-6, 1e-8)}
            rel["reverse_rtol_1e-08"] = float(abs(rev[i] - ref[i]) / abs(ref[i]))
            for (h, r), g in fd.items():
                rel[f"fd_h_{h:g}_rtol_{r:g}"] = float(abs(g[i] - ref[i]) / abs(ref[i]))
            out["accuracy"].append(dict(c=c, periods=N, grad_ref=float(ref[i]), rel_err=rel))
            print(f"  c={c:g} N={N:4d}: single dL/dk {ref[i]: .3e} (rms dphi/dk "
                  f"{out['single'][-1]['rms_dphi_dk']:.3g}, dphi/dc "
                  f"{out['single'][-1]['rms_dphi_dc']:.3g}); multiple dL/dk "
                  f"{out['multiple'][-1]['grad_k_at_k0']: .3e}; rel err fwd1e-8 "
                  f"{rel['forward_rtol_1e-08']:.1e} rev {rel['reverse_rtol_1e-08']:.1e} "
                  f"fd {rel['fd_h_1e-06_rtol_1e-12']:.1e}", flush=True)

        # Loss landscapes over k in truth +-5%: single shooting for every horizon (prefixes
        # of one batched solve), multiple shooting for the longest.
        P = np.asarray(batch(jnp.stack([jnp.asarray(ks), jnp.full(n_grid, jc),
                                        jnp.full(n_grid, phi0)], axis=1), 1e-8))
        R2 = (P - np.asarray(phi_d)[None, :]) ** 2
        ms = np.asarray(seg_landscape(jnp.asarray(ks), jnp.asarray(jc), x0s, phis, dends,
                                      1e-10)) / n_max
        land = dict(k=ks.tolist(), single={}, multiple=ms.tolist(), summary=[])
        for i, N in enumerate(horizons):
            y = R2[:, : counts[i]].mean(axis=1)
            land["single"][str(N)] = y.tolist()
            b = basin(ks, y, k_true)
            land["summary"].append(dict(method="single", periods=N, local_minima=local_minima(y),
                                        basin_below=b[0], basin_above=b[1]))
        b = basin(ks, ms, k_true)
        d2 = np.diff(ms, 2)
        land["summary"].append(dict(method="multiple", periods=horizons[-1],
                                    local_minima=local_minima(ms), basin_below=b[0],
                                    basin_above=b[1],
                                    convex_fraction=float(np.mean(d2 > 0))))
        for s in land["summary"]:
            print(f"  landscape c={c:g} {s}", flush=True)
        out["landscape"][f"{c:g}"] = land
        _say(f"c = {c:g}: landscapes over {n_grid} values of k", t0)
    return out


def figure(res: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    FIGURES.mkdir(parents=True, exist_ok=True)
    fig, axs = plt.subplots(1, 3, figsize=(15, 4.3))
    ax = axs[0]
    for c, mk in (("0", "o-"), ("0.001", "s--")):
        rows = [r for r in res["single"] if f"{r['c']:g}" == c]
        if rows:
            N = np.array([r["periods"] for r in rows])
            g = np.array([r["grad_k_at_k0"] for r in rows])
            line, = ax.loglog(N, np.abs(g), mk, label=f"single shooting, c = {c}")
            # A gradient pointing away from the truth: the start is outside the basin.
            ax.loglog(N[g < 0], -g[g < 0], "x", color="k", ms=10, zorder=5,
                      label="points away from the truth" if c == "0" else None)
            rows = [r for r in res["multiple"] if f"{r['c']:g}" == c]
            ax.loglog(N, [abs(r["grad_k_at_k0"]) for r in rows], mk, color="C2" if c == "0"
                      else "C3", label=f"multiple shooting, c = {c}")
    ax.set_xlabel("horizon N, periods")
    ax.set_ylabel("|dL/dk| at k = 1.01 k_true, rad^2 / (N*m/rad)")
    ax.set_title("Gradient of the mean squared error")
    ax.legend(fontsize=8)
    ax = axs[1]
    land = res["landscape"]["0"]
    k = np.array(land["k"])
    # Each curve scaled to its largest value: the shapes matter, not the levels.
    for N in (3, 30, 300):
        if str(N) in land["single"]:
            y = np.array(land["single"][str(N)])
            ax.plot(k, y / y.max(), lw=0.9, label=f"single, {N} periods")
    y = np.array(land["multiple"])
    ax.plot(k, y / y.max(), "k--", lw=2, label=f"multiple, {res['horizons_periods'][-1]} periods")
    ax.axvline(res["k_true"], color="grey", ls=":")
    ax.set_xlabel("k, N*m/rad (truth 2, c = 0)")
    ax.set_ylabel("L(k) / max L")
    ax.set_title("Loss landscape")
    ax.legend(fontsize=8)
    ax = axs[2]
    rows = [r for r in res["accuracy"] if r["c"] == 0.0]
    N = [r["periods"] for r in rows]
    for key, label in (("forward_rtol_1e-06", "forward mode, rtol 1e-6"),
                       ("forward_rtol_1e-08", "forward mode, rtol 1e-8"),
                       ("reverse_rtol_1e-08", "reverse mode, rtol 1e-8"),
                       ("fd_h_1e-06_rtol_1e-12", "central FD h 1e-6, rtol 1e-12"),
                       ("fd_h_1e-06_rtol_1e-08", "central FD h 1e-6, rtol 1e-8")):
        ax.loglog(N, [max(r["rel_err"][key], 1e-16) for r in rows], "o-", label=label)
    ax.set_xlabel("horizon N, periods")
    ax.set_ylabel("relative error of dL/dk (vs forward mode, rtol 1e-12)")
    ax.set_title("Gradient accuracy, c = 0")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(FIGURES / "stress_gradients.png", dpi=110)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--smoke", action="store_true", help="horizons up to 10 periods, for CI")
    p.add_argument("--plot", action="store_true",
                   help="only redraw the figure from the saved full-run results")
    a = p.parse_args(argv)
    if a.plot:
        figure(json.loads((RESULTS / "stress_gradients.json").read_text()))
        return
    t0 = time.perf_counter()
    res = dict(date=datetime.date.today().isoformat(), **_machine(), jax=jax.__version__,
               smoke=a.smoke)
    res.update(run(a.smoke))
    res["wall_s"] = time.perf_counter() - t0
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"stress_gradients{'_smoke' if a.smoke else ''}.json"
    with atomic_write(path) as f:
        json.dump(res, f, indent=1)
    if not a.smoke:
        figure(res)
    print(f"wrote {path} ({res['wall_s']:.0f} s)")


if __name__ == "__main__":
    main()
