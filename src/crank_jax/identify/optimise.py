"""The optimisers: Levenberg-Marquardt through `optimistix.least_squares`, and optax.

LM runs as `optx.least_squares(fn, StallTest(BestSoFarLeastSquares(LevenbergMarquardt)),
..., throw=False)` (`lm.py`): optimistix's own loop, extended by wrapping its solver (as optimistix
extends its solvers) rather than by copying the loop. The compiled program has no host
callback, so JAX's persistent cache keeps it between processes; progress is shown
between compiled chunks of [`CHUNK`][] iterations instead.
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
from ..persistent import enum_name
from .programs import Program, residuals_at

# Imported on first use (see lazy.py): a warm fit runs stored programs and needs neither.
optax = lazy_import("optax")
optx = lazy_import("optimistix")

__all__ = ["Run", "least_squares", "minimise_optax", "evaluate", "CHUNK",
           "STALL_STEPS", "progress_bar", "lm_chunk"]

#: LM iterations per compiled call; progress is reported between calls.
CHUNK = 16
#: The stall test looks this many iterations back (see `lm.StallTest`).
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


#: The outcomes a chunk reports by index (names of `optx.RESULTS`).
OUTCOMES = ("successful", "nonlinear_max_steps_reached", "nonlinear_divergence",
            "singular", "breakdown")


def _lm_chunk_fn(model, z, history, tol, chunk):
    from .lm import lm_chunk_fn  # optimistix: only while tracing

    return lm_chunk_fn(model, z, history, tol, chunk, OUTCOMES)


#: One compiled chunk of LM iterations: `(model, z, history, tol, chunk) -> (z, outcome
#: index, steps, history)`.
lm_chunk = Program(_lm_chunk_fn, "lm_chunk")


def least_squares(model, z0: np.ndarray, max_steps: int, tol: float, desc: str,
                  progress: bool) -> Run:
    """Levenberg-Marquardt on `model(z) -> (r, None)` (a residual module, e.g. a
    [`Subspace`][] of a problem), in compiled chunks with a progress bar between them.

    The cost reported is the best one seen (a failed solve's samples count as residuals
    of 10 rad, so a point where the solve fails never wins)."""
    z = jnp.asarray(z0)
    history = jnp.full(STALL_STEPS + 1, jnp.inf)
    it, done, result = 0, False, "successful"
    with progress_bar(max_steps, desc, progress) as bar:
        while it < max_steps and not done:
            chunk = min(CHUNK, max_steps - it)
            z, code, steps, history = lm_chunk(model, z, history, tol, chunk)
            it += int(steps)
            result = enum_name(code, OUTCOMES) or "unknown"
            done = result != "nonlinear_max_steps_reached"
            bar.n = it
            bar.set_postfix(cost=f"{float(history[-1]):.4g}", refresh=True)
    zn, cost = np.asarray(z), float(history[-1])
    if not np.all(np.isfinite(zn)):
        return Run(np.asarray(z0), float("nan"), it, False, "the iterates became non-finite")
    if not done:
        return Run(zn, cost, it, False,
                   f"stopped after max_steps = {max_steps} iterations without converging")
    if result != "successful":
        from .lm import outcome_message

        why = outcome_message(result)
        return Run(zn, cost, it, False, "Levenberg-Marquardt failed: " + why)
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
    return _outcome(model, z0, cost0, z, it, converged, optx.RESULTS.successful, max_steps)
