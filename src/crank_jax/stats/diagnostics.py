"""Residual diagnostics and honest uncertainty when the model does not explain the data.

The white-noise (Laplace) covariance `sigma^2 (J^T J)^-1` assumes independent residuals;
a wrong model (unmodelled friction, a disturbance, a drifting offset) correlates them in
time, and that covariance is overconfident, often by an order of magnitude. This module
tests the residuals for whiteness ([`residual_diagnostics`][]: Ljung-Box, the lag-1
autocorrelation, the effective number of samples), estimates a covariance that allows for
the correlation ([`hac_covariance`][]: Newey-West), and never reports variances below the
white-noise ones ([`widen`][]); [`robust_uncertainty`][] does all three for a fit.

Several records: pass `lengths` (samples per record, in order) so that no lag pairs
samples of different records. Only NumPy and the standard library (the chi-squared tail
computed here), so this module costs nothing to import.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

__all__ = ["Diagnostics", "RobustUncertainty", "residual_diagnostics", "hac_covariance",
           "widen", "robust_uncertainty", "chi2_sf", "autocorrelation", "auto_bandwidth",
           "not_white_message", "WHITE_P"]

#: Residuals with a Ljung-Box p-value below this are declared not white.
WHITE_P = 0.01
_MAX_LAGS = 20


def chi2_sf(x: float, dof: float) -> float:
    """Survival function `P(X > x)` (in [0, 1]) of a chi-squared variable with `dof` > 0
    degrees of freedom at `x` >= 0: the regularised upper incomplete gamma function
    `Q(dof/2, x/2)`, a power series below `x/2 < dof/2 + 1`, a Lentz continued fraction
    above (accurate in the far tail, where `1 - P` would cancel)."""
    if not dof > 0:
        raise ValueError(f"chi2_sf: dof must be > 0, got {dof!r}")
    if not x > 0:
        return 1.0
    if math.isinf(x):
        return 0.0
    a, y = 0.5 * dof, 0.5 * x
    log_pre = a * math.log(y) - y - math.lgamma(a)
    if y < a + 1.0:
        term = total = 1.0 / a
        ap = a
        for _ in range(10_000):
            ap += 1.0
            term *= y / ap
            total += term
            if abs(term) < abs(total) * 1e-16:
                break
        return float(min(max(1.0 - total * math.exp(log_pre), 0.0), 1.0))
    tiny = 1e-300
    b = y + 1.0 - a
    c = 1.0 / tiny
    d = 1.0 / b
    h = d
    for i in range(1, 10_000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < 1e-16:
            break
    return float(min(max(math.exp(log_pre) * h, 0.0), 1.0))


def _split(n: int, lengths: Sequence[int] | None) -> list[slice]:
    """Slices of the records in a concatenated vector of length `n`."""
    if lengths is None:
        return [slice(0, n)]
    lengths = [int(m) for m in lengths]
    if any(m < 1 for m in lengths) or sum(lengths) != n:
        raise ValueError(f"lengths {lengths} must be positive record lengths that add up to "
                         f"the number of residuals ({n})")
    ends = np.cumsum(lengths)
    return [slice(int(e - m), int(e)) for e, m in zip(ends, lengths)]


def autocorrelation(r: np.ndarray, n_lags: int, lengths: Sequence[int] | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Sample autocorrelation of residuals `r` (n,), pooled over records (`lengths`:
    samples per record), each centred on its own mean, lag-`k` products within one record:
    `rho_k = sum_records sum_t e_t e_{t+k} / sum_records sum_t e_t^2`.

    **Returns:** `(acf, pairs)`, both (n_lags + 1,): `acf[0] = 1`, and the number of
    products at each lag."""
    r = np.asarray(r, dtype=float).ravel()
    parts = [r[s] - r[s].mean() for s in _split(r.shape[0], lengths)]
    gamma = np.zeros(n_lags + 1)
    pairs = np.zeros(n_lags + 1)
    for e in parts:
        m = e.shape[0]
        for k in range(min(n_lags, m - 1) + 1):
            gamma[k] += float(e[: m - k] @ e[k:])
            pairs[k] += m - k
    if gamma[0] <= 0:
        # Residuals that are exactly constant per record carry no correlation information.
        return np.concatenate([[1.0], np.zeros(n_lags)]), pairs
    return gamma / gamma[0], pairs


