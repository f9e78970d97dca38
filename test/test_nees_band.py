"""The band of a mean NEES over correlated samples (core.metrics.correlated_nees_band)."""

import numpy as np
import pytest
from scipy import special

from orbit_tracking.core.chi2 import chi2_ppf
from orbit_tracking.core.metrics import (
    correlated_nees_band,
    nees,
    nees_summary,
    whitened_correlation,
)


def test_independent_samples_get_the_chi_square_band():
    n = 20
    lo, hi, p_in = correlated_nees_band(np.eye(3 * n))
    s = nees_summary(np.full(n, 3.0))
    assert lo == pytest.approx(s.lo, rel=0.02) and hi == pytest.approx(s.hi, rel=0.02)
    assert p_in == pytest.approx(0.95, abs=0.01)


def test_samples_sharing_one_error_get_the_band_of_one_sample():
    n = 15
    r = np.kron(np.ones((n, n)), np.eye(3))  # every sample the same error
    lo, hi, p_in = correlated_nees_band(r)
    assert lo == pytest.approx(chi2_ppf(0.025, 3), rel=0.03)
    assert hi == pytest.approx(chi2_ppf(0.975, 3), rel=0.03)
    # the mean NEES is then chi2(3) itself: its chance to land in the band of 15 samples
    s = nees_summary(np.full(n, 3.0))
    exact = special.gammainc(1.5, s.hi / 2) - special.gammainc(1.5, s.lo / 2)
    assert p_in == pytest.approx(exact, abs=0.01)
    assert p_in < 0.6


def test_band_matches_a_monte_carlo_of_honest_correlated_errors():
    """Errors of an honest estimator: Gaussian with covariance C (correlated over time,
    each sample's block anisotropic); its published covariances are C's diagonal blocks.
    The band must hold 95 % of the mean NEES of many such draws."""
    rng = np.random.default_rng(3)
    n = 12
    t = np.arange(n) * 5.0
    corr_t = np.exp(-np.abs(t[:, None] - t[None, :]) / 20.0)
    a = rng.standard_normal((3, 3))
    axes = a @ a.T + np.eye(3)
    c = np.kron(corr_t, axes)
    blocks = np.array([c[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] for k in range(n)])
    lo, hi, p_in = correlated_nees_band(whitened_correlation(c))
    e = rng.standard_normal((20_000, 3 * n)) @ np.linalg.cholesky(c).T
    means = np.array([nees(x.reshape(n, 3), blocks).mean() for x in e[:4000]])
    inside = np.mean((means >= lo) & (means <= hi))
    assert inside == pytest.approx(0.95, abs=0.015)
    s = nees_summary(np.full(n, 3.0))
    assert np.mean((means >= s.lo) & (means <= s.hi)) == pytest.approx(p_in, abs=0.03)
    assert lo < s.lo and hi > s.hi  # wider than the independent band


def test_whitened_correlation_has_identity_blocks_and_keeps_unbounded_samples_apart():
    rng = np.random.default_rng(5)
    a = rng.standard_normal((9, 9))
    c = a @ a.T + np.eye(9)
    r = whitened_correlation(c, 3, np.array([True, False, True]))
    for k in range(3):
        np.testing.assert_allclose(r[3 * k : 3 * k + 3, 3 * k : 3 * k + 3], np.eye(3), atol=1e-9)
    assert np.all(r[3:6, [0, 1, 2, 6, 7, 8]] == 0.0)
    assert np.all(np.linalg.eigvalsh(r) > -1e-9)
