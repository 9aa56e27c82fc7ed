"""Levenberg-Marquardt (MINPACK, through scipy, on the host: progress after every
iteration) over the compiled residuals-and-sensitivities program `jacobian_at` (no host
callback, so the persistent cache keeps it), its stop tests judged in the data's units
(the optax method: [`optax_fit`][crank_jax.identify.optax_fit]).
"""

from __future__ import annotations

import math

import numpy as np

from ..runtime.arrays import device_array
from ..runtime.progress import progress_bar
from .gauss_newton import Step, direction, gauss_newton
from .outcome import NON_FINITE, Run, budget_spent, failed_message, stalled_message, termination
from .programs import jacobian_at, residuals_at
from .strategy import AT_ZERO, FAR_FROM_NOISE

__all__ = ["least_squares", "evaluate", "STALL_STEPS",
           "DECREASE_FRACTION", "STEP_FRACTION", "STALL_DECREASE", "BOUND_STEPS"]

#: The stall test looks this many iterations back.
STALL_STEPS = 8
#: Converged when the Gauss-Newton step predicts a cost decrease below this many
#: `sigma^2` (the cost of a change of 2 in chi-squared) ...
DECREASE_FRACTION = 1e-4
#: ... and moves no coordinate by more than this fraction of its standard error at the
#: noise level (not the misfit's: the stricter).
STEP_FRACTION = 1e-2
#: A stall: the best cost has fallen by less than this many `sigma^2` over the last
#: [`STALL_STEPS`][] iterations while the linearisation still predicts more.
STALL_DECREASE = 1e-2
#: With `at_bounds`, a run stops once a folded parameter has sat at its bound 0 (within
#: `AT_ZERO`) this many iterations in a row.
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
    compiled [`jacobian_at`][] program; it keeps the best point seen (as optimistix's
    `BestSoFarLeastSquares`) and holds the stop tests, judged in `sigma^2`, `sigma` the
    residuals' noise level `noise` (without one, in the rms residual's square):
    converged (the Gauss-Newton test, see [`DECREASE_FRACTION`][]), stalled (see
    [`STALL_DECREASE`][]), at a bound ([`BOUND_STEPS`][]) or the budget spent.

    A stall is convergence only at an rms residual within `stall_rms` (the fit passes
    [`FAR_FROM_NOISE`][] times the record's noise level; None: anywhere). Above it the
    cost stopped falling short of the Gauss-Newton test: a local minimum (a bound held, a
    slipped turn) or a model that cannot follow the record."""

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

    @property
    def unit(self) -> tuple[float, str]:
        """The unit of cost of the tests and messages: `sigma^2`, or without a noise
        level the rms residual's square at the best point."""
        if self.noise:
            return self.noise**2, "sigma^2"
        return max(2.0 * self.best_cost / max(self.r.shape[0], 1), 1e-300), "rms^2"

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
            # MINPACK's own tests look at the damped step or the cost change, which are
            # small also where LM crawls with a large damping: these look at the
            # Gauss-Newton step, the distance to the minimum the linearisation predicts.
            gn, z = self._step_here()
            stop = (self._converged_stop(gn, z) or self._bound_stop(gn, z)
                    or self._window_stop(gn) or self._budget_stop(gn))
        if stop is not None:
            raise stop
        return self.J

    def _step_here(self) -> tuple[Step, np.ndarray]:
        """The Gauss-Newton step at the current point (standard errors at `sqrt(unit)`)
        and the point in the problem's coordinates."""
        gn = gauss_newton(self.model, self.w, self.r, self.J, math.sqrt(self.unit[0]))
        return gn, np.asarray(self.model.lift(self.w))

    def _small(self, gn: Step, z: np.ndarray) -> bool:
        """The step below `tol + tol |z|` in every coordinate of the problem (`z`, not the
        view's `w`: a subspace's `w` is the offset from its start, near 0)."""
        return bool(np.all(np.abs(gn.dz) <= self.tol + self.tol * np.abs(z)))

    def _term(self, verdict: str, words: str, gn: Step, fell: float | None,
              direction: str | None = None) -> dict:
        """The termination record at the Gauss-Newton step `gn`, `fell` the cost's fall
        per iteration (in cost; inf or None: unknown)."""
        unit = self.unit[0]
        return termination(verdict, words, predicted_decrease=gn.decrease / unit,
                           largest_step=gn.largest,
                           falling_per_iteration=None if fell is None else fell / unit,
                           direction=direction, noise=self.noise)

    def _converged(self, words: str, gn: Step, fell: float | None) -> _Stop:
        """The stop of a converged run: "converged: `words` no coordinate by more than
        (the step's largest) of its standard error"."""
        words = (f"converged: {words} no coordinate by more than {gn.largest:.2g} of its "
                 "standard error")
        return _Stop(True, "converged", self._term("converged", words, gn, fell))

    def _fell(self) -> float:
        """The best cost's fall per iteration over the stall window (or the iterations so
        far; inf before the second)."""
        seen = [c for c in self.history if math.isfinite(c)]
        return (seen[0] - seen[-1]) / (len(seen) - 1) if len(seen) > 1 else math.inf

    def _failed_stop(self) -> _Stop | None:
        """A point with failed samples has constant residuals, zero Jacobian rows: the
        tests would call it converged. With nothing left to move (every row failed, or no
        change over the stall window), or the budget spent, the run fails."""
        h = self.history
        if not np.any(self.J) or (math.isfinite(h[0]) and h[0] - h[-1] <= 0.0):
            return _Stop(False, failed_message(self.failed))
        if self.iterations > self.max_steps:
            self.iterations = self.max_steps
            return _Stop(False, failed_message(self.failed))
        return None

    def _converged_stop(self, gn: Step, z: np.ndarray) -> _Stop | None:
        """Converged in `sigma^2` (both tests at the same sigma: by Cauchy-Schwarz the
        step's is the one that binds), or, whatever the noise, a step below `tol`."""
        unit, uname = self.unit
        in_units = (self.noise is not None and gn.decrease <= DECREASE_FRACTION * unit
                    and gn.largest <= STEP_FRACTION)
        if not (in_units or self._small(gn, z)):
            return None
        return self._converged(f"the Gauss-Newton step predicts a cost decrease of "
                               f"{gn.decrease / unit:.2g} {uname} and moves", gn, self._fell())

    def _bound_stop(self, gn: Step, z: np.ndarray) -> _Stop | None:
        """With `at_bounds`: a folded parameter has sat at its bound 0 for
        [`BOUND_STEPS`][] iterations short of the Gauss-Newton test. The cost has a kink
        there: LM's steps across it are reflected, its damping grows and it crawls along
        it (experiments/misfit_rig.py, case `friction`). The caller holds those parameters
        at 0, finishes the others, then releases them (`attempt.off_the_bound`)."""
        if not self.at_bounds:
            return None
        pressed = self._pressed(z)
        self.pressing = self.pressing + 1 if pressed else 0
        if self.pressing < BOUND_STEPS:
            return None
        unit, uname = self.unit
        along = " and ".join(pressed)
        words = (f"stalled at a bound: {along} stayed at 0 for {BOUND_STEPS} iterations "
                 f"while the Gauss-Newton step predicts {gn.decrease / unit:.3g} {uname} "
                 "more; to be held there while the others are fitted")
        return _Stop(False, f"stalled at the bound {along} = 0",
                     self._term("stalled", words, gn, self._fell(), f"{along} at its bound 0"))

    def _window_stop(self, gn: Step) -> _Stop | None:
        """The stall window: the best cost fell by less than [`STALL_DECREASE`][]
        `sigma^2` over [`STALL_STEPS`][] iterations (without a noise level, by less than
        0.01 of the rms residual's square): converged where the linearisation promises no
        more than that either (as `at_end` judges MINPACK's own stop), else stalled."""
        h, n = self.history, self.r.shape[0]
        unit, uname = self.unit
        if not (math.isfinite(h[0]) and (h[0] - h[-1] <= STALL_DECREASE * unit if self.noise
                                         else h[0] - h[-1] <= 0.02 * h[-1] / n)):
            return None
        if self.noise and gn.decrease <= STALL_DECREASE * unit:
            return self._converged(
                f"the cost fell by {(h[0] - h[-1]) / unit:.2g} {uname} over the last "
                f"{STALL_STEPS} iterations and the Gauss-Newton step predicts "
                f"{gn.decrease / unit:.2g} {uname} more, moving", gn, self._fell())
        return self._stalled(gn, h[0] - h[-1], STALL_STEPS)

    def _budget_stop(self, gn: Step) -> _Stop | None:
        """The iteration budget spent, with how fast the cost still falls."""
        if self.iterations <= self.max_steps:
            return None
        self.iterations = self.max_steps
        unit, uname = self.unit
        fell = self._fell()
        message = budget_spent(self.max_steps, fell / unit, uname)
        return _Stop(False, message, self._term("budget", "budget spent: " + message, gn, fell))

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

    def _stalled(self, gn: Step, fell: float, steps: int) -> _Stop:
        """The stop of a run whose cost fell by only `fell` over its last `steps`
        iterations while the Gauss-Newton step `gn` predicts more: along that step's
        direction (a curved valley or a ridge). Converged only within `stall_rms`."""
        n = self.r.shape[0]
        unit, uname = self.unit
        rms = math.sqrt(2.0 * self.best_cost / max(n, 1))
        converged = self.stall_rms is None or rms <= self.stall_rms
        message = ("converged" if converged
                   else stalled_message(rms, self.stall_rms / FAR_FROM_NOISE))
        along = direction(getattr(self.model.problem, "names", ()), gn.dz, gn.se)
        words = (f"stalled along {along}: the cost fell by {fell / unit:.2g} {uname} over "
                 f"the last {steps} iterations while the linearization predicts "
                 f"{gn.decrease / unit:.3g} {uname} more (a curved valley or a ridge in "
                 "that combination)")
        return _Stop(converged, message, self._term("stalled", words, gn, fell / steps, along))

    def at_end(self) -> _Stop:
        """The verdict where MINPACK stopped by itself (no further progress at machine
        precision, the solve's own rounding near a minimum), by the same tests at the
        best point: what the linearisation still promises counts as nothing below what
        the stall test would notice."""
        self._at(self.best_w)
        unit, uname = self.unit
        gn, z = self._step_here()
        if (gn.decrease <= (STALL_DECREASE if self.noise else DECREASE_FRACTION) * unit
                or self._small(gn, z)):
            return self._converged(
                "no further progress at machine precision, the Gauss-Newton step predicting "
                f"a cost decrease of {gn.decrease / unit:.2g} {uname} and moving", gn, None)
        seen = [c for c in self.history if math.isfinite(c)]
        return self._stalled(gn, seen[0] - seen[-1] if seen else 0.0, max(len(seen) - 1, 1))


def least_squares(model, z0: np.ndarray, max_steps: int, tol: float, desc: str,
                  progress: bool, stall_rms: float | None = None,
                  noise: float | None = None, at_bounds: bool = False) -> Run:
    """Levenberg-Marquardt on a residual view `model` (a [`Subspace`][] or [`Pinned`][]
    problem) from `z0`, with a progress bar per iteration.

    MINPACK's `lmder` (`scipy.optimize.least_squares(method="lm")`, Marquardt's scaling)
    drives the iterations on the host; each point costs one call of the compiled
    residuals-and-sensitivities program. (A compiled optimistix LM loop compiled slowly
    per problem shape, more than half of a cold `crank-jax fit`:
    docs/benchmarks/design-figures.md, Start-up.)

    The point reported is the best one seen among points whose solves all succeed (a
    failed solve's samples are stand-ins, not a misfit: a run whose best point has
    failed samples is never `converged`, its cost NaN). `stall_rms`: the rms residual
    above which a stall is not convergence (None: none); `noise`: the residuals' noise
    level the tests are judged in (None: the relative step test and a stall relative to
    the rms residual); `at_bounds`: stop, as a stall, once a folded parameter has sat at
    its bound 0 for [`BOUND_STEPS`][] iterations. The run's `termination` says how it
    ended."""
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
        message = NON_FINITE
        return Run(z0, float("nan"), ev.iterations, False, message,
                   termination("failed", message, noise=noise))
    if ev.best_failed:
        # Never "converged" where the solve fails, and no cost: the stand-ins are no
        # misfit, so such a run never ranks above one whose solves succeed.
        message = failed_message(ev.best_failed)
        return Run(ev.best_w, float("nan"), ev.iterations, False, message,
                   termination("failed", message, noise=noise))
    return Run(ev.best_w, ev.best_cost, ev.iterations, converged, message, term)
