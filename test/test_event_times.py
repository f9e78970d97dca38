"""Issue 14: the uncertainty of the events' times in the states' covariance
(:mod:`orbit_tracking.core.estimation.event_times`).

Robustness ascent draw 67 (three stations, 5 Hz telemetry with position jumps) cuts off
at 31.448 s and ignites 0.574 s later. Placed by the measurements, the events stand at
31.496 s and 31.963 s, 48 ms and 59 ms off; the velocity beside them was up to 1.6 m/s
off at sigmas of 0.06 m/s, a covariance that took the events' times as known.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from orbit_tracking.core.estimation import event_times
from orbit_tracking.core.estimation.estimator import estimate
from orbit_tracking.tools.bench.robustness_draw import _case, worst_sigma
from orbit_tracking.tools.estimator_parameters import estimator_configs

VELOCITY = slice(3, 6)


def test_the_sigma_of_a_time_is_where_the_parabola_through_the_costs_rises_by_one():
    h = event_times.STEP
    k = 2.0 / 0.004**2  # a cost that rises by one 4 ms from its least
    assert event_times._sigma(10.0, 10.0 + 0.5 * k * h**2, 10.0 + 0.5 * k * h**2) == (
        pytest.approx(0.004)
    )
    # its least 3 ms from the event: the distance counts too
    c = lambda d: 10.0 + 0.5 * k * (d - 0.003) ** 2  # noqa: E731
    assert event_times._sigma(c(0.0), c(-h), c(h)) == pytest.approx(math.hypot(0.004, 0.003))
    # a flat or falling profile: the cap; one side only: from its rise
    assert event_times._sigma(10.0, 10.0, 10.0) == event_times.MAX_SIGMA
    assert event_times._sigma(10.0, 9.0, 11.0) == event_times.MAX_SIGMA  # a straight slope
    assert event_times._sigma(10.0, math.nan, 10.0 + 0.5 * k * h**2) >= 0.004


def test_the_term_is_the_mean_of_the_two_sigma_points_outer_products_near_the_event_only():
    ts = np.array([9.0, 10.0, 11.0])
    plus = np.zeros((3, 6))
    plus[1, 3] = 0.4  # the velocity east, at the event
    minus = np.zeros((3, 6))
    minus[1, 4] = -0.2
    term = event_times.EventTimeTerms((ts,), (plus,), (minus,), ((10.0, 0.01, 0.01),))
    cov = term.state_covariance(np.array([8.0, 10.0, 10.5]))
    assert np.all(cov[0] == 0.0)
    assert cov[1, 3, 3] == pytest.approx(0.5 * 0.16) and cov[1, 4, 4] == pytest.approx(0.02)
    assert cov[2, 3, 3] == pytest.approx(0.5 * 0.2**2)  # halfway: half the difference
    assert '10.000 s (-10/+10 ms)' in term.note()


@pytest.mark.timeout(240)
def test_velocities_beside_events_placed_tens_of_milliseconds_off_stay_within_5_sigma():
    case = _case('ascent', 67)
    assert case.draw.telemetry_model == 'jumps', case.draw.summary
    cfg, _, _ = estimator_configs({})
    t0, t1 = 0.0202, 60.0202  # the benchmark's first window
    est = estimate(case.obs_est, t0, t1, cfg)
    assert est.success, est.message
    assert 'event times (sigmas in the covariance)' in est.message, est.message
    assert worst_sigma(est, case, 30.5, 33.0, VELOCITY) < 5.0
    off = estimate(case.obs_est, t0, t1, replace(cfg, event_time_uncertainty=False))
    assert off.success, off.message
    assert worst_sigma(off, case, 30.5, 33.0, VELOCITY) > 5.0
    # away from the events the term adds nothing
    t = np.array([10.0, 20.0, 45.0])
    _, c_on = est.targets[0].states(t)
    _, c_off = off.targets[0].states(t)
    np.testing.assert_allclose(c_on, c_off, rtol=1e-9, atol=0.0)
