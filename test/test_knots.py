"""Knot placement (seed 000, section 3) and incomplete-segment detection: event
detection on synthetic telemetry, densification and l1 selection on a polynomial
trajectory, the knots chosen on seed 000's telemetry, and the 45-75 s gap found from the
measurements of both seed 000 scenarios."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.estimation.coverage import (
    CoverageConfig,
    find_incomplete_segments,
    merge_segments,
    unsampled_spans,
)
from orbit_tracking.core.estimation.knots import (
    KnotConfig,
    KnotSelectionError,
    RoughTrajectory,
    _noise_level,
    choose_knots,
    densify,
    detect_events,
    rough_trajectory,
    select_knots,
    spline_frame,
    uniform_knots,
)
from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.core.sim.simulator import World, simulate

DT = 0.05  # s, the 20 Hz telemetry of seed 000


@cache
def _seed000(name: str) -> tuple[World, Observations]:
    sc = load_scenario(name)
    world = World(sc)
    return world, Observations.from_simulation(simulate(sc, world))


def _broken_line_track(
    rng: np.random.Generator, t_jump: float, noise_v: float = 0.02
) -> RoughTrajectory:
    """Telemetry of a vehicle whose acceleration jumps at ``t_jump`` (continuous velocity:
    thrust cut-off), with white velocity and position noise."""
    t = np.arange(0.0, 20.0 + 1e-9, DT)[:, None]
    a1 = np.array([30.0, 10.0, -2.0])  # m/s^2 under thrust
    a2 = np.array([-5.0, -9.0, 0.5])  # m/s^2 after cut-off
    v0 = np.array([800.0, 600.0, 10.0])
    before, after = np.minimum(t - t_jump, 0.0), np.maximum(t - t_jump, 0.0)
    v = v0 + a1 * before + a2 * after
    p = v0 * t + 0.5 * a1 * before**2 + 0.5 * a2 * after**2
    return RoughTrajectory(
        'telemetry',
        t.ravel(),
        p + rng.standard_normal(p.shape) * 1.0,
        v + rng.standard_normal(v.shape) * noise_v,
        1.0,
        noise_v,
    )


def _polynomial(rng: np.random.Generator) -> np.ndarray:
    """Coefficients (5, 3) of a degree-4 ascent-like polynomial per axis [m]: accelerations
    of 5-25 m/s^2 and jerks below 1 m/s^3, as in seed 000's powered flight."""
    c = np.zeros((5, 3))
    c[0] = rng.uniform(-5e3, 5e3, 3)
    c[1] = rng.uniform(-800.0, 800.0, 3)
    c[2] = rng.uniform(-8.0, 8.0, 3)
    c[3] = rng.uniform(-0.02, 0.02, 3)
    c[4] = rng.uniform(-5e-4, 5e-4, 3)
    return c


def _polynomial_track(
    rng: np.random.Generator, t: np.ndarray, noise_p: float, noise_v: float
) -> tuple[RoughTrajectory, np.ndarray, np.ndarray]:
    c = _polynomial(rng)
    pp = np.polynomial.polynomial
    pos = np.stack([pp.polyval(t, c[:, k]) for k in range(3)], axis=1)
    vel = np.stack([pp.polyval(t, pp.polyder(c[:, k])) for k in range(3)], axis=1)
    rough = RoughTrajectory(
        'telemetry',
        t,
        pos + rng.standard_normal(pos.shape) * noise_p,
        vel + rng.standard_normal(vel.shape) * noise_v,
        noise_p,
        noise_v,
    )
    return rough, pos, vel


# ---------------------------------------------------------------------------------------
# events


@pytest.mark.parametrize('seed', range(5))
def test_detect_events_finds_an_acceleration_jump_to_a_tenth_of_the_sampling_interval(seed):
    rng = np.random.default_rng(seed)
    t_jump = 8.0 + rng.uniform(0.0, 4.0)  # anywhere between samples
    events = detect_events(_broken_line_track(rng, t_jump), KnotConfig())
    assert len(events) == 1, events
    # measured: within 0.03 sampling intervals over 30 seeds
    assert abs(events[0] - t_jump) < 0.1 * DT


