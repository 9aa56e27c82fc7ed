"""NUTS (blackjax) on the posterior's log density, with Stan's window warm-up, run in
chunks of compiled steps so that a progress bar follows warm-up and sampling.

The log density is that of [`posterior`][crank_jax.bayes.posterior]: the fit's
residual program, the noise level integrated out, the priors; sampled in coordinates
whitened by the Laplace covariance.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..identify.problem import Problem
from ..runtime.lazy import lazy_import
from ..runtime.progress import progress_bar
from .priors import log_prior

blackjax = lazy_import("blackjax")  # imported on first use (see lazy.py)

__all__ = ["log_density", "adaptation", "schedule", "initial_carry", "run_chains", "CHUNK"]

# Steps of NUTS per compiled chunk: the progress bar moves once per chunk.
CHUNK = 50


def _record_rows(problem: Problem) -> tuple[tuple[int, int, int], ...]:
    """(first row, rows, fitted samples) of each record's block of the residual vector
    (the count traced: the padded weights are arrays)."""
    out, k = [], 0
    for e in problem.exps:
        size = int(np.prod(e.seg.ts.shape))
        out.append((k, size, jnp.sum(e.seg.w > 0)))
        k += size
    return tuple(out)


def _loglik_and_grad(problem: Problem, z):
    """Marginal log likelihood (sigma integrated out per record) and its gradient, with
    the sensitivities by forward mode through the solve."""
    def f(x):
        r, failed, _ = problem.residuals(x)
        return r, (r, failed)

    J, (r, failed) = jax.jacfwd(f, has_aux=True)(z)
    value, grad = 0.0, jnp.zeros_like(z)
    for first, size, n in _record_rows(problem):
        rk, Jk = r[first:first + size], J[first:first + size]
        rss = jnp.sum(rk**2)
        value = value - 0.5 * n * jnp.log(rss)
        grad = grad - (n / rss) * (Jk.T @ rk)
    ok = (failed == 0) & jnp.isfinite(value)
    return jnp.where(ok, value, -jnp.inf), jnp.where(ok, grad, 0.0)


def log_density(problem: Problem, codes, params, z_hat, L):
    """`w -> log posterior density` (up to a constant) in whitened coordinates
    `z = z_hat + L w` (L: Cholesky factor of the Laplace covariance), differentiable by
    `jax.grad` (the likelihood's gradient is forward mode, through a custom VJP).

    Whitened, because the posterior in `z` can be very narrow (relative widths of 1e-5
    on a clean record): Stan's mass-matrix estimate regularises towards `1e-3 I`, which
    at that scale would swamp it. In `w` the posterior is close to `N(0, I)`, and an
    affine map leaves a flat prior flat."""
    @jax.custom_vjp
    def loglik(z):
        return _loglik_and_grad(problem, z)[0]

    def fwd(z):
        v, g = _loglik_and_grad(problem, z)
        return v, g

    def bwd(g, ct):
        return (ct * g,)

    loglik.defvjp(fwd, bwd)

    def density(w):
        z = z_hat + L @ w
        return loglik(z) + log_prior(z, problem, codes, params)

    return density


def adaptation():
    ad = blackjax.adaptation
    return (ad.step_size.dual_averaging_adaptation(0.8),
            ad.mass_matrix.mass_matrix_adaptation(is_diagonal_matrix=False))


def _chunk(problem, codes, params, z_hat, L, carry, keys, stages, batched):
    """`keys.shape[1]` NUTS transitions of every chain, adapting the step size and the
    (dense) mass matrix on Stan's schedule while warming up. The chains run one after
    another in the program (`lax.map`), or vmapped where `batched` (see `_batched`).

    `stages` (K, 2) int: `(stage, window_end)` with stage 0 fast (step size only), 1 slow
    (mass matrix too), 2 sampling (nothing adapted), -1 padding (nothing happens).
    **Returns:** `(carry, positions (C, K, p), divergent (C, K), tree_steps (C, K))`."""
    logdensity = log_density(problem, codes, params, z_hat, L)
    kernel = blackjax.nuts.build_kernel()
    (da_init, da_update, da_final), (_, mm_update, mm_final) = adaptation()

    def one(c, xs):
        key, (stage, end) = xs
        state, da, mm, eps, imm = c
        new, info = kernel(key, state, logdensity, eps, imm)
        acc = jnp.where(jnp.isfinite(info.acceptance_rate), info.acceptance_rate, 0.0)
        da2 = da_update(da, acc)
        mm2 = jax.tree.map(lambda a, b: jnp.where(stage == 1, a, b),
                           mm_update(mm, new.position), mm)
        eps2 = jnp.exp(da2.log_step_size)
        fin = mm_final(mm2)
        da3 = da_init(da_final(da2))
        is_end = (stage == 1) & (end == 1)
        pick = lambda a, b, cond: jax.tree.map(lambda x, y: jnp.where(cond, x, y), a, b)  # noqa: E731
        mm2, da2 = pick(fin, mm2, is_end), pick(da3, da2, is_end)
        eps2 = jnp.where(is_end, jnp.exp(da3.log_step_size), eps2)
        imm2 = jnp.where(is_end, fin.inverse_mass_matrix, imm)
        adapt = (stage == 0) | (stage == 1)
        out = (pick(new, state, stage >= 0), pick(da2, da, adapt), pick(mm2, mm, adapt),
               jnp.where(adapt, eps2, eps), jnp.where(adapt, imm2, imm))
        return out, (new.position, info.is_divergent & (stage >= 0), info.num_integration_steps)

    def chain(c, ks):
        return jax.lax.scan(one, c, (ks, stages))

    if batched:
        carry, (pos, div, steps) = jax.vmap(chain)(carry, keys)
    else:
        carry, (pos, div, steps) = jax.lax.map(lambda a: chain(*a), (carry, keys))
    return carry, pos, div, steps


_chunk_program = eqx.filter_jit(_chunk)


def _batched() -> bool:
    """Whether to vmap the chains (an accelerator) rather than run them one after another
    in the program (the CPU). On the CPU a vmapped `while` loop selects between the old and
    new value of its whole carry at every iteration, the ODE's buffer of saved samples
    included, and it stops XLA compiling the step loop into one function (xla_flags.py):
    four vmapped chains' gradients cost several times four one after another
    (docs/benchmarks/design-figures.md). A vmapped NUTS step also costs its slowest
    chain's tree for every chain."""
    return jax.default_backend() != "cpu"


def _shares(chains: int) -> list[list[int]]:
    """The chains of each device: on the CPU, as many devices as divide `chains` evenly
    (one program serves them all), each a thread of its own; several CPU devices exist only
    where the program asked for them (`crank_jax.configure_cpu()`, which the `crank-jax`
    program calls). Elsewhere one device."""
    devices = jax.local_devices() if not _batched() else jax.local_devices()[:1]
    d = max(k for k in range(1, min(len(devices), chains) + 1) if chains % k == 0)
    per = chains // d
    return [list(range(i * per, (i + 1) * per)) for i in range(d)]


def schedule(warmup: int) -> np.ndarray:
    """(warmup, 2) Stan window schedule (blackjax's `build_schedule`)."""
    from blackjax.adaptation.window_adaptation import build_schedule

    if warmup == 0:
        return np.zeros((0, 2), dtype=np.int32)
    return np.asarray(build_schedule(warmup), dtype=np.int32).reshape(warmup, 2)


def initial_carry(problem, codes, params, z_hat, L, chains, key):
    """Chain starts drawn from the Laplace approximation (`w ~ N(0, I)`; a start with zero
    density falls back to the estimate), and the adaptation states, stacked over chains."""
    p = problem.p
    starts = np.array(jax.random.normal(key, (chains, p)))
    logdensity = log_density(problem, codes, jnp.asarray(params), jnp.asarray(z_hat),
                              jnp.asarray(L))
    lp = np.asarray(jax.jit(jax.vmap(logdensity))(jnp.asarray(starts)))
    starts[~np.isfinite(lp)] = 0.0
    (da_init, _, _), (mm_init, _, _) = adaptation()
    states = jax.jit(jax.vmap(lambda x: blackjax.nuts.init(x, logdensity)))(jnp.asarray(starts))
    eps0 = 1.0 / math.sqrt(p)
    da = jax.vmap(lambda _: da_init(eps0))(jnp.arange(chains))
    mm = jax.vmap(lambda _: mm_init(p))(jnp.arange(chains))
    return (states, da, mm, jnp.full(chains, eps0), jnp.broadcast_to(jnp.eye(p), (chains, p, p)))


def _put(tree, device):
    """`tree`'s arrays committed to `device` (its other leaves, static to the program,
    stay as they are)."""
    arrays, rest = eqx.partition(tree, eqx.is_array)
    return eqx.combine(jax.device_put(arrays, device), rest)


def _strong(tree):
    """`tree`'s arrays without JAX's weak types: the carry a chunk returns, and the one
    the warm-up's end or `initial_carry` builds, then key the same compiled program (a
    weak-typed leaf in one of them recompiled it at every hand-over)."""
    return jax.tree.map(lambda x: jnp.asarray(x, dtype=jnp.asarray(x).dtype), tree)


def run_chains(problem, codes, params, zL, carry, key, stages, desc, progress):
    """Run the schedule `stages` (n, 2) in chunks; positions (C, n, p), divergences,
    leapfrog steps. Each device of `_shares` runs its chains' program at once (JAX
    dispatches without waiting); the chains' draws do not depend on how they are shared."""
    n = stages.shape[0]
    chains = carry[3].shape[0]
    shares = _shares(chains)
    devices = jax.local_devices()
    fixed = [_put((problem, codes, params, *zL), devices[i]) for i in range(len(shares))]
    carries = [_put(_strong(jax.tree.map(lambda x, ix=ix: x[np.asarray(ix)], carry)),
                    devices[i])
               for i, ix in enumerate(shares)]
    pos, div, steps = [], [], []
    with progress_bar(n, desc, progress and n > 0, unit="step") as bar:
        for start in range(0, n, CHUNK):
            block = stages[start:start + CHUNK]
            m = block.shape[0]
            pad = jnp.asarray(np.concatenate([block, np.full((CHUNK - m, 2), -1, np.int32)]))
            key, sub = jax.random.split(key)
            keys = jax.random.split(sub, chains * CHUNK).reshape(chains, CHUNK, -1)
            outs = [_chunk_program(*fixed[i], carries[i], _put(keys[np.asarray(ix)], devices[i]),
                                   _put(pad, devices[i]), _batched())
                    for i, ix in enumerate(shares)]
            carries = [_strong(o[0]) for o in outs]
            pos.append(np.concatenate([np.asarray(o[1]) for o in outs])[:, :m])
            div.append(np.concatenate([np.asarray(o[2]) for o in outs])[:, :m])
            steps.append(np.concatenate([np.asarray(o[3]) for o in outs])[:, :m])
            bar.update(m)
    p = problem.p
    carry = jax.tree.map(lambda *xs: jnp.concatenate([jax.device_put(x, devices[0])
                                                      for x in xs]), *carries)

    def cat(xs, shape):
        return np.concatenate(xs, axis=1) if xs else np.zeros(shape)

    return (carry, key, cat(pos, (chains, 0, p)), cat(div, (chains, 0)),
            cat(steps, (chains, 0)))
