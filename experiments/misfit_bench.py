"""A misfit bench: records whose truth has what the fitted model lacks, fitted by
`crank_jax.fit` under defaults and judged against the best rms the model can reach.

Two rigs, each fitted with the plain model (viscous crank damping, no guide friction,
the nominal geometry, an ideal encoder):

- `osc`: the lab rig (a torsion spring, about 4.5 Hz) under its known 3 Hz shaker torque
  (0.2 N*m), 3 s at 100 Hz, 1 mrad noise; free `k`, `c`, `phi0`, `dphi0`, started from
  the demo's start values (k 20% high, c 2x);
- `rot`: the motor-driven offset slider-crank of `rotating_rig.py` (no spring, tilted
  mount, `e` = 8 mm) under a constant motor torque 0.2 N*m, 3 s at 50 Hz, 2 mrad noise;
  free `tau0`, `c`, `phi0`, `dphi0`, started from half the torque and twice the damping.

The truth adds one effect per case (the fitted model has none of them):

- `guide_friction`: Coulomb plus Stribeck friction in the slider guide (a user force:
  the friction force times `dx_s/dphi`);
- `motor_droop`: the drive torque falls with the square of the speed, plus a supply
  ripple (5% of the drive at 7 Hz);
- `speed_wander`: a slowly wandering load torque (three tones in 0.1-0.5 Hz);
- `geometry`: the crank radius `r` 0.5% longer than the fitted model's;
- `eccentricity`: a once-per-revolution encoder error `eps sin(phi + 0.7)`;
- `startup`: a start-up transient in the record (`synthesize(transient=...)`).

Two records like the real ones (`--real`, `_misfit_real.py`; misfit_bench.real.json):
`rot:slide_only`, the rotating rig seen only by its slide position, with a drive that
droops with speed, a start-up and a slider force started at 0; `tooth:coast_down`, a
coast-down above 1,000 rpm by a 36-1 tooth wheel, the force by crank angle and the drag
torque started at 0. Each is judged against scipy's TRF on its own residuals.

One case more changes the start, not the truth (`--extra`, not in the default run):

- `zero_start`: the plain record, the fit started with its drive (`tau0`, rot) or its
  stiffness (`k`, osc) at exactly 0, a start a user writes when the value is unknown.

For each case the reference is the best rms the model can reach on that record, found
by brute force with a different optimiser: `scipy.optimize.least_squares(method="trf")`
with tight tolerances on the same single-shooting angle residuals (this script's own
`crank_jax.simulate` call, forward-mode sensitivities), from the fit's start, the fit's
estimate and `--starts` random starts (log-uniform within 4.5x for the positive
parameters, wide for the state). The table reports whether the fit converged, its rms
against that reference (both computed by the reference's residual function, so on the
same footing), its iterations and its wall time (compilation included: each case is a
new problem).

    python experiments/misfit_bench.py [--starts 4] [--cases osc:geometry,...]
    python experiments/misfit_bench.py --real [--starts 1]   # records like the real ones
    python experiments/misfit_bench.py --smoke    # one tiny case; misfit_bench.smoke.json
    python experiments/misfit_bench.py --table    # rewrite the table on the docs page

Writes experiments/results/misfit_bench.json; `--table` rewrites the section between
`<!-- BEGIN misfit-bench -->` and `<!-- END misfit-bench -->` in
docs/benchmarks/identification.md. Wall times on a shared machine are rough.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import json
import re
import time

from _bench import RESULTS, ROOT, machine, setup_jax

jax = setup_jax()

import _misfit_real as real  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.runtime.io import atomic_write  # noqa: E402

RIGS = ("osc", "rot")
#: Cases that change the fit's start rather than the truth (`--extra`).
START_CASES = ("zero_start",)
EFFECTS = ("guide_friction", "motor_droop", "speed_wander", "geometry", "eccentricity",
           "startup")
PAGE = ROOT / "docs" / "benchmarks" / "identification.md"
BEGIN, END = "<!-- BEGIN misfit-bench -->", "<!-- END misfit-bench -->"
#: A reference fit's rms within this relative distance of another is the same minimum.
SAME = 1e-6


# ----------------------------------------------------------------------------- rigs ---

def osc_mech(**over) -> cj.SliderCrank:
    return cj.load_scene("lab-rig").mech.replace(**over)


def rot_mech(**over) -> cj.SliderCrank:
    m = dict(r=0.05, L=0.2, b=0.1, s=0.01, m_c=0.1, m_p=0.05, m_s=0.1, I_c=2e-3, I_p=2e-4,
             k=0.0, c=0.01, g=9.81, e=0.008, gravity_angle=0.35)
    m.update(over)
    return cj.SliderCrank(**m)


RIG = {
    # free names, truth, start values, record (t1 s, rate Hz, noise rad)
    "osc": dict(free=("k", "c", "phi0", "dphi0"), truth=dict(k=2.0, c=0.002, phi0=0.5,
                                                              dphi0=0.0),
                start=dict(k=2.4, c=0.004), t1=3.0, rate=100.0, noise=1e-3),
    "rot": dict(free=("tau0", "c", "phi0", "dphi0"), truth=dict(tau0=0.2, c=0.01, phi0=0.0,
                                                                dphi0=5.0),
                start=dict(tau0=0.1, c=0.02), t1=3.0, rate=50.0, noise=2e-3),
}


def loads(rig: str, p: dict):
    """(mechanism, torque) of `rig` with the values `p` (truth or fitted)."""
    if rig == "osc":
        return (osc_mech(k=p["k"], c=p["c"]),
                cj.HarmonicLoad(0.0, 0.2, 3.0))
    return rot_mech(c=p["c"]), cj.ConstantLoad(p["tau0"])


def scene(rig: str, p: dict, t1: float, **mech) -> cj.Scene:
    m, torque = loads(rig, p)
    return cj.Scene(m.replace(**mech) if mech else m, torque=torque, phi0=p.get("phi0", 0.0),
                    dphi0=p.get("dphi0", 0.0), t1=t1, rtol=1e-10, atol=1e-12)


# -------------------------------------------------------------------- the effects ---

class GuideFriction(eqx.Module):
    """Slider-guide friction `F(v) = (F_c + (F_st - F_c) exp(-(v/v_st)^2)) tanh(v/eps)`
    (N) acting against the slider's velocity, as a crank torque `-F dx_s/dphi` (N*m)."""

    mech: cj.SliderCrank
    F_c: float
    F_st: float
    v_st: float = 0.02
    eps: float = 1e-3

    def __call__(self, t, phi, dphi):
        dx = cj.model.kinematics(self.mech, phi, 1.0, 0.0).v_s  # dx_s/dphi, m/rad
        v = dx * dphi
        f = (self.F_c + (self.F_st - self.F_c) * jnp.exp(-(v / self.v_st) ** 2))
        return -f * jnp.tanh(v / self.eps) * dx


