"""B-spline basis (seed 000's trajectory model): sparse design matrices against scipy's
``BSpline`` and finite differences, the jump matrix of the ``degree``-th derivative against
jumps measured on the polynomial pieces, continuity at repeated knots, validation, the
three-axis trajectory's world-frame design, and the least-squares fit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import BSpline
from scipy.spatial.transform import Rotation

from orbit_tracking.core.estimation.bspline import SplineAxis, SplineTrajectory, clamped_knots

DEGREE = 4


def _random_axis(rng: np.random.Generator, degree: int = DEGREE) -> SplineAxis:
    """A clamped axis on [0, 10] with random single knots and one knot repeated
    ``degree - 1`` times (the staging knot of seed 000)."""
    single = np.sort(rng.uniform(0.3, 9.7, size=6))
    repeated = rng.uniform(2.0, 8.0)
    # keep the repeated knot clear of the others so every interval has a finite width
    single = single[np.abs(single - repeated) > 0.2]
    interior = np.sort(np.concatenate([single, np.full(degree - 1, repeated)]))
    return SplineAxis.from_interior(interior, 0.0, 10.0, degree)


def _times(rng: np.random.Generator, ax: SplineAxis, n: int = 200) -> np.ndarray:
    """Random epochs strictly between knots, plus both ends of the span."""
    t = rng.uniform(ax.t0, ax.t1, size=n)
    brk = np.unique(ax.knots)
    t = t[np.min(np.abs(t[:, None] - brk[None, :]), axis=1) > 1e-6]
    return np.concatenate([[ax.t0], t, [ax.t1]])


# ---------------------------------------------------------------------------------------
# design matrices


@pytest.mark.parametrize('seed', range(4))
@pytest.mark.parametrize('nu', range(DEGREE + 1))
def test_design_matrix_matches_scipy_bspline_derivatives(seed, nu):
    rng = np.random.default_rng(seed)
    ax = _random_axis(rng)
    t = _times(rng, ax)
    coef = rng.standard_normal(ax.n_coef)
    d = ax.design(t, nu)
    assert d.shape == (t.size, ax.n_coef)
    ref = BSpline(ax.knots, coef, ax.degree)(t, nu)
    scale = np.max(np.abs(ref)) + 1.0
    np.testing.assert_allclose(d @ coef, ref, rtol=0.0, atol=1e-10 * scale)
    # column by column too: each basis function's derivative
    eye = np.eye(ax.n_coef)
    ref_cols = np.stack([BSpline(ax.knots, eye[i], ax.degree)(t, nu) for i in range(ax.n_coef)], 1)
    np.testing.assert_allclose(d.toarray(), ref_cols, rtol=0.0, atol=1e-10 * scale)


@pytest.mark.parametrize('nu', range(1, DEGREE + 1))
def test_design_derivatives_match_central_differences_of_the_lower_derivative(nu):
    rng = np.random.default_rng(11)
    ax = _random_axis(rng)
    coef = rng.standard_normal(ax.n_coef) * 100.0
    h = 1e-5
    brk = np.unique(ax.knots)
    t = rng.uniform(ax.t0 + h, ax.t1 - h, size=300)
    # the stencil must not straddle a knot: there the lower derivative may have a kink
    t = t[np.min(np.abs(t[:, None] - brk[None, :]), axis=1) > 10 * h]
    fd = (ax.evaluate(coef, t + h, nu - 1) - ax.evaluate(coef, t - h, nu - 1)) / (2 * h)
    got = ax.evaluate(coef, t, nu)
    np.testing.assert_allclose(got, fd, rtol=1e-5, atol=1e-5 * np.max(np.abs(got)))


def test_design_above_the_degree_is_zero_and_sparse_rows_touch_degree_plus_one_columns():
    rng = np.random.default_rng(5)
    ax = _random_axis(rng)
    t = _times(rng, ax)
    assert ax.design(t, ax.degree + 1).nnz == 0
    assert ax.design(t, ax.degree + 1).shape == (t.size, ax.n_coef)
    nnz_per_row = np.diff(ax.design(t).indptr)
    assert nnz_per_row.max() <= ax.degree + 1


def test_design_rows_of_the_basis_sum_to_one():
    rng = np.random.default_rng(6)
    ax = _random_axis(rng)
    t = _times(rng, ax)
    np.testing.assert_allclose(np.asarray(ax.design(t).sum(axis=1)).ravel(), 1.0, atol=1e-13)


# ---------------------------------------------------------------------------------------
# jump matrix


def _measured_jumps(ax: SplineAxis, coef: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Jumps of the ``degree``-th derivative at the distinct interior knots, measured by
    fitting a degree-``p`` polynomial to samples of the spline inside each knot interval:
    its ``p``-th derivative is ``p!`` times the leading coefficient."""
    brk = np.unique(ax.knots)
    per_interval = []
    for a, b in zip(brk[:-1], brk[1:], strict=True):
        # sample and fit in the interval's own unit variable to keep the fit well posed
        u = np.linspace(0.1, 0.9, 3 * (ax.degree + 1))
        y = ax.evaluate(coef, a + u * (b - a))
        lead = np.polyfit(u, y, ax.degree)[0] / (b - a) ** ax.degree
        per_interval.append(lead * np.prod(np.arange(1, ax.degree + 1)))
    return np.diff(per_interval), brk[1:-1]