@pytest.mark.parametrize('seed', range(3))
def test_detect_events_finds_none_on_a_smooth_track(seed):
    rng = np.random.default_rng(100 + seed)
    rough, _, _ = _polynomial_track(rng, np.arange(0.0, 20.0 + 1e-9, DT), 1.0, 0.02)
    assert detect_events(rough, KnotConfig()) == []


def test_detect_events_finds_none_on_a_steady_jerk():
    t = np.arange(0.0, 20.0 + 1e-9, DT)
    jerk = 2.5  # m/s^3, noise-free
    v = np.zeros((t.size, 3))
    v[:, 0] = 0.5 * jerk * t**2
    p = np.zeros((t.size, 3))
    p[:, 0] = jerk * t**3 / 6.0
    rough = RoughTrajectory('telemetry', t, p, v, 1e-3, 1e-3)
    assert detect_events(rough, KnotConfig()) == []


def _take(rough: RoughTrajectory, keep: np.ndarray) -> RoughTrajectory:
    assert rough.velocity is not None
    return RoughTrajectory(
        rough.source,
        rough.time[keep],
        rough.position[keep],
        rough.velocity[keep],
        rough.position_noise,
        rough.velocity_noise,
    )


@pytest.mark.parametrize('seed', range(3))
def test_the_edges_of_a_telemetry_outage_are_not_events(seed):
    """An ascent under a steady jerk with its telemetry out for 6 s: no event. Before the
    fix the outage's two edges came out as events (the fits took the samples across the
    hole as evenly spaced), which freed the spline there from the jerk prior: robustness
    draw ascent 47 went 176 m off in its outage, 0.3 m after."""
    rng = np.random.default_rng(200 + seed)
    t = np.arange(0.0, 30.0 + 1e-9, DT)
    rough, _, _ = _polynomial_track(rng, t, 1.0, 0.02)
    out = (t > 9.0 + seed) & (t < 15.0 + seed)
    assert detect_events(rough, KnotConfig()) == []
    assert detect_events(_take(rough, ~out), KnotConfig()) == []


def test_an_event_away_from_an_outage_is_still_found():
    rng = np.random.default_rng(7)
    rough = _broken_line_track(rng, 13.3)
    t = rough.time
    events = detect_events(_take(rough, (t < 4.0) | (t > 8.0)), KnotConfig())
    assert len(events) == 1 and abs(events[0] - 13.3) < 0.1 * DT, events


def test_detect_events_needs_velocity_samples():
    rng = np.random.default_rng(4)
    r = _broken_line_track(rng, 10.0)
    fixes = RoughTrajectory('fixes', r.time, r.position, None, 1.0, 0.0)
    assert detect_events(fixes, KnotConfig()) == []


# ---------------------------------------------------------------------------------------
# densification and sparse selection


@pytest.fixture(scope='module')
def polynomial_densified():
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 30.0 + 1e-9, DT)
    # little rough-trajectory noise: the tolerances are then delta, not 3 sigma of the fit
    rough, pos, vel = _polynomial_track(rng, t, 0.05, 0.002)
    cfg = KnotConfig()
    frame = (np.zeros(3), np.eye(3))
    axes, coefs, covs, rounds = densify(rough, frame, 0.0, 30.0, [], [], cfg)
    return rough, pos, vel, cfg, axes, coefs, covs, rounds


def test_densify_fits_a_polynomial_track_on_the_base_grid_within_sigma(polynomial_densified):
    rough, pos, vel, cfg, axes, coefs, _, rounds = polynomial_densified
    # a polynomial needs no insertion: the 1 s grid stays as it is
    assert rounds == 0
    np.testing.assert_allclose(axes[0].interior, np.arange(1.0, 30.0))
    for a in range(3):
        assert np.max(np.abs(axes[a].evaluate(coefs[a], rough.time) - pos[:, a])) < (
            cfg.sigma_position
        )
        assert np.max(np.abs(axes[a].evaluate(coefs[a], rough.time, 1) - vel[:, a])) < (
            cfg.sigma_velocity
        )


