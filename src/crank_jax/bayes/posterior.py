"""The Bayesian posterior of a fit's free parameters, sampled with NUTS.

The model is the fit's own: the residual program of [`build_problem`][] (single
shooting, one or several records), its coordinates `z` (log-values for positive
parameters, so sampling is unconstrained), and Gaussian noise of unknown level per record.
Each record's noise level `sigma_k` is integrated out under the Jeffreys prior
`p(sigma) ~ 1/sigma`, which gives the exact marginal likelihood

    log p(data | z) = sum_k -(n_k / 2) log RSS_k(z) + const,

so no noise parameter needs sampling. Priors (see [`parse_priors`][]) are on the physical
values, carried to `z` with the Jacobian of the transformation; a parameter without one is
flat in `z` (log-uniform for a positive parameter), within the model's validity (a trial
point whose solve fails has zero density).

Why blackjax and not numpyro: blackjax is a library of samplers over any JAX
log-density, which is what we have (our own likelihood through our own ODE solve, with a
forward-mode gradient); numpyro is a probabilistic programming language whose models are
written in its own primitives, and would wrap the same function as a `factor`. Blackjax's
building blocks (the NUTS kernel, Stan's dual averaging and mass-matrix windows) also let
the warm-up run in chunks, so a progress bar follows it.

The gradient goes through the ODE solve in forward mode (`jax.jacfwd`, one tangent per
parameter, the fit's own Jacobian program), then `grad = sum_k -(n_k / RSS_k) J_k^T r_k`:
measured on the lab rig (4 parameters, 600 samples) it is cheaper than a reverse-mode
gradient through the solve (see `experiments/posterior_timing.py`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..identify.fit import fit
from ..identify.fit_plan import single_problem
from ..identify.fit_result import FitResult
from ..identify.problem import Problem, pick_solver
from ..identify.programs import jacobian_at
from ..identify.request import STATE_NAMES, normalize
from ..identify.strategy import MAX_ODE_STEPS, ode_budget
from ..records.data import Data
from ..runtime.blas import one_blas_thread
from ..runtime.lazy import lazy_import
from ..scene import Scene
from ..sweep.distributions import AbstractDistribution
from .nuts import adaptation, initial_carry, run_chains, schedule
from .priors import base_name, in_support, parse_priors, prior_arrays, prior_precision

blackjax = lazy_import("blackjax")  # imported on first use (see lazy.py)

__all__ = ["Posterior", "posterior", "posterior_bytes", "check_posterior_memory",
           "moved_fraction", "sampler_warnings", "MIN_MOVED"]


@dataclasses.dataclass
class Posterior:
    """Posterior draws of the free parameters (see [`posterior`][]).

    **Fields:** `names` (p,); `draws`: name -> (chains, draws) array in physical units;
    `rhat`, `ess`: name -> rank-normalised split R-hat and bulk effective sample size
    (Vehtari et al. 2021); `divergences`: divergent transitions after warm-up (any is a
    warning sign: the sampler missed part of the posterior); `chains`, `n_draws`,
    `warmup`; `step_size` (chains,) after adaptation; `mean_tree_steps`: leapfrog steps
    per draw; `gradient_evaluations`: leapfrog steps (each one evaluation of the log
    density and its gradient) of warm-up and sampling, all chains; `seconds`: wall time
    of warm-up and sampling; `fit`: the least-squares fit the chains started from (its
    Laplace intervals for comparison); `priors`: name -> the
    prior in text form (flat in the coordinates where absent); `moved` (chains,): the
    fraction of each chain's draws that differ from the draw before; `stuck`: the chains
    that hardly moved (below [`MIN_MOVED`][]) even after the step-size retries, whose
    draws only repeat their start; `warnings`: sentences for the user. `reliable` is
    False when any chain is stuck: the spread of the draws is then no posterior.
    """

    names: tuple[str, ...]
    draws: dict[str, np.ndarray]
    rhat: dict[str, float]
    ess: dict[str, float]
    divergences: int
    chains: int
    n_draws: int
    warmup: int
    step_size: np.ndarray
    mean_tree_steps: float
    gradient_evaluations: int
    seconds: float
    fit: FitResult
    priors: dict[str, str]
    moved: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    stuck: tuple[int, ...] = ()
    warnings: list[str] = dataclasses.field(default_factory=list)

    @property
    def reliable(self) -> bool:
        """Whether every chain moved (see `stuck`)."""
        return not self.stuck

    def summary(self) -> dict[str, dict[str, float]]:
        """name -> {"mean", "sd", "q2.5", "q97.5", "rhat", "ess_bulk"} over all draws."""
        out = {}
        for n in self.names:
            x = np.asarray(self.draws[n]).reshape(-1)
            q = np.quantile(x, [0.025, 0.975])
            out[n] = {"mean": float(np.mean(x)), "sd": float(np.std(x, ddof=1)),
                      "q2.5": float(q[0]), "q97.5": float(q[1]), "rhat": self.rhat[n],
                      "ess_bulk": self.ess[n]}
        return out

    def to_json(self) -> dict:
        """The JSON the CLI writes: parameters, divergences, draws, chains, settings, fit."""
        summary = {n: {k: (v if np.isfinite(v) else None) for k, v in s.items()}
                   for n, s in self.summary().items()}  # NaN (one chain's R-hat): null
        return {"reliable": self.reliable, "stuck_chains": list(self.stuck),
                "moved_fraction": [float(m) for m in self.moved],
                "warnings": list(self.warnings),
                "parameters": summary, "divergences": int(self.divergences),
                "draws": int(self.n_draws), "chains": int(self.chains),
                "warmup": int(self.warmup), "priors": dict(self.priors),
                "step_size": [float(s) for s in self.step_size],
                "mean_tree_steps": float(self.mean_tree_steps),
                "gradient_evaluations": int(self.gradient_evaluations),
                "seconds": float(self.seconds),
                "laplace": {n: {"value": self.fit.values[n], "stderr": self.fit.stderr[n],
                                "ci95": list(self.fit.ci95[n]) if self.fit.ci95[n] else None}
                            for n in self.names},
                "samples": {n: np.asarray(v).tolist() for n, v in self.draws.items()}}


def posterior_bytes(draws: int, chains: int, warmup: int, p: int) -> int:
    """Host memory a posterior of `chains` x `draws` draws of `p` parameters after `warmup`
    steps holds at its peak, bytes, about: per step of warm-up and sampling and chain,
    its positions (8 bytes each), divergence flag and tree size, in the chunks and their
    concatenation; per draw and chain, the draws whitened back and in physical units
    (8 bytes each, twice) and as Python floats for the JSON document (32 bytes each);
    per warm-up step, Stan's window schedule (a Python list)."""
    steps, draws, chains, warmup = (int(draws) + int(warmup), int(draws), int(chains),
                                    int(warmup))
    per_step = chains * 2 * (8 * p + 1 + 8)
    per_draw = chains * p * (2 * 8 + 32)
    return steps * per_step + draws * per_draw + warmup * 128 + steps * 8