class MotorDroop(eqx.Module):
    """The drive torque less `drop (dphi / w)^2` of itself, plus a supply ripple."""

    drive: float
    omega: float
    drop: float
    ripple: float
    ripple_hz: float
    shaker_hz: float | None = None  # the oscillating rig's drive is a sine at this rate

    def __call__(self, t, phi, dphi):
        drive = self.drive * (jnp.sin(2 * jnp.pi * self.shaker_hz * t)
                              if self.shaker_hz is not None else 1.0)
        return (-drive * self.drop * (dphi / self.omega) ** 2
                + self.ripple * self.drive * jnp.sin(2 * jnp.pi * self.ripple_hz * t))


class Wander(eqx.Module):
    """A slowly wandering load torque: three tones in 0.1-0.5 Hz, N*m."""

    amps: jax.Array
    freqs: jax.Array
    phases: jax.Array

    def __call__(self, t, phi, dphi):
        return jnp.sum(self.amps * jnp.sin(2 * jnp.pi * self.freqs * t + self.phases))


def record(rig: str, effect: str, seed: int, t1: float | None = None) -> cj.Data:
    """One record of `rig` whose truth has `effect`, angle channel only."""
    cfg = RIG[rig]
    t1 = cfg["t1"] if t1 is None else t1
    truth = cfg["truth"]
    rng = np.random.default_rng(seed)
    mech_over, force, transient = {}, None, 0.0
    drive = 0.2  # N*m: the shaker's amplitude or the motor's torque
    if effect == "guide_friction":
        m = loads(rig, truth)[0]
        force = GuideFriction(m, 0.3, 0.5) if rig == "osc" else GuideFriction(m, 0.5, 0.8)
    elif effect == "motor_droop":
        force = (MotorDroop(drive, 30.0, 0.2, 0.05, 7.0, 3.0) if rig == "osc"
                 else MotorDroop(drive, 20.0, 0.3, 0.05, 7.0))
    elif effect == "speed_wander":
        amps = jnp.asarray(rng.uniform(0.5, 1.0, 3))
        amps = amps / jnp.sqrt(jnp.sum(amps**2) / 2) * 0.05 * drive  # rms 5% of the drive
        force = Wander(amps, jnp.asarray(rng.uniform(0.1, 0.5, 3)),
                       jnp.asarray(rng.uniform(0, 2 * np.pi, 3)))
    elif effect == "geometry":
        mech_over = {"r": float(loads(rig, truth)[0].r) * 1.005}
    elif effect == "startup":
        transient = 0.05 if rig == "osc" else 0.1
    elif effect not in ("eccentricity",) + START_CASES:
        raise ValueError(f"unknown effect {effect!r}")
    sc = scene(rig, truth, t1, **mech_over)
    d = cj.synthesize(sc, rate=cfg["rate"], noise_std=cfg["noise"], seed=seed, force=force,
                      transient=transient, transient_time=0.3, transient_hz=8.0)
    phi = np.asarray(d.phi)
    if effect == "eccentricity":
        # The encoder reads the angle with a once-per-revolution error (a disc off its
        # axis): eps = 3 mrad on the oscillating rig, 5 mrad on the rotating one.
        eps = 3e-3 if rig == "osc" else 5e-3
        phi = phi + eps * np.sin(phi + 0.7)
    return cj.Data(np.asarray(d.ts), phi, source=f"{rig}:{effect} seed {seed}")


