"""The misfit bench's records like the real ones (`misfit_bench.py --real`): a rotating rig
seen only by its slide, and a fast coast-down seen by a toothed wheel.

- `slide_only` (the `rot` rig of the bench): a motor whose torque falls with speed plus a
  supply ripple (`MotorDroop`) spins it up from 5 rad/s through a start-up transient to
  about 16 rad/s, about 10 turns in 4 s; the record has ONE channel, the slide position
  `x_s` (m) at 50 Hz with 0.2 mm of noise, no angle. Fitted with the plain model (a
  constant drive `tau0`, viscous `c`, a constant slider force `P0`): free `I_c`, `tau0`,
  `c`, `P0`, `phi0`, `dphi0`, from `I_c` 1.5x, `tau0` half and `c` twice the truth's and
  `P0` at exactly 0 (the truth has none: the start a user writes for an unknown load).
- `coast_down` (an engine-like slider-crank, `force_by_angle.py`'s): coasting from 1,300
  rpm (136 rad/s) to about 950 rpm (99 rad/s) in 0.8 s, 16 turns, under a gas force that
  follows the crank (the record's force column, 1% noise) with crank-bearing Coulomb
  friction and a windage drag growing with the square of the speed; the angle at the edges
  of a 36-1 toothed wheel (irregular times with 20 us of jitter, a gap each turn). Fitted
  with the force by angle (`load_by="angle"` where the code has it) and the plain model:
  free `I_c`, `c`, `tau0` (a constant drag), `phi0`, `dphi0`, from `I_c` 20% high, `c`
  twice the truth's and `tau0` at exactly 0, the start a user writes for an unknown drag.

Each case's reference is scipy's TRF on the same residuals (the slide in m; the angle in
rad at the tooth times), with the positive parameters in logs and `tau0` linear.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _bench import tooth_edges

import crank_jax as cj

try:
    from crank_jax.model import AngleLoad
except ImportError:  # the code before `load_by="angle"`: records from RECORDS, time tables
    AngleLoad = None

#: The coast-down records as this code makes them, for a run of older code to read.
RECORDS = Path(__file__).resolve().parent / "results" / "misfit_bench.real.records.npz"

REAL = ("slide_only", "coast_down")
RIG_OF = {"slide_only": "rot", "coast_down": "tooth"}

# ------------------------------------------------------------------ slide only ---
SLIDE = dict(free=("I_c", "tau0", "c", "P0", "phi0", "dphi0"),
             truth=dict(I_c=2e-3, tau0=0.2, c=0.01, P0=0.0, phi0=0.0, dphi0=5.0),
             start=dict(I_c=3e-3, tau0=0.1, c=0.02, P0=0.0), t1=4.0, rate=50.0, noise=2e-4)


def slide_mech(I_c, c):
    m = dict(r=0.05, L=0.2, b=0.1, s=0.01, m_c=0.1, m_p=0.05, m_s=0.1, I_c=I_c, I_p=2e-4,
             k=0.0, c=c, g=9.81, e=0.008, gravity_angle=0.35)
    return cj.SliderCrank(**m)


class Droop(eqx.Module):
    """The drive torque less `drop (dphi / w)^2` of itself, plus a 7 Hz supply ripple."""

    drive: float = 0.2
    omega: float = 20.0
    drop: float = 0.3
    ripple: float = 0.05

    def __call__(self, t, phi, dphi):
        return (-self.drive * self.drop * (dphi / self.omega) ** 2
                + self.ripple * self.drive * jnp.sin(2 * jnp.pi * 7.0 * t))


def slide_record(seed: int, t1: float) -> cj.Data:
    p = SLIDE["truth"]
    sc = cj.Scene(slide_mech(p["I_c"], p["c"]), torque=cj.ConstantLoad(p["tau0"]),
                  phi0=p["phi0"], dphi0=p["dphi0"], t1=t1, rtol=1e-10, atol=1e-12)
    d = cj.synthesize(sc, rate=SLIDE["rate"], noise_std={"x_s": SLIDE["noise"]}, seed=seed,
                      force=Droop(), transient=0.1, transient_time=0.3, transient_hz=8.0,
                      sensors=(cj.Sensor("x_s"),))
    return cj.Data(np.asarray(d.ts), None, channels={"x_s": np.asarray(d.channels["x_s"])},
                   source=f"rot:slide_only seed {seed}")


# ------------------------------------------------------------------ coast down ---
TEETH = 36
AREA = np.pi * 0.05**2 / 4
# The truth's `tau0`: its Coulomb friction as the constant drag it is while turning forward.
COAST = dict(free=("I_c", "c", "tau0", "phi0", "dphi0"),
             truth=dict(I_c=0.01, c=5e-4, tau0=-0.05, phi0=0.3, dphi0=1300 * np.pi / 30),
             start=dict(I_c=0.012, c=1e-3, tau0=0.0), t1=0.8)
GEOM = dict(r=0.025, L=0.09, b=0.03, s=0.0, m_c=0.3, m_p=0.15, m_s=0.12, I_p=1e-4, k=0.0)


def gas_force(phi) -> np.ndarray:
    """A motored cylinder's slider force by crank angle, N (polytropic, ratio 8, the
    expansion 10% below the compression)."""
    w = (np.asarray(phi, dtype=float) + np.pi) % (2 * np.pi) - np.pi
    r, L = GEOM["r"], GEOM["L"]
    x = r * np.cos(w) + np.sqrt(L**2 - (r * np.sin(w)) ** 2)
    v_c = 2 * r / 7.0
    p = 1e5 * ((2 * r + v_c) / (r + L - x + v_c)) ** 1.3
    return (p * (1.0 - 0.1 / (1.0 + np.exp(-w / 0.15))) - 1e5) * AREA


class Windage(eqx.Module):
    """A drag torque `-k dphi |dphi|`, N*m (k in N*m*s^2)."""

    k: float = 2e-6

    def __call__(self, t, phi, dphi):
        return -self.k * dphi * jnp.abs(dphi)


def coast_record(seed: int, t1: float, keep: bool = False) -> cj.Data:
    """The record of `seed` (t1 s): made here (and with `keep` added to RECORDS), or read
    from RECORDS by older code."""
    key = f"s{seed}_t{t1:g}"
    if AngleLoad is None:
        with np.load(RECORDS) as f:
            ts, angle, force = (f[f"{key}_{c}"] for c in ("ts", "phi", "P"))
    else:
        ts, angle, force = _coast_samples(seed, t1)
    if AngleLoad is not None and keep:
        old = dict(np.load(RECORDS)) if RECORDS.exists() else {}
        old.update({f"{key}_ts": ts, f"{key}_phi": angle, f"{key}_P": force})
        tmp = RECORDS.with_suffix(".tmp")
        with open(tmp, "wb") as f:  # whole or not at all
            np.savez(f, **old)
        os.replace(tmp, RECORDS)
    return cj.Data(ts, angle, load=cj.SampledLoad(ts, force),
                   source=f"tooth:coast_down seed {seed}")


def _coast_samples(seed: int, t1: float):
    p = COAST["truth"]
    grid = np.linspace(-np.pi, np.pi, 1441)
    load = AngleLoad.from_samples(grid, gas_force(grid), period=2 * np.pi)
    mech = cj.SliderCrank(**GEOM, I_c=p["I_c"], c=p["c"], T_c=0.05, w_c=0.5)
    tf = np.linspace(0.0, t1, int(t1 * 4000) + 1)
    tr = cj.simulate(mech, p["phi0"], p["dphi0"], jnp.asarray(tf), load=load, force=Windage(),
                     rtol=1e-10, atol=1e-10)
    phi, dphi = np.asarray(tr.phi), np.asarray(tr.dphi)
    rng = np.random.default_rng(seed)
    ts, angle = tooth_edges(tf, phi, dphi, TEETH, rng)
    force = gas_force(angle) + rng.normal(0.0, 0.01 * gas_force(0.0), angle.shape)
    return ts, angle, force


def coast_load(data: cj.Data):
    """The record's force column tabled by its own angle (what `load_by="angle"` does);
    interpolated in time by code without it."""
    if AngleLoad is None:
        return data.load
    return AngleLoad.from_samples(np.asarray(data.phi), np.asarray(data.load(data.ts)),
                                  ts=np.asarray(data.ts))


# ------------------------------------------------------------------------ cases ---

def case(effect: str, seed: int, t1: float | None = None, keep: bool = False):
    """(record, start scene, free names, fit keywords) of `effect` (`keep`: add a
    coast-down record to RECORDS for older code to read)."""
    if effect == "slide_only":
        cfg = SLIDE
        data = slide_record(seed, cfg["t1"] if t1 is None else t1)
        s = dict(cfg["truth"], **cfg["start"])
        scene = cj.Scene(slide_mech(s["I_c"], s["c"]), torque=cj.ConstantLoad(s["tau0"]),
                         load=cj.ConstantLoad(s["P0"]), phi0=s["phi0"], dphi0=s["dphi0"],
                         t1=float(data.ts[-1]),
                         sensors=(cj.Sensor("x_s"),))
        return data, scene, cfg["free"], {}
    cfg = COAST
    data = coast_record(seed, cfg["t1"] if t1 is None else t1, keep)
    s = dict(cfg["truth"], **cfg["start"])
    scene = cj.Scene(cj.SliderCrank(**GEOM, I_c=s["I_c"], c=s["c"]),
                     torque=cj.ConstantLoad(s["tau0"]), phi0=s["phi0"], dphi0=s["dphi0"],
                     t1=float(data.ts[-1]))
    import inspect
    kw = {"load_by": "angle"} if "load_by" in inspect.signature(cj.fit).parameters else {}
    return data, scene, cfg["free"], kw


def theta_of(effect: str, v: dict) -> np.ndarray:
    """The reference's coordinates: `(ln I_c, ln tau0, ln c, phi0, dphi0, P0)` (slide) or
    `(ln I_c, ln c, tau0, phi0, dphi0)` (coast)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        if effect == "slide_only":
            return np.array([np.log(v["I_c"]), np.log(v["tau0"]), np.log(v["c"]), v["phi0"],
                             v["dphi0"], v["P0"]], dtype=float)
        return np.array([np.log(v["I_c"]), np.log(v["c"]), v["tau0"], v["phi0"], v["dphi0"]],
                        dtype=float)


