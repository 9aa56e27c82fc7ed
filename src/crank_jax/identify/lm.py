"""Levenberg-Marquardt as optimistix runs it, with a statistical stopping test: the one
module of the fit that imports optimistix (imported when a fit's program is traced, not
when a stored one runs: optimistix, lineax and diffrax take ~0.3 s to import).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array

from ..persistent import enum_code

__all__ = ["StallTest", "lm_chunk_fn", "outcome_message"]

class _StallState(eqx.Module):
    history: Array  # (window + 1,) best cost after each of the last steps
    n: Array  # number of residuals
    inner: Any


def _with_residual(fn, y, args):
    out, aux = fn(y, args)
    return out, (out, aux)


class StallTest(optx.AbstractLeastSquaresSolver):
    """Wraps a least-squares solver with a statistical stopping test.

    Besides the wrapped solver's own test on the step and residual changes, stop when the
    best cost has fallen by less than `0.01 sigma^2` over the last `window` steps
    (with `sigma^2 ~ 2 cost / n`): LM can crawl for hundreds of steps along a weakly
    determined valley while moving the estimate by a tiny fraction of its confidence
    region. `options["cost_history"]` carries the history from one call to the next.
    """

    solver: optx.AbstractLeastSquaresSolver
    window: int = eqx.field(static=True, default=8)

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
        history = options.get("cost_history", jnp.full(self.window + 1, jnp.inf))
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


def outcome_message(name: str) -> str:
    """optimistix's message for the outcome `name` (a name of `optx.RESULTS`)."""
    item = getattr(optx.RESULTS, name, None)
    return optx.RESULTS[item] if item is not None else "an unexpected outcome"


def lm_chunk_fn(model, z, history, tol, chunk, outcomes):
    """`chunk` LM iterations from `z`: `(z, outcome index in outcomes, steps, history)`."""
    lm = optx.BestSoFarLeastSquares(optx.LevenbergMarquardt(rtol=tol, atol=tol))
    solver = StallTest(lm, window=history.shape[0] - 1)
    sol = optx.least_squares(_call, solver, z, args=model,
                             options={"cost_history": history}, max_steps=chunk,
                             throw=False)
    code = enum_code(sol.result, optx.RESULTS, outcomes)
    return sol.value, code, sol.stats["num_steps"], sol.state.history