# ------------------------------------------------------------------ the reference ---

def _coords(rig):
    """Names of the reference's coordinates: log for the positive ones, then the state."""
    return ("tau0", "c") if rig == "rot" else ("k", "c")


@functools.cache
def reference_program(rig: str):
    """`(residuals, jacobian)` on the host, both of `(theta, ts, phi_data)` (n,), with
    `theta = (ln a, ln c, phi0, dphi0)` and `a` = k (osc) or tau0 (rot)."""
    pos = _coords(rig)

    def model(theta, ts, phi_data):
        p = {pos[0]: jnp.exp(theta[0]), "c": jnp.exp(theta[1])}
        m, torque = loads(rig, p)
        tr = cj.simulate(m, theta[2], theta[3], ts, torque=torque, adjoint="forward",
                         rtol=1e-10, atol=1e-12, throw=False)
        # A failed solve is a large residual, which the trust region rejects.
        ok = tr.ok
        return jnp.where(ok, tr.phi - phi_data, 10.0)

    res = jax.jit(model)
    jac = jax.jit(jax.jacfwd(model))
    return (lambda th, ts, y: np.asarray(res(jnp.asarray(th), ts, y)),
            lambda th, ts, y: np.asarray(jac(jnp.asarray(th), ts, y)))


def theta_of(rig: str, values: dict) -> np.ndarray:
    a, = [n for n in _coords(rig) if n != "c"]
    with np.errstate(divide="ignore"):  # a value at 0 (a zero start) is ln 0 = -inf
        return np.array([np.log(float(values[a])), np.log(float(values["c"])),
                         values["phi0"], values["dphi0"]])