@functools.cache
def program(effect: str):
    """`(residuals, jacobian)` of `(theta, ts, y, load)` on the host."""

    def model(theta, ts, y, load):
        # A trial step far out (ln c of 10^3) is a failed solve, not an overflow to inf.
        theta = jnp.clip(theta, -40.0, 40.0).at[4].set(theta[4])
        if effect == "slide_only":
            m = slide_mech(jnp.exp(theta[0]), jnp.exp(theta[2]))
            tr = cj.simulate(m, theta[3], theta[4], ts, torque=cj.ConstantLoad(
                jnp.exp(theta[1])), load=cj.ConstantLoad(theta[5]), adjoint="forward",
                rtol=1e-10, atol=1e-12, throw=False, checks=False)
            out = cj.model.kinematics(m, tr.phi, 0.0, 0.0).x_s
        else:
            m = cj.SliderCrank(**GEOM, I_c=jnp.exp(theta[0]), c=jnp.exp(theta[1]))
            tr = cj.simulate(m, theta[3], theta[4], ts, load=load,
                             torque=cj.ConstantLoad(theta[2]), adjoint="forward",
                             rtol=1e-10, atol=1e-12, throw=False, checks=False)
            out = tr.phi
        return jnp.where(tr.ok, out - y, 10.0)

    res, jac = jax.jit(model), jax.jit(jax.jacfwd(model))
    return (lambda th, ts, y, ld: np.asarray(res(jnp.asarray(th), ts, y, ld)),
            lambda th, ts, y, ld: np.asarray(jac(jnp.asarray(th), ts, y, ld)))


