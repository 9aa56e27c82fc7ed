"""The optax method of a fit (`method="optax"`): Adam, then L-BFGS, on the sum of squares
with reverse-mode gradients (one backward solve, whatever the number of coordinates), for
large problems; [`optimize`][crank_jax.identify.optimize] holds Levenberg-Marquardt."""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..runtime.lazy import lazy_import
from ..runtime.progress import progress_bar
from .optimize import evaluate
from .outcome import FAILS_AT_END, FAILS_AT_START, NON_FINITE, Run, budget_spent

# Imported on first use (see lazy.py): only the optax method needs it.
optax = lazy_import("optax")

__all__ = ["minimize_optax"]


def _outcome(model, z0, cost0, z, it, done, max_steps) -> Run:
    cost, failed = evaluate(model, z)
    zn = np.asarray(z)
    if not np.all(np.isfinite(zn)):
        return Run(np.asarray(z0), float(cost0), it, False, NON_FINITE)
    if failed > 0:
        return Run(zn, cost, it, False, FAILS_AT_END)
    if not done:
        return Run(zn, float(cost), it, False, budget_spent(max_steps))
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


def minimize_optax(model, z0: np.ndarray, max_steps: int, tol: float, desc: str,
                   progress: bool) -> Run:
    """Adam (a robust first phase far from the optimum), then L-BFGS, on 0.5 |r|^2, with
    reverse-mode gradients (the model must use the reverse adjoint)."""
    cost0, failed0 = evaluate(model, jnp.asarray(z0))
    if failed0 > 0 or not np.isfinite(cost0):
        return Run(np.asarray(z0), float("nan"), 0, False, FAILS_AT_START)
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