def reference(rig: str, data: cj.Data, starts: list[np.ndarray]) -> dict:
    """The best rms over TRF runs from each of `starts` (tight tolerances)."""
    res_fn, jac_fn = reference_program(rig)  # one program per rig: the effect is in the data
    ts, y = jnp.asarray(data.ts), jnp.asarray(data.phi)
    best, rows = None, []
    for th0 in starts:
        sol = least_squares(res_fn, th0, jac=jac_fn, args=(ts, y), method="trf",
                            x_scale="jac", ftol=1e-14, xtol=1e-14, gtol=1e-14, max_nfev=200)
        rms = float(np.sqrt(np.mean(sol.fun**2)))
        rows.append(rms)
        if np.isfinite(rms) and (best is None or rms < best[0]):
            best = (rms, sol.x, int(sol.nfev))
    if best is None:
        return {"rms": float("nan"), "starts": len(starts), "rms_per_start": rows}
    hits = sum(abs(r / best[0] - 1) <= SAME for r in rows if np.isfinite(r))
    return {"rms": best[0], "theta": best[1].tolist(), "starts": len(starts),
            "starts_reaching_best": hits, "rms_per_start": rows,
            "rms_fn": lambda th: float(np.sqrt(np.mean(res_fn(np.asarray(th), ts, y)**2)))}


def random_starts(rig: str, k: int, rng) -> list[np.ndarray]:
    truth = theta_of(rig, RIG[rig]["truth"])
    out = []
    for _ in range(k):
        th = truth.copy()
        th[:2] += rng.uniform(-1.5, 1.5, 2)  # within 4.5x
        if rig == "osc":
            th[2] += rng.uniform(-0.3, 0.3)
            th[3] += rng.uniform(-1.0, 1.0)
        else:
            th[2] += rng.uniform(-0.5, 0.5)
            th[3] *= rng.uniform(0.6, 1.4)
        out.append(th)
    return out


# ------------------------------------------------------------------------ the run ---

def run_case(rig: str, effect: str, seed: int, n_starts: int, t1: float | None = None,
             smoke: bool = False) -> dict:
    cfg = RIG[rig]
    data = record(rig, effect, seed, t1)
    start_vals = dict(cfg["truth"], **cfg["start"])
    if effect == "zero_start":
        start_vals[_coords(rig)[0]] = 0.0
    start_scene = scene(rig, start_vals, float(data.ts[-1]))
    t = time.perf_counter()
    res = cj.fit(start_scene, data, free=cfg["free"], progress=False, warn=False)
    wall = time.perf_counter() - t
    th_fit = theta_of(rig, {n: res.values[n] for n in cfg["free"]})
    # The fit's own start state is the scene's; the reference starts there too.
    th_start = theta_of(rig, {**start_vals, "phi0": float(start_scene.phi0),
                              "dphi0": float(start_scene.dphi0)})
    rng = np.random.default_rng(seed + 1)
    t = time.perf_counter()
    fixed = [th_fit] if smoke else [th_fit, th_start]
    fixed = [th for th in fixed if np.all(np.isfinite(th))]  # (a zero start has no log)
    ref = reference(rig, data, fixed + random_starts(rig, n_starts, rng))
    ref_wall = time.perf_counter() - t
    rms_fn = ref.pop("rms_fn", None)
    rms_fit = rms_fn(th_fit) if rms_fn is not None else float("nan")
    return {
        "rig": rig, "effect": effect, "seed": seed, "samples": int(data.n),
        "converged": bool(res.converged), "message": res.message,
        "strategy": res.strategy, "iterations": int(res.iterations),
        "seconds": wall, "rms_fit": rms_fit, "rms_fit_reported": res.rms_residual,
        "rms_reference": ref["rms"],
        "rms_ratio": rms_fit / ref["rms"] if ref["rms"] > 0 else float("nan"),
        "white": (res.diagnostics.white if res.diagnostics is not None else None),
        "values": {n: res.values[n] for n in cfg["free"]},
        "reference": ref, "reference_seconds": ref_wall,
    }


