"""Issue 14: the estimator on every telemetry error class with an incomplete segment.

One drawn ascent (family seed 4 cut to 40 s: seven stations, an incomplete segment of
9.8-31.5 s in which only a theodolite and a pulse radar measure, two staging events),
simulated once per telemetry error model of the randomised families, estimated as
``orbit-tracking estimate`` does and scored against the Cramér-Rao bound of the draw
(:mod:`orbit_tracking.tools.bench.robustness_draw`). Before issue 14 correlated, jumpy or
inconsistent telemetry errors made the knots run away and the window fail silently with
errors of hundreds of bound; the limits below catch a return of that.

Silent failures are states more than 5 sigma off by their own covariance (Mahalanobis)
while their window claims success. The issue's targets (gap within 1.5 bounds, NEES in
its band) are not all met on this draw (see ``python -m orbit_tracking.tools.cli bench
--suite robustness``); the limits here are regression guards, not the targets; a class
listed in ``KNOWN_FAILING`` is a strict xfail (it fails the suite once it passes, so the
mark is removed then).
"""

from __future__ import annotations

import numpy as np
import pytest

from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.estimator import estimate
from orbit_tracking.core.sim.families import TELEMETRY_MODELS
from orbit_tracking.tools.bench.robustness import GAP_TARGET
from orbit_tracking.tools.bench.robustness_draw import _bounds, _case, run_draw

SEED, SPAN = 4, 40.0

GAP_LIMIT: dict[str, float] = {}
"""Gap RMS over its bound, where a class is known to be weaker than the default 3."""


KNOWN_FAILING: dict[str, str] = {}
"""Classes known to fail, with the reason (strict xfail). time_skew was one until the
events found in the telemetry were moved to its estimated velocity delay (its 43 silent
states came from a staging placed 35 ms late, which pulled the delay estimate to 10.6 ms);
separate_velocity's 5.03-sigma states went with the events no longer claimed at an
outage's edges, came back, and went again with the consider term around events
(``event_manoeuvre_density``; its gap ratio, 1.6, and NEES, 7.4, are as before). drift
was one (inside the incomplete segment 0.1 m off for seconds at 5.0-5.3 sigma, gap 1.6-1.9
bounds, NEES 7.4-8.9) until the covariance carried the separate velocity error its
window's test could not exclude (``telemetry_velocity.velocity_error_consider``)."""


@pytest.mark.timeout(120)
@pytest.mark.parametrize(
    'model',
    [
        pytest.param(m, marks=pytest.mark.xfail(strict=True, reason=KNOWN_FAILING[m]))
        if m in KNOWN_FAILING
        else m
        for m in TELEMETRY_MODELS
    ],
)
def test_every_telemetry_error_class_is_estimated_within_a_few_bounds_and_honestly(model):
    d = run_draw('ascent', SEED, 30.0, methods=('ours',), span_s=SPAN, telemetry_model=model)
    assert not d.error, d.error
    assert d.telemetry_model == model and d.gaps, d.summary
    (m,) = d.methods
    assert m.ran, m.error
    assert m.windows_failed == 0 and m.windows_raised == 0, m.window_messages
    assert m.silent == 0
    assert m.coverage > 0.95
    assert m.pos_ratio_gap <= GAP_LIMIT.get(model, 3.0), (m.pos_rms_gap, m.pos_ratio_gap)
    assert m.pos_ratio_out <= 2.5, (m.pos_rms_out, m.pos_ratio_out)
    # honest within a factor 2 of the band's top (7 samples: the band is wide already)
    assert m.nees_mean <= 2.0 * m.nees_hi, (m.nees_mean, m.nees_hi)


