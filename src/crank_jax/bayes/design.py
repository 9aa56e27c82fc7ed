"""Optimal experiment design: a multisine crank torque chosen to make free parameters
identifiable from the crank angle.

The Fisher information of a record sampled at `rate` over `[0, t1]` with white angle noise
`sigma` is `F = J^T J / sigma^2`, with `J = d phi(t_i) / d z` the sensitivities in the
fit's coordinates (log-values for mechanism fields, so `F^-1` holds relative variances;
linear for `phi0`, `dphi0`). The excitation is

    tau(t) = A s(t) / max_grid |s|,   s(t) = sum_j a_j sin(2 pi f_j t + p_j),

so its peak on a fine grid is exactly the bound `A` whatever the design variables
(weights `a_j`, phases `p_j`, frequencies `f_j` kept in `[1/t1, f_max]` through a
sigmoid); after the optimisation the amplitudes are scaled down (by a fraction of a
percent) so that the bound holds between the points of a 10x finer grid too. The
criterion is D (`log det F`, maximised) or c (`-log (F^-1)_tt` for a
target parameter t, i.e. its variance minimised). The gradient is forward mode through
forward sensitivities (`jax.jacfwd` of `jax.jacfwd` through diffrax's `ForwardMode`:
3 x tones outer tangents of the p inner ones; a reverse pass cannot go through the
solver's unbounded while loop), and Adam (optax) takes the steps.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..model.dynamics import CrankField, Structure
from ..model.loads import MultiSineLoad, NoLoad
from ..model.params import FIELDS, SIGNED_FIELDS
from ..runtime.blas import one_blas_thread
from ..runtime.lazy import lazy_import
from ..runtime.progress import progress_bar
from ..scene import Scene
from ..simulation import linearize
from ..solve.adjoints import ForwardSensitivities
from ..solve.solvers import Diffrax, solve

diffrax = lazy_import("diffrax")
optax = lazy_import("optax")

__all__ = ["Design", "design", "max_tones", "CRITERIA"]

CRITERIA = ("D", "c")
# Samples of the excitation per period of its highest allowed frequency, for the peak.
_GRID_PER_PERIOD = 16


def max_tones(t1: float, rate: float) -> int:
    """Tones that fit: spaced at least `1/t1` apart, between `1/t1` and `rate/4` (four
    samples per period of the highest)."""
    return max(int(math.floor((rate / 4 - 1 / t1) * t1)) + 1, 0)


@dataclasses.dataclass
class Design:
    """An excitation and what it is predicted to give (see [`design`][]).

    **Fields:** `scene`: the input scene with the designed multisine as its `[torque]`
    (and `t1`, samples at `rate`); `torque`: that [`MultiSineLoad`][]; `names`;
    `log_det_fisher`, `baseline_log_det_fisher`: `log det F` of the designed and the
    baseline (the scene's own loads) experiments, in the coordinates `z`;
    `predicted_stderr`: name -> {"designed", "baseline"} in physical units (`inf` where
    `F` is singular); `criterion`, `target`; `history`: the objective per iteration;
    `peak`: the torque's largest magnitude on a fine grid, N*m; `force`: the designed
    slider force (a [`MultiSineLoad`][], N) or None; `release`: the designed
    `(phi0, dphi0)` (rad, rad/s) or None.
    """

    scene: Scene
    torque: MultiSineLoad
    names: tuple[str, ...]
    log_det_fisher: float
    baseline_log_det_fisher: float
    predicted_stderr: dict[str, dict[str, float]]
    criterion: str
    target: str | None
    history: list[float]
    peak: float
    force: MultiSineLoad | None = None
    release: tuple[float, float] | None = None

    def to_json(self) -> dict:
        def num(x):
            return float(x) if math.isfinite(x) else None

        return {"log_det_fisher": num(self.log_det_fisher),
                "baseline_log_det_fisher": num(self.baseline_log_det_fisher),
                "predicted_stderr": {n: {k: num(v) for k, v in d.items()}
                                     for n, d in self.predicted_stderr.items()},
                "criterion": self.criterion, "target": self.target,
                "torque": {"amplitudes": np.asarray(self.torque.amplitudes).tolist(),
                           "freqs_hz": np.asarray(self.torque.freqs_hz).tolist(),
                           "phases": np.asarray(self.torque.phases).tolist(),
                           "peak": self.peak},
                "force": None if self.force is None else {
                    "amplitudes": np.asarray(self.force.amplitudes).tolist(),
                    "freqs_hz": np.asarray(self.force.freqs_hz).tolist(),
                    "phases": np.asarray(self.force.phases).tolist()},
                "release": None if self.release is None else {
                    "phi0": self.release[0], "dphi0": self.release[1]},
                "history": [num(h) for h in self.history]}


def _check_extra(scene, force_amplitude, release_speed) -> None:
    """The optional design variables: a slider-force multisine's bound (N) and the release
    speed's bound (rad/s)."""
    if force_amplitude is not None:
        if not (math.isfinite(force_amplitude) and force_amplitude > 0):
            raise ValueError(f"`force_amplitude=` must be > 0 N, got {force_amplitude:g}")
        if not isinstance(scene.load, NoLoad):
            raise ValueError("`force_amplitude=`: the scene has its own slider load "
                             f"({type(scene.load).__name__}); remove its [load] to design "
                             "the slider force")
    if release_speed is not None and not (math.isfinite(release_speed) and release_speed > 0):
        raise ValueError(f"`release_speed=` must be > 0 rad/s, got {release_speed:g}")


def _check(scene, free, t1, rate, amplitude, tones, criterion, target, noise_std, iterations):
    if not (math.isfinite(t1) and t1 > 0):
        raise ValueError(f"`t1=` must be a duration > 0 s, got {t1}")
    if not (math.isfinite(rate) and rate > 0):
        raise ValueError(f"`rate=` must be a sample rate > 0 Hz, got {rate}")
    if not (math.isfinite(amplitude) and amplitude > 0):
        raise ValueError(f"`amplitude=` (the torque amplitude) must be > 0 N*m, got {amplitude}")
    if not (math.isfinite(noise_std) and noise_std > 0):
        raise ValueError(f"`noise_std=` must be > 0 rad, got {noise_std}")
    if not isinstance(tones, int) or tones < 1:
        raise ValueError(f"`tones=` must be an integer >= 1, got {tones!r}")
    if tones > max_tones(t1, rate):
        raise ValueError(f"`tones=`: {tones} tones do not fit at rate {rate:g} Hz over t1 {t1:g} "
                         f"s (at most {max_tones(t1, rate)}, spaced 1/t1 apart below rate/4)")
    if not isinstance(iterations, int) or iterations < 0:
        raise ValueError(f"`iterations=` must be an integer >= 0, got {iterations!r}")
    free = tuple(dict.fromkeys(free))
    ok = tuple(FIELDS) + ("phi0", "dphi0")
    bad = [n for n in free if n not in ok]
    if bad or not free:
        raise ValueError(f"`free=`: {bad or 'nothing'} cannot be designed for; choose from {ok}")
    mech = scene.mech.as_dict()
    zero = [n for n in free if n in FIELDS and (mech[n] <= 0 or n in SIGNED_FIELDS)]
    if zero:
        raise ValueError(f"`free=`: {zero} must be positive mechanism fields (the design is in "
                         "relative terms)")
    if criterion not in CRITERIA:
        raise ValueError(f"`criterion=` must be one of {CRITERIA}, got {criterion!r}")
    if criterion == "c" and target not in free:
        raise ValueError(f"`target=` {target!r} is not free; the c criterion needs one of "
                         f"{list(free)}")
    return free


def _sensitivities(scene: Scene, free, ts, torque, load, y0, z):
    """phi(ts) as a function of the coordinates z (p,), through [`solve`][] with
    diffrax's Dopri5 in forward mode ([`ForwardSensitivities`][]: diffrax's `ForwardMode`).
    `y0` (2,): the release angle and speed; a free `phi0`/`dphi0` is `y0` plus its
    coordinate (0 at the design point), so the release may itself be designed."""
    vals = {n: (jnp.exp(z[i]) if n in FIELDS else z[i]) for i, n in enumerate(free)}
    mech = scene.mech.replace(**{n: v for n, v in vals.items() if n in FIELDS})
    y0 = jnp.stack([jnp.asarray(y0[0] + vals.get("phi0", 0.0), float),
                    jnp.asarray(y0[1] + vals.get("dphi0", 0.0), float)])
    field = CrankField(mech, load, torque, Structure.of(scene.mech))
    # No kinks clipped (`step_ts`): a multisine torque is smooth.
    (phi, _), result, _ = solve(field, Diffrax(diffrax.Dopri5()), ts, (y0[0], y0[1]),
                                rtol=1e-7, atol=1e-9, max_steps=100_000,
                                adjoint=ForwardSensitivities(), throw=False,
                                prepare=CrankField.packed)
    ok = result == diffrax.RESULTS.successful
    return jnp.where(ok, phi, jnp.nan)


def _objective(scene, free, ts, z, sigma, criterion, j):
    def fisher(torque, load, y0):
        J = jax.jacfwd(lambda x: _sensitivities(scene, free, ts, torque, load, y0, x))(z)
        return J.T @ J / sigma**2

    def crit(F):
        if criterion == "D":
            return jnp.linalg.slogdet(F)[1]
        return -jnp.log(jnp.linalg.inv(F)[j, j])

    return fisher, crit


def _torque(w, amplitude, f_lo, f_hi, grid, tones):
    a, p, v = w[:tones], w[tones:2 * tones], w[2 * tones:]
    f = f_lo + (f_hi - f_lo) * jax.nn.sigmoid(v)
    s = jnp.sum(a * jnp.sin(2 * jnp.pi * f * grid[:, None] + p), axis=1)
    peak = jnp.max(jnp.abs(s))
    return MultiSineLoad(amplitude * a / peak, f, p)


def _stderr(F: np.ndarray, free, values) -> dict[str, float]:
    try:
        cov = np.linalg.inv(F)
    except np.linalg.LinAlgError:
        return {n: math.inf for n in free}
    d = np.diag(cov)
    return {n: (float(values[i] * math.sqrt(d[i])) if n in FIELDS else float(math.sqrt(d[i])))
            if d[i] > 0 and np.isfinite(d[i]) else math.inf for i, n in enumerate(free)}


def _log_det(F: np.ndarray) -> float:
    sign, ld = np.linalg.slogdet(F)
    return float(ld) if sign > 0 else -math.inf


@one_blas_thread
def design(
    scene: Scene,
    free: Sequence[str],
    t1: float,
    rate: float,
    *,
    amplitude: float = 0.2,
    tones: int = 6,
    criterion: str = "D",
    target: str | None = None,
    noise_std: float = 1e-3,
    iterations: int = 60,
    learning_rate: float = 0.1,
    seed: int = 0,
    progress: bool = True,
    force_amplitude: float | None = None,
    release: bool = False,
    release_speed: float | None = None,
) -> Design:
    """Design a multisine crank torque of peak `amplitude` (N*m) for identifying `free`.

    **Arguments:**

    - `scene`: the mechanism (its values are the design point), initial state and loads;
      its own torque is replaced by the design, and kept for the baseline.
    - `free`: positive mechanism fields and/or `phi0`, `dphi0`.
    - `t1` (s), `rate` (Hz): the record's duration and sample rate.
    - `amplitude`: the torque's bound, N*m (> 0). `tones`: sines in the multisine (see
      [`max_tones`][]).
    - `criterion`: `"D"` (max `log det F`) or `"c"` (min the variance of `target`).
    - `noise_std`: the angle noise, rad (scales F; the design itself does not depend on
      it). `iterations`, `learning_rate`: Adam's. `seed`: the start phases.
    - `force_amplitude`: also design a multisine slider force of this peak, N (`tones`
      sines; the scene must have no slider load of its own). Default: no force.
    - `release`: also design the release angle `phi0` (rad). `release_speed`: also design
      the release speed `dphi0`, within `[-release_speed, release_speed]` rad/s.

    **Returns:** a [`Design`][]. **Raises:** `ValueError` for a bad request, before any
    solve.
    """
    free = _check(scene, free, t1, rate, amplitude, tones, criterion, target, noise_std,
                  iterations)
    _check_extra(scene, force_amplitude, release_speed)
    n = int(round(t1 * rate)) + 1
    ts = jnp.linspace(0.0, t1, n)
    mech = scene.mech.as_dict()
    values = np.array([mech[k] if k in FIELDS else float(getattr(scene, k)) for k in free])
    # A free state's coordinate is its offset from the (possibly designed) release.
    z = jnp.asarray([math.log(v) if k in FIELDS else 0.0 for k, v in zip(free, values)])
    j = free.index(target) if criterion == "c" else 0
    fisher, crit = _objective(scene, free, ts, z, noise_std, criterion, j)
    f_lo, f_hi = 1.0 / t1, rate / 4
    lin = linearize(scene.mech, scene.load)
    fn = float(np.asarray(lin.omega_n)) / (2 * math.pi)
    fn = fn if math.isfinite(fn) and fn > 0 else math.sqrt(f_lo * f_hi)
    grid = jnp.linspace(0.0, t1, int(t1 * f_hi * _GRID_PER_PERIOD) + 1)
    w = _start(scene, tones, seed, fn, f_lo, f_hi, force_amplitude is not None, release,
               release_speed)

    def unpack(w):
        """(torque, slider load, (phi0, dphi0)) of the design variables `w`."""
        T = 3 * tones
        torque, k, load = _torque(w[:T], amplitude, f_lo, f_hi, grid, tones), T, scene.load
        if force_amplitude is not None:
            load, k = _torque(w[k:k + T], force_amplitude, f_lo, f_hi, grid, tones), k + T
        phi0 = w[k] if release else jnp.asarray(scene.phi0, float)
        k += int(release)
        dphi0 = (release_speed * jnp.tanh(w[k]) if release_speed is not None
                 else jnp.asarray(scene.dphi0, float))
        return torque, load, jnp.stack([phi0, dphi0])

    def loss(w):
        return -crit(fisher(*unpack(w)))

    w, history = _adam(loss, w, iterations, learning_rate, progress)
    torque, load, y0 = unpack(w)
    torque, peak = _within_bound(torque, amplitude, t1, 10 * grid.shape[0])
    force = None
    if force_amplitude is not None:
        load, _ = _within_bound(load, force_amplitude, t1, 10 * grid.shape[0])
        force = load
    y0 = (float(y0[0]), float(y0[1]))
    F_des = np.asarray(jax.jit(fisher)(torque, load, jnp.asarray(y0)))
    F_base = np.asarray(jax.jit(fisher)(scene.torque, scene.load,
                                        jnp.asarray([scene.phi0, scene.dphi0], float)))
    designed = _with_torque(scene, torque, t1, n, load, y0)
    se_d, se_b = _stderr(F_des, free, values), _stderr(F_base, free, values)
    return Design(designed, torque, free, _log_det(F_des), _log_det(F_base),
                  {k: {"designed": se_d[k], "baseline": se_b[k]} for k in free},
                  criterion, target if criterion == "c" else None, history, peak, force,
                  y0 if release or release_speed is not None else None)


def _adam(loss, w, iterations: int, learning_rate: float, progress: bool):
    """Adam on `loss` from `w` for `iterations` steps (stopping at a non-finite gradient).
    **Returns:** the best point seen and the criterion's history (`-loss` per step)."""
    step = jax.jit(lambda w: (loss(w), jax.jacfwd(loss)(w)))
    opt = optax.adam(learning_rate)
    state = opt.init(w)
    history = []
    best = (math.inf, w)
    bar = progress_bar(iterations, "design", progress)
    for _ in range(iterations):
        bar.update()
        value, g = step(w)
        value = float(value)
        history.append(-value)
        if math.isfinite(value) and value < best[0]:
            best = (value, w)
        if not np.all(np.isfinite(np.asarray(g))):
            break
        updates, state = opt.update(g, state)
        w = optax.apply_updates(w, updates)
    bar.close()
    final = float(jax.jit(loss)(w)) if iterations else math.inf
    if math.isfinite(final) and final < best[0]:
        best = (final, w)
    return best[1], history


def _start(scene, tones, seed, fn, f_lo, f_hi, force, release, release_speed):
    """The design variables' start: each multisine with equal weights, random phases and
    frequencies log-spaced around the natural frequency `fn`; the scene's release."""
    f0 = np.clip(fn * np.geomspace(0.5, 2.0, tones), f_lo * 1.01, f_hi * 0.99)
    v0 = np.log((f0 - f_lo) / (f_hi - f0))
    p0 = np.random.default_rng(seed).uniform(0, 2 * np.pi, tones)
    parts = [np.ones(tones), p0, v0]
    if force:
        parts += [np.ones(tones), np.random.default_rng(seed + 1).uniform(0, 2 * np.pi, tones),
                  v0]
    if release:
        parts.append([scene.phi0])
    if release_speed is not None:
        parts.append([math.atanh(float(np.clip(scene.dphi0 / release_speed, -0.9, 0.9)))])
    return jnp.asarray(np.concatenate(parts))


def _within_bound(torque: MultiSineLoad, amplitude: float, t1: float, n: int):
    """The torque scaled so that its true peak is at most `amplitude`, and its peak on an
    n-point grid. Between grid points `h` apart, a function exceeds its grid maximum by
    at most `h^2 / 8 max|s''|`, and `max|s''| <= sum_j |a_j| (2 pi f_j)^2`: scaling by that
    bound makes the bound hold everywhere, not only on the grid."""
    fine = np.linspace(0.0, t1, n)
    grid_peak = float(np.max(np.abs(np.asarray(torque(jnp.asarray(fine))))))
    a, f = np.asarray(torque.amplitudes), np.asarray(torque.freqs_hz)
    curvature = float(np.sum(np.abs(a) * (2 * np.pi * f) ** 2))
    bound = grid_peak + (t1 / (n - 1)) ** 2 / 8 * curvature
    if bound > amplitude:
        scale = amplitude / bound
        torque = MultiSineLoad(torque.amplitudes * scale, torque.freqs_hz, torque.phases)
        grid_peak *= scale
    return torque, grid_peak


def _with_torque(scene: Scene, torque, t1: float, n: int, load, y0) -> Scene:
    """`scene` with `torque`, slider `load` and release `y0`, recorded over `t1` s in `n`
    samples."""
    return Scene(scene.mech, load, torque, y0[0], y0[1], scene.rtol,
                 scene.atol, t1=float(t1), samples=n, solver=scene.solver,
                 outputs=scene.outputs, name=scene.name,
                 description=(scene.description + " (designed multisine torque)").strip(),
                 sensors=scene.sensors)  # the rig's sensors: records of the design use them
