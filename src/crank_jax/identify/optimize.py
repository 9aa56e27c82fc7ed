"""Levenberg-Marquardt (MINPACK, through scipy) over the compiled residuals-and-
sensitivities program, with its termination judged in the data's units (the optax
method is [`optax_fit`][crank_jax.identify.optax_fit]).

LM's loop runs on the host (see [`least_squares`][] for why): the only compiled program
it calls is `jacobian_at`, which on the fused solvers and diffrax's explicit ones has no
host callback, so JAX's persistent cache and the program store keep it between processes,
and progress is shown after every iteration.
"""

from __future__ import annotations

import math

import numpy as np

from ..runtime.arrays import device_array
from ..runtime.progress import progress_bar
from .gauss_newton import Step, direction, gauss_newton
from .outcome import Run, budget_spent, failed_message, stalled_message, termination
from .programs import jacobian_at, residuals_at
from .strategy import AT_ZERO, FAR_FROM_NOISE

__all__ = ["least_squares", "evaluate", "STALL_STEPS",
           "DECREASE_FRACTION", "STEP_FRACTION", "STALL_DECREASE", "BOUND_STEPS"]

#: The stall test looks this many iterations back (see `_Evaluations`).
STALL_STEPS = 8
#: Converged in the data's units when the Gauss-Newton step predicts a cost decrease
#: below this fraction of one noise-level unit of cost (`sigma^2`, the cost of a change
#: of 2 in chi-squared) ...
DECREASE_FRACTION = 1e-4
#: ... and moves no coordinate by more than this fraction of its standard error
#: (`sigma sqrt(diag (J^T J)^-1)`, the noise level's, not the misfit's: the stricter).
STEP_FRACTION = 1e-2
#: A stall: the best cost has fallen by less than this many `sigma^2` over the last
#: [`STALL_STEPS`][] iterations while the linearisation still predicts more.
STALL_DECREASE = 1e-2
#: A run with `at_bounds` stops once a folded parameter has sat at its bound 0 (within
#: `AT_ZERO`) this many iterations in a row without the run converging.
BOUND_STEPS = 3


def evaluate(problem, z) -> tuple[float, int]:
    """(0.5 |r|^2, number of failed samples) at `z`."""
    r, failed, _ = residuals_at(problem, device_array(z))
    r = np.asarray(r)
    return 0.5 * float(r @ r), int(failed)


class _Stop(Exception):
    """Ends MINPACK's loop from inside a callback (scipy passes the exception through)."""

    def __init__(self, converged: bool, message: str, term: dict | None = None):
        super().__init__(message)
        self.converged, self.message = converged, message
        self.term = term or termination("converged" if converged else "failed", message)