def run_real(effect: str, seed: int, n_starts: int, t1: float | None = None) -> dict:
    """One case of `--real` (see `_misfit_real.py`): the fit under defaults, then the
    reference from the fit's estimate, its start (where finite) and random starts."""
    data, start_scene, free, kw = real.case(effect, seed, t1, keep=True)
    t = time.perf_counter()
    res = cj.fit(start_scene, data, free=free, progress=False, warn=False, **kw)
    wall = time.perf_counter() - t
    values = {n: float(res.values[n]) for n in free}
    print(f"  fit: converged={res.converged} it={res.iterations} {wall:.1f} s {values}",
          flush=True)
    th_fit = real.theta_of(effect, values)
    m0 = start_scene.mech
    th_start = real.theta_of(effect, {"I_c": float(m0.I_c), "c": float(m0.c),
                                      "tau0": float(start_scene.torque.value),
                                      "P0": float(getattr(start_scene.load, "value", 0.0)),
                                      "phi0": float(start_scene.phi0),
                                      "dphi0": float(start_scene.dphi0)})
    res_fn, jac_fn = real.program(effect)
    ts, y, load = real.observed(effect, data)
    # The truth too: a slide's TRF from a generic start can land on the other branch.
    starts = [th for th in (th_fit, th_start, real.truth_theta(effect))
              if np.all(np.isfinite(th))]
    starts += real.random_starts(effect, n_starts, np.random.default_rng(seed + 1))
    t = time.perf_counter()
    rows, best = [], None
    for th0 in starts:
        sol = least_squares(res_fn, th0, jac=jac_fn, args=(ts, y, load), method="trf",
                            x_scale="jac", ftol=1e-14, xtol=1e-14, gtol=1e-14, max_nfev=200)
        rms = float(np.sqrt(np.mean(sol.fun**2)))
        rows.append(rms)
        if np.isfinite(rms) and (best is None or rms < best[0]):
            best = (rms, sol.x)
    ref_wall = time.perf_counter() - t

    def rms_of(th):
        return float(np.sqrt(np.mean(res_fn(np.asarray(th), ts, y, load) ** 2)))

    rms_fit = rms_of(th_fit) if np.all(np.isfinite(th_fit)) else float("nan")
    hits = sum(abs(r / best[0] - 1) <= SAME for r in rows if np.isfinite(r))
    return {
        "rig": real.RIG_OF[effect], "effect": effect, "seed": seed, "samples": int(data.n),
        "converged": bool(res.converged), "message": res.message,
        "strategy": res.strategy, "iterations": int(res.iterations), "seconds": wall,
        "rms_fit": rms_fit, "rms_fit_reported": res.rms_residual,
        "rms_reference": best[0], "rms_ratio": rms_fit / best[0],
        "values": values, "load_by": kw.get("load_by", "time"),
        "record_sha1": hashlib.sha1(np.asarray(ts).tobytes() + np.asarray(y).tobytes())
        .hexdigest(),
        "reference": {"rms": best[0], "theta": best[1].tolist(), "starts": len(starts),
                      "starts_reaching_best": hits, "rms_per_start": rows},
        "reference_seconds": ref_wall,
    }


