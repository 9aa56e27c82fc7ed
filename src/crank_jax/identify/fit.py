"""Parameter identification: fit a scene's parameters to one or more crank-angle records.

`fit` reads as its stages, each taking the fit's state and returning a new one: the
request ([`request`][crank_jax.identify.request]), the plan
([`fit_plan`][crank_jax.identify.fit_plan]), the optimisation and its escalation
([`escalation`][crank_jax.identify.escalation]), the channels' reweighting, then the
uncertainty and identifiability at the estimate
([`uncertainty`][crank_jax.identify.uncertainty]).

- `method="lm"` (default): Levenberg-Marquardt on the host, the residuals and Jacobian
  from one compiled program (forward-mode sensitivities through the ODE solve). Best for
  one or a few records and up to a dozen or two parameters; its Jacobian serves the
  uncertainty too.
- `method="optax"`: Adam, then L-BFGS, with reverse-mode gradients (one backward solve
  whatever the number of coordinates), for large problems (many records or segments).

Multiple shooting: each segment starts from its own state, continuity at the shared
samples a weighted residual; single shooting then polishes the estimate, so it and its
uncertainty are those of the ordinary least-squares problem.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Sequence

import numpy as np

from ..records.data import Data
from ..runtime.blas import one_blas_thread
from ..scene import Scene
from . import channel_noise as ch
from .escalation import optimize_fit
from .fit_plan import make_plan
from .fit_result import (
    ConvergenceWarning,
    FitResult,
    IdentifiabilityWarning,
    Profile,
    with_wrapped_angles,
)
from .measurement import fitted_channels
from .outcome import FAILS_AT_END, Run, termination
from .profile import hessian_disagreement, profile_likelihood
from .request import free_names, normalize
from .reweight import reweight
from .stages import FitState
from .start import regressor_start
from .strategy import (
    AUTO_PERIODS,
    SEGMENT_PERIODS,
)
from .uncertainty import assess, undefined

__all__ = ["fit", "finish", "FitResult", "Profile", "IdentifiabilityWarning", "ConvergenceWarning",
           "FREE_NAMES", "AUTO_PERIODS", "SEGMENT_PERIODS", "regressor_start"]

#: Names that can be free (the mechanism fields, load amplitudes and initial state).
FREE_NAMES: tuple[str, ...] = free_names()


def _all_tries(message: str, term: dict, own: int, total: int, max_steps: int):
    """`(message, term)` of a run whose budget ran out, saying the iterations of every
    try (`total`, fit.json's `iterations`) beside the reported try's own (`own`, in its
    words), so the two never seem to disagree."""
    if total == own or term["verdict"] != "budget":
        return message, term
    extra = (f"; {total} iterations in all over the fit's tries (`max_steps=` "
             f"{max_steps} per try)")
    return message + extra, {**term, "words": term["words"] + extra}


def _result(state: FitState, t_begin: float) -> FitResult:
    """The result stage: the estimate's uncertainty, verdicts, profile and report."""
    req, plan, best, iterations = state.req, state.plan, state.best, state.iterations
    ss = plan.single
    # (`plan.z0` may be multiple shooting's coordinates; the start values are not.)
    z_hat = (best.z[:ss.p] if np.all(np.isfinite(best.z))
             else ss.to_z([plan.start[n] for n in ss.names]))
    converged, message = best.converged, best.message
    if plan.abort:  # nothing was solved, and nothing more is
        r_hat, values = ss.no_residuals(), ss.host_values(z_hat)
        rms, unc, more, diag = float("nan"), undefined(ss.p, "did not converge"), [], None
    else:
        # (The fleet's run holds its residuals and sensitivities at its estimate.)
        at = best.solved[1:] if best.solved is not None and best.solved[0] is ss else None
        r_hat, values, rms, unc, more, diag = assess(ss, z_hat, converged, req.known_sigma,
                                                     at=at)
    term = best.termination
    if converged and not math.isfinite(rms):
        converged, message = False, FAILS_AT_END
        term = None
    if plan.abort:
        term = termination("refused", plan.abort)
    elif term is None:  # the optax method, or a failure outside LM's loop
        term = termination("converged" if converged else "failed", message)
    message, term = _all_tries(message, term, best.iterations, iterations, req.max_steps)
    notes = more + list(state.notes) + list(plan.notes)
    if not converged:
        notes.insert(0, f"fit did not converge: {message}; no standard errors are given")
    prof = None
    if req.profile is not None:
        j = ss.names.index(req.profile)
        c = unc.covariance_z[j, j]
        se_z = math.sqrt(max(c, 0.0)) if np.isfinite(c) else float("nan")
        prof = profile_likelihood(ss, z_hat, j, se_z, ss.n_residuals, req.max_steps, req.tol,
                                  req.progress)
        if converged and np.all(np.isfinite(unc.ci95[j])):
            note = hessian_disagreement(prof, float(values[j]), tuple(unc.ci95[j]))
            notes += [note] if note else []

    def show(i):
        return converged and bool(np.isfinite(unc.stderr[i]))

    names = ss.names
    return FitResult(
        names=names,
        values={nm: float(values[i]) for i, nm in enumerate(names)},
        start={nm: float(plan.start[nm]) for nm in names},
        stderr={nm: float(unc.stderr[i]) if show(i) else None for i, nm in enumerate(names)},
        ci95={nm: (float(unc.ci95[i, 0]), float(unc.ci95[i, 1])) if show(i) else None
              for i, nm in enumerate(names)},
        correlation=unc.correlation, condition_number=float(unc.condition_number),
        singular_values=unc.singular_values,
        identifiable=bool(unc.identifiable) if converged else None,
        unidentifiable_directions=list(unc.directions) if converged else [],
        rms_residual=rms, n_samples=int(ss.n_residuals), converged=bool(converged),
        iterations=int(iterations), seconds=time.perf_counter() - t_begin, warnings=notes,
        message=message, method=req.method.value,
        shooting=state.shooting.mode,
        mech=ss.host_mech(z_hat), data=list(req.records),
        fitted=ss.fitted(r_hat), profile=prof, strategy=state.shooting.label, diagnostics=diag,
        channels=ch.channel_report(ss, r_hat, req.sigmas, converged),
        fitted_channels=fitted_channels(ss, r_hat), termination=term)


@one_blas_thread
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
    window: tuple[float | None, float | None] | None = None,
    progress: bool = True,
    warn: bool = True,
    per_record: Sequence[str] = (),
    force=None,
    load_by: str = "time",
) -> FitResult:
    """Fit free parameters of a scene to crank-angle records by least squares.

    **Arguments:**

    - `scene`: the [`Scene`][] giving the fixed values, the start values and the loads; or
      one scene per record (they may differ only in loads and initial state).
    - `data`: a [`Data`][] record, or a sequence of them (a multi-experiment fit: the
      mechanism is shared, each record has its own initial state and loads). A record's
      own `load`/`torque` replace its scene's.
    - `free`: names from [`FREE_NAMES`][]: the mechanism fields, the load amplitudes `P0`,
      `P1`, `tau0`, `tau1` (the scene's constant or harmonic load) and `phi0`, `dphi0`
      (the state at each record's first sample). A field that cannot be negative and
      starts positive is fitted in log space; the friction terms `T_c`, `c_s`, `F_s` and
      any field that cannot be negative and starts at 0 as `ref |z|` (always valid; a
      true 0 gets the interval `[0, v + 1.96 se]`); the others (a signed offset, the
      loads and states) in linear coordinates.
    - `init`: `"scene"` (the scene's values), `"regressor"` (masses, inertias, k and c
      from the linear regressor form) or a dict of start values. Free `phi0`/`dphi0` always
      start from a local fit to the first samples.
    - `method`: `"lm"` or `"optax"` (see the module notes for which to use).
    - `shooting`: `"auto"` (judged from the record's zero crossings against the start
      model's; escalates to multiple shooting, then to more starts, when the fit stalls far
      above the record's noise level), `"single"` or `"multiple"`; `segments` fixes their
      number.
    - `multistart`: number of starts (the first is `init`; the others perturb the
      log-parameters by a factor `exp(N(0, 0.5^2))`); the lowest-cost converged start
      wins (if none converged, the lowest-cost one, and the warnings say so).
    - `seed`: seed of the multistart perturbations.
    - `max_steps`: iteration budget per start, 1 to `fit_options.MAX_ITERATIONS` (default
      100 for LM, 2000 for optax).
    - `tol`: relative and absolute tolerance of the optimiser's termination test.
    - `sigma`: the noise standard deviation (rad) if known, within `fit_options.SIGMA_RANGE`;
      default: from the residuals.
    - `profile`: a reported name whose profile likelihood to compute.
    - `window`: `(t_start, t_end)`, s: fit only the samples in it (either end None: open),
      e.g. to trim a release transient.
    - `progress`: show progress bars on stderr. `warn`: emit Python warnings
      ([`IdentifiabilityWarning`][], [`ConvergenceWarning`][]) besides `result.warnings`.
    - `per_record`: free names that take a separate value in each record (reported as
      `name[i]`); the others are shared.
    - `force`: a user's force term, as `simulate` takes it (an `eqx.Module` callable
      `f(t, phi, dphi) -> N*m`); its float fields can be freed as `force.<field>` (or
      `force.<field>[i]` for an array's elements).
    - `load_by`: what a record's measured `P`/`tau` columns follow: `"time"` (default,
      interpolated in time) or `"angle"` (tabled by the record's own angle channel, which
      must turn one way, and evaluated at the model's angle, held at the end values
      beyond the record's angles; see `records.load_by`): a force that follows the
      crank then meets the model's crank at the right angle when their phases differ.

    Records may carry any sensor channels (`phi`, `dphi`, `x_s`, `v_s`, `a_s`, see
    [`Data`][]): each is compared with the model's reading `scale h + offset` and
    weighted by its noise level (`sigma` a dict, channel -> SI level; a number is the
    first channel's; unknown levels are estimated from the record, then from the
    residuals). Offsets can be freed as `<channel>_offset`.

    **Returns:** a [`FitResult`][]. A fit that fails or does not converge returns
    `converged=False` with a message (and finite values: the last good iterate or the
    start); it never raises for a numerical failure. A record with no motion above its
    noise, one that moves more than pi between samples, or one the start values cannot
    follow is refused before any optimisation, with `converged=False` and a message
    naming it. Mistakes in the request (unknown names, too few samples, a start value
    outside a parameter's domain, a profile of a name that is not free, an option out
    of its range) raise `ValueError` before any compute.
    """
    t_begin = time.perf_counter()
    req = normalize(scene, data, free, init=init, method=method, shooting=shooting,
                    segments=segments, multistart=multistart, seed=seed, max_steps=max_steps,
                    tol=tol, sigma=sigma, profile=profile, window=window, progress=progress,
                    warn=warn, per_record=per_record, force=force, load_by=load_by)
    plan = make_plan(req)
    state = FitState(req, plan, Run(plan.z0, float("nan"), 0, False, plan.abort or ""), 0,
                     (), plan.shooting)
    if not plan.abort:
        state = optimize_fit(state)
    return finish(state, t_begin)


def finish(state: FitState, t_begin: float, stacklevel: int = 3) -> FitResult:
    """A fit's last stages from its best run (`state`): the channels reweighted (a refit
    while their noise levels move), the uncertainty at the estimate, and the warnings
    (`req.warn`, attributed `stacklevel` frames up: the caller of `fit` or `fit_many`)."""
    if not state.plan.abort:
        state = reweight(state)
    req = state.req
    res = with_wrapped_angles(_result(state, t_begin))
    if req.warn:
        if res.identifiable is False:
            warnings.warn("; ".join(res.unidentifiable_directions), IdentifiabilityWarning,
                          stacklevel=stacklevel)
        if not res.converged:
            warnings.warn(f"fit did not converge: {res.message}", ConvergenceWarning,
                          stacklevel=stacklevel)
    return res
