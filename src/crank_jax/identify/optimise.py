"""The optimisers: Levenberg-Marquardt through `optimistix.least_squares`, and optax.

LM runs as `optx.least_squares(fn, StallTest(BestSoFarLeastSquares(LevenbergMarquardt)),
..., throw=False)`: optimistix's own loop, extended by wrapping its solver (as optimistix
extends its solvers) rather than by copying the loop. The compiled program has no host
callback, so JAX's persistent cache keeps it between processes; progress is shown
between compiled chunks of [`CHUNK`][] iterations instead.
"""

from __future__ import annotations

import math
import sys
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
from jaxtyping import Array

from .programs import Program, residuals_at

__all__ = ["Run", "StallTest", "least_squares", "minimise_optax", "evaluate", "CHUNK",
           "STALL_STEPS", "progress_bar", "lm_chunk"]

#: LM iterations per compiled call; progress is reported between calls.
CHUNK = 16
#: The stall test looks this many iterations back.
STALL_STEPS = 8


class Run(NamedTuple):
    """One optimisation: final coordinates, cost `0.5 |r|^2`, iterations, outcome."""

    z: np.ndarray
    cost: float
    iterations: int
    converged: bool
    message: str


def progress_bar(total: int, desc: str, progress: bool):
    """A tqdm bar on stderr (disabled when not `progress`)."""
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, file=sys.stderr, disable=not progress, leave=False,
                dynamic_ncols=True)


def evaluate(problem, z) -> tuple[float, int]:
    """(0.5 |r|^2, number of failed samples) at `z`."""
    r, failed, _ = residuals_at(problem, jnp.asarray(z))
    r = np.asarray(r)
    return 0.5 * float(r @ r), int(failed)


class _StallState(eqx.Module):
    history: Array  # (STALL_STEPS + 1,) best cost after each of the last steps
    n: Array  # number of residuals
    inner: Any


def _with_residual(fn, y, args):
    out, aux = fn(y, args)
    return out, (out, aux)


class StallTest(optx.AbstractLeastSquaresSolver):
    """Wraps a least-squares solver with a statistical stopping test.

    Besides the wrapped solver's own test on the step and residual changes, stop when the
    best cost has fallen by less than `0.01 sigma^2` over the last `STALL_STEPS` steps
    (with `sigma^2 ~ 2 cost / n`): LM can crawl for hundreds of steps along a weakly
    determined valley while moving the estimate by a tiny fraction of its confidence
    region. `options["cost_history"]` carries the history from one call to the next.
    """

    solver: optx.AbstractLeastSquaresSolver

    @property
    def rtol(self):
        return self.solver.rtol

    @property
    def atol(self):
        return self.solver.atol

    @property
    def norm(self):
        return self.solver.norm

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        wrapped = eqx.Partial(_with_residual, fn)
        inner = self.solver.init(wrapped, y, args, options, f_struct, (f_struct, aux_struct),
                                 tags)
        history = options.get("cost_history", jnp.full(STALL_STEPS + 1, jnp.inf))
        n = jnp.asarray(sum(x.size for x in jax.tree_util.tree_leaves(f_struct)), float)
        return _StallState(jnp.asarray(history, float), n, inner)

    def step(self, fn, y, args, options, state, tags):
        wrapped = eqx.Partial(_with_residual, fn)
        y, inner, (f, aux) = self.solver.step(wrapped, y, args, options, state.inner, tags)
        cost = 0.5 * sum(jnp.sum(x**2) for x in jax.tree_util.tree_leaves(f))
        best = jnp.minimum(cost, state.history[-1])
        history = jnp.roll(state.history, -1).at[-1].set(best)
        return y, _StallState(history, state.n, inner), aux

    def terminate(self, fn, y, args, options, state, tags):
        wrapped = eqx.Partial(_with_residual, fn)
        done, result = self.solver.terminate(wrapped, y, args, options, state.inner, tags)
        h = state.history
        stalled = jnp.isfinite(h[0]) & (h[0] - h[-1] <= 0.02 * h[-1] / state.n)
        return done | stalled, optx.RESULTS.where(stalled & ~done, optx.RESULTS.successful,
                                                  result)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        wrapped = eqx.Partial(_with_residual, fn)
        y, _, stats = self.solver.postprocess(wrapped, y, (None, aux), args, options,
                                              state.inner, tags, result)
        return y, aux, stats