def check_posterior_memory(draws: int, chains: int, warmup: int, p: int,
                           max_memory: int | None = None) -> None:
    """Raise `ValueError` naming `draws` (the CLI's `--draws`) and the largest count that
    fits when [`posterior_bytes`][] exceeds `max_memory` (default: half this host's memory),
    before any work: a billion draws would otherwise grow past 8 GB before failing."""
    from ..sweep.plan import host_memory

    limit = host_memory() // 2 if max_memory is None else int(max_memory)
    need = posterior_bytes(draws, chains, warmup, p)
    if not limit or need <= limit:
        return
    why = "half this host's memory" if max_memory is None else "max_memory"
    if posterior_bytes(0, chains, warmup, p) > limit:  # the warm-up alone is too long
        per = posterior_bytes(0, chains, 1, p)
        raise ValueError(f"`warmup=` {warmup} steps x `chains=` {chains} need about "
                         f"{need / 2**30:.3g} GiB of memory, over the limit of "
                         f"{limit / 2**30:.3g} GiB ({why}); give `warmup=` <= "
                         f"{max(limit - posterior_bytes(draws, chains, 0, p), 0) // per}")
    fit_draws = ((limit - posterior_bytes(0, chains, warmup, p))
                 // max(posterior_bytes(1, chains, 0, p), 1))
    raise ValueError(f"`draws=` {draws} x `chains=` {chains} of {p} parameters need about "
                     f"{need / 2**30:.3g} GiB of memory, over the limit of "
                     f"{limit / 2**30:.3g} GiB ({why}); give `draws=` <= {fit_draws} (or "
                     "fewer `chains=` or `warmup=` steps)")


def _check_counts(draws, chains, warmup) -> None:
    for name, v, lo in (("draws", draws, 1), ("chains", chains, 1), ("warmup", warmup, 0)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
            raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
    if chains > 1 and draws < 4:
        raise ValueError(f"draws must be >= 4 with several chains (R-hat needs them), got "
                         f"{draws}")


def _problem_at(req, res: FitResult) -> tuple[Problem, np.ndarray]:
    """The single-shooting residual problem at the fit's estimate, and its coordinates:
    built by the fit's own builder from the same records, so every channel is read
    through its sensor and weighted by the noise level the fit ended with."""
    values = res.values
    multi = len(req.records) > 1
    final = {n: c["sigma"] for n, c in (res.channels or {}).items()}
    req = dataclasses.replace(req, sigmas={**req.sigmas, **final})

    def state(i, k):
        name = STATE_NAMES[k]
        key = f"{name}[{i}]" if multi else name
        return values[key] if key in values else req.states[i][k]

    states = [(state(i, 0), state(i, 1)) for i in range(len(req.records))]
    start = {n: values[n] for n in req.free if n not in STATE_NAMES}
    solver = pick_solver(res.mech, req.loads[0][0], float(req.scene.rtol), req.scene.solver)

    def build(budget):
        return single_problem(req, start, states, budget, solver)

    problem = build(MAX_ODE_STEPS)
    z = problem.to_z([values[n] for n in problem.names])
    _, _, steps, _ = jacobian_at(problem, jnp.asarray(z))
    budget = ode_budget(int(np.max(np.asarray(steps))))
    if budget != problem.max_steps:
        problem = build(budget)
    return problem, z


def _laplace_z(problem: Problem, z: np.ndarray, codes, params) -> np.ndarray:
    """(p, p) Laplace covariance of the coordinates at z (noise from the residuals), with
    the priors' precisions added (roughly: only the chains' starts and whitening use it),
    so that a direction the data leave open but a prior closes keeps a finite scale."""
    r, failed, _, J = (np.asarray(x) for x in jacobian_at(problem, jnp.asarray(z)))
    n = problem.n_residuals
    s2 = float(r @ r) / max(n - problem.p, 1)
    H = J.T @ J / max(s2, 1e-300) + np.diag(prior_precision(codes, params, problem, z))
    if int(failed) or not np.all(np.isfinite(H)):
        return np.eye(problem.p)
    w, V = np.linalg.eigh(0.5 * (H + H.T))
    # A direction neither data nor prior determine (the posterior refuses those) or a
    # numerically flat one: a unit scale, which the warm-up's mass matrix then adapts.
    w = np.where(w > 1e-12 * max(w.max(), 1e-300), w, 1.0)
    return (V / w) @ V.T


@one_blas_thread
def posterior(
    scene: Scene | Sequence[Scene],
    data: Data | Sequence[Data],
    free: Sequence[str] = ("k", "c", "phi0", "dphi0"),
    priors: Mapping[str, str | AbstractDistribution] | None = None,
    draws: int = 1000,
    chains: int = 4,
    seed: int = 0,
    *,
    warmup: int = 500,
    window: tuple[float | None, float | None] | None = None,
    progress: bool = True,
    load_by: str = "time",
) -> Posterior:
    """Sample the posterior of the free parameters with NUTS (blackjax).

    First [`fit`][] finds the least-squares estimate and its Laplace covariance; the chains
    start around it, in coordinates whitened by that covariance (priors included). Warm-up
    then adapts the step size and a dense mass matrix on Stan's windows, and every chain
    draws `draws` samples. On the CPU the chains are shared over the JAX CPU devices and run
    one after another on each (`crank_jax.configure_cpu()` asks for a device per core and
    XLA's faster CPU flags: call it first in a program); on an accelerator, vmapped.

    **Arguments:**

    - `scene`, `data`, `free`, `window`, `load_by`: as for [`fit`][] (several records
      share the mechanism; each has its own noise level and, when free, initial state).
    - `priors`: name -> distribution (text like `"lognormal(0.7, 0.5)"`, see
      [`parse_priors`][]); default flat in the coordinates (log-uniform for positive
      parameters).
    - `draws`: draws per chain after warm-up; `chains`; `seed`; `warmup`: warm-up steps
      per chain.
    - `progress`: progress bars on stderr (the fit's, warm-up's and sampling's).

    **Returns:** a [`Posterior`][]. **Raises:** `ValueError` for a bad request (before any
    sampling), or when the fit cannot give a start: it did not converge, or the free
    parameters are not identifiable and lack priors (the flat posterior would then be
    improper).
    """
    _check_counts(draws, chains, warmup)
    req = normalize(scene, data, free, init="scene", method="lm", shooting="auto",
                    segments=None, multistart=1, seed=seed, max_steps=None, tol=1e-8,
                    sigma=None, profile=None, window=window, progress=progress, warn=False,
                    load_by=load_by)
    check_posterior_memory(draws, chains, warmup, len(req.names))
    prior = parse_priors(priors, req.free)
    res = fit(scene, data, req.free, window=window, progress=progress, warn=False,
              load_by=load_by)
    if not res.converged:
        raise ValueError(f"the fit that starts the chains did not converge ({res.message}); "
                         "fix the start values or the free parameters first")
    if res.identifiable is False:
        loose = [n for n in res.names if res.stderr[n] is None and base_name(n) not in prior]
        if loose:
            raise ValueError(f"{', '.join(loose)} are not identifiable from these data "
                             f"({'; '.join(res.unidentifiable_directions)}); give them "
                             "priors, or fix them, for a proper posterior")
    for n, d in prior.items():
        bad = [m for m in res.names if base_name(m) == n and not in_support(d, res.values[m])]
        if bad:
            raise ValueError(f"priors.{n}: the data put {n} at {res.values[bad[0]]:.6g}, "
                             f"outside its prior {d}'s support; widen the prior")
    problem, z_hat = _problem_at(req, res)
    codes, params = prior_arrays(problem.names, prior, problem.log)
    L = np.linalg.cholesky(_laplace_z(problem, z_hat, codes, params))
    zL = (jnp.asarray(z_hat), jnp.asarray(L))
    key = jax.random.PRNGKey(seed)
    key, k0 = jax.random.split(key)
    carry = initial_carry(problem, codes, params, z_hat, L, chains, k0)
    t_sample = time.perf_counter()
    carry, key, _, _, warm_steps = run_chains(problem, codes, params, zL, carry, key,
                                              schedule(warmup), "warm-up", progress)
    (_, _, da_final), _ = adaptation()
    eps = jax.vmap(da_final)(carry[1]) if warmup else carry[3]
    carry = (carry[0], carry[1], carry[2], eps, carry[4])
    w_draws, div, steps, eps, moved, notes = _sample(problem, codes, params, zL, carry, key,
                                                     draws, progress)
    seconds = time.perf_counter() - t_sample
    z_draws = z_hat + w_draws @ L.T
    values = np.asarray(jax.vmap(jax.vmap(problem.values))(jnp.asarray(z_draws)))
    out = {n: values[:, :, i] for i, n in enumerate(problem.names)}
    stuck = tuple(int(i) for i in np.flatnonzero(moved < MIN_MOVED))
    return Posterior(
        names=tuple(problem.names), draws=out,
        rhat={n: _diag(blackjax.diagnostics.rhat, v, chains) for n, v in out.items()},
        ess={n: _diag(blackjax.diagnostics.ess_bulk, v, chains) for n, v in out.items()},
        divergences=int(div.sum()), chains=chains, n_draws=draws, warmup=warmup,
        step_size=np.asarray(eps), mean_tree_steps=float(np.mean(steps)),
        gradient_evaluations=int(np.sum(warm_steps) + np.sum(steps)), seconds=seconds,
        fit=res, priors={n: str(d) for n, d in prior.items()}, moved=moved, stuck=stuck,
        warnings=notes + sampler_warnings(moved, eps, chains, draws))


#: A chain whose draws differ from the one before in less than this fraction of its
#: draws hardly moved: NUTS at its target acceptance (0.8) moves at nearly every draw.
#: Measured on a 1.5 s lab-rig record, one chain: a warm-up of 20 steps left a step size
#: (3.3) that moved in 0% of 30 draws (sd 0); one of 30 steps, 2.7 and 10% (sd of k 2.5x
#: too small); healthy chains moved in 100%.
MIN_MOVED = 0.5
#: Times the sampling is repeated, each with the step size of the stuck chains divided by
#: [`STEP_CUT`][], before a stuck chain is reported.
STUCK_RETRIES = 2
STEP_CUT = 4.0


def moved_fraction(w_draws: np.ndarray) -> np.ndarray:
    """(chains,) the fraction of each chain's draws (chains, draws, p) that differ from
    the draw before (1 for a chain of one draw: nothing to judge)."""
    w = np.asarray(w_draws)
    if w.shape[1] < 2:
        return np.ones(w.shape[0])
    return np.mean(np.any(np.diff(w, axis=1) != 0, axis=2), axis=1)


def _sample(problem, codes, params, zL, carry, key, draws: int, progress: bool):
    """The draws after warm-up (whitened, (chains, draws, p)) from the warmed-up `carry`;
    chains that hardly move (a step size adapted too large on a short warm-up: every
    proposal rejected) are sampled again with their step cut by [`STEP_CUT`][], up to
    [`STUCK_RETRIES`][] times. **Returns:** `(draws, divergent, tree steps, step sizes,
    moved fraction, notes)`."""
    sampling = np.tile(np.asarray([[2, 0]], dtype=np.int32), (draws, 1))
    notes: list[str] = []
    eps = np.asarray(carry[3], dtype=float)
    for retry in range(STUCK_RETRIES + 1):
        c = (carry[0], carry[1], carry[2], jnp.asarray(eps, dtype=carry[3].dtype), carry[4])
        _, _, w, div, steps = run_chains(problem, codes, params, zL, c, key, sampling,
                                         "sampling", progress)
        w = np.asarray(w)
        moved = moved_fraction(w)
        stuck = moved < MIN_MOVED
        if not stuck.any() or retry == STUCK_RETRIES:
            return w, div, steps, eps, moved, notes
        notes.append(f"chain(s) {', '.join(map(str, np.flatnonzero(stuck)))} moved in "
                     f"{100 * float(moved[stuck].min()):.0f}% of their draws at step size "
                     f"{float(eps[stuck].max()):.3g}: sampled again with it cut by "
                     f"{STEP_CUT:g}")
        eps = np.where(stuck, eps / STEP_CUT, eps)


def sampler_warnings(moved: np.ndarray, eps: np.ndarray, chains: int, draws: int
                     ) -> list[str]:
    """What the chains' movement and number say about the draws: a stuck chain (its
    spread is no posterior), one chain (no R-hat)."""
    out = []
    stuck = np.flatnonzero(np.asarray(moved) < MIN_MOVED)
    if stuck.size:
        out.append(f"UNRELIABLE: chain(s) {', '.join(map(str, stuck))} moved in only "
                   f"{100 * float(np.min(moved[stuck])):.0f}% of their {draws} draws (step "
                   f"size {float(np.max(np.asarray(eps)[stuck])):.3g} even after "
                   f"{STUCK_RETRIES} cuts): their draws repeat their start, so the spread "
                   "(sd, quantiles) is not the posterior's; run a longer warm-up (`warmup=`) "
                   "or give priors")
    if chains == 1:
        out.append("one chain: R-hat cannot be computed (it compares chains), so nothing "
                   "checks that the chain found the whole posterior; run 2 or more chains "
                   "(`chains=`)")
    return out


def _diag(fn, x: np.ndarray, chains: int) -> float:
    """A convergence diagnostic of (chains, draws) draws; NaN where undefined (one chain
    for R-hat, too few draws)."""
    if x.shape[1] < 4 or (fn is blackjax.diagnostics.rhat and chains < 2):
        return float("nan")
    if np.ptp(x) == 0:
        return float("nan")
    return float(np.asarray(fn(jnp.asarray(x))))
