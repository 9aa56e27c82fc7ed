"""Parameter identification: fit a scene's parameters to one or more crank-angle records.

Which solver to use:

- `method="lm"` (default): Levenberg-Marquardt from optimistix, with the Jacobian by
  forward-mode sensitivities through the ODE solve (`diffrax.ForwardMode`). Best for the
  usual problem: one or a few records, up to a dozen or two parameters. It converges in a
  handful of iterations and its Jacobian is needed for the uncertainty anyway.
- `method="optax"`: Adam, then L-BFGS, on the sum of squares with reverse-mode gradients
  (one backward solve, whatever the number of parameters). Use it for large problems (many
  records or many multiple-shooting segments, so many coordinates), or when you want to
  drive the fit yourself with mini-batches. It needs more iterations than LM.

Multiple shooting: each segment starts from its own state, and continuity at the shared
samples is a weighted residual; the result is then polished by single shooting (so the
estimate and its uncertainty are those of the ordinary least-squares problem).
`shooting="auto"` uses it when a record spans more than [`AUTO_PERIODS`][] linearised
periods of the start scene, with one segment per [`SEGMENT_PERIODS`][] periods: a start
whose frequency is off by a fraction `e` drifts `2 pi e N` rad in phase over `N` periods,
and single shooting loses the basin of attraction once that nears `pi/2`.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
import warnings
from collections.abc import Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
from tqdm.auto import tqdm

from ..data import Data
from ..model.dynamics import coriolis, generalized_force, mass
from ..model.loads import AbstractLoad
from ..model.params import FIELDS, SliderCrank
from ..scene import Scene
from .problem import (
    LOAD_NAMES,
    SCALE_GROUP,
    STATE_NAMES,
    Problem,
    build_problem,
    load_param,
    natural_period,
    pick_solver,
    smooth_derivatives,
)
from .uncertainty import RANK_TOL, Uncertainty, analyse

__all__ = ["fit", "FitResult", "Profile", "IdentifiabilityWarning", "ConvergenceWarning",
           "FREE_NAMES", "AUTO_PERIODS", "SEGMENT_PERIODS", "regressor_start"]

#: Names that can be free besides the twelve mechanism fields.
FREE_NAMES: tuple[str, ...] = FIELDS + tuple(LOAD_NAMES) + STATE_NAMES
#: `shooting="auto"` switches to multiple shooting above this many linearised periods.
AUTO_PERIODS = 25.0
#: Target length of a multiple-shooting segment, in linearised periods.
SEGMENT_PERIODS = 8.0
_MAX_ODE_STEPS = 200_000
_SMALL_ODE_BUDGET = 32_768
_STALL = 8
_CHI2_95 = 3.841458820694124  # 95% quantile of chi-squared with 1 degree of freedom


class IdentifiabilityWarning(UserWarning):
    """The data cannot determine some free parameters (see `FitResult.warnings`)."""


class ConvergenceWarning(UserWarning):
    """A fit stopped without converging (see `FitResult.warnings`)."""


class Profile(NamedTuple):
    """Profile likelihood of one parameter: every other free parameter re-fitted.

    `values` (k,): the pinned values; `deviance` (k,): `n ln(RSS / RSS_min)`, which is
    asymptotically chi-squared with one degree of freedom; `ci95`: the interval where the
    deviance stays below 3.84 (an end is `None` when the grid does not reach the crossing).
    """

    name: str
    values: np.ndarray
    deviance: np.ndarray
    ci95: tuple[float | None, float | None]


class FitResult(NamedTuple):
    """The outcome of [`fit`][]. Every dict is keyed by the reported parameter names
    (`names`: the free names, with `phi0[i]`, `dphi0[i]` per record when there are several).

    `stderr`/`ci95` are `None` where they are undefined: for parameters in an
    unidentifiable direction, and for every parameter when the fit did not converge.
    """

    names: tuple[str, ...]
    values: dict[str, float]
    start: dict[str, float]
    stderr: dict[str, float | None]
    ci95: dict[str, tuple[float, float] | None]
    correlation: np.ndarray
    """(p, p), NaN where undefined."""
    condition_number: float
    """Of the sensitivity matrix with columns scaled by the parameter values."""
    singular_values: np.ndarray
    identifiable: bool
    unidentifiable_directions: list[str]
    rms_residual: float
    """Root-mean-square residual, rad (the estimate of the noise level)."""
    n_samples: int
    converged: bool
    iterations: int
    seconds: float
    warnings: list[str]
    message: str
    method: str
    shooting: str
    mech: SliderCrank
    """The mechanism with the fitted values."""
    data: list[Data]
    fitted: list[np.ndarray]
    """Model angle at each record's sample times, rad."""
    profile: Profile | None

    def to_json(self) -> dict:
        """The `fit.json` document (exactly the documented top-level keys)."""
        def num(x):
            return float(x) if x is not None and math.isfinite(x) else None

        est = {}
        for i, n in enumerate(self.names):
            ci = self.ci95[n]
            est[n] = {
                "value": num(self.values[n]),
                "stderr": num(self.stderr[n]) if self.stderr[n] is not None else None,
                "ci95": [num(ci[0]), num(ci[1])] if ci is not None else None,
                "start": num(self.start[n]),
                "correlation": {m: num(float(self.correlation[i, j]))
                                for j, m in enumerate(self.names)},
            }
            if self.profile is not None and self.profile.name == n:
                est[n]["profile"] = {
                    "values": [float(v) for v in self.profile.values],
                    "deviance": [num(float(d)) for d in self.profile.deviance],
                    "ci95": [num(c) if c is not None else None for c in self.profile.ci95],
                }
        return {
            "estimates": est,
            "identifiable": bool(self.identifiable),
            "unidentifiable_directions": list(self.unidentifiable_directions),
            "rms_residual": num(self.rms_residual),
            "n_samples": int(self.n_samples),
            "converged": bool(self.converged),
            "iterations": int(self.iterations),
            "seconds": float(self.seconds),
            "warnings": list(self.warnings),
        }

    def summary(self) -> str:
        """A human-readable table of the estimates with their 95% intervals."""
        lines = [f"{'parameter':<10} {'start':>12} {'estimate':>12} {'stderr':>11} "
                 f"{'95% CI':>27}"]
        for n in self.names:
            se, ci = self.stderr[n], self.ci95[n]
            se_s = f"{se:11.4g}" if se is not None else f"{'-':>11}"
            ci_s = (f"[{ci[0]:.6g}, {ci[1]:.6g}]" if ci is not None else "not determined")
            lines.append(f"{n:<10} {self.start[n]:12.6g} {self.values[n]:12.6g} {se_s} "
                         f"{ci_s:>27}")
        state = "converged" if self.converged else f"NOT converged ({self.message})"
        lines.append(f"{state} after {self.iterations} iterations in {self.seconds:.1f} s "
                     f"({self.method}, {self.shooting} shooting); rms residual "
                     f"{self.rms_residual:.3g} rad over {self.n_samples} samples; condition "
                     f"number {self.condition_number:.3g}")
        lines.append("identifiable: " + ("yes" if self.identifiable else "NO"))
        return "\n".join(lines)