def test_select_knots_drops_every_knot_of_a_degree_four_polynomial(polynomial_densified):
    rough, pos, vel, cfg, axes, coefs, covs, _ = polynomial_densified
    for a in range(3):
        reduced, jumps, info = select_knots(axes[a], coefs[a], covs[a], rough.time, cfg)
        assert info['status'] == 'optimal'
        assert jumps.shape == (axes[a].interior.size,)
        # a degree-4 polynomial has no 4th-derivative jump: every knot goes
        assert reduced.interior.size == 0, reduced.interior
        assert np.max(np.abs(jumps)) <= cfg.jump_epsilon
        # and the reduced basis still holds the densified fit within delta
        dense_p = axes[a].evaluate(coefs[a], rough.time)
        dense_v = axes[a].evaluate(coefs[a], rough.time, 1)
        w = np.full(rough.time.size, 1.0)
        c = reduced.fit(rough.time, dense_p, w, rough.time, dense_v, w, ridge=0.0)
        assert np.max(np.abs(reduced.evaluate(c, rough.time) - dense_p)) <= cfg.delta_position
        err_v = np.max(np.abs(reduced.evaluate(c, rough.time, 1) - dense_v))
        assert err_v <= cfg.delta_velocity
        # and the truth within delta too
        assert np.max(np.abs(reduced.evaluate(c, rough.time) - pos[:, a])) <= cfg.delta_position


def test_select_knots_keeps_the_fixed_event_knots(polynomial_densified):
    rough, _, _, cfg, axes, coefs, covs, _ = polynomial_densified
    reduced, jumps, _ = select_knots(axes[0], coefs[0], covs[0], rough.time, cfg, fixed=[12.0])
    np.testing.assert_array_equal(reduced.interior, [12.0])
    assert jumps.shape == (axes[0].interior.size - 1,)


def test_select_knots_raises_for_a_solver_that_is_not_installed(polynomial_densified, monkeypatch):
    import cvxpy as cp

    rough, _, _, _, axes, coefs, covs, _ = polynomial_densified

    # whatever this machine has installed, the solve fails the way cvxpy reports a
    # missing solver
    def missing(self, *args, **kwargs):
        raise cp.error.SolverError('The solver ECOS is not installed.')

    monkeypatch.setattr(cp.Problem, 'solve', missing)
    with pytest.raises(KnotSelectionError, match='solver ECOS failed.*installed'):
        select_knots(axes[0], coefs[0], covs[0], rough.time, KnotConfig(solver='ECOS'))


def test_knot_config_rejects_an_unknown_solver():
    with pytest.raises(ValueError, match='solver must be one of'):
        KnotConfig(solver='GUROBI_TYPO')


# ---------------------------------------------------------------------------------------
# seed 000


@pytest.fixture(scope='module')
def seed000_selection():
    _, obs = _seed000('seed000_s1')
    rough = rough_trajectory(obs, 0, 0.0, 94.0)
    assert rough is not None and rough.source == 'telemetry'
    return choose_knots(rough, 0.0, 94.0, [(45.0, 75.0)], KnotConfig())


def test_choose_knots_on_seed000_keeps_far_fewer_knots_than_the_dense_grid(seed000_selection):
    sel = seed000_selection
    # measured: 219 dense interior knots per axis (1 s, 0.2 s in the gap) -> 9, 8, 6
    for dense, kept in zip(sel.dense, sel.selected, strict=True):
        assert dense > 150
        assert kept < dense / 5


def test_choose_knots_on_seed000_repeats_knots_at_the_staging_events(seed000_selection):
    """Stage-1 cut-off 33.4 s into the span, stage-2 ignition 1.5 s later."""
    sel = seed000_selection
    deg = KnotConfig().degree
    np.testing.assert_allclose(sel.events, [33.4, 34.9], atol=0.1 * DT)
    for ax in sel.trajectory.axes:
        for event in sel.events:
            assert np.sum(np.abs(ax.interior - event) < 1e-9) == deg - 1
        # no other knot is repeated
        _, counts = np.unique(ax.interior, return_counts=True)
        assert np.sum(counts > 1) == 2


def test_uniform_knots_repeat_events_and_refine_segments():
    k = uniform_knots(0.0, 10.0, 1.0, [(4.0, 6.0)], 0.5, [7.02], degree=4)
    np.testing.assert_allclose(
        k, [1, 2, 3, 4, 4.5, 5, 5.5, 6, 7.02, 7.02, 7.02, 8, 9], rtol=0.0, atol=1e-12
    )


# ---------------------------------------------------------------------------------------
# incomplete segments