def auto_bandwidth(rho1: float | np.ndarray, n: int,
                   var: np.ndarray | None = None) -> int:
    """Newey-West truncation lag from Andrews' (1991) AR(1) plug-in for Bartlett weights.

    `S = 1.1447 (alpha n)^(1/3)` with, for one series, `alpha = 4 rho^2 / ((1 - rho)^2
    (1 + rho)^2)`, and for several (the components of the scores, Andrews' eq. 6.4 with
    equal weights) `alpha = sum_a 4 rho_a^2 v_a^2 / ((1 - rho_a)^6 (1 + rho_a)^2) /
    sum_a v_a^2 / (1 - rho_a)^4` (`v_a`: innovation variances). Each `rho` is clipped to
    [-0.97, 0.97] and `S` to [1, n // 4]: a window near the record length makes the
    sandwich collapse (at the least-squares optimum `sum_t J_t r_t = 0`, so the
    full-length sum of its autocovariances is zero).

    **Arguments:** `rho1`: lag-1 autocorrelation(s), scalar or (p,); `n`: samples (of the
    shortest record); `var` (p,): innovation variances (default: equal). **Returns:** the
    number of lags, >= 1 (so at least lag 1 gets weight 1/2)."""
    rho = np.atleast_1d(np.asarray(rho1, dtype=float))
    rho = np.clip(np.where(np.isfinite(rho), rho, 0.0), -0.97, 0.97)
    v = np.ones_like(rho) if var is None else np.asarray(var, dtype=float)
    den = float(np.sum(v**2 / (1 - rho) ** 4))
    num = float(np.sum(4 * rho**2 * v**2 / ((1 - rho) ** 6 * (1 + rho) ** 2)))
    alpha = num / den if den > 0 else 0.0
    s = 1.1447 * (alpha * n) ** (1 / 3)
    return int(min(max(math.ceil(s), 1), max(n // 4, 1)))


def _score_bandwidth(g: np.ndarray, slices: list[slice], shortest: int) -> int:
    """Andrews' plug-in from an AR(1) fitted to each component of the scores `g` (n, p)."""
    p = g.shape[1]
    xy, xx, ss, m = np.zeros(p), np.zeros(p), np.zeros(p), 0
    centred = [g[s] - g[s].mean(axis=0) for s in slices]
    for gs in centred:
        xy += np.sum(gs[1:] * gs[:-1], axis=0)
        xx += np.sum(gs[:-1] ** 2, axis=0)
        m += gs.shape[0] - 1
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = np.where(xx > 0, xy / xx, 0.0)
    rho = np.clip(rho, -0.97, 0.97)
    for gs in centred:
        ss += np.sum((gs[1:] - rho * gs[:-1]) ** 2, axis=0)
    keep = xx > 0
    if not keep.any():
        return 1
    return auto_bandwidth(rho[keep], shortest, ss[keep] / max(m, 1))


class Diagnostics(NamedTuple):
    """Whiteness of the residuals of a fit.

    - `ljung_box_p`: p-value of the Ljung-Box test of `n_lags` autocorrelations (small:
      correlated residuals, the model does not explain the data).
    - `ljung_box_q`: its statistic, chi-squared with `n_lags` degrees of freedom under H0.
    - `n_lags`: lags tested.
    - `lag1_autocorrelation`: `rho_1`, in [-1, 1].
    - `effective_samples`: `n / tau` with the integrated autocorrelation time
      `tau = 1 + 2 sum_l w_l rho_l` (Bartlett weights, [`auto_bandwidth`][]), clipped to
      [1, n]: the number of independent samples the residuals are worth.
    - `n_samples`: n.
    - `white`: `ljung_box_p >= WHITE_P`.
    - `acf` (k + 1,): autocorrelation at lags 0..k (k = max(n_lags, bandwidth)).
    - `bandwidth`: the truncation lag of the Bartlett window used for `effective_samples`
      ([`auto_bandwidth`][] from `rho_1`).
    """

    ljung_box_p: float
    ljung_box_q: float
    n_lags: int
    lag1_autocorrelation: float
    effective_samples: float
    n_samples: int
    white: bool
    acf: np.ndarray
    bandwidth: int

    def not_white_message(self) -> str:
        """[`not_white_message`][crank_jax.stats.diagnostics.not_white_message] of
        these diagnostics (a method, so that the report reads it without importing the fit)."""
        return not_white_message(self)

    def to_json(self) -> dict:
        """The `diagnostics` object of `fit.json` (plain floats, ints and bools)."""
        return {
            "ljung_box_p": float(self.ljung_box_p),
            "ljung_box_q": float(self.ljung_box_q),
            "ljung_box_lags": int(self.n_lags),
            "lag1_autocorrelation": float(self.lag1_autocorrelation),
            "effective_samples": float(self.effective_samples),
            "n_samples": int(self.n_samples),
            "white": bool(self.white),
            "bandwidth": int(self.bandwidth),
            "acf": [float(a) for a in self.acf],
        }


def residual_diagnostics(r: np.ndarray, n_lags: int | None = None,
                         lengths: Sequence[int] | None = None) -> Diagnostics:
    """Test residuals `r` (n,) for whiteness (several records concatenated, `lengths`
    samples each; default one), over `n_lags` lags (default `min(20, shortest // 5)`, at
    least 1). **Returns:** a [`Diagnostics`][]. The Ljung-Box statistic over several
    records is `Q = n (n + 2) sum_k rho_k^2 / m_k`, `m_k` the number of lag-`k` pairs."""
    r = np.asarray(r, dtype=float).ravel()
    n = r.shape[0]
    if n < 3 or not np.all(np.isfinite(r)):
        raise ValueError(f"residual_diagnostics: need at least 3 finite residuals, got {n} "
                         f"({int(np.sum(~np.isfinite(r)))} not finite)")
    shortest = min(s.stop - s.start for s in _split(n, lengths))
    if n_lags is None:
        n_lags = max(1, min(_MAX_LAGS, shortest // 5))
    if not (1 <= n_lags < shortest):
        raise ValueError(f"n_lags = {n_lags} must be >= 1 and below the shortest record's "
                         f"length ({shortest})")
    rho1, _ = autocorrelation(r, 1, lengths)
    bw = min(auto_bandwidth(float(rho1[1]), shortest), shortest - 1)
    k = max(n_lags, bw)
    acf, pairs = autocorrelation(r, k, lengths)
    lags = np.arange(1, n_lags + 1)
    q = float(n * (n + 2) * np.sum(acf[lags] ** 2 / pairs[lags]))
    p = chi2_sf(q, n_lags)
    w = 1.0 - np.arange(1, bw + 1) / (bw + 1)
    tau = 1.0 + 2.0 * float(np.sum(w * acf[1:bw + 1]))
    n_eff = float(min(max(n / tau, 1.0), n)) if tau > 0 else float(n)
    return Diagnostics(p, q, int(n_lags), float(acf[1]), n_eff, n, p >= WHITE_P, acf, bw)


def hac_covariance(J: np.ndarray, r: np.ndarray, bandwidth: int | None = None,
                   lengths: Sequence[int] | None = None) -> np.ndarray:
    """Newey-West (HAC) sandwich covariance of least-squares estimates.

    `(J^T J)^-1 Omega (J^T J)^-1` with the long-run covariance of the scores
    `g_t = J_t r_t`: `Omega = c (Gamma_0 + sum_{l=1}^S w_l (Gamma_l + Gamma_l^T))`,
    `Gamma_l = sum_t g_t g_{t-l}^T` (within each record), Bartlett weights
    `w_l = 1 - l / (S + 1)` (which keep Omega positive semi-definite) and the small-sample
    factor `c = n / (n - p)`; for white residuals the same as `sigma^2 (J^T J)^-1`.

    `J` (n, p): the residuals' Jacobian; `r` (n,): the residuals; `bandwidth`: S (default
    [`auto_bandwidth`][] from an AR(1) fitted to each component of the scores);
    `lengths`: samples per record. **Returns:** (p, p), `J^T J` pseudo-inverted on its
    numerical null space, like the white-noise one."""
    J = np.asarray(J, dtype=float)
    r = np.asarray(r, dtype=float).ravel()
    n, p = J.shape
    if r.shape[0] != n:
        raise ValueError(f"hac_covariance: J has {n} rows but r has {r.shape[0]} entries")
    slices = _split(n, lengths)
    shortest = min(s.stop - s.start for s in slices)
    g = J * r[:, None]
    if bandwidth is None:
        bandwidth = _score_bandwidth(g, slices, shortest)
    bandwidth = int(min(max(bandwidth, 0), shortest - 1))
    omega = np.zeros((p, p))
    for s in slices:
        gs = g[s]
        omega += gs.T @ gs
        for lag in range(1, bandwidth + 1):
            gam = gs[lag:].T @ gs[:-lag]
            omega += (1.0 - lag / (bandwidth + 1)) * (gam + gam.T)
    omega *= n / max(n - p, 1)
    bread = _pinv_gram(J)
    return bread @ omega @ bread


def _pinv_gram(J: np.ndarray) -> np.ndarray:
    """`(J^T J)^+` from the SVD of J, dropping the numerical null space (s < 1e-7 s_max)."""
    _, s, Vt = np.linalg.svd(J, full_matrices=False)
    keep = s > 1e-7 * (s[0] if s.size and s[0] > 0 else 1.0)
    inv = np.where(keep, 1.0 / np.where(keep, s, 1.0) ** 2, 0.0)
    return (Vt.T * inv) @ Vt


def widen(cov_white: np.ndarray, cov_hac: np.ndarray) -> np.ndarray:
    """`D cov_hac D` (p, p), `D = diag(max(1, sqrt(white_ii / hac_ii)))`: the HAC
    correlations with each variance at least the white-noise one (the HAC estimate can
    come out smaller by chance; a report never claims more precision than the white-noise
    analysis). `cov_white` where `cov_hac` has a non-positive or non-finite variance."""
    cw = np.asarray(cov_white, dtype=float)
    ch = np.asarray(cov_hac, dtype=float)
    dw, dh = np.diag(cw), np.diag(ch)
    if cw.shape != ch.shape or not (np.all(np.isfinite(ch)) and np.all(dh > 0)):
        return cw.copy()
    d = np.sqrt(np.maximum(1.0, np.where(np.isfinite(dw), dw, 0.0) / dh))
    return ch * np.outer(d, d)


def not_white_message(diag: Diagnostics) -> str:
    """The warning for correlated residuals (contains 'not white')."""
    ratio = diag.n_samples / max(diag.effective_samples, 1.0)
    return (f"the residuals are not white (Ljung-Box p = {diag.ljung_box_p:.2g} over "
            f"{diag.n_lags} lags; lag-1 autocorrelation {diag.lag1_autocorrelation:.2f}; about "
            f"{diag.effective_samples:.0f} independent samples of {diag.n_samples}, "
            f"{ratio:.0f}x fewer): the model does not explain the data, so the white-noise "
            "standard errors are overconfident; the reported ones allow for the correlation "
            "(Newey-West), but a better model (friction, a load, a trimmed start-up "
            "transient) is the real fix")


class RobustUncertainty(NamedTuple):
    """Output of [`robust_uncertainty`][]: covariances of the coordinates z, all (p, p).

    `cov` is the one to report: `cov_white` when the residuals are white, otherwise
    `widen(cov_white, cov_hac)`. `inflation` (p,): `sqrt(cov_ii / cov_white_ii)` >= 1, the
    factor applied to each white-noise standard error. `warning` is `None` or the
    [`not_white_message`][].
    """

    diagnostics: Diagnostics
    cov_white: np.ndarray
    cov_hac: np.ndarray
    cov: np.ndarray
    inflation: np.ndarray
    warning: str | None


def robust_uncertainty(J: np.ndarray, r: np.ndarray, lengths: Sequence[int] | None = None,
                       sigma: float | None = None) -> RobustUncertainty:
    """Whiteness test plus the covariance to report, for a least-squares fit: `J` (n, p)
    the residuals' Jacobian at the estimate (one row per sample), `r` (n,) the residuals,
    `lengths` samples per record, `sigma` the noise level if known (default
    `|r| / sqrt(n - p)`). **Returns:** a [`RobustUncertainty`][]."""
    J = np.asarray(J, dtype=float)
    r = np.asarray(r, dtype=float).ravel()
    n, p = J.shape
    diag = residual_diagnostics(r, lengths=lengths)
    if sigma is None:
        sigma = float(np.sqrt(r @ r / max(n - p, 1)))
    cov_white = sigma**2 * _pinv_gram(J)
    cov_hac = hac_covariance(J, r, None, lengths)
    cov = cov_white.copy() if diag.white else widen(cov_white, cov_hac)
    with np.errstate(invalid="ignore", divide="ignore"):
        infl = np.sqrt(np.diag(cov) / np.diag(cov_white))
    infl = np.where(np.isfinite(infl), infl, 1.0)
    return RobustUncertainty(diag, cov_white, cov_hac, cov, infl,
                             None if diag.white else not_white_message(diag))
