"""Issue 14: the telemetry's noise levels re-estimated from its residuals count their
correlation over a knot interval (``telemetry_noise.reestimate_telemetry_noise``).

White noise on top of an error correlated over a second or two (a velocity of its own
between the knots of ``w``) has a small lag-1 autocorrelation: the first-order formula
took the mean of a second's samples as ~20 independent ones. The long-run variance over
the lags of a base knot interval does not (robustness ascent draw 5, a velocity from
another source: its first window's velocity was 0.2 m/s off at sigmas of 0.04 m/s).
"""

from __future__ import annotations

import numpy as np
import pytest

from orbit_tracking.core.estimation import telemetry_noise
from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.estimator import estimate
from orbit_tracking.core.metrics import nees
from orbit_tracking.tools.bench.robustness_draw import _case


def _correlated(rng: np.random.Generator, n: int, tau: float) -> np.ndarray:
    """(n, 3) first-order autoregressive samples of unit variance, correlation time
    ``tau`` samples."""
    a = np.exp(-1.0 / tau)
    out = np.empty((n, 3))
    out[0] = rng.standard_normal(3)
    for i in range(1, n):
        out[i] = a * out[i - 1] + np.sqrt(1.0 - a * a) * rng.standard_normal(3)
    return out


def test_white_residuals_have_a_long_run_ratio_near_one():
    rng = np.random.default_rng(1)
    ratios = [telemetry_noise.long_run_ratio(rng.standard_normal((1200, 3)), 20) for _ in range(5)]
    assert all(1.0 <= r < 1.5 for r in ratios), ratios


def test_white_noise_on_a_correlated_error_counts_more_than_its_lag_one():
    rng = np.random.default_rng(2)
    e = rng.standard_normal((1200, 3)) + _correlated(rng, 1200, 10.0)
    rho = telemetry_noise.lag1(e)
    first_order = (1.0 + rho) / (1.0 - rho)
    ratio = telemetry_noise.long_run_ratio(e, 20)
    # half the variance correlated over 10 samples: ~1 + 0.5 * 2 * 10 over all lags, the
    # Bartlett weights over 20 lags keep most of it; the first-order formula ~2.6
    assert first_order < 3.5, first_order
    assert ratio > 2.0 * first_order, (ratio, first_order)
    # no lags (fewer than four rows per lag): nothing to say
    assert telemetry_noise.long_run_ratio(e[:3], 20) == 1.0


def _worst_velocity(est, case) -> float:
    s = est.targets[0]
    sel = (case.truth_t >= s.t0) & (case.truth_t <= s.t1)
    t = case.truth_t[sel][::2]
    x, cov = s.states(t)
    err = x - case.truth_x[sel][::2]
    return float(np.sqrt(nees(err[:, 3:6], cov[:, 3:6, 3:6]).max()))


@pytest.mark.timeout(180)
def test_a_velocity_of_its_own_correlated_over_seconds_is_not_published_overconfident(
    monkeypatch,
):
    case = _case('ascent', 5)
    assert case.draw.telemetry_model == 'separate_velocity', case.draw.summary
    est = estimate(case.obs_est, 0.0, 60.0, EstimatorConfig())
    assert est.success, est.message
    assert _worst_velocity(est, case) < 5.0
    # the first-order formula alone: the same window's velocity beyond 5 sigma
    monkeypatch.setattr(telemetry_noise, 'long_run_ratio', lambda e, lags: 1.0)
    before = estimate(case.obs_est, 0.0, 60.0, EstimatorConfig())
    assert before.success, before.message
    assert _worst_velocity(before, case) > 5.0