@pytest.mark.parametrize('name', ['seed000_s1', 'seed000_s2'])
@pytest.mark.parametrize('bin_s', [0.5, 1.0, 2.0])
def test_find_incomplete_segments_recovers_the_seed000_gap_within_a_bin(name, bin_s):
    world, obs = _seed000(name)
    segs = find_incomplete_segments(
        obs, 0, lambda t: world.target_state(0, t), 0.0, 94.0, CoverageConfig(bin=bin_s)
    )
    assert len(segs) == 1, segs
    np.testing.assert_allclose(segs[0], (45.0, 75.0), rtol=0.0, atol=bin_s + 1e-9)


@pytest.mark.parametrize('name', ['seed000_s1', 'seed000_s2'])
def test_find_incomplete_segments_finds_the_gap_from_a_rough_trajectory_held_past_its_samples(
    name,
):
    # fixes stop where the gap starts: the rough trajectory holds its first state over
    # the gap. Linearised there, every row of a bin sat at one position, and the gap's
    # blind direction came out determined; on the bins' own motion it does not
    world, obs = _seed000(name)
    segs = find_incomplete_segments(
        obs, 0, lambda t: world.target_state(0, np.clip(t, 75.0, None)), 40.0, 94.0
    )
    assert len(segs) == 1, segs
    np.testing.assert_allclose(segs[0], (45.0, 75.0), rtol=0.0, atol=1.0 + 1e-9)


def test_find_incomplete_segments_finds_nothing_where_every_station_measures():
    world, obs = _seed000('seed000_s1')
    segs = find_incomplete_segments(obs, 0, lambda t: world.target_state(0, t), 0.0, 40.0)
    assert segs == []


def test_find_incomplete_segments_marks_a_window_without_measurements_whole():
    world, obs = _seed000('seed000_s1')
    assert find_incomplete_segments(
        obs.without_telemetry(), 7, lambda t: world.target_state(0, t), 0.0, 10.0
    ) == [(0.0, 10.0)]


@pytest.mark.parametrize(
    ('segments', 'join', 'expected'),
    [
        ([], 0.0, []),
        ([(3.0, 4.0), (1.0, 2.0)], 0.0, [(1.0, 2.0), (3.0, 4.0)]),  # sorted
        ([(1.0, 3.0), (2.0, 4.0)], 0.0, [(1.0, 4.0)]),  # overlapping
        ([(1.0, 2.0), (2.0, 3.0)], 0.0, [(1.0, 3.0)]),  # touching
        ([(1.0, 2.0), (2.4, 3.0)], 0.5, [(1.0, 3.0)]),  # closer than join
        ([(1.0, 2.0), (2.6, 3.0)], 0.5, [(1.0, 2.0), (2.6, 3.0)]),
        ([(1.0, 5.0), (2.0, 3.0)], 0.0, [(1.0, 5.0)]),  # contained
        ([(2.0, 2.0), (3.0, 1.0), (4.0, 5.0)], 0.0, [(4.0, 5.0)]),  # empty ones dropped
    ],
)
def test_merge_segments_returns_the_sorted_union(segments, join, expected):
    assert merge_segments(segments, join) == expected


def test_coverage_config_rejects_bad_values():
    with pytest.raises(ValueError, match='bin > 0'):
        CoverageConfig(bin=0.0)
    with pytest.raises(ValueError, match='factor > 1'):
        CoverageConfig(factor=1.0)


def test_select_knots_drops_every_knot_of_a_polynomial_without_a_degenerate_lp():
    """A rough trajectory that is one polynomial has 4th-derivative jumps at rounding
    level; scaling the LP by them once made both solvers fail (seen on seed003_q3)."""
    from orbit_tracking.core.estimation.bspline import SplineAxis
    from orbit_tracking.core.estimation.knots import KnotConfig, select_knots

    ax = SplineAxis.from_interior(np.arange(1.0, 10.0), 0.0, 10.0, 4)
    t = np.linspace(0.0, 10.0, 201)
    coef = ax.fit(t, 3.0 + 2.0 * t - 0.5 * t**2 + 0.01 * t**3, ridge=0.0)
    reduced, jumps, info = select_knots(ax, coef, np.eye(ax.n_coef) * 1e-4, t, KnotConfig())
    assert reduced.interior.size == 0
    assert np.max(np.abs(jumps)) < 1e-6
    assert info['status'] == 'negligible jumps'


