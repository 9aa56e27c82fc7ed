"""Synthetic records: simulate a scene and sample it like a data logger would.

**Noise model of [`synthesize`][]** (applied in this order to the exact solution):

1. *Sample-time jitter*: sample `i` is taken at `t_i + e_i`, `e_i ~ N(0, jitter_std^2)`
   (clipped to +-0.45 sample periods so the order never changes), but logged at the
   nominal time `t_i = t_start + i / rate`. The fit sees only `t_i`.
2. *Dropped samples*: each sample after the first is lost with probability `drop`.
3. *Encoder quantisation*: with `quantization = N` counts per revolution the angle is
   rounded to the nearest multiple of `2 pi / N`.
4. *Gaussian noise*: `N(0, noise_std^2)` is added, independently per sample.

Before these, an optional *start-up transient* (`transient`, rad) is added to the exact
angle: `transient * exp(-t / transient_time) * cos(2 pi transient_hz t)` with `t` the time
since the release (t = 0), by default a 15 Hz ringing that decays in 0.1 s. It stands for
what a hand release or a motor start puts into the first tenths of a second of a real
record (a wobble of the rig, a coupling, a slipping grip): nothing in the model explains
it, so a fit has to trim it (a window, [`Data.window`][]). Coulomb friction, the other
thing real records contain, comes through the scene.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..model.loads import InputLoad, NoLoad
from .checks import check_synth_options
from .data import MIN_SAMPLES, Data
from .sensors import Sensor

__all__ = ["synthesize"]


def synthesize(
    scene,
    *,
    t1: float | None = None,
    rate: float = 200.0,
    noise_std: float = 0.0,
    quantization: int | None = None,
    jitter_std: float = 0.0,
    drop: float = 0.0,
    t_start: float = 0.0,
    seed: int = 0,
    transient: float = 0.0,
    transient_time: float = 0.1,
    transient_hz: float = 15.0,
    sensors: Sequence[Sensor] | None = None,
    force=None,
    timestamps: str = "nominal",
) -> Data:
    """Simulate a scene and sample it like a data logger would (see the module's noise model).

    **Arguments:**

    - `scene`: a [`Scene`][]; its state `(phi0, dphi0)` is at t = 0.
    - `t1`: end of the record, s (default: the scene's `t1`).
    - `rate`: nominal sampling rate, Hz.
    - `noise_std`: standard deviation of the additive Gaussian angle noise, rad; or, with
      sensors, a dict channel -> standard deviation in the channel's SI unit.
    - `quantization`: encoder counts per revolution (`None`: no quantisation); with
      sensors, the `phi` channel's reading (SI) is rounded to steps of `2 pi / N`.
    - `jitter_std`: standard deviation of the sampling instants, s.
    - `drop`: probability that a sample (other than the first) is lost.
    - `t_start`: time of the first sample, s (`0 <= t_start < t1`): real records rarely
      start at the release.
    - `seed`: seed of the noise (numpy's `default_rng`).
    - `transient`: amplitude of the start-up transient, rad (0: none);
      `transient_time` (s, > 0) its decay time and `transient_hz` (Hz, >= 0) its
      frequency (see the module's noise model).
    - `sensors`: the channels to record ([`Sensor`][crank_jax.records.sensors.Sensor]s; default:
      the scene's `sensors`, and with none the angle alone). Each reads
      `scale * h + offset` of its model output `h` (the transient is added to the angle
      before it), then its noise.
    - `timestamps`: `"nominal"` (the logger writes `t_start + i / rate`, so jitter is an
      error the fit does not see) or `"actual"` (it writes the instant each sample was
      taken: irregular times, which a fit uses as recorded).
    - `force`: a user's force term `f(t, phi, dphi) -> N*m` in the motion (as
      `simulate` takes it).

    **Returns:** a [`Data`][] whose `load` and `torque` are the scene's (exact) loads, so
    a fit of in-memory synthetic data has no interpolation error; [`save_data`][] writes
    them as sampled `P`/`tau` columns.
    """
    t1 = float(scene.t1 if t1 is None else t1)
    sensors = tuple(getattr(scene, "sensors", ()) if sensors is None else sensors)
    noise = _channel_noise(noise_std, sensors)
    noise_std = max(noise.values(), default=0.0)
    check_synth_options(t1, rate, noise_std, jitter_std, drop, t_start, seed, transient,
                        transient_time, transient_hz, quantization)
    rng = np.random.default_rng(seed)
    n = int(math.floor((t1 - t_start) * rate + 1e-9)) + 1
    if n < MIN_SAMPLES:
        raise ValueError(f"synthesize: only {n} samples in [{t_start}, {t1}] s at {rate} Hz; "
                         f"need at least {MIN_SAMPLES}: raise `rate=` or `t1=`")
    nominal = t_start + np.arange(n) / rate
    jitter = np.clip(rng.normal(0.0, jitter_std, n), -0.45 / rate, 0.45 / rate)
    actual = np.maximum(nominal + jitter, 0.0)
    keep = np.ones(n, dtype=bool)
    keep[1:] = rng.random(n - 1) >= drop
    if int(keep.sum()) < MIN_SAMPLES:
        raise ValueError(f"synthesize: `drop=` {drop!r} left {int(keep.sum())} of the {n} "
                         f"samples, but a record needs at least {MIN_SAMPLES}: lower "
                         "`drop=` or sample more (`rate=`, `t1=`)")
    nominal, actual = nominal[keep], actual[keep]
    if timestamps not in ("nominal", "actual"):
        raise ValueError(f"synthesize: timestamps must be 'nominal' or 'actual', got "
                         f"{timestamps!r}")
    if timestamps == "actual":
        nominal = actual
    # The scene's state is at t = 0, so integrate from there when the record starts later.
    sim_ts = actual if actual[0] == 0.0 else np.concatenate([[0.0], actual])
    # simulate's default budget (200,000 steps) plus one per sample: a step may end at
    # each save time, so a dense record (10^6 samples in 1 ms) must not run out of steps.
    budget = dict(max_steps=200_000 + int(sim_ts.shape[0]))
    traj = scene.simulate(sim_ts, **budget) if force is None else scene.simulate(
        sim_ts, force=force, **budget)
    phi = np.asarray(traj.phi)[-actual.shape[0]:]
    if transient != 0.0:
        phi = phi + transient * np.exp(-actual / transient_time) * np.cos(
            2 * math.pi * transient_hz * actual)
    # An input-driven load is not data: the record carries its input's column instead.
    load, torque = (None if isinstance(x, (NoLoad, InputLoad)) else x
                    for x in (scene.load, scene.torque))
    inputs = {x.column: x.signal for x in (scene.load, scene.torque)
              if isinstance(x, InputLoad)}
    if sensors:
        dphi = np.asarray(traj.dphi)[-actual.shape[0]:]
        channels = _read_sensors(scene, sensors, actual, phi, dphi, quantization, noise, rng,
                                 force)
        return Data(nominal, None, load, torque, source="synthetic", channels=channels,
                    sensors=sensors, inputs=inputs)
    if quantization is not None:
        step = 2 * math.pi / int(quantization)
        phi = np.round(phi / step) * step
    phi = phi + rng.normal(0.0, noise_std, phi.shape) if noise_std > 0 else phi
    return Data(nominal, phi, load, torque, source="synthetic", inputs=inputs)


def _channel_noise(noise_std, sensors) -> dict[str, float]:
    """Noise standard deviation per channel, SI (a float is the angle's)."""
    if isinstance(noise_std, dict):
        names = {s.name for s in sensors} or {"phi"}
        bad = [k for k in noise_std if k not in names]
        if bad:
            raise ValueError(f"synthesize: noise_std names channel {bad[0]!r}, which is not "
                             f"recorded; the channels are {sorted(names)}")
        out = {k: float(v) for k, v in noise_std.items()}
    else:
        if sensors and noise_std and "phi" not in {s.name for s in sensors}:
            raise ValueError("synthesize: noise_std as a number is the angle's (rad); the "
                             "sensors record no angle: give noise_std={channel: std}")
        out = {"phi": float(noise_std)}
    for k, v in out.items():
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"synthesize: noise_std of {k} = {v!r} is out of range")
    return out


def _read_sensors(scene, sensors, ts, phi, dphi, quantization, noise, rng, force) -> dict:
    """Each sensor's reading at `ts` (SI) of the exact motion `phi`, `dphi` (n,)."""
    from ..model.outputs import output

    out = {}
    for s in sensors:
        h = output(s.name, scene.mech, ts, phi, dphi, scene.load, scene.torque, force=force)
        y = np.asarray(s.measure(np.asarray(h)), dtype=np.float64)
        if s.name == "phi" and quantization is not None:
            step = 2 * math.pi / int(quantization)
            y = np.round(y / step) * step
        sd = noise.get(s.name, 0.0)
        out[s.name] = y + rng.normal(0.0, sd, y.shape) if sd > 0 else y
    return out
