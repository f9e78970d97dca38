"""Issue 14: time-tag delays of the telemetry (``telemetry_delays: auto``, the default).

A manoeuvring aircraft (robustness family, seed 4: two ships with a radar each, GPS at
2 Hz; its first 60 s window, with a turn) whose GPS positions are tagged ``d_p`` late and
its velocities ``d_v``: the window's score test asks for the two delays and the solve
recovers them within a few of their sigmas; the same draw with white GPS errors keeps the
model without delays. The delay rows (residuals and Jacobian) are checked against finite
differences on the solved window.
"""

from __future__ import annotations

import numpy as np
import pytest

from orbit_tracking.core.estimation import estimator as estimator_module
from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.estimator import estimate
from orbit_tracking.tools.bench.robustness_draw import _case
from orbit_tracking.tools.estimate import _window_summary

SEED, T0, T1 = 4, 0.0, 60.0


def _window(model: str | None, cfg: EstimatorConfig):
    case = _case('aircraft', SEED, None, model)  # None: as drawn (a time skew)
    return case, estimate(case.obs_est, T0, T1, cfg)


@pytest.mark.timeout(120)
def test_a_time_tag_skew_is_detected_and_its_delays_recovered():
    case, est = _window(None, EstimatorConfig(telemetry_delays='auto'))
    assert case.draw.telemetry_model == 'time_skew', case.draw.summary
    assert est.success, est.message
    assert 'time-tag delays estimated' in est.message, est.message
    delays = est.targets[0].telemetry_delays
    assert delays is not None
    d_p, s_p, d_v, s_v = delays
    params = case.draw.scenario.telemetry.error_parameters
    assert 0.0 < s_p < 0.01 and 0.0 < s_v < 0.01, delays
    assert abs(d_p - params['position_delay_s']) < 4.0 * s_p + 1e-3, (delays, params)
    assert abs(d_v - params['velocity_delay_s']) < 4.0 * s_v + 1e-3, (delays, params)
    # the offline summary reports them per target
    assert _window_summary(est)['telemetry_delays_s'] == {0: list(delays)}


@pytest.mark.timeout(120)
def test_white_telemetry_keeps_the_model_without_delays():
    _, est = _window('white', EstimatorConfig(telemetry_delays='auto'))
    assert est.success, est.message
    assert 'time-tag delays not estimated' in est.message, est.message
    assert est.targets[0].telemetry_delays is None
    assert _window_summary(est)['telemetry_delays_s'] == {}


@pytest.mark.timeout(120)
def test_the_delay_rows_match_finite_differences(monkeypatch):
    captured = {}
    solve = estimator_module.solve

    def spy(prob, beta, cfg, **kw):
        out = solve(prob, beta, cfg, **kw)
        captured['prob'], captured['beta'] = prob, out[0].beta.copy()
        return out

    monkeypatch.setattr(estimator_module, 'solve', spy)
    _window(None, EstimatorConfig(telemetry_delays='on', refine_rounds=0))
    prob, beta = captured['prob'], captured['beta']
    (tb,) = prob.telemetry
    assert tb.delays
    r0, jac, _ = prob.evaluate(beta, True)
    jac = jac.toarray()
    o = prob.offsets[0]
    for k, h in ((tb.delay_offset, 1e-6), (tb.delay_offset + 1, 1e-6), (o + 5, 1e-3)):
        b2 = beta.copy()
        b2[k] += h
        r1, _, _ = prob.evaluate(b2, False)
        # residuals are data minus model, the Jacobian is the model's derivative
        np.testing.assert_allclose(-(r1 - r0) / h, jac[:, k], atol=1e-3 * np.abs(jac[:, k]).max())