def test_rough_axis_sigma_rotates_the_covariance_into_the_frame():
    n = 4
    cov = np.zeros((n, 6, 6))
    cov[:, :3, :3] = np.diag([1.0, 4.0, 9.0])
    cov[:, 3:, 3:] = np.diag([0.01, 0.04, 0.09])
    rot = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # axes: z, x, y
    t = np.arange(n, dtype=float)
    rough = RoughTrajectory('first solution', t, np.zeros((n, 3)), np.zeros((n, 3)), 1.0, 0.1, cov)
    sd = rough.axis_sigma(rot)
    assert sd is not None
    np.testing.assert_allclose(sd[0], np.tile([3.0, 1.0, 2.0], (n, 1)))
    np.testing.assert_allclose(sd[1], np.tile([0.3, 0.1, 0.2], (n, 1)))
    assert RoughTrajectory('fixes', t, np.zeros((n, 3)), None, 1.0, 0.0).axis_sigma(rot) is None


def test_select_knots_accepts_any_spline_within_three_sigma_of_an_estimate():
    """A first solution wiggles about the truth within its own uncertainty (here 2 m
    with 1 m sigma); held to its white-noise fit tolerance the selection keeps knots for
    the wiggle, given the estimate's sigma it keeps none."""
    from orbit_tracking.core.estimation.bspline import SplineAxis

    ax = SplineAxis.from_interior(np.arange(1.0, 20.0, 0.5), 0.0, 20.0, 4)
    t = np.linspace(0.0, 20.0, 401)
    y = 3.0 + 200.0 * t - 4.0 * t**2 + 0.02 * t**3 + 2.0 * np.sin(2 * np.pi * t / 4.0)
    coef = ax.fit(t, y, ridge=0.0)
    cov = np.eye(ax.n_coef) * 1e-4
    tight, _, _ = select_knots(ax, coef, cov, t, KnotConfig())
    floor = (np.full(t.size, 1.0), np.full(t.size, 10.0))
    loose, _, _ = select_knots(ax, coef, cov, t, KnotConfig(), floor=floor)
    assert tight.interior.size >= 10
    assert loose.interior.size == 0


def _rough_with(kind: str, rng: np.random.Generator) -> tuple[RoughTrajectory, float]:
    """60 s of 20 Hz rough trajectory along a smooth climbing track, with telemetry errors
    of one ``kind`` (issue 14's failure classes), and its sampling interval."""
    t = np.arange(0.0, 60.0 + 1e-9, 0.05)
    p = np.stack([300.0 * t + 4.0 * t**2, 500.0 * t - 2.0 * t**2, 1000.0 * np.sin(t / 10.0)], 1)
    v = np.stack([300.0 + 8.0 * t, 500.0 - 4.0 * t, 100.0 * np.cos(t / 10.0)], 1)
    n = t.size
    if kind == 'random_walk':  # position error a random walk, velocity white and separate
        p = p + np.cumsum(rng.normal(0.0, 0.05, (n, 3)), axis=0)
        v = v + rng.normal(0.0, 0.02, (n, 3))
    elif kind == 'separate_velocity':  # smooth position drift, velocity from another source
        p = p + np.outer(np.sin(t / 7.0), [3.0, -2.0, 1.0])
        v = v + np.outer(np.cos(t / 3.0), [0.3, 0.2, -0.1])
    elif kind == 'time_skew':  # position stamped 50 ms late
        p = p - 0.05 * v
    else:  # white: the seed's assumption
        p = p + rng.normal(0.0, 0.3, (n, 3))
        v = v + rng.normal(0.0, 0.01, (n, 3))
    rough = RoughTrajectory('telemetry', t, p, v, _noise_level(p), _noise_level(v))
    return rough, 0.05


