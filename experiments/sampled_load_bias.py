"""The bias a sampled load's interpolation puts into a model and into a fit.

Scenario A (DESIGN.md section 7, issue 8): the lab rig driven by a continuous 4-tone
multisine crank torque (1.3-6.8 Hz), released at 1.5 rad (large amplitude), recorded for
5 s at 250 Hz with 1 mrad of noise; the torque is logged at the same 250 Hz (a `tau`
column). Scenario B: the torque *is* a command held between the 250 Hz samples (a digital
controller's output), where the zero-order hold is exact.

For each interpolation of the logged torque (`cubic`, `linear`, `zoh`; plus diffrax's
backward Hermite spline and the cubic without steps ended at its knots, for comparison):

- the model error: rms of phi(t) driven by the interpolated torque minus phi(t) driven by
  the true torque, at the record's samples, rad; and the solver's steps;
- the fit bias: m_p, m_s, I_p, k, c, phi0, dphi0 fitted to the record with the sampled
  torque (`Data(torque=SampledLoad(...))`), as `(estimate - truth) / stderr`.

    python experiments/sampled_load_bias.py [--seeds 1] [--no-fits]

Writes experiments/results/sampled_load_bias.json.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.model import Nonsmooth  # noqa: E402
from crank_jax.runtime.io import atomic_write  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TONES = dict(amplitudes=[0.4, 0.3, 0.25, 0.2], freqs_hz=[1.3, 2.9, 4.7, 6.8],
             phases=[0.0, 1.0, 2.0, 3.0])
RATE, T1, NOISE = 250.0, 5.0, 1e-3
FREE = ("m_p", "m_s", "I_p", "k", "c", "phi0", "dphi0")
START = {"m_p": 0.6, "m_s": 0.35, "I_p": 2e-3, "k": 2.2, "c": 0.003}
REFERENCE = dict(solver="dopri8", rtol=1e-11, atol=1e-13)


class UnclippedCubic(cj.AbstractLoad):
    """The cubic spline without the solver's steps ended at its knots (to measure what
    clipping at the C2 knots gains)."""

    inner: cj.SampledLoad

    def __call__(self, t):
        return self.inner(t)

    def mean(self):
        return self.inner.mean()

    def nonsmooth(self):
        return Nonsmooth()


class BackwardHermite(cj.AbstractLoad):
    """diffrax's `backward_hermite_coefficients` + `CubicInterpolation` (C1, causal: the
    slope at a knot is the backward difference)."""

    ts: jax.Array
    coeffs: tuple

    def __init__(self, ts, values):
        self.ts = jnp.asarray(ts)
        self.coeffs = diffrax.backward_hermite_coefficients(self.ts, jnp.asarray(values))

    def __call__(self, t):
        spline = diffrax.CubicInterpolation(self.ts, self.coeffs)
        return jnp.vectorize(spline.evaluate)(jnp.clip(t, self.ts[0], self.ts[-1]))

    def mean(self):
        t = jnp.linspace(self.ts[0], self.ts[-1], 20001)
        return jnp.trapezoid(self(t), t) / (self.ts[-1] - self.ts[0])


def interpolations(ts, values) -> dict[str, cj.AbstractLoad]:
    out = {i: cj.SampledLoad(ts, values, i) for i in cj.model.INTERPOLATIONS}
    out["cubic-unclipped"] = UnclippedCubic(out["cubic"])
    out["backward-hermite"] = BackwardHermite(ts, values)
    return out


def model_errors(scene, true_torque, ts) -> dict[str, dict]:
    """rms model error and steps of each interpolation of the torque sampled at `ts`."""
    ref = cj.simulate(scene.mech, scene.phi0, scene.dphi0, ts, torque=true_torque,
                      **REFERENCE)
    out = {"true": {"rms_rad": 0.0, "steps": int(ref.num_steps)}}
    for name, ld in interpolations(ts, np.asarray(true_torque(ts))).items():
        t0 = time.perf_counter()
        tr = cj.simulate(scene.mech, scene.phi0, scene.dphi0, ts, torque=ld, **REFERENCE)
        out[name] = {"rms_rad": float(np.sqrt(np.mean(np.asarray(tr.phi - ref.phi) ** 2))),
                     "steps": int(tr.num_steps),
                     "seconds_incl_compile": time.perf_counter() - t0}
    return out


def clipping(mech, true_torque, ts) -> list[dict]:
    """Steps and error (vs a 1e-12 reference) of the cubic spline with and without steps
    ended at its knots, per solver and tolerance."""
    cub = cj.SampledLoad(ts, np.asarray(true_torque(ts)))
    ref = cj.simulate(mech, 1.5, 0.0, ts, torque=cub, solver="dopri8", rtol=1e-12,
                      atol=1e-14)
    rows = []
    for solver in ("tsit5", "dopri8"):
        for rtol in (1e-6, 1e-8, 1e-10):
            for name, ld in (("clipped", cub), ("unclipped", UnclippedCubic(cub))):
                tr = cj.simulate(mech, 1.5, 0.0, ts, torque=ld, solver=solver, rtol=rtol,
                                 atol=rtol * 1e-2)
                rows.append({"solver": solver, "rtol": rtol, "cubic": name,
                             "steps": int(tr.num_steps), "rms_error_rad": float(
                                 np.sqrt(np.mean(np.asarray(tr.phi - ref.phi) ** 2)))})
                print(json.dumps(rows[-1]), flush=True)
    return rows


def fit_bias(scene, true_torque, logged, seed: int) -> dict[str, dict]:
    """Fit the record with the torque `logged` at its samples, with each interpolation."""
    data = cj.synthesize(scene, t1=T1, rate=RATE, noise_std=NOISE, seed=seed)
    assert data.n == logged.shape[0]
    loads = {"true": true_torque}
    loads.update({i: cj.SampledLoad(data.ts, logged, i) for i in cj.model.INTERPOLATIONS})
    out = {}
    for name, ld in loads.items():
        rec = cj.Data(data.ts, data.phi, None, ld, source=f"synthetic, {name} torque")
        res = cj.fit(scene, rec, free=FREE, init=START, progress=False, warn=False)
        truth = {n: float(getattr(scene.mech, n)) for n in FREE if n in cj.model.FIELDS}
        z = {n: (res.values[n] - v) / res.stderr[n] if res.stderr[n] else None
             for n, v in truth.items()}
        out[name] = {"converged": res.converged, "identifiable": res.identifiable,
                     "seconds": res.seconds, "rms_residual_rad": res.rms_residual,
                     "bias_in_stderr": z,
                     "max_abs_bias_in_stderr": max((abs(v) for v in z.values()
                                                    if v is not None), default=None),
                     "relative_error": {n: res.values[n] / v - 1 for n, v in truth.items()},
                     "warnings": res.warnings}
        print(name, json.dumps(out[name]), flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--no-fits", action="store_true")
    args = ap.parse_args()
    mech = cj.load_scene("lab-rig").mech
    # The same sample times as `synthesize` (i / rate): a held command sampled a rounding
    # error before its own knots would read the previous value.
    ts = np.arange(round(T1 * RATE) + 1) / RATE
    multisine = cj.MultiSineLoad(**TONES)
    held = cj.SampledLoad(ts, np.asarray(multisine(ts)), "zoh")
    scenes = {"A: continuous multisine": cj.Scene(mech, torque=multisine, phi0=1.5),
              "B: held command (zoh)": cj.Scene(mech, torque=held, phi0=1.5)}
    doc = {"experiment": __doc__.split("\n\n")[1].replace("\n", " "),
           "rate_hz": RATE, "t1_s": T1, "noise_rad": NOISE, "free": FREE,
           "model_error": {}, "cubic_clipping": [], "fit": {}}
    for label, scene in scenes.items():
        doc["model_error"][label] = model_errors(scene, scene.torque, ts)
        print(label, json.dumps(doc["model_error"][label], indent=1), flush=True)
    doc["cubic_clipping"] = clipping(mech, multisine, ts)
    _write(doc)
    if not args.no_fits:
        for label, scene in scenes.items():
            logged = np.asarray(held.values) if scene.torque is held else \
                np.asarray(multisine(ts))
            doc["fit"][label] = [fit_bias(scene, scene.torque, logged, 100 + s)
                                 for s in range(args.seeds)]
            _write(doc)


def _write(doc) -> None:
    doc.update(date=time.strftime("%Y-%m-%d"),
               machine=f"{platform.machine()} {jax.devices()[0].device_kind}, shared 2-core "
                       "VM")
    out = ROOT / "experiments" / "results" / "sampled_load_bias.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(out) as f:
        json.dump(doc, f, indent=1)


if __name__ == "__main__":
    main()
