"""The manoeuvres an incomplete segment may hide, as consider parameters of the state
covariance (core/estimation/gap_manoeuvres.py)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from orbit_tracking.core.estimation.bspline import SplineAxis, SplineTrajectory
from orbit_tracking.core.estimation.gap_manoeuvres import (
    MAX_INSTANTS,
    event_spans,
    gap_manoeuvres,
    instants,
)


def test_instants_cover_each_segment_and_share_its_length() -> None:
    taus, widths = instants(((10.0, 12.0), (20.0, 21.0)), 0.5)
    assert taus.tolist() == [10.0, 10.5, 11.0, 11.5, 12.0, 20.0, 20.5, 21.0]
    assert widths.tolist() == [0.25, 0.5, 0.5, 0.5, 0.25, 0.25, 0.5, 0.25]
    taus, widths = instants(((0.0, 1000.0),), 0.5)
    assert taus.size <= MAX_INSTANTS
    assert widths.sum() == pytest.approx(1000.0)
    assert instants((), 0.5)[0].size == 0


def _problem(rng: np.random.Generator):
    """A small linear problem: 4 spline coefficients per axis (degree 3 on [0, 10] s),
    two extra parameters, 300 rows measuring random combinations of position and velocity
    at random times, three of target 0 per time and some of another target."""
    ax = SplineAxis(np.array([0.0] * 4 + [5.0] + [10.0] * 4), 3)
    traj = SplineTrajectory((ax, ax, ax), np.zeros(3), np.eye(3))
    nc = traj.n_coef
    m = 100
    t = np.sort(rng.uniform(0.0, 10.0, m))
    fp = rng.normal(size=(m, 3, 3))
    fv = rng.normal(size=(m, 3, 3))
    pw = traj.world_design(t, 0).toarray().reshape(m, 3, nc)
    vw = traj.world_design(t, 1).toarray().reshape(m, 3, nc)
    j_coef = (np.einsum('mkc,mcn->mkn', fp, pw) + np.einsum('mkc,mcn->mkn', fv, vw)).reshape(
        3 * m, nc
    )
    extra = rng.normal(size=(3 * m, 2))
    other = rng.normal(size=(20, nc + 2))  # rows of another target (and a prior)
    jac = np.vstack([np.hstack([j_coef, extra]), other])
    rows = [
        (0, np.repeat(t, 3), fp.reshape(3 * m, 3), fv.reshape(3 * m, 3), False),
        (1, rng.uniform(0.0, 10.0, 20), rng.normal(size=(20, 3)), rng.normal(size=(20, 3)), False),
    ]
    return traj, rows, jac


def test_event_spans_are_clipped_to_the_window_and_merged() -> None:
    assert event_spans((5.0, 1.0, 5.5, 9.8), 1.0, 0.0, 10.0) == (
        (0.0, 2.0),
        (4.0, 6.5),
        (8.8, 10.0),
    )
    assert event_spans((), 1.0, 0.0, 10.0) == ()
    assert event_spans((12.0,), 1.0, 0.0, 10.0) == ()


@pytest.mark.parametrize(
    ('segs', 'q', 'events', 'q_event', 'unseen', 'q_unseen', 'weak'),
    [
        (((2.0, 4.0), (6.5, 7.5)), 7.0, (), 0.0, (), 0.0, ()),
        # event spans with their own density, one overlapping a segment, one alone
        (((2.0, 4.0),), 7.0, ((3.5, 5.0), (8.0, 9.0)), 0.3, (), 0.0, ()),
        ((), 7.0, ((3.5, 5.0),), 0.3, (), 0.0, ()),
        # a telemetry outage's span, overlapping an event span, and one alone
        (((2.0, 4.0),), 7.0, ((3.5, 5.0),), 0.3, ((4.5, 6.0), (8.0, 9.5)), 2.0, ()),
        ((), 0.0, (), 0.0, ((1.0, 6.0),), 2.0, ()),
        # spans around weak changes, each with its own density, overlapping each other
        # and an event span
        ((), 0.0, ((3.5, 5.0),), 0.3, (), 0.0, (((4.0, 6.0), 0.05), ((5.0, 7.0), 1.5))),
        ((), 0.0, (), 0.0, (), 0.0, (((1.0, 3.0), 0.5),)),
    ],
)
def test_the_split_rows_give_the_augmented_models_covariance(
    segs, q, events, q_event, unseen, q_unseen, weak
) -> None:
    """Gain and posterior equal those of the full normal matrix with the steps as extra
    parameters under their prior, built by brute force with dense step columns."""
    rng = np.random.default_rng(3)
    traj, rows, jac = _problem(rng)
    n, nc = jac.shape[1], traj.n_coef
    cov = np.linalg.inv(jac.T @ jac)
    groups = [
        (instants(spans, 0.5), density)
        for spans, density in (
            (segs, q),
            (events, q_event),
            (unseen, q_unseen),
            *(((span,), qw) for span, qw in weak),
        )
        if density > 0.0 and spans
    ]
    taus = np.concatenate([g[0][0] for g in groups])
    variances = np.concatenate([density * g[1] for g, density in groups])
    order = np.argsort(taus, kind='stable')
    taus, variances = taus[order], variances[order]
    scale = 2.0
    got = gap_manoeuvres(
        rows,
        sp.csr_matrix(jac),
        cov,
        0,
        nc,
        0,
        segs,
        0.5,
        q,
        scale,
        events,
        q_event,
        unseen,
        q_unseen,
        weak,
    )
    assert got is not None
    assert got.weak_densities == tuple(qw for _, qw in weak)
    assert got.taus.tolist() == taus.tolist()
    t = np.concatenate([r[1] for r in rows])
    mine = np.concatenate([np.full(r[1].size, r[0] == 0) for r in rows])
    fp = np.concatenate([r[2] for r in rows])
    fv = np.concatenate([r[3] for r in rows])
    d = np.where(mine[:, None], np.maximum(t[:, None] - taus[None, :], 0.0), 0.0)
    hc = np.zeros((t.size, 3 * taus.size))
    for i in range(3):
        hc[:, i::3] = fp[:, i, None] * 0.5 * d**2 + fv[:, i, None] * d
    a = np.hstack([jac, hc]) / np.sqrt(scale)  # the data, less informative by the misfit
    normal = a.T @ a
    normal[n:, n:] += np.diag(1.0 / np.repeat(variances, 3))
    sigma = np.linalg.inv(normal)
    np.testing.assert_allclose(got.posterior, sigma[n:, n:], rtol=1e-7, atol=1e-12)
    # Sigma_xc = -(s P) (U / s) M^-1: the gain is P U = -Sigma_xc Sigma_cc^-1
    gain = -sigma[:n, n:] @ np.linalg.inv(sigma[n:, n:])
    np.testing.assert_allclose(got.gain, gain[:nc], rtol=1e-6, atol=1e-9)
    # and the state term is the augmented model's state covariance minus the formal one
    tt = np.array([1.0, 3.0, 5.0, 7.2, 9.5])
    m = tt.size
    g = np.zeros((m, 6, n + hc.shape[1]))
    for nu in (0, 1):
        g[:, 3 * nu : 3 * nu + 3, :nc] = traj.world_design(tt, nu).toarray().reshape(m, 3, nc)
    dd = np.maximum(tt[:, None] - taus[None, :], 0.0)
    for i in range(3):
        g[:, i, n + i :: 3] = 0.5 * dd**2
        g[:, 3 + i, n + i :: 3] = dd
    full = np.einsum('maj,jk,mbk->mab', g, sigma, g)
    formal = np.einsum('maj,jk,mbk->mab', g[:, :, :n], scale * cov, g[:, :, :n])
    np.testing.assert_allclose(got.state_covariance(traj, tt), full - formal, rtol=1e-6, atol=1e-9)


def test_the_term_grows_with_the_density_and_vanishes_without_it() -> None:
    rng = np.random.default_rng(4)
    traj, rows, jac = _problem(rng)
    cov = np.linalg.inv(jac.T @ jac)
    segs = ((3.0, 6.0),)
    nc = traj.n_coef
    tt = np.linspace(0.0, 10.0, 11)
    traces = []
    for q in (0.1, 1.0, 10.0):
        c = gap_manoeuvres(rows, sp.csr_matrix(jac), cov, 0, nc, 0, segs, 0.5, q)
        assert c is not None
        term = c.state_covariance(traj, tt)
        assert np.all(np.linalg.eigvalsh(term) > -1e-9)  # it only ever adds
        traces.append(np.trace(term, axis1=1, axis2=2))
    # more density, more room for the steps: the term grows everywhere (before the
    # first instant too, through the coefficients the later data moved)
    assert np.all(np.diff(np.array(traces), axis=0) > 0.0)
    assert gap_manoeuvres(rows, sp.csr_matrix(jac), cov, 0, nc, 0, segs, 0.5, 0.0) is None


def _staging_in_a_segment(density: float):
    """Robustness ascent draw 78, its window 40-95.1 s: staging at 62.46 and 65.25 s
    inside an incomplete segment (47.6-67.1 s, two CW radars) where the telemetry is out
    (55.96-68.43 s), so no rough trajectory shows the events."""
    from orbit_tracking.core.estimation.config import EstimatorConfig
    from orbit_tracking.core.estimation.estimator import estimate
    from orbit_tracking.tools.bench.robustness_draw import _case

    case = _case('ascent', 78)
    cfg = EstimatorConfig(
        gap_manoeuvre_density=density, event_manoeuvre_density=0.0, unseen_manoeuvre_density=0.0
    )
    est = estimate(case.obs_est, 40.0, 95.1, cfg)
    sel = (case.truth_t >= 55.0) & (case.truth_t <= 65.0)
    x, cov = est.targets[0].states(case.truth_t[sel])
    e = x[:, :3] - case.truth_x[sel, :3]
    maha = np.sqrt(np.einsum('ki,kij,kj->k', e, np.linalg.inv(cov[:, :3, :3]), e))
    return est, x, maha


@pytest.mark.timeout(180)
def test_a_staging_hidden_in_a_segment_widens_the_covariance_instead_of_failing_silently() -> None:
    est, x, maha = _staging_in_a_segment(30.0)
    assert est.success, est.message
    assert est.targets[0].manoeuvres is not None
    assert maha.max() < 5.0
    est_off, x_off, maha_off = _staging_in_a_segment(0.0)
    assert est_off.targets[0].manoeuvres is None
    assert maha_off.max() > 5.0  # the silent failure the term removes
    np.testing.assert_array_equal(x, x_off)  # the estimate itself is not touched


def _aircraft_window(seed: int, t0: float, t1: float, a: float, b: float, **changes):
    """Robustness draw aircraft ``seed``'s window [t0, t1] solved alone with the default
    settings but ``changes``: the window, its target, the states on a 0.1 s grid over
    [a, b] (within the window's spline) and their velocity Mahalanobis distances."""
    import dataclasses

    from orbit_tracking.core.estimation.windows import solve_windows
    from orbit_tracking.tools.bench.robustness_draw import TARGET, _case
    from orbit_tracking.tools.estimator_parameters import estimator_configs

    case = _case('aircraft', seed)
    est, win, _ = estimator_configs({})
    (res,) = solve_windows(case.obs_est.window(t0, t1), dataclasses.replace(est, **changes), win)
    sol = res.targets[TARGET]
    sel = (case.truth_t >= max(a, sol.t0)) & (case.truth_t <= min(b, sol.t1))
    tt = case.truth_t[sel][::2]
    x, cov = sol.states(tt)
    e = x[:, 3:6] - case.truth_x[sel][::2, 3:6]
    maha = np.sqrt(np.einsum('ki,kij,kj->k', e, np.linalg.inv(cov[:, 3:6, 3:6]), e))
    return res, sol, x, maha


def _turn_window(density: float):
    """Robustness draw aircraft 78 (1 Hz GPS with position jumps), its window 120-180 s:
    a turn whose ramp ends the detector places at 145.0 and 156.2 s (the outage term off,
    to see this one alone)."""
    return _aircraft_window(
        78,
        120.0,
        180.0,
        120.0,
        180.0,
        event_manoeuvre_density=density,
        unseen_manoeuvre_density=0.0,
    )


def _staging_without_telemetry(density: float, doubtful_events: bool = False):
    """Robustness draw ascent 7 (no telemetry: the rough trajectory is the fixes, then the
    first solution), its window 0-60 s over a staging at 16.19 and 18.52 s. The window,
    its knot selection and the velocity Mahalanobis distances on a 0.1 s grid (by default
    without the events the measurements ask for at doubtful changes: the consider term
    alone)."""
    from orbit_tracking.core.estimation.config import EstimatorConfig
    from orbit_tracking.core.estimation.estimator import estimate
    from orbit_tracking.tools.bench.robustness_draw import _case

    case = _case('ascent', 7)
    cfg = EstimatorConfig(event_manoeuvre_density=density, doubtful_events=doubtful_events)
    est = estimate(case.obs_est, 0.0, 60.0, cfg)
    sol = est.targets[0]
    sel = (case.truth_t >= 0.0) & (case.truth_t <= 60.0)
    tt = case.truth_t[sel][::2]
    x, cov = sol.states(tt)
    e = x[:, 3:6] - case.truth_x[sel][::2, 3:6]
    maha = np.sqrt(np.einsum('ki,kij,kj->k', e, np.linalg.inv(cov[:, 3:6, 3:6]), e))
    return est, sol.knots, maha


@pytest.mark.timeout(300)
def test_a_staging_only_the_first_solution_shows_is_doubtful_and_covered() -> None:
    """Without telemetry nothing shows the staging before the first solution; its velocity
    (a smooth spline, no knots from it) marks doubtful changes around both events, and the
    consider term there leaves at most a few velocity states beyond 5 sigma (measured: 2,
    and 20 without the term)."""
    est, knots, maha = _staging_without_telemetry(30.0)
    assert est.success, est.message
    assert knots.rough_source == 'fixes, then first solution'
    assert knots.events == ()
    for event in (16.19, 18.52):
        assert np.min(np.abs(np.asarray(knots.doubtful) - event)) < 1.5, knots.doubtful
    assert 'doubtful (no knots)' in est.message
    assert np.sum(maha > 5.0) <= 5
    _, _, maha_off = _staging_without_telemetry(0.0)
    assert np.sum(maha_off > 5.0) >= 12
    # with the test at the doubtful changes (the default), events the measurements asked
    # for beside the first jump, and the states as honest as with the term alone
    est, knots, maha = _staging_without_telemetry(30.0, doubtful_events=True)
    assert est.success, est.message
    assert knots.events and np.min(np.abs(np.asarray(knots.events) - 16.19)) < 0.2
    assert np.sum(maha > 5.0) <= 5


def _turn_in_an_outage(density: float):
    """Robustness draw aircraft 35 (1 Hz quantised GPS, two ship radars and a camera), its
    window 0-60 s: a turn entered by a ramp at 16.76-17.77 s, inside the GPS outage
    15.565-40.768 s, so no event is found for it; the states from 10 to 25 s."""
    return _aircraft_window(35, 0.0, 60.0, 10.0, 25.0, unseen_manoeuvre_density=density)


@pytest.mark.timeout(300)
@pytest.mark.parametrize(
    ('window', 'density', 'phrase'),
    [
        (_turn_window, 30.0, 'spans around events (found or doubtful) leave unmodelled (30'),
        (
            _turn_in_an_outage,
            10.0,
            '1 spans where the rough trajectory had no samples may hide (10',
        ),
    ],
)
def test_a_turn_the_knots_follow_only_roughly_widens_the_velocity_covariance(
    window, density, phrase
) -> None:
    """Without its term a window claims centimetres per second where its velocity is
    tenths off near the turn's ramp ends: a ramp end the detector placed off (aircraft 78,
    measured: 32 states beyond 5 sigma) or a ramp inside a GPS outage that nothing found
    (aircraft 35, 0.5-1.6 m/s off at sigmas of 0.02-0.1 m/s; measured: 17, the worst at
    17). With it at most a few remain (measured: none in either), and the estimate is the
    same."""
    res, sol, x, maha = window(density)
    assert res.success, res.message
    assert sol.manoeuvres is not None
    assert phrase in res.message
    assert np.sum(maha > 5.0) <= 3
    _, sol_off, x_off, maha_off = window(0.0)
    assert sol_off.manoeuvres is None
    assert np.sum(maha_off > 5.0) >= 10
    np.testing.assert_array_equal(x, x_off)


def test_the_outage_spans_reach_as_far_as_the_event_detector_is_blind() -> None:
    """The event detector's fits take max(3, event_window / dt) samples on each side and
    see no event whose samples reach across a hole: the spans carrying the outage term
    are widened by that reach (3 s at 1 Hz, 1 s at 5 Hz), not by event_window alone."""
    from orbit_tracking.core.data.observations import Observations
    from orbit_tracking.core.data.tables import TargetStates
    from orbit_tracking.core.estimation.config import EstimatorConfig
    from orbit_tracking.core.estimation.gap_manoeuvres import unseen_spans

    def spans(rate: float) -> tuple[tuple[float, float], ...]:
        t = np.arange(0.0, 60.0 + 1e-9, 1.0 / rate)
        t = t[(t < 20.0) | (t > 30.0)]
        n = t.size
        z = np.zeros((n, 3))
        tel = TargetStates(0, t, z, z, np.ones(n), np.ones(n))
        obs = Observations(stations=(), telemetry={0: tel})
        return unseen_spans(obs, 0, 0.0, 60.0, EstimatorConfig())

    ((a1, b1),) = spans(1.0)
    assert a1 == pytest.approx(19.0 - 3.0) and b1 == pytest.approx(31.0 + 3.0)
    ((a5, b5),) = spans(5.0)
    assert a5 == pytest.approx(19.8 - 1.0) and b5 == pytest.approx(30.2 + 1.0)


def test_a_gentle_turn_below_the_event_thresholds_is_covered_by_its_weak_changes() -> None:
    """Robustness draw aircraft 1026 (2 Hz GPS with position jumps), its window 0-60 s: it
    begins in a gentle turn and leaves it over 1.2 s, and enters and leaves another at
    36.4-37.5 s, 1.9-2.8 m/s^2 of lateral acceleration: no event, no doubt, four weak
    changes. Without their term the velocity was 0.1-0.2 m/s off where it claimed a few
    centimetres per second (measured: 34 states beyond 5 sigma); with it (densities about
    1 m^2/s^5, sized by the jumps) none, and the estimate is the same."""
    res, sol, x, maha = _aircraft_window(1026, 0.0, 60.0, 0.0, 60.0)
    assert res.success, res.message
    assert len(sol.knots.weak) == 4
    assert '4 weak (no knots)' in res.message
    assert 'spans around weak changes leave unmodelled' in res.message
    assert np.sum(maha > 5.0) <= 3
    res_off, _, x_off, maha_off = _aircraft_window(
        1026, 0.0, 60.0, 0.0, 60.0, weak_manoeuvre_gain=0.0
    )
    assert 'spans around weak changes' not in res_off.message
    assert np.sum(maha_off > 5.0) >= 10
    np.testing.assert_array_equal(x, x_off)