@pytest.mark.timeout(120)
@pytest.mark.parametrize(('model', 'separate'), [('white', False), ('time_skew', True)])
def test_the_telemetry_velocity_gets_an_error_of_its_own_only_when_its_residuals_ask(
    model, separate
):
    """White telemetry errors keep the one-source model (velocity error = d/dt position
    error); a time-tag skew between position and velocity (velocity error = acceleration x
    skew, not the position's) is detected by the score test and modelled. (By default the
    skew is taken by time-tag delays, ``test_telemetry_delays.py``; here they are off.)"""
    case = _case('ascent', SEED, SPAN, model)
    est = estimate(case.obs_est, 0.0, SPAN, EstimatorConfig(telemetry_delays='off'))
    assert est.success, est.message
    own = 'velocity error of its own' in est.message
    assert own == separate, est.message
    assert est.targets[0].telemetry_velocity == ('separate' if separate else 'derivative')
    derivative = EstimatorConfig(telemetry_velocity_error='derivative', telemetry_delays='off')
    fixed = estimate(case.obs_est, 0.0, SPAN, derivative)
    assert 'velocity error' not in fixed.message
    if not separate:  # the same solve either way
        assert fixed.cost == pytest.approx(est.cost, rel=1e-12)


def test_the_velocity_error_options_are_checked():
    with pytest.raises(ValueError, match='telemetry_velocity_error must be one of'):
        EstimatorConfig(telemetry_velocity_error='guess')
    with pytest.raises(ValueError, match='telemetry_velocity_error_spacing'):
        EstimatorConfig(telemetry_velocity_error_spacing=0.0)
    for bad in (0.0, 21.0):
        with pytest.raises(ValueError, match='telemetry_velocity_error_min_spacing'):
            EstimatorConfig(telemetry_velocity_error_min_spacing=bad)
    with pytest.raises(ValueError, match='telemetry_velocity_alpha'):
        EstimatorConfig(telemetry_velocity_alpha=1.0)
    for bad in (0.0, -1.0, float('nan'), 11.0):
        with pytest.raises(ValueError, match='jerk_grid'):
            EstimatorConfig(jerk_grid=bad)


@pytest.mark.timeout(120)
def test_the_size_of_the_telemetry_error_spline_comes_from_the_data():
    """White telemetry has no slow error: its error spline's level and steps shrink far
    below the declared sigma. A drift of tens of metres that changes slowly keeps its level
    at about the declared sigma, while its steps (one coefficient to the next, 15 s) stay
    a small part of it, so the telemetry still fixes the shape of the trajectory. Held at
    the declared sigma (``estimate_telemetry_error: false``) both stay there, and the
    message says which."""
    levels, steps = {}, {}
    for model in ('white', 'drift'):
        case = _case('ascent', SEED, SPAN, model)
        declared = float(np.median(case.obs_est.telemetry[0].position_sigma))
        est = estimate(case.obs_est, 0.0, SPAN, EstimatorConfig())
        assert est.success, est.message
        sigma = est.targets[0].telemetry_error_sigma
        assert sigma is not None
        level, step = sigma
        assert (
            f'error spline sigma {level:.3g} m, steps {step:.3g} m (declared {declared:.3g} m)'
            in est.message
        )
        levels[model], steps[model] = level / declared, step / declared
        held = estimate(case.obs_est, 0.0, SPAN, EstimatorConfig(estimate_telemetry_error=False))
        assert held.targets[0].telemetry_error_sigma == pytest.approx((declared, declared))
        assert 'error spline sigma' not in held.message
    assert levels['white'] < 0.1 and steps['white'] < 0.1, (levels, steps)
    assert 0.5 < levels['drift'] < 2.0, levels
    assert steps['drift'] < 0.2 * levels['drift'], (levels, steps)