@pytest.mark.parametrize('seed', range(6))
def test_jump_matrix_matches_numerical_jumps_on_random_splines(seed):
    rng = np.random.default_rng(seed)
    ax = _random_axis(rng)
    coef = rng.standard_normal(ax.n_coef)
    c, tau = ax.jump_matrix()
    ref, ref_tau = _measured_jumps(ax, coef)
    np.testing.assert_array_equal(tau, ref_tau)
    assert tau.size == np.unique(ax.interior).size  # the repeated knot appears once
    assert c.shape == (tau.size, ax.n_coef)
    got = c @ coef
    np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-6 * np.max(np.abs(ref)))


def test_jump_matrix_is_zero_for_a_single_polynomial_written_with_knots():
    """A degree-p polynomial (every jump zero) has a zero jump vector on any knots."""
    rng = np.random.default_rng(3)
    ax = _random_axis(rng)
    t = np.linspace(ax.t0, ax.t1, 400)
    poly = np.polynomial.Polynomial(rng.standard_normal(ax.degree + 1))
    coef = ax.fit(t, poly(t), ridge=0.0)
    c, _ = ax.jump_matrix()
    scale = np.max(np.abs(poly.deriv(ax.degree).coef))
    np.testing.assert_allclose(c @ coef, 0.0, atol=1e-7 * scale)


def test_jump_matrix_of_an_axis_without_interior_knots_is_empty():
    ax = SplineAxis.from_interior([], 0.0, 5.0, DEGREE)
    c, tau = ax.jump_matrix()
    assert c.shape == (0, ax.n_coef)
    assert tau.size == 0


def test_triple_knot_in_a_quartic_leaves_velocity_continuous_and_lets_acceleration_jump():
    """Multiplicity m = 3 at degree 4 leaves the spline C^(4-3) = C^1 there; a single
    knot leaves it C^3."""
    rng = np.random.default_rng(8)
    ax = SplineAxis.from_interior([2.0, 4.0, 5.0, 5.0, 5.0, 6.5, 8.0], 0.0, 10.0, DEGREE)
    eps = 1e-7
    jumps = {nu: [] for nu in range(4)}
    for _ in range(20):
        coef = rng.standard_normal(ax.n_coef) * 50.0
        for nu in range(4):
            left, right = ax.evaluate(coef, [5.0 - eps, 5.0 + eps], nu)
            jumps[nu].append(abs(right - left))
    # position and velocity: only the O(eps) change of a continuous function
    assert max(jumps[0]) < 1e-4
    assert max(jumps[1]) < 1e-3
    # acceleration: a finite jump for generic coefficients
    assert min(jumps[2]) > 1e-2
    # and at a single knot the acceleration and jerk are continuous
    coef = rng.standard_normal(ax.n_coef) * 50.0
    for nu in (2, 3):
        left, right = ax.evaluate(coef, [4.0 - eps, 4.0 + eps], nu)
        assert abs(right - left) < 1e-2


