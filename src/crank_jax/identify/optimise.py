"""The optimisers: Levenberg-Marquardt (MINPACK, through scipy) over the compiled
residuals-and-sensitivities program, and optax.

LM's loop runs on the host (see [`least_squares`][] for why): the only compiled program
it calls is `jacobian_at`, which on the fused solvers and diffrax's explicit ones has no
host callback, so JAX's persistent cache and the program store keep it between processes,
and progress is shown after every iteration.
"""

from __future__ import annotations

import functools
import math
import sys
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..lazy import lazy_import
from .programs import jacobian_at, residuals_at
from .strategy import FAR_FROM_NOISE

# Imported on first use (see lazy.py): only the optax method needs it.
optax = lazy_import("optax")

__all__ = ["Run", "least_squares", "minimise_optax", "evaluate", "STALL_STEPS",
           "progress_bar", "stalled_message"]

#: The stall test looks this many iterations back (see `_Evaluations`).
STALL_STEPS = 8


class Run(NamedTuple):
    """One optimisation: final coordinates, cost `0.5 |r|^2`, iterations, outcome."""

    z: np.ndarray
    cost: float
    iterations: int
    converged: bool
    message: str


class _NoBar:
    """What `progress_bar` returns when there is no progress to show."""

    n = 0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def update(self, n=1):
        pass

    def set_postfix(self, *args, **kwargs):
        pass


def progress_bar(total: int, desc: str, progress: bool):
    """A tqdm bar on stderr, or a silent stand-in when not `progress` (tqdm is imported
    only for a bar that shows: 0.1-0.3 s of a warm CLI fit otherwise)."""
    if not progress:
        return _NoBar()
    from tqdm import tqdm  # the text bar: it works in terminals, logs and notebooks

    return tqdm(total=total, desc=desc, file=sys.stderr, leave=False, dynamic_ncols=True)


def evaluate(problem, z) -> tuple[float, int]:
    """(0.5 |r|^2, number of failed samples) at `z`."""
    r, failed, _ = residuals_at(problem, jnp.asarray(z))
    r = np.asarray(r)
    return 0.5 * float(r @ r), int(failed)


def _budget_spent(max_steps: int) -> str:
    """The message of a run that used its iteration budget without converging."""
    return (f"stopped after {max_steps} iterations without converging (max_steps = "
            f"{max_steps}: raise it to go on)")


def _failed_message(failed: int) -> str:
    """The message of a run whose best point still has failed ODE solves."""
    return (f"the ODE solve fails at every point tried ({failed} samples failed at the best "
            "one): the parameters make the model far stiffer or faster than the record; "
            "choose other start values")


class _Stop(Exception):
    """Ends MINPACK's loop from inside a callback (scipy passes the exception through)."""

    def __init__(self, converged: bool, message: str):
        super().__init__(message)
        self.converged, self.message = converged, message