class _Run(NamedTuple):
    z: np.ndarray
    cost: float
    iterations: int
    converged: bool
    message: str


# ---------------------------------------------------------------------------------------
# Optimisers


def _bar(total: int, desc: str, progress: bool):
    return tqdm(total=total, desc=desc, file=sys.stderr, disable=not progress, leave=False,
                dynamic_ncols=True)


def _evaluate(problem: Problem, z) -> tuple[float, int]:
    """(0.5 |r|^2, number of failed samples) at `z`."""
    r, failed, _ = _residuals_jit(problem, jnp.asarray(z))
    r = np.asarray(r)
    return 0.5 * float(r @ r), int(failed)


# The bar that the jitted loops report to (one fit runs at a time in a process).
_BAR: list = [None]


def _tick(it, cost, n) -> None:
    bar = _BAR[0]
    if bar is not None:
        bar.n = int(it)
        bar.set_postfix(rms=f"{math.sqrt(2 * float(cost) / max(int(n), 1)):.3g}", refresh=False)
        bar.refresh()


@eqx.filter_jit
def _lm_solve(solver, problem, z0, max_steps):
    """Levenberg-Marquardt iterations in one compiled loop (a Python loop would pass the
    solver state, with its linearisation closure, across the jit boundary and recompile on
    every fit). Returns (z, iterations, done, result)."""
    f_struct = jax.eval_shape(lambda: problem(z0)[0])
    state = solver.init(problem, z0, None, {}, f_struct, None, frozenset())
    n = f_struct.size
    ring = jnp.full(_STALL + 1, jnp.inf)
    dyn, static = eqx.partition((z0, state), eqx.is_array)

    def cond(carry):
        _, it, done, _ = carry
        return (~done) & (it < max_steps)

    def body(carry):
        d, it, _, ring = carry
        z, st = eqx.combine(d, static)
        z, st, _ = solver.step(problem, z, None, {}, st, frozenset())
        cost = 0.5 * jnp.sum(st.f_info.residual**2)
        ring = jnp.roll(ring, -1).at[-1].set(cost)
        # Besides optimistix's test on the step and residual changes, a statistical one:
        # stop when the cost has fallen by less than 0.01 sigma^2 over the last _STALL
        # steps (sigma^2 ~ 2 cost / n). LM can crawl for hundreds of steps along a weakly
        # determined valley while moving the estimate by a tiny fraction of its
        # confidence region.
        stalled = (it >= _STALL) & (ring[0] - cost <= 0.02 * cost / n)
        jax.debug.callback(_tick, it + 1, cost, n)
        new_dyn, new_static = eqx.partition((z, st), eqx.is_array)
        del new_static  # identical to `static` (optimistix keeps its jaxpr stable)
        return new_dyn, it + 1, st.terminate | stalled, ring

    dyn, it, done, _ = jax.lax.while_loop(cond, body, (dyn, jnp.asarray(0), jnp.asarray(False),
                                                       ring))
    z, state = eqx.combine(dyn, static)
    return z, it, done, state.result