# ---------------------------------------------------------------------------------------
# validation


@pytest.mark.parametrize(
    ('knots', 'message'),
    [
        ([0, 0, 0, 0, 1, 2, 3, 3, 3, 3, 3], 'clamped'),  # start repeated 4, not 5, times
        ([0, 0, 0, 0, 0, 2, 1, 3, 3, 3, 3, 3], 'non-decreasing'),
        ([0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 3, 3, 3, 3, 3], 'more than degree'),
        ([0, 0, 0, 0, 0, 3, 3, 3, 3], 'at least 10 knots'),
    ],
)
def test_axis_rejects_invalid_knot_vectors_with_a_message(knots, message):
    with pytest.raises(ValueError, match=message):
        SplineAxis(np.asarray(knots, dtype=float), DEGREE)


def test_axis_rejects_degree_zero():
    with pytest.raises(ValueError, match='degree must be >= 1'):
        SplineAxis(np.array([0.0, 1.0, 2.0]), 0)


@pytest.mark.parametrize('t', [[-0.5, 1.0], [1.0, 10.001]])
def test_design_rejects_times_outside_the_span(t):
    ax = SplineAxis.from_interior([5.0], 0.0, 10.0, DEGREE)
    with pytest.raises(ValueError, match='outside the spline span'):
        ax.design(t)


def test_clamped_knots_rejects_interior_knots_on_or_beyond_the_ends():
    with pytest.raises(ValueError, match='strictly inside'):
        clamped_knots([0.0, 5.0], 0.0, 10.0, DEGREE)
    with pytest.raises(ValueError, match='strictly inside'):
        clamped_knots([5.0, 11.0], 0.0, 10.0, DEGREE)
    with pytest.raises(ValueError, match='t1 > t0'):
        clamped_knots([], 10.0, 10.0, DEGREE)


def test_trajectory_rejects_axes_with_different_spans_and_a_non_orthonormal_rotation():
    a = SplineAxis.from_interior([5.0], 0.0, 10.0, DEGREE)
    b = SplineAxis.from_interior([5.0], 0.0, 11.0, DEGREE)
    with pytest.raises(ValueError, match='share their span'):
        SplineTrajectory((a, a, b), np.zeros(3), np.eye(3))
    with pytest.raises(ValueError, match='orthonormal'):
        SplineTrajectory((a, a, a), np.zeros(3), 2.0 * np.eye(3))


# ---------------------------------------------------------------------------------------
# trajectory and fit


def _trajectory(rng: np.random.Generator) -> SplineTrajectory:
    axes = (
        _random_axis(rng),
        SplineAxis.from_interior([2.5, 5.0, 7.5], 0.0, 10.0, DEGREE),
        SplineAxis.from_interior([], 0.0, 10.0, DEGREE),
    )
    rot = Rotation.from_rotvec(rng.standard_normal(3)).as_matrix()
    return SplineTrajectory(axes, np.array([-1.2e6, 4.8e6, 4.1e6]), rot)


@pytest.mark.parametrize('nu', [0, 1])
def test_world_design_matches_finite_differences_of_states_in_the_coefficients(nu):
    rng = np.random.default_rng(21)
    traj = _trajectory(rng)
    coef = rng.standard_normal(traj.n_coef) * 1e3
    t = np.linspace(traj.t0, traj.t1, 23)
    g = traj.world_design(t, nu).toarray()
    assert g.shape == (3 * t.size, traj.n_coef)
    cols = slice(3 * nu, 3 * nu + 3)
    h = 1.0  # the states are linear in the coefficients: the difference is exact
    fd = np.empty_like(g)
    for i in range(traj.n_coef):
        e = np.zeros(traj.n_coef)
        e[i] = h
        diff = traj.states(coef + e, t)[:, cols] - traj.states(coef - e, t)[:, cols]
        fd[:, i] = (diff / (2 * h)).ravel()  # rows 3 j + c: time-major, as documented
    np.testing.assert_allclose(g, fd, rtol=0.0, atol=1e-8)


