"""Residual whiteness tests and the Newey-West covariance (stats/diagnostics.py)."""

import math

import numpy as np
import pytest
import scipy.stats

import crank_jax as cj
from crank_jax.stats import diagnostics as dg


def ar1(rng, n, rho, sigma=1.0):
    """A stationary AR(1) series with innovation std sigma."""
    e = rng.normal(0.0, sigma, n)
    x = np.empty(n)
    x[0] = e[0] / math.sqrt(1 - rho**2)
    for t in range(1, n):
        x[t] = rho * x[t - 1] + e[t]
    return x


@pytest.mark.parametrize("x", [0.0, 1e-3, 0.5, 3.0, 17.3, 40.0, 120.0, 400.0])
@pytest.mark.parametrize("dof", [1, 2, 5, 10, 20, 57])
def test_chi2_sf_matches_scipy(x, dof):
    want = scipy.stats.chi2.sf(x, dof)
    got = dg.chi2_sf(x, dof)
    assert got == pytest.approx(want, rel=1e-10, abs=1e-300)


def test_ljung_box_statistic_and_p_independent():
    # Q and p from a direct transcription of the textbook formula, with scipy's tail.
    rng = np.random.default_rng(1)
    r = rng.normal(size=300) + 0.3 * np.sin(np.arange(300) / 7.0)
    d = dg.residual_diagnostics(r, n_lags=12)
    e = r - r.mean()
    n = e.size
    rho = np.array([e[:-k] @ e[k:] / (e @ e) for k in range(1, 13)])
    q = n * (n + 2) * np.sum(rho**2 / (n - np.arange(1, 13)))
    assert d.ljung_box_q == pytest.approx(q, rel=1e-12)
    assert d.ljung_box_p == pytest.approx(scipy.stats.chi2.sf(q, 12), rel=1e-9)
    assert d.lag1_autocorrelation == pytest.approx(rho[0], rel=1e-12)


def test_white_noise_p_uniform_and_neff_near_n():
    rng = np.random.default_rng(2)
    n = 1000
    ps, neffs = [], []
    for _ in range(200):
        d = dg.residual_diagnostics(rng.normal(size=n))
        ps.append(d.ljung_box_p)
        neffs.append(d.effective_samples)
    ps = np.array(ps)
    # Under H0 p is uniform: about 1% rejections at 0.01, and a KS test does not reject.
    assert np.mean(ps < dg.WHITE_P) < 0.04
    assert scipy.stats.kstest(ps, "uniform").pvalue > 1e-3
    assert np.median(neffs) > 0.9 * n
    assert np.all(np.array(neffs) <= n)


def test_ar1_detected_with_its_effective_sample_size():
    rng = np.random.default_rng(3)
    n, rho = 20000, 0.9
    d = dg.residual_diagnostics(ar1(rng, n, rho))
    assert d.ljung_box_p < dg.WHITE_P and not d.white
    assert d.lag1_autocorrelation == pytest.approx(rho, abs=0.01)
    assert d.effective_samples == pytest.approx(n * (1 - rho) / (1 + rho), rel=0.2)
    assert "not white" in dg.not_white_message(d)


def test_hac_standard_error_of_a_mean_under_ar1():
    # The least-squares estimate of a mean has J = 1; under AR(1) its variance tends to
    # the long-run variance / n = sigma_e^2 / (1 - rho)^2 / n. Averaged over 20 series
    # (one HAC estimate scatters by ~8%); Bartlett weights are biased low by ~5% here.
    rng = np.random.default_rng(4)
    n, rho = 20000, 0.8
    want = 1.0 / (1 - rho) ** 2 / n
    ratios, white = [], []
    for _ in range(20):
        x = ar1(rng, n, rho)
        r = x - x.mean()
        ratios.append(dg.hac_covariance(np.ones((n, 1)), r)[0, 0] / want)
        white.append(r @ r / (n - 1) / n / want)
    assert np.mean(ratios) == pytest.approx(1.0, abs=0.1)
    # The white-noise variance is overconfident by (1 + rho) / (1 - rho) = 9.
    assert np.mean(white) == pytest.approx(1 / 9, rel=0.1)


def test_hac_equals_white_for_white_noise_on_average():
    rng = np.random.default_rng(5)
    n = 2000
    t = np.linspace(0, 1, n)
    J = np.column_stack([np.ones(n), t, np.sin(9 * t)])
    ratios = []
    for _ in range(50):
        y = rng.normal(size=n)
        beta, *_ = np.linalg.lstsq(J, y, rcond=None)
        r = y - J @ beta
        white = (r @ r / (n - 3)) * np.linalg.inv(J.T @ J)
        ratios.append(np.diag(dg.hac_covariance(J, r)) / np.diag(white))
    assert np.allclose(np.mean(ratios, axis=0), 1.0, atol=0.05)