class _Evaluations:
    """The residuals and sensitivities MINPACK asks for, each point from one call of the
    compiled [`jacobian_at`][] program (MINPACK asks for the Jacobian at a point whose
    residuals it has just had). It keeps the best point seen (as optimistix's
    `BestSoFarLeastSquares`) and decides when to stop, in the data's units when the
    residuals' noise level `noise` (sigma) is known:

    - converged: the Gauss-Newton step predicts a cost decrease below
      [`DECREASE_FRACTION`][] `sigma^2` and moves no coordinate by more than
      [`STEP_FRACTION`][] of its standard error (or, whatever the noise, the step is below
      `tol + tol |z|` in every coordinate);
    - stalled: the best cost has fallen by less than [`STALL_DECREASE`][] `sigma^2` over
      the last [`STALL_STEPS`][] iterations (LM crawling along a curved valley or a ridge,
      the direction named from the Gauss-Newton step); without a noise level, by less
      than `0.01` of the rms residual's square;
    - the iteration budget spent.

    A stall is convergence only where the fit explains the record: at an rms residual
    within `stall_rms` (the fit passes [`FAR_FROM_NOISE`][] times the record's noise
    level; None: anywhere). Above it, the cost has stopped falling without the
    Gauss-Newton test being met: a local minimum (a bound held, a slipped turn) or a
    model that cannot follow the record, reported as a stall, not as convergence."""

    def __init__(self, model, max_steps: int, tol: float, bar,
                 stall_rms: float | None = None, noise: float | None = None,
                 at_bounds: bool = False):
        self.model, self.max_steps, self.tol, self.bar = model, max_steps, tol, bar
        self.stall_rms, self.noise = stall_rms, noise
        self.at_bounds, self.pressing = at_bounds, 0
        self.w = self.r = self.J = None
        self.failed = 0
        self.best_w, self.best_cost, self.best_failed = None, math.inf, 0
        self.history = [math.inf] * (STALL_STEPS + 1)
        self.iterations = 0
        self.last = termination("budget", "")  # how it ended, set by each stop

    def _at(self, w: np.ndarray) -> None:
        if self.w is not None and np.array_equal(w, self.w):
            return
        z = np.asarray(self.model.lift(w))
        if not np.all(np.isfinite(z)):
            # Outside the view's valid set (a value in log space stepped to or below 0):
            # a failed point, every sample, with no solve.
            if self.r is None:
                raise ValueError("the optimisation's start is outside its view's valid set")
            n = self.r.shape[0]
            self.w, self.r, self.failed = np.array(w), np.full(n, 1e3), n
            self.J = np.zeros((n, np.asarray(w).shape[0]))
            return
        r, failed, _, J = jacobian_at(self.model.problem, device_array(z))
        # A failed solve's samples are residuals of 10 rad already (problem.py); anything
        # non-finite left must not reach MINPACK, which has no test for it.
        r = np.nan_to_num(np.asarray(r), nan=1e3, posinf=1e3, neginf=-1e3)
        self.w, self.r, self.failed = np.array(w), r, int(failed)
        self.J = np.nan_to_num(self.model.restrict(np.asarray(J), w), nan=0.0, posinf=0.0,
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

    def _unit(self, n: int) -> tuple[float, str]:
        """The unit of cost the tests and messages use: `sigma^2` when the noise level is
        known, else the rms residual's square at the best point."""
        if self.noise:
            return self.noise**2, "sigma^2"
        return max(2.0 * self.best_cost / max(n, 1), 1e-300), "rms^2"

    def jacobian(self, w):
        # MINPACK asks for the Jacobian once per iteration, at the accepted point.
        self._at(w)
        self.iterations += 1
        self.history = self.history[1:] + [self.best_cost]
        self.bar.n = self.iterations
        self.bar.set_postfix(cost=f"{self.best_cost:.4g}", refresh=True)
        if self.failed:
            stop = self._failed_stop()
        else:
            # Converged when the Gauss-Newton step, the distance to the minimum the
            # linearisation predicts, is small in the data's units: its predicted cost
            # decrease a small fraction of sigma^2 (a chi-squared change far below 1) and
            # every coordinate's move a small fraction of its standard error (with both at
            # the same sigma, the first bounds the second by Cauchy-Schwarz: the second is
            # the one that binds). MINPACK's own tests look at the damped step or the cost
            # change, which are small also where LM crawls with a large damping.
            gn, z = self._step_here()
            stop = (self._converged_stop(gn, z) or self._bound_stop(gn, z)
                    or self._window_stop(gn) or self._budget_stop(gn))
        if stop is not None:
            raise stop
        return self.J

    def _step_here(self) -> tuple[Step, np.ndarray]:
        """The Gauss-Newton step at the current point (standard errors at the noise level,
        or at the rms residual without one) and the point in the problem's coordinates."""
        unit = self._unit(self.r.shape[0])[0]
        gn = gauss_newton(self.model, self.w, self.r, self.J, math.sqrt(unit))
        return gn, np.asarray(self.model.lift(self.w))

    def _converged(self, words: str, gn: Step, fell: float | None) -> _Stop:
        """The stop of a converged run, `words` its verdict in words."""
        unit = self._unit(self.r.shape[0])[0]
        return _Stop(True, "converged", termination(
            "converged", words, predicted_decrease=gn.decrease / unit,
            largest_step=gn.largest,
            falling_per_iteration=None if fell is None else fell / unit, noise=self.noise))

    def _fell(self) -> float:
        """The best cost's fall per iteration over the stall window (or the iterations so
        far; inf before the second)."""
        seen = [c for c in self.history if math.isfinite(c)]
        return (seen[0] - seen[-1]) / (len(seen) - 1) if len(seen) > 1 else math.inf

    def _failed_stop(self) -> _Stop | None:
        """A point with failed samples: its residuals are a constant, so its Jacobian rows
        are zero and the tests would see no slope and call that convergence. With nothing
        left to move (every row failed, or no change over the stall window), or the budget
        spent, the run stops as a failure."""
        h = self.history
        if not np.any(self.J) or (math.isfinite(h[0]) and h[0] - h[-1] <= 0.0):
            return _Stop(False, failed_message(self.failed))
        if self.iterations > self.max_steps:
            self.iterations = self.max_steps
            return _Stop(False, failed_message(self.failed))
        return None

    def _converged_stop(self, gn: Step, z: np.ndarray) -> _Stop | None:
        """Converged in the data's units (see `jacobian`), or, whatever the noise, the
        step below `tol + tol |z|` in every coordinate of the problem (`z`, not the
        view's `w`: a subspace's `w` is the offset from its start, near 0), for records
        with no noise."""
        unit, uname = self._unit(self.r.shape[0])
        in_units = (self.noise is not None and gn.decrease <= DECREASE_FRACTION * unit
                    and gn.largest <= STEP_FRACTION)
        if not (in_units or np.all(np.abs(gn.dz) <= self.tol + self.tol * np.abs(z))):
            return None
        return self._converged(f"converged: the Gauss-Newton step predicts a cost decrease "
                               f"of {gn.decrease / unit:.2g} {uname} and moves no coordinate "
                               f"by more than {gn.largest:.2g} of its standard error", gn,
                               self._fell())

    def _bound_stop(self, gn: Step, z: np.ndarray) -> _Stop | None:
        """With `at_bounds`: the stop of a run whose folded parameter has sat at its bound
        for [`BOUND_STEPS`][] iterations (see `_at_bound`)."""
        if not self.at_bounds:
            return None
        pressed = self._pressed(z)
        self.pressing = self.pressing + 1 if pressed else 0
        if self.pressing < BOUND_STEPS:
            return None
        return self._at_bound(pressed, gn, self._fell())

    def _window_stop(self, gn: Step) -> _Stop | None:
        """The stall window: a run whose best cost has fallen by less than
        [`STALL_DECREASE`][] `sigma^2` over [`STALL_STEPS`][] iterations (without a noise
        level, by less than 0.01 of the rms residual's square) has converged where the
        linearisation promises no more than that either, and has stalled otherwise."""
        h, n = self.history, self.r.shape[0]
        unit, uname = self._unit(n)
        if not (math.isfinite(h[0]) and (h[0] - h[-1] <= STALL_DECREASE * unit if self.noise
                                         else h[0] - h[-1] <= 0.02 * h[-1] / n)):
            return None
        if self.noise and gn.decrease <= STALL_DECREASE * unit:
            # At rest at a minimum, as `at_end` judges MINPACK's own stop (the friction
            # stand-in's run released from its bound ended at the best minimum "stalled"
            # with 1.4e-4 sigma^2 left to gain, and the fit reported a worse point that
            # had converged).
            return self._converged(
                f"converged: the cost fell by {(h[0] - h[-1]) / unit:.2g} {uname} over the "
                f"last {STALL_STEPS} iterations and the Gauss-Newton step predicts "
                f"{gn.decrease / unit:.2g} {uname} more, moving no coordinate by more than "
                f"{gn.largest:.2g} of its standard error", gn, self._fell())
        return self._stalled(gn, h[0] - h[-1], STALL_STEPS)

    def _budget_stop(self, gn: Step) -> _Stop | None:
        """The iteration budget spent, with how fast the cost still falls."""
        if self.iterations <= self.max_steps:
            return None
        self.iterations = self.max_steps
        unit, uname = self._unit(self.r.shape[0])
        fell = self._fell()
        per = fell / unit if math.isfinite(fell) else None
        message = budget_spent(self.max_steps, per, uname)
        return _Stop(False, message, termination(
            "budget", "budget spent: " + message, predicted_decrease=gn.decrease / unit,
            largest_step=gn.largest, falling_per_iteration=per, noise=self.noise))

    def _pressed(self, z: np.ndarray) -> list[str]:
        """The folded parameters (`value = ref |z|`, see `problem.folded`) at their bound 0
        (within [`AT_ZERO`][] of it) that the view can move."""
        pr = self.model.problem
        at0 = [i for i, f in enumerate(getattr(pr, "folded", ())) if f and abs(z[i]) < AT_ZERO]
        if not at0:
            return []
        # (Not those the view holds, at their bound on purpose: rows of `dz/dw` at 0.)
        moves = np.linalg.norm(self.model.restrict(np.eye(z.shape[0]), self.w), axis=1) > 1e-9
        return [pr.names[i] for i in at0 if moves[i]]

    def _at_bound(self, pressed: list[str], gn: Step, fell: float) -> _Stop:
        """The stop of a run that has sat on a bound for [`BOUND_STEPS`][] iterations,
        short of the Gauss-Newton test. The cost has a kink there in the folded
        coordinate: LM's steps across it are reflected, its damping grows, and it crawls
        along the kink (experiments/misfit_rig.py, case `friction`: 30-100 iterations
        each time, the cost falling by less than 0.01 sigma^2 an iteration while the
        Gauss-Newton step predicts thousands). The caller holds those parameters at 0 and
        finishes the others, then releases them where the cost falls into the feasible
        side (`attempt.off_the_bound`), as an active-set method does."""
        unit, uname = self._unit(self.r.shape[0])
        along = " and ".join(pressed)
        words = (f"stalled at a bound: {along} stayed at 0 for {BOUND_STEPS} iterations "
                 f"while the Gauss-Newton step predicts {gn.decrease / unit:.3g} {uname} "
                 "more; to be held there while the others are fitted")
        return _Stop(False, f"stalled at the bound {along} = 0", termination(
            "stalled", words, predicted_decrease=gn.decrease / unit,
            largest_step=gn.largest, falling_per_iteration=fell / unit,
            direction=f"{along} at its bound 0", noise=self.noise))

    def _stalled(self, gn: Step, fell: float, steps: int) -> _Stop:
        """The stop of a run whose cost fell by only `fell` over its last `steps`
        iterations while the Gauss-Newton step `gn` predicts more: along the direction
        of that step (a curved valley or a ridge)."""
        n = self.r.shape[0]
        unit, uname = self._unit(n)
        converged, message = self._stall(self.best_cost, n)
        along = direction(getattr(self.model.problem, "names", ()), gn.dz, gn.se)
        words = (f"stalled along {along}: the cost fell by {fell / unit:.2g} {uname} over "
                 f"the last {steps} iterations while the linearization predicts "
                 f"{gn.decrease / unit:.3g} {uname} more (a curved valley or a ridge in "
                 "that combination)")
        return _Stop(converged, message, termination(
            "stalled", words, predicted_decrease=gn.decrease / unit,
            largest_step=gn.largest, falling_per_iteration=fell / steps / unit,
            direction=along, noise=self.noise))

    def at_end(self) -> _Stop:
        """The verdict where MINPACK stopped by itself (no further progress at machine
        precision), by the same tests at the best point: converged where the Gauss-Newton
        step is small in the data's units (or relative to `tol`), else a stall."""
        self._at(self.best_w)
        unit, uname = self._unit(self.r.shape[0])
        gn, z = self._step_here()
        # MINPACK found no step that lowers the cost at machine precision (the solve's
        # own rounding, near a minimum). What the linearisation still promises counts as
        # nothing when it is below what the stall test would notice.
        if (gn.decrease <= (STALL_DECREASE if self.noise else DECREASE_FRACTION) * unit
                or np.all(np.abs(gn.dz) <= self.tol + self.tol * np.abs(z))):
            return self._converged(
                "converged: no further progress at machine precision, the Gauss-Newton "
                f"step predicting a cost decrease of {gn.decrease / unit:.2g} {uname} and "
                f"moving no coordinate by more than {gn.largest:.2g} of its standard error",
                gn, None)
        seen = [c for c in self.history if math.isfinite(c)]
        return self._stalled(gn, seen[0] - seen[-1] if seen else 0.0, max(len(seen) - 1, 1))

    def _stall(self, cost: float, n: int) -> tuple[bool, str]:
        """(converged, message) of a run whose best cost has stopped falling."""
        rms = math.sqrt(2.0 * cost / max(n, 1))
        if self.stall_rms is None or rms <= self.stall_rms:
            return True, "converged"
        return False, stalled_message(rms, self.stall_rms / FAR_FROM_NOISE)


def least_squares(model, z0: np.ndarray, max_steps: int, tol: float, desc: str,
                  progress: bool, stall_rms: float | None = None,
                  noise: float | None = None, at_bounds: bool = False) -> Run:
    """Levenberg-Marquardt on a residual view `model` (a [`Subspace`][] or [`Pinned`][]
    problem) from `z0`, with a progress bar per iteration.

    MINPACK's `lmder` (through `scipy.optimize.least_squares(method="lm")`, Marquardt's
    scaling of the coordinates) drives the iterations on the host; each point costs one
    call of the compiled residuals-and-sensitivities program, which the fit needs at its
    start and at its estimate anyway. A compiled optimistix LM loop was tried first: its
    program holds the residual solve and its linearisation inside optimistix's loop and
    compiled slowly per problem shape, more than half of a cold `crank-jax fit`
    (experiments/bench_end_to_end.py; docs/benchmarks/design-figures.md, Start-up); each
    iteration costs the same solves either way.

    The point reported is the best one seen: the lowest cost among points whose solves
    all succeed (a failed solve's samples count as residuals of 10 rad, a stand-in, not a
    misfit). A run whose best point still has failed samples is never `converged`, and
    its cost is NaN. `stall_rms`: the rms residual above which a stall is not
    convergence (see `_Evaluations`; None: a stall is convergence anywhere); `noise`:
    the residuals' noise level, in which the termination tests are judged (None: only
    the relative step test and a stall relative to the rms residual); `at_bounds`: stop,
    as a stall, once a folded parameter has sat at its bound 0 for [`BOUND_STEPS`][]
    iterations without converging (for a caller that then holds it there). The
    run's `termination` says how it ended."""
    from scipy.optimize import least_squares as minpack_lm

    z0 = np.asarray(z0, dtype=float)
    with progress_bar(max_steps, desc, progress) as bar:
        ev = _Evaluations(model, max_steps, tol, bar, stall_rms, noise, at_bounds)
        # MINPACK's own tests at machine precision: they stop it only where it can make
        # no further progress; the tests that decide are `_Evaluations.jacobian`'s. (Not
        # below it: MINPACK's "tolerance too small" outcomes have no status in scipy.)
        eps = float(np.finfo(float).eps)
        try:
            sol = minpack_lm(ev.residuals, z0, jac=ev.jacobian, method="lm", x_scale="jac",
                             ftol=eps, xtol=eps, gtol=eps, max_nfev=100 * (max_steps + 1))
            if sol.status > 0 and ev.best_w is not None and not ev.best_failed:
                raise ev.at_end()
            converged = sol.status > 0
            message = "converged" if converged else (
                budget_spent(max_steps) if sol.status == 0
                else "Levenberg-Marquardt failed: " + sol.message)
            term = termination(
                "converged" if converged else "budget" if sol.status == 0 else "failed",
                message, noise=noise)
        except _Stop as stop:
            converged, message, term = stop.converged, stop.message, stop.term
    if ev.best_w is None or not np.all(np.isfinite(ev.best_w)):
        message = "the iterates became non-finite"
        return Run(z0, float("nan"), ev.iterations, False, message,
                   termination("failed", message, noise=noise))
    if ev.best_failed:
        # Never "converged" where the solve fails, and no cost: the stand-ins are no
        # misfit, so such a run never ranks above one whose solves succeed.
        message = failed_message(ev.best_failed)
        return Run(ev.best_w, float("nan"), ev.iterations, False, message,
                   termination("failed", message, noise=noise))
    return Run(ev.best_w, ev.best_cost, ev.iterations, converged, message, term)
