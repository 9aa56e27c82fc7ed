"""Uncertainty and identifiability from the sensitivity matrix.

With residuals `r(z)` (n,) and coordinates `z` (p,): sensitivities `J = dr/dz` (n, p) by
forward mode through the ODE solve (p tangents are cheaper than n cotangents); noise
variance `sigma^2 = |r|^2 / (n - p)`; Laplace covariance `sigma^2 (J^T J)^-1` from the SVD
`J = U diag(s) V^T`. A direction of z is **unidentifiable** when it is numerically in the
null space ([`RANK_TOL`][]) or its standard error `sigma / s` exceeds
[`PRACTICAL_LIMIT`][] (each parameter on its own scale); the model's known flat
directions ([`symmetries`][crank_jax.identify.symmetries]) are tested by name.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from ..runtime.arrays import device_array
from ..stats.diagnostics import robust_uncertainty
from .coordinates import own_scale
from .programs import jacobian_at
from .symmetries import fixed_scale_members, known_directions, name_list
from .verdict import Z95, check

__all__ = ["Uncertainty", "analyze", "assess", "undefined", "PRACTICAL_LIMIT", "RANK_TOL", "Z95",
           "sample_rows", "inflate", "misfit", "own_scale"]

#: Relative singular values below this are the numerical null space.
RANK_TOL = 1e-7
#: A direction whose standard error (in log coordinates, or a linear one in units of its
#: own magnitude) exceeds this is unidentifiable in practice: the data cannot even pin it
#: down to within +-50%.
PRACTICAL_LIMIT = 0.5
# A parameter whose unit vector has at least this component in an unidentifiable
# subspace has no meaningful standard error.
_AFFECTED = 0.05
# Two unit directions whose inner product exceeds this (in magnitude) are the same one.
_SAME_DIRECTION = 0.99
_RICHER = ", or make the experiment richer (a larger amplitude, a known load)"


class Uncertainty(NamedTuple):
    """Uncertainty of the reported parameters (p of them), in physical units.

    NaN marks a quantity that is undefined (an unidentifiable parameter's stderr and CI).
    """

    stderr: np.ndarray
    """(p,) standard errors, in each parameter's unit."""
    ci95: np.ndarray
    """(p, 2) 95% confidence intervals (log-normal for positive parameters)."""
    correlation: np.ndarray
    """(p, p) correlation matrix."""
    covariance_z: np.ndarray
    """(p, p) Laplace covariance of the coordinates z."""
    singular_values: np.ndarray
    """(p,) singular values of the scaled sensitivity matrix, descending."""
    condition_number: float
    """s_max / s_min of the scaled sensitivity matrix (inf when singular)."""
    sigma: float
    """Noise standard deviation estimated from the residuals (or given), rad."""
    identifiable: bool
    directions: list[str]
    """One sentence per unidentifiable direction (empty when identifiable)."""
    affected: np.ndarray
    """(p,) bool: parameters involved in an unidentifiable direction."""
    candidates: tuple = ()
    """`(u, se)` of each flagged direction that is weak rather than exactly flat (unit
    vector u (p,) in z, its standard error): a quadratic guess, for the profile
    likelihood to confirm (`verdict.check`)."""


def _term(name: str, coef: float, log: bool) -> str:
    sign = "-" if coef < 0 else "+"
    return f"{sign} {abs(coef):.2f} {'ln ' + name if log else name}"


def analyze(
    J: np.ndarray,
    residuals: np.ndarray,
    n: int,
    names: Sequence[str],
    values: np.ndarray,
    log: Sequence[bool],
    ref: np.ndarray,
    sigma: float | None = None,
    geometry: dict[str, float] | None = None,
    folded: Sequence[bool] | None = None,
    fixed_scale: Sequence[str] = (),
    closed: Sequence[np.ndarray] = (),
) -> Uncertainty:
    """Standard errors, intervals, correlations and identifiability of a fit.

    **Arguments:** `J` (N, p): the residuals' Jacobian in z (rows of zero weight
    allowed); `residuals` (N,) at the estimate; `n`: fitted samples; `names`, `values`
    (p,), `log` (p,), `ref` (p,): the reported parameters, their estimates, whether each
    is in log space, the scale of linear ones; `sigma`: the noise level if known (default:
    from the residuals); `geometry`: `r`, `L`, `b`, `s` (m), for the coupler's
    equivalent-mass direction; `folded` (p,): parameters `>= 0` (interval cut at 0);
    `fixed_scale`: fixed non-zero members of the common scale
    ([`fixed_scale_members`][crank_jax.identify.symmetries.fixed_scale_members]: any one
    and there is none); `closed`: unit vectors of z along which the profile likelihood
    closes ([`verdict.check`][crank_jax.identify.verdict.check]), not flagged.

    Every verdict is judged on the parameters' own scale ([`own_scale`][]), a linear
    coordinate in units of `max(|value|, ref)` (a torque started near 0 has a tiny `ref`,
    and in units of it a well-determined torque looked undetermined). The covariance
    returned is that of z. **Returns:** an [`Uncertainty`][].
    """
    log = np.asarray(log, dtype=bool)
    values = np.asarray(values, dtype=float)
    per = own_scale(values, log, ref)
    closed_w = [_unit(np.asarray(c, float) / per) for c in closed]
    unc = _analyze_own(np.asarray(J, dtype=float) * per, residuals, n, names, values, log,
                       np.asarray(ref, float) * per, sigma, geometry, folded, fixed_scale,
                       closed_w)
    # Back to z = per * w: the covariance, and each candidate direction with its error.
    cands = []
    for u, se in unc.candidates:
        g = float(np.linalg.norm(u * per))
        cands.append((u * per / g, se * g))
    return unc._replace(covariance_z=unc.covariance_z * np.outer(per, per),
                        candidates=tuple(cands))


def _unit(u: np.ndarray) -> np.ndarray:
    norm = float(np.linalg.norm(u))
    return u / norm if norm > 0 else u


def _analyze_own(J, residuals, n, names, values, log, ref, sigma, geometry, folded,
                 fixed_scale, closed) -> Uncertainty:
    """[`analyze`][] in coordinates on the parameters' own scale (`J`, `ref` and the
    `closed` directions in them); the covariance and candidates returned are in them."""
    p = J.shape[1]
    dof = max(n - p, 1)
    if sigma is None:
        sigma = float(np.sqrt(np.sum(np.square(residuals)) / dof))
    _, s, Vt = np.linalg.svd(J, full_matrices=False)
    s_max = s[0] if s.size and s[0] > 0 else 1.0
    numeric_null = s <= RANK_TOL * s_max
    with np.errstate(divide="ignore"):
        se_dir = np.where(s > 0, sigma / np.where(s > 0, s, 1.0), np.inf)
    V = Vt.T  # columns: right singular vectors (unit, in z)

    def confirmed(u):  # not along a direction the profile likelihood closes
        return all(abs(float(u @ c)) < _SAME_DIRECTION for c in closed)

    weak = (se_dir > PRACTICAL_LIMIT) & ~numeric_null
    weak &= np.array([confirmed(V[:, i]) for i in range(V.shape[1])], dtype=bool)
    flagged = numeric_null | weak

    known = known_directions(names, values, log, ref, geometry, fixed_scale)
    directions, Vf, candidates = _named(J, V, flagged, weak, se_dir, sigma, s_max, known,
                                        names, log, confirmed)
    affected = (np.linalg.norm(Vf, axis=1) > _AFFECTED) if Vf.size else np.zeros(p, bool)
    # Laplace covariance; the numerical null space is left out (a pseudo-inverse), so
    # parameters orthogonal to it keep their (correct) standard errors.
    inv_s2 = np.where(numeric_null, 0.0, 1.0 / np.where(s > 0, s, 1.0) ** 2)
    cov = sigma**2 * (V * inv_s2) @ V.T
    se_z, ci = _intervals(cov, affected, values, log, ref, folded)
    stderr = np.where(log, values * se_z, ref * se_z)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.sqrt(np.diag(cov))
        corr = cov / np.outer(d, d)
    corr[affected, :] = np.nan
    corr[:, affected] = np.nan
    s_min = s[-1] if s.size else 0.0
    cond = float(s_max / s_min) if s_min > 0 else math.inf
    return Uncertainty(stderr, ci, corr, cov, s, cond, sigma,
                       not directions, directions, affected, tuple(candidates))


def _named(J, V, flagged, weak, se_dir, sigma, s_max, known, names, log, confirmed):
    """The flagged directions in words: the known structural ones (`known`, tested
    explicitly so they can be stated by name) first, then what is left of the flagged
    singular directions `V[:, flagged]`. **Returns:** `(directions, Vf, candidates)`:
    the messages, an orthonormal basis (p, f) of everything flagged, and the weak
    (not exactly flat) directions with their standard errors, for the profile check."""
    p = V.shape[0]
    directions: list[str] = []
    Vf = V[:, flagged]
    found, candidates = [], []
    for u, message in known:
        gain = float(np.linalg.norm(J @ u))
        exact = gain <= RANK_TOL * s_max
        if exact or (sigma / max(gain, 1e-300) > PRACTICAL_LIMIT and confirmed(u)):
            directions.append(message)
            found.append(u)
            if not exact:
                candidates.append((u, sigma / gain))
    # An orthonormal basis of the named directions found.
    Q = np.linalg.qr(np.column_stack(found))[0] if found else np.zeros((p, 0))
    for i in np.flatnonzero(weak):
        # A weak singular direction not (mostly) one of the named symmetries.
        if np.linalg.norm(Q.T @ V[:, i]) < _SAME_DIRECTION:
            candidates.append((V[:, i], float(se_dir[i])))
    if not found:
        _describe(Vf, names, log, se_dir, directions)
        return directions, Vf, candidates
    rest = Vf - Q @ (Q.T @ Vf)
    if rest.size:
        ur, sr, _ = np.linalg.svd(rest, full_matrices=False)
        rest = ur[:, sr > 0.5]
    _describe(rest, names, log, se_dir, directions)
    return directions, (np.column_stack([Q, rest]) if rest.size else Q), candidates


def _intervals(cov, affected, values, log, ref, folded) -> tuple[np.ndarray, np.ndarray]:
    """The standard errors in z (p,) of the covariance `cov` (NaN where `affected`) and
    the 95% Laplace intervals (p, 2): log-normal for log coordinates, normal for linear
    ones, cut at 0 for a folded parameter (`>= 0`: an estimate near its bound 0 gets
    `[0, value + 1.96 se]`, which holds 0 when the data cannot tell it from 0)."""
    se_z = np.sqrt(np.maximum(np.diag(cov), 0.0))
    se_z[affected] = np.nan
    log = np.asarray(log, dtype=bool)
    lo = np.where(log, values * np.exp(-Z95 * se_z), values - Z95 * ref * se_z)
    hi = np.where(log, values * np.exp(Z95 * se_z), values + Z95 * ref * se_z)
    if folded is not None:
        lo = np.where(np.asarray(folded, dtype=bool), np.maximum(lo, 0.0), lo)
    return se_z, np.column_stack([lo, hi])


def _describe(Vf: np.ndarray, names, log, se_dir, out: list[str]) -> None:
    """Append one sentence for the unidentifiable subspace spanned by the columns of Vf."""
    if Vf.size == 0:
        return
    d = Vf.shape[1]
    weight = np.linalg.norm(Vf, axis=1)
    involved = [names[i] for i in np.argsort(-weight) if weight[i] > _AFFECTED]
    if d == 1:
        v = Vf[:, 0]
        v = v * np.sign(v[np.argmax(np.abs(v))])
        order = [i for i in np.argsort(-np.abs(v)) if abs(v[i]) > _AFFECTED]
        combo = " ".join(_term(names[i], v[i], bool(log[i])) for i in order).lstrip("+ ")
        out.append(f"the combination {combo} is not determined by the data: fix one of "
                   f"{name_list(involved)}{_RICHER}")
    elif len(involved) <= d:
        out.append(f"none of {name_list(involved)} is determined by the data, alone or in "
                   f"combination: fix them{_RICHER}")
    else:
        out.append(f"{name_list(involved)} enter the data only through "
                   f"{max(len(involved) - d, 0)} combinations ({d} directions are not "
                   f"determined): fix {d} of them{_RICHER}")


def null_space(J: np.ndarray) -> np.ndarray:
    """(p, h) orthonormal basis of the numerical null space of `J` (`s <= RANK_TOL s_max`):
    the exactly flat directions."""
    _, s, Vt = np.linalg.svd(np.asarray(J, dtype=float), full_matrices=True)
    s = np.concatenate([s, np.zeros(Vt.shape[0] - s.size)])
    s_max = s[0] if s.size and s[0] > 0 else 1.0
    return Vt[s <= RANK_TOL * s_max].T


def undefined(p: int, why: str) -> Uncertainty:
    """An [`Uncertainty`][] with nothing defined (NaN), for a fit with no estimate."""
    nan = np.full(p, np.nan)
    return Uncertainty(nan, np.full((p, 2), np.nan), np.full((p, p), np.nan),
                       np.full((p, p), np.nan), nan, math.inf, float("nan"), False, [why],
                       np.ones(p, bool))


def _series(ss):
    """`(channel, weight, rows, n)` of each record's channels, in the order of the
    single-shooting residual vector of `ss`: its `n` fitted rows there (padding left out)
    and the channel's weight in the residuals."""
    k = 0
    for e in ss.exps:
        n, size = e.n, int(np.prod(e.seg.ts.shape))
        for c, name in enumerate(e.channels):
            yield name, float(e.weight[c]), k + np.arange(n), n
            k += size


def sample_rows(ss) -> tuple[np.ndarray, list[int]]:
    """Indices of the fitted samples in the single-shooting residual vector of `ss` (time
    order), and the number of samples per series (one per record and channel)."""
    series = list(_series(ss))
    return np.concatenate([s[2] for s in series]), [s[3] for s in series]


def channel_rows(ss) -> dict[str, tuple[np.ndarray, list[int], float]]:
    """Channel name -> (its fitted rows over every record that has it, the samples per
    record, its weight in the residuals)."""
    out: dict[str, tuple[list, list, float]] = {}
    for name, w, rows, n in _series(ss):
        got = out.setdefault(name, ([], [], w))
        got[0].append(rows)
        got[1].append(n)
    return {name: (np.concatenate(r), ln, w) for name, (r, ln, w) in out.items()}


def inflate(unc: Uncertainty, factor: np.ndarray, values: np.ndarray, log, ref,
            folded=None) -> Uncertainty:
    """`unc` with every standard error multiplied by `factor` (p,) >= 1 and the intervals
    and the covariance widened to match (correlations unchanged)."""
    cov = unc.covariance_z * np.outer(factor, factor)
    _, ci = _intervals(cov, unc.affected, values, log, ref, folded)
    return unc._replace(stderr=unc.stderr * factor, ci95=ci, covariance_z=cov)


def misfit(ss, unc: Uncertainty, r_hat, J, values, sigma):
    """Whiteness of the residuals and, when they are not white, the standard errors
    widened for their correlation (a Newey-West sandwich, never below the white-noise
    ones). **Returns:** `(Uncertainty, Diagnostics, notes)`."""
    rows, lengths = sample_rows(ss)
    rob = robust_uncertainty(J[rows], r_hat[rows], lengths, sigma)
    if rob.warning is None:
        return unc, rob.diagnostics, []
    wide = inflate(unc, rob.inflation, values, ss.log, np.asarray(ss.ref), ss.folded)
    worst = float(np.max(rob.inflation))
    return wide, rob.diagnostics, [
        f"{rob.warning}; the standard errors and intervals account for the correlation "
        f"(up to {worst:.3g}x the white-noise ones)"]


def assess(ss, z_hat, converged: bool, sigma: float | None = None, at=None):
    """Residuals, sensitivities and uncertainty at the estimate `z_hat` of the single-
    shooting problem `ss` (`at`: those residuals (N,) and sensitivities (N, p) if solved).
    **Returns:** `(r, values, rms, Uncertainty, notes, Diagnostics or None)`.

    Identifiability is judged only at a converged estimate: a fit that did not converge
    says so, not that the data cannot determine a direction."""
    try:
        r_hat, failed, _, J = (np.asarray(x) for x in (
            (at[0], 0, 0, at[1]) if at is not None else jacobian_at(ss, device_array(z_hat))))
    except (RuntimeError, ValueError) as e:
        return (ss.no_residuals(), ss.host_values(z_hat),
                float("nan"), undefined(ss.p, f"sensitivities could not be computed: "
                                                f"{str(e).splitlines()[0]}"), [], None)
    values = ss.host_values(z_hat)
    n = ss.n_residuals
    rms = float(np.sqrt(np.sum(r_hat**2) / n)) if int(failed) == 0 else float("nan")
    notes: list[str] = []
    if not converged or int(failed) > 0:
        return r_hat, values, rms, undefined(ss.p, "did not converge"), notes, None
    if not np.all(np.isfinite(J)):
        return r_hat, values, rms, undefined(
            ss.p, "the sensitivities are undefined at the estimate (the solve failed), so "
                  "nothing can be said about identifiability"), notes, None
    fixed = fixed_scale_members(ss.base, ss.names, [(e.load, e.torque) for e in ss.exps])

    def judge(closed=()):
        return analyze(J, r_hat, n, ss.names, values, ss.log, np.asarray(ss.ref), sigma,
                       {k: float(getattr(ss.base, k)) for k in "rLbs"}, ss.folded, fixed,
                       closed)

    unc = judge()
    if unc.candidates:
        # The sensitivities only suggest a weak direction; the profile likelihood decides.
        checked = check(ss, z_hat, unc.candidates, values, ss.log, np.asarray(ss.ref),
                        ss.folded, ss.names, n, float(r_hat @ r_hat), hold=null_space(J))
        notes += checked.notes
        if checked.closed:
            unc = judge(checked.closed)
    if not unc.identifiable:
        notes += [f"not identifiable: {m}" for m in unc.directions]
        bad = [nm for nm, a in zip(ss.names, unc.affected) if a]
        notes.append(f"no standard errors for {', '.join(bad)}: the values reported for them "
                     "are one point of a set that fits equally well, not estimates")
    elif unc.condition_number > 1e6:
        notes.append(f"the scaled sensitivity matrix is poorly conditioned (condition number "
                     f"{unc.condition_number:.2g}): expect large, strongly correlated errors")
    unc, diag, more = misfit(ss, unc, r_hat, J, values, sigma)
    return r_hat, values, rms, unc, more + notes, diag
