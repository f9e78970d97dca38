"""The core's chi-square quantiles are scipy.stats.chi2's, bit for bit."""

from __future__ import annotations

import math

import numpy as np
from scipy.stats import chi2

from orbit_tracking.core.chi2 import chi2_isf, chi2_isf_each, chi2_ppf, chi2_ppf_each


def test_the_quantiles_are_scipys_to_the_last_bit() -> None:
    rng = np.random.default_rng(1)
    p = np.concatenate([rng.random(1500), 10 ** -rng.uniform(0, 15, 1500), [0.0, 1.0, 0.5]])
    k = rng.integers(1, 3000, p.size).astype(float)
    k[:50] = rng.uniform(0.01, 3.0, 50)  # fractional degrees of freedom too
    want_ppf, want_isf = chi2.ppf(p, k), chi2.isf(p, k)
    for j in range(p.size):
        assert chi2_ppf(p[j], k[j]) == want_ppf[j], (p[j], k[j])
        assert chi2_isf(p[j], k[j]) == want_isf[j], (p[j], k[j])
    for q in (0.0, 1e-9, 0.01, 0.5, 0.999, 1.0):
        dofs = np.concatenate([k, [0.0, -1.0]])
        np.testing.assert_array_equal(chi2_ppf_each(q, dofs), chi2.ppf(q, dofs))
        np.testing.assert_array_equal(chi2_isf_each(q, dofs), chi2.isf(q, dofs))


def test_outside_the_domain_is_nan() -> None:
    for p, k in ((-0.1, 3), (1.5, 3), (0.5, 0), (0.5, -2), (math.nan, 3)):
        assert math.isnan(chi2_ppf(p, k)) and math.isnan(chi2_isf(p, k))