def observed(effect: str, data: cj.Data):
    """(ts, y, load) the reference fits."""
    if effect == "slide_only":
        return jnp.asarray(data.ts), jnp.asarray(data.channels["x_s"]), None
    return jnp.asarray(data.ts), jnp.asarray(data.phi), coast_load(data)


def truth_theta(effect: str) -> np.ndarray:
    """The truth's values in the reference's coordinates (a start, not the optimum: the
    truth has what the model lacks)."""
    return theta_of(effect, (SLIDE if effect == "slide_only" else COAST)["truth"])


def random_starts(effect: str, k: int, rng) -> list[np.ndarray]:
    cfg = SLIDE if effect == "slide_only" else COAST
    truth = theta_of(effect, cfg["truth"])
    out = []
    for _ in range(k):
        th = truth.copy()
        if effect == "slide_only":
            th[:3] += rng.uniform(-1.0, 1.0, 3)
            th[3] += rng.uniform(-0.5, 0.5)
            th[4] *= rng.uniform(0.6, 1.4)
            th[5] = rng.uniform(-0.3, 0.3)
        else:
            th[:2] += rng.uniform(-0.7, 0.7, 2)
            th[2] = rng.uniform(-0.1, 0.05)
            th[3] += rng.uniform(-0.05, 0.05)
            th[4] *= rng.uniform(0.97, 1.03)
        out.append(th)
    return out