def table(doc: dict) -> str:
    """The markdown section for the docs page."""
    m = doc["machine"]
    lines = [
        f"**Misfit bench** ({m['date']}, {m['cores']} cores, shared: wall times are rough; "
        "`experiments/misfit_bench.py`, results in `experiments/results/misfit_bench.json`). "
        "Each record's truth has one effect the fitted model lacks; the reference is the "
        "best rms of scipy's TRF from the fit's start, its estimate and "
        f"{doc['starts']} random starts, tight tolerances, on the same residuals. "
        f"Code: {doc.get('code', 'this branch')}.",
        "",
        "| rig | effect | converged | rms / reference | reference rms (rad) | LM iterations "
        "| wall time (s) | strategy |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in doc["cases"]:
        lines.append(
            f"| {r['rig']} | {r['effect'].replace('_', ' ')} | "
            f"{'yes' if r['converged'] else '**no**'} | {r['rms_ratio']:.3f} | "
            f"{r['rms_reference']:.3g} | {r['iterations']} | {r['seconds']:.1f} | "
            f"{r['strategy']} |")
    return "\n".join(lines)


EXTRA_BEGIN, EXTRA_END = "<!-- BEGIN misfit-extra -->", "<!-- END misfit-extra -->"


def extra_table(doc: dict, before: dict | None) -> str:
    """The docs section of the `--extra` cases, with the code before beside (`before`)."""
    rows = [("this code", doc)] + ([("before", before)] if before else [])
    lines = [f"**Zero starts** ({doc['machine']['date']}, `experiments/misfit_bench.py "
             "--extra`, results in `experiments/results/misfit_bench.extra.json`"
             + (", the code before from `--before`" if before else "") + "): the plain "
             "record, the fit started with the drive (rot) or the stiffness (osc) at 0. The "
             "start from the motion already mended these before; the zero start that failed "
             "(a drag torque held fixed as a flat direction) is a coast-down's, "
             "`tests/test_physical_ranges.py::test_a_drag_torque_started_at_zero_is_"
             "determined`.", "",
             "| rig | code | converged | rms / reference | LM iterations | wall time (s) |",
             "|---|---|---|---|---|---|"]
    for label, d in rows:
        for r in d["cases"]:
            lines.append(f"| {r['rig']} | {d.get('code') or label} | "
                         f"{'yes' if r['converged'] else '**no**'} | {r['rms_ratio']:.3f} | "
                         f"{r['iterations']} | {r['seconds']:.1f} |")
    return "\n".join(lines)


REAL_BEGIN, REAL_END = "<!-- BEGIN misfit-real -->", "<!-- END misfit-real -->"


def real_table(doc: dict, befores: list[dict]) -> str:
    """The docs section of the `--real` cases, with runs of older code beside."""
    lines = [f"**Records like the real ones** ({doc['machine']['date']}, `experiments/"
             "misfit_bench.py --real`, results in `experiments/results/misfit_bench.real"
             "[.before-*].json`; the cases in `experiments/_misfit_real.py`). The reference: "
             "scipy's TRF from the fit's estimate, its start (where finite), the truth and "
             f"{doc['starts']} random start(s), on the same residuals (the slide in m, the "
             "angle in rad at the tooth edges). Older code fits the coast-down's force "
             "interpolated in time (it has no `load_by`) and is judged against the TRF "
             "reference of that problem.", "",
             "| case | code | converged | fit rms | rms / reference | reference rms "
             "| LM iterations | wall time (s) | strategy |",
             "|---|---|---|---|---|---|---|---|---|"]
    unit = {"slide_only": "mm", "coast_down": "mrad"}
    # A record fitted by several codes (the same samples) is judged by the best reference.
    best = {}
    for d in [doc] + befores:
        for r in d["cases"]:
            k = (r.get("record_sha1"), r.get("load_by"))
            best[k] = min(best.get(k, np.inf), r["rms_reference"])
    for d in [doc] + befores:
        for r in d["cases"]:
            r["rms_reference"] = best[(r.get("record_sha1"), r.get("load_by"))]
            ratio = r["rms_fit"] / r["rms_reference"]
            lines.append(
                f"| {r['rig']}: {r['effect'].replace('_', ' ')} | {d.get('code') or '?'} | "
                f"{'yes' if r['converged'] else '**no**'} | "
                f"{1e3 * r['rms_fit']:.4g} {unit[r['effect']]} | "
                f"{ratio:.3f}{'' if ratio <= 1.1 else ' (**off**)'} | "
                f"{1e3 * r['rms_reference']:.3g} {unit[r['effect']]} | {r['iterations']} | "
                f"{r['seconds']:.1f} | {r['strategy']} |")
    return "\n".join(lines)


def write_section(begin: str, end: str, block: str) -> None:
    """Replace the section between `begin` and `end` on the page (or add it at its end)."""
    src = PAGE.read_text()
    pat = re.compile(re.escape(begin) + ".*?" + re.escape(end), re.S)
    text = (pat.sub(lambda _: f"{begin}\n{block}\n{end}", src) if pat.search(src)
            else src.replace(EXTRA_END, f"{EXTRA_END}\n\n{begin}\n{block}\n{end}", 1))
    with atomic_write(PAGE) as f:
        f.write(text)


def write_table(doc: dict) -> None:
    src = PAGE.read_text()
    pat = re.compile(re.escape(BEGIN) + ".*?" + re.escape(END), re.S)
    if not pat.search(src):
        raise SystemExit(f"{PAGE} has no misfit-bench markers")
    text = pat.sub(lambda _: f"{BEGIN}\n{table(doc)}\n{END}", src)
    with atomic_write(PAGE) as f:
        f.write(text)
    print(f"rewrote the misfit-bench table in {PAGE.relative_to(ROOT)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--starts", type=int, default=4, help="random starts of the reference")
    ap.add_argument("--cases", default="",
                    help="comma-separated RIG:EFFECT (default: every rig and effect)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--code", default="", help="what code ran (a note for the table)")
    ap.add_argument("--extra", action="store_true",
                    help=f"the cases that change the start instead ({', '.join(START_CASES)}), "
                         "written to misfit_bench.extra.json (or --out)")
    ap.add_argument("--real", action="store_true",
                    help=f"records like the real ones instead ({', '.join(real.REAL)}), "
                         "written to misfit_bench.real.json (or --out)")
    ap.add_argument("--before", help="with --extra/--real --table: results files of the "
                                     "code before (comma-separated), shown beside")
    ap.add_argument("--out", help="results file (default: experiments/results/misfit_bench"
                                  "[.smoke|.extra].json)")
    ap.add_argument("--smoke", action="store_true",
                    help="one short case, one random start; misfit_bench.smoke.json")
    ap.add_argument("--table", action="store_true",
                    help="rewrite the docs table from misfit_bench.json and stop")
    a = ap.parse_args()
    out = RESULTS / ("misfit_bench.smoke.json" if a.smoke else "misfit_bench.extra.json"
                     if a.extra else "misfit_bench.real.json" if a.real
                     else "misfit_bench.json")
    if a.out:
        out = ROOT / a.out if not a.out.startswith("/") else type(ROOT)(a.out)
    if a.table and a.real:
        befores = [json.loads(open(f).read()) for f in (a.before or "").split(",") if f]
        doc = json.loads((RESULTS / "misfit_bench.real.json").read_text())
        write_section(REAL_BEGIN, REAL_END, real_table(doc, befores))
        return
    if a.table and a.extra:
        before = json.loads(open(a.before).read()) if a.before else None
        doc = json.loads((RESULTS / "misfit_bench.extra.json").read_text())
        src = PAGE.read_text()
        block = f"{EXTRA_BEGIN}\n{extra_table(doc, before)}\n{EXTRA_END}"
        pat = re.compile(re.escape(EXTRA_BEGIN) + ".*?" + re.escape(EXTRA_END), re.S)
        text = pat.sub(lambda _: block, src) if pat.search(src) else src.replace(
            END, END + "\n\n" + block, 1)
        with atomic_write(PAGE) as f:
            f.write(text)
        return
    if a.table:
        write_table(json.loads((RESULTS / "misfit_bench.json").read_text()))
        return
    if a.starts < 0:
        raise SystemExit("--starts must be >= 0")
    kinds = START_CASES if a.extra else EFFECTS
    cases = [c.split(":") for c in a.cases.split(",") if c] or (
        [(real.RIG_OF[e], e) for e in real.REAL] if a.real else
        [(r, e) for r in RIGS for e in kinds])
    for c in cases:
        if len(c) == 2 and c[1] in real.REAL and c[0] == real.RIG_OF[c[1]]:
            continue
        if len(c) != 2 or c[0] not in RIGS or c[1] not in EFFECTS + START_CASES:
            raise SystemExit(f"--cases: {':'.join(c)} is not RIG:EFFECT with RIG in "
                             f"{', '.join(RIGS)} and EFFECT in {', '.join(EFFECTS)}")
    starts, t1 = a.starts, None
    if a.smoke:
        cases, starts, t1 = [("osc", "geometry")], 1, 0.6
    doc = {"smoke": a.smoke, "machine": machine(), "starts": starts, "seed": a.seed,
           "code": a.code or None, "rigs": {k: {kk: vv for kk, vv in v.items()}
                                            for k, v in RIG.items()}, "cases": []}
    t0 = time.perf_counter()
    for rig, effect in cases:
        row = (run_real(effect, a.seed, starts, t1) if effect in real.REAL
               else run_case(rig, effect, a.seed, starts, t1, a.smoke))
        doc["cases"].append(row)
        print(f"{rig:>3} {effect:<15} converged={row['converged']!s:<5} "
              f"rms/ref={row['rms_ratio']:.4f} ref={row['rms_reference']:.4g} "
              f"it={row['iterations']:>4} {row['seconds']:6.1f} s ({row['strategy']})",
              flush=True)
        doc["wall_seconds"] = time.perf_counter() - t0
        with atomic_write(out) as f:  # rewritten after every case: a cut run keeps them
            json.dump(doc, f, indent=1)
            f.write("\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