@pytest.mark.parametrize('kind', ['white', 'random_walk', 'separate_velocity', 'time_skew'])
def test_densification_stays_bounded_whatever_the_rough_trajectory_errors(kind):
    """Correlated telemetry errors, a velocity from another source, a time-tag skew: the
    second differences see almost none of them, and densification used to run away
    (hundreds of knots per axis, finer than the telemetry's sampling). The knots stay
    within the budget (the base grid twice over) and no interval is shorter than two
    samples; a 30 s incomplete segment does not change that."""
    rough, dt = _rough_with(kind, np.random.default_rng(11))
    frame = spline_frame(rough)
    segments = [(15.0, 45.0)]
    base = uniform_knots(0.0, 60.0, 1.0, segments, 0.2, (), 4)
    axes, coefs, _, _ = densify(rough, frame, 0.0, 60.0, segments, (), KnotConfig())
    for ax in axes:
        assert ax.interior.size <= 2 * base.size, (kind, ax.interior.size, base.size)
        assert np.min(np.diff(np.unique(ax.knots))) >= 2.0 * dt - 1e-9
    sel = choose_knots(rough, 0.0, 60.0, segments, KnotConfig())
    assert max(sel.selected) <= 2 * base.size


def test_long_spans_without_a_knot_are_filled_from_a_grid_that_ignores_the_edges():
    from orbit_tracking.core.estimation.bspline import SplineAxis
    from orbit_tracking.core.estimation.knots import _fill_long_spans

    cfg = KnotConfig(max_spacing=5.0)
    event = [31.2] * 3  # a repeated (event) knot stays repeated
    ax = SplineAxis.from_interior(np.array([12.0, *event, 33.0]), 0.3, 60.3, cfg.degree)
    out = _fill_long_spans(ax, cfg).interior
    np.testing.assert_allclose(out, [5, 12, 15, 20, 25, *event, 33, 40, 45, 50, 55])
    gaps = np.diff(np.concatenate([[0.3], out, [60.3]]))
    assert gaps.max() <= 1.5 * cfg.max_spacing
    # moving the window's edges by a microsecond adds the same knots
    moved = SplineAxis.from_interior(np.array([12.0, *event, 33.0]), 0.300001, 60.300001, 4)
    np.testing.assert_array_equal(_fill_long_spans(moved, cfg).interior, out)
    # an axis whose knots are close enough is left alone; 0 turns the limit off
    dense = SplineAxis.from_interior(np.arange(3.0, 60.0, 4.0), 0.3, 60.3, cfg.degree)
    assert _fill_long_spans(dense, cfg) is dense
    bare = SplineAxis.from_interior(np.zeros(0), 0.3, 60.3, cfg.degree)
    sel = KnotConfig(max_spacing=0.0)
    assert sel.max_spacing == 0.0
    with pytest.raises(ValueError, match='max_spacing'):
        KnotConfig(max_spacing=-1.0)
    assert _fill_long_spans(bare, cfg).interior.size == 11  # 5, 10, ..., 55
    # a span without a grid point (a short window), with or without segments
    short = SplineAxis.from_interior(np.zeros(0), 61.0, 64.0, cfg.degree)
    assert _fill_long_spans(short, cfg, [(62.0, 63.0)]) is short
    # none inside an incomplete segment
    inside = _fill_long_spans(bare, cfg, [(38.0, 52.0)]).interior
    np.testing.assert_allclose(inside, [5, 10, 15, 20, 25, 30, 35, 55])


def test_unsampled_spans_are_the_holes_widened_by_the_detector_s_reach() -> None:
    t = np.concatenate([np.arange(3.0, 20.0, 1.0), np.arange(30.0, 50.5, 1.0)])
    # an outage 19-30 s, the start before the first sample (0-3 s), a hole of one sample
    # (2 s, not longer than the 2.5 s asked) and the end after the last (50-60 s)
    t = t[t != 40.0]
    assert unsampled_spans(t, 0.0, 60.0, 2.5, 1.0) == [(0.0, 4.0), (18.0, 31.0), (49.0, 60.0)]
    # holes whose widened spans touch merge; everything is clipped to the window
    assert unsampled_spans(np.array([5.0, 10.0, 13.0, 20.0]), 6.0, 19.0, 2.5, 2.0) == [(6.0, 19.0)]
    # no samples (or one) in the window: no rough trajectory of this kind, no spans
    assert unsampled_spans(np.array([100.0]), 0.0, 60.0, 2.5, 1.0) == []
    assert unsampled_spans(np.arange(0.0, 60.5, 1.0), 0.0, 60.0, 2.5, 1.0) == []