@pytest.mark.timeout(120)
def test_the_white_jerk_prior_bridges_a_turn_in_a_gps_outage():
    """An aircraft turning at 2-3 g through a 30 s GPS outage with one ship radar left:
    the white-jerk prior (density from the data) holds the trajectory where the radar
    alone leaves the spline's knots free, and its sigmas still cover the error."""
    case = _case('aircraft', 6, 60.0)
    inside = (case.truth_t > 23.0) & (case.truth_t < 50.0)
    t, truth = case.truth_t[inside], case.truth_x[inside, :3]
    rms, nees = {}, {}
    for on in (True, False):
        est = estimate(case.obs_est, 0.0, 60.0, EstimatorConfig(jerk_prior=on))
        assert est.success, est.message
        x, cov = est.targets[0].states(t)
        err = x[:, :3] - truth
        rms[on] = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
        nees[on] = float(
            np.mean(np.einsum('ni,nij,nj->n', err, np.linalg.inv(cov[:, :3, :3]), err))
        )
        q = est.targets[0].jerk_density
        assert (q is not None) == on
        assert ('white-jerk prior' in est.message) == on
        if on:
            assert q is not None and 0.1 < q < 100.0, q
    # the gain goes through the knot selection, which floating point on different CPUs
    # moves: below 0.6 on the machine this was written on, 0.74 (3.96 m against 5.34 m,
    # both with NEES 1.4) on another with the same code and libraries (issue 14's chaos)
    assert rms[True] < 0.8 * rms[False], rms
    assert nees[True] < 6.0, nees


def _gap_rms(case, est) -> float:
    x, _ = est.targets[0].states(case.truth_t)
    e = x[case.in_gap, :3] - case.truth_x[case.in_gap, :3]
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


def _gap_bound(case) -> float:
    """The draw's stations+telemetry Cramér-Rao bound, RMS over the incomplete segment."""
    b = _bounds(case)[0]['stations+telemetry']
    return float(np.sqrt(np.mean(b.position_var[case.in_gap])))


@pytest.mark.timeout(120)
def test_a_separate_velocity_error_gets_faster_knots_only_when_its_residuals_ask():
    """Telemetry velocity from another source, its error drifting within seconds (family
    seed 12, 40 s: an incomplete segment at the start with one theodolite): the score test
    halves the separate error's knot spacing twice, to 5 s, and the trajectory in the
    segment is within the issue's gap target (1.5 bounds). When written, the 20 s error
    left 1.1-1.7 m in the segment (5 bounds) and the 5 s one 0.25-0.8 m; since the
    telemetry velocity noise counts its correlation over a knot interval
    (:mod:`.telemetry_noise`, the long-run ratio with ``w``) the 20 s error's leftovers are
    no longer weighed as white and both are within the bound on this draw (0.18 m and
    0.32 m against 0.32 m), so the gain is not asserted on it; on the 35-draw ascent family
    holding ``w`` at 20 s gave 189 silent states against 114 with the test.
    A slow velocity error (seed 94, time constant 55 s) is tested and left at 20 s: the
    same solve as without the test. Time-tag delays off: their test is near its threshold
    on this draw and would decide by rounding."""
    on = EstimatorConfig(telemetry_delays='off')
    off = EstimatorConfig(telemetry_delays='off', telemetry_velocity_error_min_spacing=20.0)
    case = _case('ascent', 12, SPAN, 'separate_velocity')
    fast = estimate(case.obs_est, 0.0, SPAN, on)
    slow = estimate(case.obs_est, 0.0, SPAN, off)
    assert fast.success and slow.success, (fast.message, slow.message)
    assert 'velocity error knots every 5 s asked for' in fast.message, fast.message
    assert 'knots every' not in slow.message
    assert _gap_rms(case, fast) < GAP_TARGET * _gap_bound(case)

    case = _case('ascent', 94, SPAN, 'separate_velocity')
    tested = estimate(case.obs_est, 0.0, SPAN, on)
    plain = estimate(case.obs_est, 0.0, SPAN, off)
    assert 'velocity error of its own' in tested.message, tested.message
    assert 'velocity error knots every 10 s not asked for' in tested.message, tested.message
    assert tested.cost == pytest.approx(plain.cost, rel=1e-12)