class _Evaluations:
    """The residuals and sensitivities MINPACK asks for, each point from one call of the
    compiled [`jacobian_at`][] program (MINPACK asks for the Jacobian at a point whose
    residuals it has just had). It keeps the best point seen (as optimistix's
    `BestSoFarLeastSquares`) and decides when to stop: a Gauss-Newton convergence test, a
    stall test (the best cost has fallen by less than `0.01 sigma^2` over the last
    [`STALL_STEPS`][] iterations, with `sigma^2 ~ 2 cost / n`: LM can crawl for hundreds of
    steps along a weakly determined valley while moving the estimate by a tiny fraction of
    its confidence region), and the iteration budget.

    A stall is convergence only where the fit explains the record: at an rms residual
    within `stall_rms` (the fit passes [`FAR_FROM_NOISE`][] times the record's noise
    level; None: anywhere). Above it, the cost has stopped falling without the
    Gauss-Newton test being met: a local minimum (a bound held, a slipped turn) or a
    model that cannot follow the record, reported as a stall, not as convergence."""

    def __init__(self, model, max_steps: int, tol: float, bar,
                 stall_rms: float | None = None):
        self.model, self.max_steps, self.tol, self.bar = model, max_steps, tol, bar
        self.stall_rms = stall_rms
        self.w = self.r = self.J = None
        self.failed = 0
        self.best_w, self.best_cost, self.best_failed = None, math.inf, 0
        self.history = [math.inf] * (STALL_STEPS + 1)
        self.iterations = 0

    def _at(self, w: np.ndarray) -> None:
        if self.w is not None and np.array_equal(w, self.w):
            return
        r, failed, _, J = jacobian_at(self.model.problem, jnp.asarray(self.model.lift(w)))
        # A failed solve's samples are residuals of 10 rad already (problem.py); anything
        # non-finite left must not reach MINPACK, which has no test for it.
        r = np.nan_to_num(np.asarray(r), nan=1e3, posinf=1e3, neginf=-1e3)
        self.w, self.r, self.failed = np.array(w), r, int(failed)
        self.J = np.nan_to_num(self.model.restrict(np.asarray(J)), nan=0.0, posinf=0.0,
                               neginf=0.0)
        cost = 0.5 * float(r @ r)
        # A point with failed samples wins only over other failed points: its cost is
        # a stand-in (10 rad per failed sample), not a misfit.
        if self.best_w is None or (self.failed, cost) < (self.best_failed, self.best_cost):
            if self.best_w is not None and self.failed < self.best_failed:
                # Fewer failed samples, maybe a higher cost: the stall test starts afresh.
                self.history = [math.inf] * (STALL_STEPS + 1)
            self.best_w, self.best_cost, self.best_failed = self.w, cost, self.failed

    def residuals(self, w):
        self._at(w)
        return self.r

    def jacobian(self, w):
        # MINPACK asks for the Jacobian once per iteration, at the accepted point.
        self._at(w)
        self.iterations += 1
        self.history = self.history[1:] + [self.best_cost]
        self.bar.n = self.iterations
        self.bar.set_postfix(cost=f"{self.best_cost:.4g}", refresh=True)
        h, n = self.history, self.r.shape[0]
        if self.failed:
            # A failed solve's residuals are a constant, so its Jacobian rows are zero:
            # the tests below would see no slope and call that convergence. With nothing
            # left to move (every row failed, or no change over the stall window), stop
            # as a failure.
            if not np.any(self.J) or (math.isfinite(h[0]) and h[0] - h[-1] <= 0.0):
                raise _Stop(False, _failed_message(self.failed))
        elif math.isfinite(h[0]) and h[0] - h[-1] <= 0.02 * h[-1] / n:
            raise _Stop(*self._stall(h[-1], n))
        # Converged when the Gauss-Newton step, the distance to the minimum the
        # linearisation predicts, is below `tol + tol |z|` in every coordinate of the
        # problem (`z`, not the view's `w`: a subspace's `w` is the offset from its start,
        # near 0, and a test relative to it asked a polish for steps of 1e-8 absolute,
        # below the Jacobian's rounding, so it ran to the stall test). MINPACK's
        # own tests look at the damped step or the cost change, which are small also where
        # LM crawls with a large damping; and its relative step test means little for
        # coordinates near 0 (log-ratios to `ref`).
        gn = np.linalg.lstsq(self.J, -self.r, rcond=None)[0]
        z = np.asarray(self.model.lift(self.w))
        step = np.asarray(self.model.lift(self.w + gn)) - z
        if not self.failed and np.all(np.abs(step) <= self.tol + self.tol * np.abs(z)):
            raise _Stop(True, "converged")
        if self.iterations > self.max_steps:
            self.iterations = self.max_steps
            raise _Stop(False, _budget_spent(self.max_steps))
        return self.J

    def _stall(self, cost: float, n: int) -> tuple[bool, str]:
        """(converged, message) of a run whose best cost has stopped falling."""
        rms = math.sqrt(2.0 * cost / max(n, 1))
        if self.stall_rms is None or rms <= self.stall_rms:
            return True, "converged"
        return False, stalled_message(rms, self.stall_rms / FAR_FROM_NOISE)


def stalled_message(rms: float, noise: float) -> str:
    """The message of a run whose cost stopped falling far above the noise level `noise`
    (both in the residuals' unit)."""
    return (f"stalled: the cost stopped falling at an rms residual {rms / noise:.3g} times "
            "the record's noise level, before the Gauss-Newton step became small (a local "
            "minimum, or a model that cannot follow the record); try start values nearer "
            "the truth or more starts (multistart)")