def _lm(problem, z0: np.ndarray, max_steps: int, tol: float, desc: str, progress: bool
        ) -> _Run:
    """Levenberg-Marquardt (optimistix) with forward-mode Jacobians, with a progress bar."""
    solver = optx.LevenbergMarquardt(rtol=tol, atol=tol)
    z = jnp.asarray(z0)
    cost0, failed0 = _evaluate(problem, z)
    if failed0 > 0 or not np.isfinite(cost0):
        return _Run(np.asarray(z0), float("nan"), 0, False,
                    "the ODE solve fails at the start values; choose other start values")
    with _bar(max_steps, desc, progress) as bar:
        _BAR[0] = bar if progress else None
        try:
            z, it, done, result = _lm_solve(solver, problem, z, jnp.asarray(max_steps))
            jax.block_until_ready(z)
        finally:
            _BAR[0] = None
    it, done = int(it), bool(done)
    cost, failed = _evaluate(problem, z)
    zn = np.asarray(z)
    if not np.all(np.isfinite(zn)):
        return _Run(np.asarray(z0), float(cost0), it, False, "the iterates became non-finite")
    if failed > 0:
        return _Run(zn, cost, it, False, "the ODE solve fails at the final estimate")
    if not done:
        return _Run(zn, float(cost), it, False,
                    f"stopped after max_steps = {max_steps} iterations without converging")
    if result != optx.RESULTS.successful:
        return _Run(zn, float(cost), it, False, "Levenberg-Marquardt failed: "
                    + optx.RESULTS[result])
    return _Run(zn, float(cost), it, True, "converged")


def _loss(z, prob):
    r = prob.residuals(z)[0]
    return 0.5 * jnp.sum(r * r)


# Module-level optimisers and steps: optax transformations made per fit would be new
# static objects, and every fit would recompile.
_ADAM = optax.adam(0.02)
_LBFGS = optax.lbfgs()


@eqx.filter_jit
def _adam_step(z, st, prob):
    v, g = jax.value_and_grad(_loss)(z, prob)
    u, st = _ADAM.update(g, st, z)
    return optax.apply_updates(z, u), st, v


@eqx.filter_jit
def _lbfgs_step(z, st, prob):
    f = lambda x: _loss(x, prob)  # noqa: E731
    v, g = optax.value_and_grad_from_state(f)(z, state=st)
    u, st = _LBFGS.update(g, st, z, value=v, grad=g, value_fn=f)
    return optax.apply_updates(z, u), st, v, jnp.max(jnp.abs(g))


def _optax(problem: Problem, z0: np.ndarray, max_steps: int, tol: float, desc: str,
           progress: bool) -> _Run:
    """Adam (a robust first phase far from the optimum), then L-BFGS, on 0.5 |r|^2."""
    cost0, failed0 = _evaluate(problem, jnp.asarray(z0))
    if failed0 > 0 or not np.isfinite(cost0):
        return _Run(np.asarray(z0), float("nan"), 0, False,
                    "the ODE solve fails at the start values; choose other start values")
    adam, lbfgs, adam_step, lbfgs_step = _ADAM, _LBFGS, _adam_step, _lbfgs_step
    z = jnp.asarray(z0)
    n_adam = max_steps // 4
    it, converged, stall = 0, False, 0
    with _bar(max_steps, desc, progress) as bar:
        st = adam.init(z)
        for _ in range(n_adam):
            z, st, v = adam_step(z, st, problem)
            it += 1
            bar.update(1)
            bar.set_postfix(loss=f"{float(v):.3g}", phase="adam")
        st = lbfgs.init(z)
        prev = math.inf
        while it < max_steps:
            z, st, v, gmax = lbfgs_step(z, st, problem)
            it += 1
            v = float(v)
            bar.update(1)
            bar.set_postfix(loss=f"{v:.3g}", phase="lbfgs")
            # Stop when the loss has stopped decreasing for a few steps in a row.
            stall = stall + 1 if abs(prev - v) <= tol * max(abs(v), 1e-300) else 0
            prev = v
            if stall >= 3 or float(gmax) == 0.0:
                converged = True
                break
    cost, failed = _evaluate(problem, z)
    zn = np.asarray(z)
    if not np.all(np.isfinite(zn)) or not np.isfinite(cost):
        return _Run(np.asarray(z0), float(cost0), it, False, "the iterates became non-finite")
    if failed > 0:
        return _Run(zn, cost, it, False, "the ODE solve fails at the final estimate")
    if not converged:
        return _Run(zn, float(cost), it, False,
                    f"stopped after max_steps = {max_steps} iterations without converging")
    return _Run(zn, float(cost), it, True, "converged")