def test_world_design_reproduces_states_and_acceleration():
    rng = np.random.default_rng(22)
    traj = _trajectory(rng)
    coef = rng.standard_normal(traj.n_coef) * 1e3
    t = np.linspace(traj.t0, traj.t1, 31)
    x = traj.states(coef, t)
    np.testing.assert_allclose(
        (traj.world_design(t, 0) @ coef).reshape(-1, 3) + traj.origin, x[:, :3], atol=1e-8
    )
    np.testing.assert_allclose((traj.world_design(t, 1) @ coef).reshape(-1, 3), x[:, 3:])
    np.testing.assert_allclose(
        (traj.world_design(t, 2) @ coef).reshape(-1, 3), traj.acceleration(coef, t)
    )
    # the spline frame is a rigid frame: world = origin + R s
    np.testing.assert_allclose(
        x[:, :3], traj.local(coef, t) @ traj.rotation.T + traj.origin, atol=1e-8
    )


def test_states_velocity_is_the_time_derivative_of_position():
    rng = np.random.default_rng(23)
    traj = _trajectory(rng)
    coef = rng.standard_normal(traj.n_coef) * 1e3
    brk = np.unique(np.concatenate([a.knots for a in traj.axes]))
    t = np.linspace(0.05, 9.95, 57)
    t = t[np.min(np.abs(t[:, None] - brk[None, :]), axis=1) > 1e-3]
    h = 1e-4
    fd = (traj.states(coef, t + h)[:, :3] - traj.states(coef, t - h)[:, :3]) / (2 * h)
    np.testing.assert_allclose(traj.states(coef, t)[:, 3:], fd, rtol=0.0, atol=2e-4)


@pytest.mark.parametrize('seed', range(3))
def test_fit_without_ridge_reproduces_an_exact_spline(seed):
    rng = np.random.default_rng(seed)
    ax = _random_axis(rng)
    coef = rng.standard_normal(ax.n_coef) * 1e3
    t = np.linspace(ax.t0, ax.t1, 500)
    got = ax.fit(t, ax.evaluate(coef, t), ridge=0.0)
    np.testing.assert_allclose(got, coef, rtol=0.0, atol=1e-9 * np.max(np.abs(coef)))
    # with first derivatives and weights (seed 000's rho-weighted rough fit)
    got = ax.fit(
        t,
        ax.evaluate(coef, t),
        np.full(t.size, 0.5),
        t,
        ax.evaluate(coef, t, 1),
        np.full(t.size, 0.5 * 1e4),
        ridge=0.0,
    )
    np.testing.assert_allclose(got, coef, rtol=0.0, atol=1e-9 * np.max(np.abs(coef)))


@pytest.mark.parametrize('seed', range(3))
def test_fit_with_the_default_ridge_reproduces_an_exact_spline_to_a_part_in_1e7(seed):
    """The default ridge (1e-9 of the largest normal-matrix diagonal) shrinks the
    coefficients toward zero; on position data alone the bias stays below 1e-7 of the
    coordinates' size (measured: up to 2e-8)."""
    rng = np.random.default_rng(seed)
    ax = _random_axis(rng)
    coef = rng.standard_normal(ax.n_coef) * 1e3
    t = np.linspace(ax.t0, ax.t1, 500)
    y = ax.evaluate(coef, t)
    got = ax.evaluate(ax.fit(t, y), t)
    np.testing.assert_allclose(got, y, rtol=0.0, atol=1e-7 * np.max(np.abs(y)))


def test_fit_states_reproduces_an_exact_trajectory():
    rng = np.random.default_rng(31)
    traj = _trajectory(rng)
    coef = rng.standard_normal(traj.n_coef) * 1e3
    t = np.linspace(traj.t0, traj.t1, 400)
    x = traj.states(coef, t)
    got = traj.fit_states(t, x[:, :3], x[:, 3:], 1.0, 100.0)
    # local coordinates of about 1e3 m; the default ridge biases them by < 1e-4 m
    # (measured 7e-5 m)
    np.testing.assert_allclose(traj.states(got, t), x, rtol=0.0, atol=2e-4)