def test_records_are_not_paired_across_boundaries():
    # Two records, each a constant offset of opposite sign with white noise on top:
    # centred per record, they are white; pooled as one record they are strongly correlated.
    rng = np.random.default_rng(6)
    a = 5.0 + rng.normal(size=500)
    b = -5.0 + rng.normal(size=500)
    r = np.concatenate([a, b])
    assert dg.residual_diagnostics(r, lengths=[500, 500]).white
    assert not dg.residual_diagnostics(r).white
    # HAC on two records equals the sum of the per-record meats (block diagonal scores).
    J = np.column_stack([np.ones(1000), np.linspace(-1, 1, 1000)])
    full = dg.hac_covariance(J, r, bandwidth=4, lengths=[500, 500])
    bread = np.linalg.inv(J.T @ J)
    meat = np.zeros((2, 2))
    for s in (slice(0, 500), slice(500, 1000)):
        g = J[s] * r[s, None]
        meat += g.T @ g
        for lag in range(1, 5):
            gam = g[lag:].T @ g[:-lag]
            meat += (1 - lag / 5) * (gam + gam.T)
    assert np.allclose(full, bread @ meat @ bread * 1000 / 998, rtol=1e-12)
    with pytest.raises(ValueError, match="lengths"):
        dg.residual_diagnostics(r, lengths=[400, 500])


def test_widen_never_shrinks_and_stays_psd():
    rng = np.random.default_rng(7)
    for _ in range(100):
        A = rng.normal(size=(4, 4))
        B = rng.normal(size=(4, 4))
        cw, ch = A @ A.T + 0.1 * np.eye(4), B @ B.T + 0.1 * np.eye(4)
        c = dg.widen(cw, ch)
        assert np.all(np.diag(c) >= np.diag(cw) * (1 - 1e-12))
        assert np.all(np.diag(c) >= np.diag(ch) * (1 - 1e-12))
        assert np.allclose(np.diag(c), np.maximum(np.diag(cw), np.diag(ch)), rtol=1e-12)
        assert np.linalg.eigvalsh(c).min() > -1e-12 * np.abs(c).max()
    bad = np.diag([1.0, 0.0])
    assert np.array_equal(dg.widen(np.eye(2), bad), np.eye(2))


def test_robust_uncertainty_white_and_not_white():
    rng = np.random.default_rng(8)
    n = 3000
    t = np.linspace(0, 3, n)
    J = np.column_stack([np.ones(n), t])
    white = dg.robust_uncertainty(J, rng.normal(size=n))
    assert white.warning is None and np.array_equal(white.cov, white.cov_white)
    assert np.all(white.inflation == 1.0)
    red = dg.robust_uncertainty(J, ar1(rng, n, 0.95))
    assert "not white" in red.warning
    assert np.all(red.inflation >= 1.0) and red.inflation[0] > 2.0
    doc = red.diagnostics.to_json()
    for key in ("ljung_box_p", "lag1_autocorrelation", "effective_samples"):
        assert isinstance(doc[key], float)


def test_bad_input_names_the_field():
    with pytest.raises(ValueError, match="residuals"):
        dg.residual_diagnostics(np.array([1.0, np.nan, 2.0, 3.0]))
    with pytest.raises(ValueError, match="n_lags"):
        dg.residual_diagnostics(np.ones(10), n_lags=10)
    with pytest.raises(ValueError, match="rows"):
        dg.hac_covariance(np.ones((5, 1)), np.ones(4))
    with pytest.raises(ValueError, match="dof"):
        dg.chi2_sf(1.0, 0)


def test_public_names():
    assert cj.identify.residual_diagnostics is dg.residual_diagnostics
    assert cj.identify.hac_covariance is dg.hac_covariance


def test_auto_bandwidth_several_components_reduce_to_one():
    # Andrews' multi-series plug-in with identical components is the one-series rule.
    for rho in (0.0, 0.3, 0.9):
        assert dg.auto_bandwidth([rho, rho, rho], 5000) == dg.auto_bandwidth(rho, 5000)
    assert dg.auto_bandwidth(0.0, 5000) == 1
    assert dg.auto_bandwidth(0.99, 40) == 10  # capped at n // 4