def least_squares(model, z0: np.ndarray, max_steps: int, tol: float, desc: str,
                  progress: bool, stall_rms: float | None = None) -> Run:
    """Levenberg-Marquardt on a residual view `model` (a [`Subspace`][] or [`Pinned`][]
    problem) from `z0`, with a progress bar per iteration.

    MINPACK's `lmder` (through `scipy.optimize.least_squares(method="lm")`, Marquardt's
    scaling of the coordinates) drives the iterations on the host; each point costs one
    call of the compiled residuals-and-sensitivities program, which the fit needs at its
    start and at its estimate anyway. A compiled optimistix LM loop was tried first: its
    program holds the residual solve and its linearisation inside optimistix's loop and
    compiled in 3-5 s per problem shape, more than half of a cold `crank-jax fit`
    (experiments/bench_end_to_end.py); each iteration costs the same solves either way.

    The point reported is the best one seen: the lowest cost among points whose solves
    all succeed (a failed solve's samples count as residuals of 10 rad, a stand-in, not a
    misfit). A run whose best point still has failed samples is never `converged`, and
    its cost is NaN. `stall_rms`: the rms residual above which a stall is not
    convergence (see `_Evaluations`; None: a stall is convergence anywhere)."""
    from scipy.optimize import least_squares as minpack_lm

    z0 = np.asarray(z0, dtype=float)
    with progress_bar(max_steps, desc, progress) as bar:
        ev = _Evaluations(model, max_steps, tol, bar, stall_rms)
        # MINPACK's own tests at machine precision: they stop it only where it can make
        # no further progress; the tests that decide are `_Evaluations.jacobian`'s. (Not
        # below it: MINPACK's "tolerance too small" outcomes have no status in scipy.)
        eps = float(np.finfo(float).eps)
        try:
            sol = minpack_lm(ev.residuals, z0, jac=ev.jacobian, method="lm", x_scale="jac",
                             ftol=eps, xtol=eps, gtol=eps, max_nfev=100 * (max_steps + 1))
            converged = sol.status > 0
            message = "converged" if converged else (
                _budget_spent(max_steps) if sol.status == 0
                else "Levenberg-Marquardt failed: " + sol.message)
        except _Stop as stop:
            converged, message = stop.converged, stop.message
    if ev.best_w is None or not np.all(np.isfinite(ev.best_w)):
        return Run(z0, float("nan"), ev.iterations, False, "the iterates became non-finite")
    if ev.best_failed:
        # Never "converged" where the solve fails, and no cost: the stand-ins are no
        # misfit, so such a run never ranks above one whose solves succeed.
        return Run(ev.best_w, float("nan"), ev.iterations, False,
                   _failed_message(ev.best_failed))
    return Run(ev.best_w, ev.best_cost, ev.iterations, converged, message)


def _outcome(model, z0, cost0, z, it, done, max_steps) -> Run:
    cost, failed = evaluate(model, z)
    zn = np.asarray(z)
    if not np.all(np.isfinite(zn)):
        return Run(np.asarray(z0), float(cost0), it, False, "the iterates became non-finite")
    if failed > 0:
        return Run(zn, cost, it, False, "the ODE solve fails at the final estimate")
    if not done:
        return Run(zn, float(cost), it, False, _budget_spent(max_steps))
    return Run(zn, float(cost), it, True, "converged")


def _loss(z, model):
    r = model.residuals(z)[0]
    return 0.5 * jnp.sum(r * r)


# One (immutable) optimiser each, made on first use (optax is imported then): optax
# transformations made per fit would be new static objects, and every fit would recompile.
@functools.cache
def _adam():
    return optax.adam(0.02)


@functools.cache
def _lbfgs():
    return optax.lbfgs()


@eqx.filter_jit
def _adam_step(z, st, model):
    v, g = jax.value_and_grad(_loss)(z, model)
    u, st = _adam().update(g, st, z)
    return optax.apply_updates(z, u), st, v


@eqx.filter_jit
def _lbfgs_step(z, st, model):
    def f(x):
        return _loss(x, model)

    v, g = optax.value_and_grad_from_state(f)(z, state=st)
    u, st = _lbfgs().update(g, st, z, value=v, grad=g, value_fn=f)
    return optax.apply_updates(z, u), st, v, jnp.max(jnp.abs(g))


def minimise_optax(model, z0: np.ndarray, max_steps: int, tol: float, desc: str,
                   progress: bool) -> Run:
    """Adam (a robust first phase far from the optimum), then L-BFGS, on 0.5 |r|^2, with
    reverse-mode gradients (the model must use the reverse adjoint)."""
    cost0, failed0 = evaluate(model, jnp.asarray(z0))
    if failed0 > 0 or not np.isfinite(cost0):
        return Run(np.asarray(z0), float("nan"), 0, False,
                   "the ODE solve fails at the start values; choose other start values")
    z = jnp.asarray(z0)
    it, converged, stall = 0, False, 0
    with progress_bar(max_steps, desc, progress) as bar:
        st = _adam().init(z)
        for _ in range(max_steps // 4):
            z, st, v = _adam_step(z, st, model)
            it += 1
            bar.update(1)
        st = _lbfgs().init(z)
        prev = math.inf
        while it < max_steps:
            z, st, v, gmax = _lbfgs_step(z, st, model)
            it += 1
            v = float(v)
            bar.update(1)
            bar.set_postfix(loss=f"{v:.3g}", refresh=False)
            # Stop when the loss has stopped decreasing for a few steps in a row.
            stall = stall + 1 if abs(prev - v) <= tol * max(abs(v), 1e-300) else 0
            prev = v
            if stall >= 3 or float(gmax) == 0.0:
                converged = True
                break
    return _outcome(model, z0, cost0, z, it, converged, max_steps)