def _call(w, model):
    return model(w, None)[0]


def _lm_chunk_fn(model, z, history, tol, chunk):
    solver = StallTest(optx.BestSoFarLeastSquares(optx.LevenbergMarquardt(rtol=tol, atol=tol)))
    sol = optx.least_squares(_call, solver, z, args=model,
                             options={"cost_history": history}, max_steps=chunk,
                             throw=False)
    return sol.value, sol.result, sol.stats["num_steps"], sol.state.history


#: One compiled chunk of LM iterations: `(model, z, history, tol, chunk) -> (z, result,
#: steps, history)`.
lm_chunk = Program(eqx.filter_jit(_lm_chunk_fn))


def least_squares(model, z0: np.ndarray, max_steps: int, tol: float, desc: str,
                  progress: bool) -> Run:
    """Levenberg-Marquardt on `model(z) -> (r, None)` (a residual module, e.g. a
    [`Subspace`][] of a problem), in compiled chunks with a progress bar between them.

    The cost reported is the best one seen (a failed solve's samples count as residuals
    of 10 rad, so a point where the solve fails never wins)."""
    z = jnp.asarray(z0)
    history = jnp.full(STALL_STEPS + 1, jnp.inf)
    it, done, result = 0, False, optx.RESULTS.successful
    with progress_bar(max_steps, desc, progress) as bar:
        while it < max_steps and not done:
            chunk = min(CHUNK, max_steps - it)
            z, result, steps, history = lm_chunk(model, z, history, tol, chunk)
            it += int(steps)
            done = result != optx.RESULTS.nonlinear_max_steps_reached
            bar.n = it
            bar.set_postfix(cost=f"{float(history[-1]):.4g}", refresh=True)
    zn, cost = np.asarray(z), float(history[-1])
    if not np.all(np.isfinite(zn)):
        return Run(np.asarray(z0), float("nan"), it, False, "the iterates became non-finite")
    if not done:
        return Run(zn, cost, it, False,
                   f"stopped after max_steps = {max_steps} iterations without converging")
    if result != optx.RESULTS.successful:
        return Run(zn, cost, it, False, "Levenberg-Marquardt failed: " + optx.RESULTS[result])
    return Run(zn, cost, it, True, "converged")


def _outcome(model, z0, cost0, z, it, done, result, max_steps) -> Run:
    cost, failed = evaluate(model, z)
    zn = np.asarray(z)
    if not np.all(np.isfinite(zn)):
        return Run(np.asarray(z0), float(cost0), it, False, "the iterates became non-finite")
    if failed > 0:
        return Run(zn, cost, it, False, "the ODE solve fails at the final estimate")
    if not done:
        return Run(zn, float(cost), it, False,
                   f"stopped after max_steps = {max_steps} iterations without converging")
    if result != optx.RESULTS.successful:
        return Run(zn, float(cost), it, False, "Levenberg-Marquardt failed: "
                   + optx.RESULTS[result])
    return Run(zn, float(cost), it, True, "converged")


def _loss(z, model):
    r = model.residuals(z)[0]
    return 0.5 * jnp.sum(r * r)


# Module-level (immutable) optimisers: optax transformations made per fit would be new
# static objects, and every fit would recompile.
_ADAM = optax.adam(0.02)
_LBFGS = optax.lbfgs()


@eqx.filter_jit
def _adam_step(z, st, model):
    v, g = jax.value_and_grad(_loss)(z, model)
    u, st = _ADAM.update(g, st, z)
    return optax.apply_updates(z, u), st, v


@eqx.filter_jit
def _lbfgs_step(z, st, model):
    def f(x):
        return _loss(x, model)

    v, g = optax.value_and_grad_from_state(f)(z, state=st)
    u, st = _LBFGS.update(g, st, z, value=v, grad=g, value_fn=f)
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
        st = _ADAM.init(z)
        for _ in range(max_steps // 4):
            z, st, v = _adam_step(z, st, model)
            it += 1
            bar.update(1)
        st = _LBFGS.init(z)
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
    return _outcome(model, z0, cost0, z, it, converged, optx.RESULTS.successful, max_steps)