def _guarded(run, *args) -> _Run:
    """Run an optimiser; any failure inside the solve becomes `converged=False`."""
    z0 = args[1]
    try:
        return run(*args)
    except (RuntimeError, ValueError, FloatingPointError) as e:
        # e.g. eqx.error_if rejecting a geometry the optimiser wandered into (L <= r).
        first = next((ln.strip() for ln in str(e).splitlines() if ln.strip()), type(e).__name__)
        return _Run(np.asarray(z0), float("nan"), 0, False, f"the fit failed: {first}")


# ---------------------------------------------------------------------------------------
# Start values


@eqx.filter_jit
def _regressor(mech, phi, dphi, ddphi, ts, load, torque):
    """Rows Y (n, 7) and offsets e0 (n,) with `M phi'' + K phi'^2 - q = Y theta + e0`,
    theta = (m_c, m_p, m_s, I_c, I_p, k, c): the equation is linear in theta."""
    theta0 = jnp.stack([getattr(mech, n) for n in SCALE_GROUP])

    def eom(theta, p, dp, ddp, t):
        m = mech.replace(**dict(zip(SCALE_GROUP, theta)))
        return (mass(m, p) * ddp + coriolis(m, p) * dp**2
                - generalized_force(m, p, dp, t, load, torque))

    def row(p, dp, ddp, t):
        e = eom(theta0, p, dp, ddp, t)
        Yrow = jax.jacfwd(lambda th: eom(th, p, dp, ddp, t))(theta0)
        return Yrow, e - Yrow @ theta0

    return jax.vmap(row)(phi, dphi, ddphi, ts)


def _half_window(ts: np.ndarray, period: float | None) -> int:
    # A cubic fitted over a quarter period follows a sinusoid closely while averaging out
    # the noise of the samples in it.
    dt = float(np.median(np.diff(ts)))
    span = (period if period is not None else (ts[-1] - ts[0]) / 10) / 8
    return int(np.clip(round(span / dt), 2, max(2, (ts.shape[0] - 1) // 2)))


def regressor_start(
    mech: SliderCrank,
    records: Sequence[tuple[Data, AbstractLoad, AbstractLoad]],
    free: Sequence[str],
) -> tuple[dict[str, float], list[str]]:
    """Start values of the free masses, inertias, k and c from the linear regressor form.

    The equation of motion is linear in theta = (m_c, m_p, m_s, I_c, I_p, k, c):
    `Y(phi, phi', phi'', t) theta = tau(t) + P(t) lever(phi)`, with phi' and phi'' from
    local cubic fits to the data. The fixed members of theta and the known loads fix the
    scale; the free ones follow by linear least squares.

    **Returns:** `(start values of the free members of theta, warnings)`; a member whose
    estimate is not positive (or a scale nothing fixes) keeps the scene's value, with a
    warning.
    """
    free_g = [n for n in SCALE_GROUP if n in free]
    if not free_g:
        return {}, []
    Ys, es = [], []
    for data, load, torque in records:
        half = _half_window(data.ts, natural_period(mech, load))
        phi, dphi, ddphi = smooth_derivatives(data.ts, data.phi, half)
        sl = slice(half, data.n - half) if data.n > 2 * half + 2 else slice(None)
        Y, e0 = _regressor(mech, jnp.asarray(phi[sl]), jnp.asarray(dphi[sl]),
                           jnp.asarray(ddphi[sl]), jnp.asarray(data.ts[sl]), load, torque)
        Ys.append(np.asarray(Y))
        es.append(np.asarray(e0))
    Y, e0 = np.concatenate(Ys), np.concatenate(es)
    theta = np.array([float(getattr(mech, n)) for n in SCALE_GROUP])
    fi = [SCALE_GROUP.index(n) for n in free_g]
    xi = [i for i in range(len(SCALE_GROUP)) if i not in fi]
    b = -(e0 + Y[:, xi] @ theta[xi])
    Yf = Y[:, fi]
    # Column scaling by the scene's values makes the least squares well posed in units.
    scale = np.where(theta[fi] > 0, theta[fi], 1.0)
    if np.linalg.norm(b) <= 1e-9 * np.linalg.norm(Yf @ scale):
        return {}, ["regressor start: nothing fixes the common scale (no known load and no "
                    "fixed mass, inertia, k or c), so the scene's values are used"]
    sol, *_ = np.linalg.lstsq(Yf * scale, b, rcond=1e-10)
    sol = sol * scale
    out, notes = {}, []
    for n, v in zip(free_g, sol):
        if np.isfinite(v) and v > 0:
            out[n] = float(v)
        else:
            notes.append(f"regressor start for {n} is {v:.3g} (not positive); the scene's "
                         "value is used instead")
    return out, notes


# ---------------------------------------------------------------------------------------
# The fit


def _segments(span: float, period: float | None, shooting: str, segments: int | None) -> int:
    if shooting == "single":
        return 1
    n_per = span / period if period else 0.0
    if segments is not None:
        return int(segments)
    if shooting == "auto":
        return 1 if n_per <= AUTO_PERIODS else math.ceil(n_per / SEGMENT_PERIODS)
    return max(2, math.ceil(n_per / SEGMENT_PERIODS))


class _Subspace(eqx.Module):
    """The residuals on the affine subspace `z = z0 + B w` (B: orthonormal columns)."""

    problem: Problem
    z0: jax.Array
    B: jax.Array

    def residuals(self, w):
        return self.problem.residuals(self.z0 + self.B @ w)

    def __call__(self, w, args=None):
        return self.residuals(w)[0], None


class _Pinned(eqx.Module):
    """The residuals with coordinate `j` held at `zj` (for profile likelihoods)."""

    problem: Problem
    zj: jax.Array
    j: int = eqx.field(static=True)

    def full(self, zr):
        return jnp.concatenate([zr[:self.j], self.zj[None], zr[self.j:]])

    def residuals(self, zr):
        return self.problem.residuals(self.full(zr))

    def __call__(self, zr, args=None):
        return self.residuals(zr)[0], None


def fit(
    scene: Scene | Sequence[Scene],
    data: Data | Sequence[Data],
    free: Sequence[str] = ("k", "c", "phi0", "dphi0"),
    *,
    init: str | dict[str, float] = "scene",
    method: str = "lm",
    shooting: str = "auto",
    segments: int | None = None,
    multistart: int = 1,
    seed: int = 0,
    max_steps: int | None = None,
    tol: float = 1e-8,
    sigma: float | None = None,
    profile: str | None = None,
    progress: bool = True,
    warn: bool = True,
) -> FitResult:
    """Fit free parameters of a scene to crank-angle records by least squares.

    **Arguments:**

    - `scene`: the [`Scene`][] giving the fixed values, the start values and the loads; or
      one scene per record.
    - `data`: a [`Data`][] record, or a sequence of them (a multi-experiment fit: the
      mechanism is shared, each record has its own initial state and loads). A record's
      own `load`/`torque` replace its scene's.
    - `free`: names from the twelve mechanism fields, the load amplitudes `P0`, `P1`,
      `tau0`, `tau1` (the scene's constant or harmonic load) and `phi0`, `dphi0` (the
      state at each record's first sample). Mechanism fields are fitted in log space.
    - `init`: `"scene"` (the scene's values), `"regressor"` (masses, inertias, k and c
      from the linear regressor form) or a dict of start values. Free `phi0`/`dphi0` always
      start from a local cubic fit to the first samples.
    - `method`: `"lm"` or `"optax"` (see the module notes for which to use).
    - `shooting`: `"auto"`, `"single"` or `"multiple"`; `segments` fixes their number.
    - `multistart`: number of starts (the first is `init`; the others perturb the
      log-parameters by a factor `exp(N(0, 0.5^2))`); the lowest cost wins.
    - `seed`: seed of the multistart perturbations.
    - `max_steps`: iteration budget per start (default 100 for LM, 2000 for optax).
    - `tol`: relative and absolute tolerance of the optimiser's termination test.
    - `sigma`: the noise standard deviation (rad) if known; default: from the residuals.
    - `profile`: a reported name whose profile likelihood to compute.
    - `progress`: show progress bars on stderr. `warn`: emit Python warnings
      ([`IdentifiabilityWarning`][], [`ConvergenceWarning`][]) besides `result.warnings`.

    **Returns:** a [`FitResult`][]. A fit that fails or does not converge returns
    `converged=False` with a message (and finite values: the last good iterate or the
    start); it never raises for a numerical failure. Mistakes in the request (unknown
    names, too few samples, a non-positive start of a log-parameter) raise `ValueError`.
    """
    t_begin = time.perf_counter()
    records = [data] if isinstance(data, Data) else list(data)
    if not records or not all(isinstance(d, Data) for d in records):
        raise ValueError("data must be a Data record or a non-empty sequence of them")
    scenes = [scene] * len(records) if isinstance(scene, Scene) else list(scene)
    if len(scenes) != len(records):
        raise ValueError(f"got {len(scenes)} scenes for {len(records)} records; give one "
                         "scene, or one per record")
    free = list(dict.fromkeys(free))
    unknown = [n for n in free if n not in FREE_NAMES]
    if unknown or not free:
        raise ValueError(f"unknown free parameter(s) {unknown}; choose from {list(FREE_NAMES)}"
                         if unknown else "free must name at least one parameter")
    if method not in ("lm", "optax"):
        raise ValueError(f"method must be 'lm' or 'optax', got {method!r}")
    if shooting not in ("auto", "single", "multiple"):
        raise ValueError(f"shooting must be 'auto', 'single' or 'multiple', got {shooting!r}")
    if segments is not None and (segments < 1 or shooting == "single" and segments > 1):
        raise ValueError(f"segments = {segments} is not valid with shooting={shooting!r}")
    if multistart < 1:
        raise ValueError(f"multistart must be >= 1, got {multistart}")
    if max_steps is None:
        max_steps = 100 if method == "lm" else 2000
    mech = scenes[0].mech
    notes: list[str] = []

    # Loads of each record: its own (from data) or its scene's.
    rec = []
    for d, sc in zip(records, scenes):
        load = d.load if d.load is not None else sc.load
        torque = d.torque if d.torque is not None else sc.torque
        rec.append((d, load, torque))
    start: dict[str, float] = {n: float(getattr(mech, n)) for n in free if n in FIELDS}
    for n in free:
        if n in LOAD_NAMES:
            which, field = LOAD_NAMES[n]
            v = None
            for (d, load, torque), sc in zip(rec, scenes):
                obj = load if which == "load" else torque
                if (d.load if which == "load" else d.torque) is not None:
                    raise ValueError(f"{n} cannot be free: record {d.source} supplies its own "
                                     f"{'P' if which == 'load' else 'tau'} as data")
                v = load_param(obj, field)
                if v is None:
                    raise ValueError(f"{n} cannot be free: the scene's "
                                     f"{'load' if which == 'load' else 'torque'} is "
                                     f"{type(obj).__name__}, not a harmonic (or, for {n[:-1]}0, "
                                     "constant) load")
            start[n] = float(v)
    if isinstance(init, dict):
        bad = [n for n in init if n not in start]
        if bad:
            raise ValueError(f"init gives start values for {bad}, which are not free global "
                             f"parameters ({sorted(start)})")
        start.update({n: float(v) for n, v in init.items()})
    elif init == "regressor":
        reg, reg_notes = regressor_start(mech, rec, free)
        start.update(reg)
        notes += reg_notes
    elif init != "scene":
        raise ValueError(f"init must be 'scene', 'regressor' or a dict, got {init!r}")
    for n, v in start.items():
        if n in FIELDS and not (math.isfinite(v) and v > 0):
            raise ValueError(f"the start value of {n} is {v}; it is fitted in log space and "
                             f"needs a positive start: pass init={{'{n}': ...}} or "
                             "init='regressor'")
    mech_start = mech.replace(**{n: v for n, v in start.items() if n in FIELDS})

    # Initial states: from the data (a smoothed first sample), since the scene's state is
    # at t = 0 and real records start anywhere.
    states, nseg, seg_states = [], [], []
    for (d, load, torque), sc in zip(rec, scenes):
        period = natural_period(mech_start, load)
        half = _half_window(d.ts, period)
        ps, dps, _ = smooth_derivatives(d.ts, d.phi, half)
        phi0 = float(ps[0]) if "phi0" in free else float(sc.phi0)
        dphi0 = float(dps[0]) if "dphi0" in free else float(sc.dphi0)
        states.append((phi0, dphi0))
        S = _segments(float(d.ts[-1] - d.ts[0]), period, shooting, segments)
        nseg.append(S)
        seg_states.append((ps, dps))
    p_report = len(free) + (len(records) - 1) * sum(n in STATE_NAMES for n in free)
    n_total = sum(d.n for d in records)
    if n_total <= p_report:
        raise ValueError(f"too few samples: {n_total} samples for {p_report} free parameters")

    solver = pick_solver(mech_start, rec[0][1], float(scenes[0].rtol), scenes[0].solver)
    opts = dict(solver=solver, rtol=float(scenes[0].rtol), atol=float(scenes[0].atol),
                )
    full_start = dict(start)
    multi = len(records) > 1
    for i, (phi0, dphi0) in enumerate(states):
        sfx = f"[{i}]" if multi else ""
        if "phi0" in free:
            full_start["phi0" + sfx] = phi0
        if "dphi0" in free:
            full_start["dphi0" + sfx] = dphi0

    def problem_for(segs, budget):
        return build_problem(mech, [(d, lo, to, st[0], st[1]) for (d, lo, to), st
                                    in zip(rec, states)], free, start, segs, max_steps=budget,
                             **opts)

    # ODE step budget: generous next to the solve at the start values, so that a trial
    # point in a stiff corner fails fast (and is rejected) instead of grinding through
    # hundreds of thousands of steps.
    ss = problem_for([1] * len(records), _MAX_ODE_STEPS)
    names = ss.names
    z_start = ss.to_z([full_start[n] for n in names])
    _, failed0, steps0 = _residuals_jit(ss, jnp.asarray(z_start))
    budget = _MAX_ODE_STEPS
    if int(failed0) == 0:
        # Two levels only: the start state varies with each record's noise, and a finer
        # bucket would straddle a boundary (and recompile) from one record to the next.
        budget = _SMALL_ODE_BUDGET if 20 * int(steps0) <= _SMALL_ODE_BUDGET else _MAX_ODE_STEPS
        ss = problem_for([1] * len(records), budget)
    ms = problem_for(nseg, budget) if max(nseg) > 1 else ss
    z0 = np.concatenate([z_start, _segment_z(ms, seg_states)])
    shooting_used = "single" if ms is ss else f"multiple ({'+'.join(map(str, nseg))} segments)"
    if method == "optax":
        ms = dataclasses.replace(ms, adjoint="reverse")

    # Directions in which the residuals are exactly flat at the start (the common scale)
    # are held fixed: the optimiser would otherwise wander along them, and the reported
    # point is the one on the ridge nearest to the start.
    B = np.eye(z0.shape[0])
    if int(failed0) == 0:
        try:
            J0 = np.asarray(_jacobian(ss, jnp.asarray(z_start)))
            _, s0, Vt0 = np.linalg.svd(J0, full_matrices=False)
            keep = s0 > RANK_TOL * s0[0]
            if np.all(np.isfinite(J0)) and not np.all(keep):
                B[:ss.p, :ss.p] = 0.0
                B = np.delete(B, np.s_[keep.sum():ss.p], axis=1)
                B[:ss.p, :keep.sum()] = Vt0[keep].T
        except (RuntimeError, ValueError):
            pass
    polish_B = B[:ss.p, :B.shape[1] - (z0.shape[0] - ss.p)]

    # Optimise (multistart: the first start is the given one).
    run_fn = _lm if method == "lm" else _optax
    rng = np.random.default_rng(seed)
    runs = []
    for k in range(multistart):
        zk = z0.copy()
        if k > 0:
            for i, n in enumerate(names):
                if n in FIELDS:
                    zk[i] += rng.normal(0.0, 0.5)
                elif n in LOAD_NAMES:
                    zk[i] *= 1 + rng.normal(0.0, 0.3)
        desc = f"fit {k + 1}/{multistart}" if multistart > 1 else "fit"
        sub = _Subspace(ms, jnp.asarray(z0), jnp.asarray(B))
        run = _guarded(run_fn, sub, B.T @ (zk - z0), max_steps, tol, desc, progress)
        run = run._replace(z=z0 + B @ run.z)
        if ms is not ss and np.isfinite(run.cost):
            # Polish by single shooting from the multiple-shooting estimate.
            zp = run.z[:ss.p]
            sub = _Subspace(ss, jnp.asarray(zp), jnp.asarray(polish_B))
            pol = _guarded(_lm, sub, np.zeros(polish_B.shape[1]), max_steps, tol,
                           desc + " (polish)", progress)
            run = _Run(zp + polish_B @ pol.z, pol.cost, run.iterations + pol.iterations,
                       run.converged and pol.converged,
                       pol.message if not pol.converged else run.message)
        runs.append(run)
    ok = [r for r in runs if np.isfinite(r.cost)]
    best = min(ok, key=lambda r: (not r.converged, r.cost)) if ok else runs[0]
    if multistart > 1:
        costs = np.array([r.cost for r in ok])
        distinct = int(np.sum(costs > best.cost * (1 + 1e-3) + 1e-300))
        notes.append(f"multistart: {sum(r.converged for r in runs)} of {multistart} starts "
                     f"converged; {distinct} ended at a higher cost than the best")
    z_hat = best.z[:ss.p] if np.all(np.isfinite(best.z)) else z_start
    iterations = sum(r.iterations for r in runs)

    # Residuals, sensitivities and uncertainty at the estimate (single shooting).
    r_hat, failed, _ = _residuals_jit(ss, jnp.asarray(z_hat))
    r_hat = np.asarray(r_hat)
    values = np.asarray(ss.values(jnp.asarray(z_hat)))
    n = ss.n_residuals
    rms = float(np.sqrt(np.sum(r_hat**2) / n)) if int(failed) == 0 else float("nan")
    unc: Uncertainty | None = None
    converged, message = best.converged, best.message
    try:
        J = np.asarray(_jacobian(ss, jnp.asarray(z_hat)))
        if np.all(np.isfinite(J)) and int(failed) == 0:
            unc = analyse(J, r_hat, n, names, values, ss.log, np.asarray(ss.ref), sigma,
                          geometry={k: float(getattr(ss.base, k)) for k in "rLbs"})
    except (RuntimeError, ValueError) as e:
        notes.append(f"sensitivities could not be computed: {str(e).splitlines()[0]}")
    p = len(names)
    if unc is None:
        nan = np.full(p, np.nan)
        unc = Uncertainty(nan, np.full((p, 2), np.nan), np.full((p, p), np.nan),
                          np.full((p, p), np.nan), nan, math.inf, float("nan"), False,
                          ["the sensitivities are undefined at the estimate (the solve "
                           "failed), so nothing can be said about identifiability"],
                          np.ones(p, bool))
    if not unc.identifiable:
        notes = [f"not identifiable: {m}" for m in unc.directions] + notes
        bad = [nm for nm, a in zip(names, unc.affected) if a]
        notes.append(f"no standard errors for {', '.join(bad)}: the values reported for them "
                     "are one point of a set that fits equally well, not estimates")
    elif unc.condition_number > 1e6:
        notes.append(f"the scaled sensitivity matrix is poorly conditioned (condition number "
                     f"{unc.condition_number:.2g}): expect large, strongly correlated errors")
    if not converged:
        notes.insert(0, f"fit did not converge: {message}; no standard errors are given")

    prof = None
    if profile is not None:
        if profile not in names:
            raise ValueError(f"--profile {profile!r} is not a free parameter; choose from "
                             f"{list(names)}")
        j = names.index(profile)
        se_z = math.sqrt(max(unc.covariance_z[j, j], 0.0)) if np.isfinite(
            unc.covariance_z[j, j]) else float("nan")
        prof = _profile(ss, z_hat, j, se_z, n, max_steps, tol, progress)

    def show(i):
        return converged and bool(np.isfinite(unc.stderr[i]))

    res = FitResult(
        names=names,
        values={nm: float(values[i]) for i, nm in enumerate(names)},
        start={nm: float(full_start[nm]) for nm in names},
        stderr={nm: float(unc.stderr[i]) if show(i) else None for i, nm in enumerate(names)},
        ci95={nm: (float(unc.ci95[i, 0]), float(unc.ci95[i, 1])) if show(i) else None
              for i, nm in enumerate(names)},
        correlation=unc.correlation,
        condition_number=float(unc.condition_number),
        singular_values=unc.singular_values,
        identifiable=bool(unc.identifiable),
        unidentifiable_directions=list(unc.directions),
        rms_residual=rms,
        n_samples=int(n),
        converged=bool(converged),
        iterations=int(iterations),
        seconds=time.perf_counter() - t_begin,
        warnings=notes,
        message=message,
        method=method,
        shooting=shooting_used,
        mech=ss.unpack(jnp.asarray(z_hat))[0],
        data=records,
        fitted=_fitted(ss, r_hat),
        profile=prof,
    )
    if warn:
        if not res.identifiable:
            warnings.warn("; ".join(res.unidentifiable_directions), IdentifiabilityWarning,
                          stacklevel=2)
        if not res.converged:
            warnings.warn(f"fit did not converge: {res.message}", ConvergenceWarning,
                          stacklevel=2)
    return res


def _segment_z(problem: Problem, seg_states) -> np.ndarray:
    """Start coordinates of the multiple-shooting segment states (smoothed data)."""
    out = []
    for e, (ps, dps) in zip(problem.exps, seg_states):
        S = e.seg.ts.shape[0]
        if S == 1:
            continue
        for s in range(1, S):
            # Segment s starts at the shared sample; the rows before it fit exactly the
            # samples before it, so their weights count its index in the record.
            k = int(np.sum(np.asarray(e.seg.w[:s])))
            out += [ps[k] / float(e.ref_phi), dps[k] / float(e.ref_dphi)]
    return np.asarray(out, dtype=float)


@eqx.filter_jit
def _residuals_jit(problem: Problem, z):
    return problem.residuals(z)


@eqx.filter_jit
def _jacobian(problem: Problem, z):
    return jax.jacfwd(lambda x: problem.residuals(x)[0])(z)


def _fitted(problem: Problem, r: np.ndarray) -> list[np.ndarray]:
    """Model angles per record from single-shooting residuals (r = model - data)."""
    out, k = [], 0
    for e in problem.exps:
        out.append(np.asarray(e.seg.phi[0]) + r[k:k + e.n])
        k += e.n
    return out


def _profile(problem: Problem, z_hat, j: int, se_z: float, n: int, max_steps: int,
             tol: float, progress: bool) -> Profile:
    """Profile likelihood on a grid of +-3 standard errors (or +-ln 2 / +-50% if none)."""
    half = 3 * se_z if math.isfinite(se_z) and se_z > 0 else (
        math.log(2) if problem.log[j] else 0.5)
    grid = np.linspace(-half, half, 9)
    z_hat = np.asarray(z_hat)
    rss_min = 2 * _evaluate(problem, z_hat)[0]
    rss = np.full(grid.shape, np.nan)
    centre = int(np.argmin(np.abs(grid)))
    zr_hat = np.delete(z_hat, j)
    with _bar(len(grid), f"profile {problem.names[j]}", progress) as bar:
        for direction in (range(centre, len(grid)), range(centre - 1, -1, -1)):
            zr = zr_hat.copy()
            for k in direction:
                pinned = _Pinned(problem, jnp.asarray(z_hat[j] + grid[k]), j)
                run = _guarded(_lm, pinned, zr, max_steps, tol, "", False)
                if np.isfinite(run.cost):
                    rss[k] = 2 * run.cost
                    zr = run.z  # warm start the next grid point
                bar.update(1)
    rss_min = min(rss_min, float(np.nanmin(rss))) if np.any(np.isfinite(rss)) else rss_min
    dev = n * np.log(rss / rss_min)
    zs = z_hat[j] + grid
    values = np.exp(zs) if problem.log[j] else zs * float(problem.ref[j])
    return Profile(problem.names[j], values, dev, _crossings(values, dev, centre))


def _crossings(values, dev, centre) -> tuple[float | None, float | None]:
    def cross(rng):
        prev = centre
        for k in rng:
            if not np.isfinite(dev[k]):
                return None
            if dev[k] > _CHI2_95:
                d0, d1 = dev[prev], dev[k]
                f = (_CHI2_95 - d0) / (d1 - d0) if d1 != d0 else 0.0
                return float(values[prev] + f * (values[k] - values[prev]))
            prev = k
        return None

    return cross(range(centre - 1, -1, -1)), cross(range(centre + 1, len(values)))

