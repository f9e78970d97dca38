"""The per-draw Cramér–Rao bound (orbit_tracking.core.crb) against independent references:
finite differences for the measurement Jacobians through the spline, the closed-form
variance of polynomial regression, a Monte-Carlo of an efficient estimator (maximum
likelihood by Gauss-Newton) on a tiny problem with station values and correlated
telemetry, and the oracle's knots against the truth they represent."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
import scipy.linalg as sla
from scipy.optimize import least_squares

from orbit_tracking.core import frames
from orbit_tracking.core.crb import (
    TelemetryErrorCovariance,
    bound,
    oracle_spline,
    station_information,
    station_jacobian,
    telemetry_information,
)
from orbit_tracking.core.estimation.bspline import SplineAxis, SplineTrajectory
from orbit_tracking.core.models.measurements import StationPose, predict
from orbit_tracking.core.sim.families import draw
from orbit_tracking.core.sim.simulator import World

LAT, LON = np.radians(30.0), np.radians(10.0)
ORIGIN = frames.geodetic_to_ecef(LAT, LON, 5000.0)
ENU = frames.enu_rotation(LAT, LON)


def _trajectory(interior: tuple[float, ...] = (), span: float = 10.0) -> SplineTrajectory:
    axes = tuple(SplineAxis.from_interior(interior, 0.0, span, 4) for _ in range(3))
    return SplineTrajectory((axes[0], axes[1], axes[2]), ORIGIN, ENU)


def _coef(traj: SplineTrajectory) -> np.ndarray:
    """A climbing, turning track in the local frame (east, north, up) [m]."""
    t = np.linspace(traj.t0, traj.t1, 200)
    local = np.stack([300.0 * t + 2.0 * t**2, 100.0 * t - 0.5 * t**3, 80.0 * t + 3.0 * t**2], 1)
    world = ORIGIN + local @ ENU.T
    return traj.fit_states(t, world)


def _station(east_km: float, north_km: float) -> StationPose:
    site = ORIGIN + ENU @ np.array([east_km * 1e3, north_km * 1e3, -4000.0])
    return StationPose.fixed(site, ENU, 1)


def _rows(traj, coef, stations, rate=10.0):
    """(fields, time, pose, states, sigmas, valid) of each station, states from the spline."""
    t = np.arange(traj.t0, traj.t1 + 1e-9, 1.0 / rate)
    x = traj.states(coef, t)
    out = []
    for fields, sig, pose in stations:
        p = StationPose.fixed(pose.position[0], pose.rotation[0], t.size)
        s = np.tile(sig, (t.size, 1))
        out.append((fields, t, p, x, s, np.ones(s.shape, dtype=bool)))
    return out


STATIONS = [
    (('range', 'range_rate'), [0.8, 0.05], _station(-20.0, 15.0)),
    (('range', 'azimuth', 'elevation'), [5.0, 3e-4, 3e-4], _station(25.0, -10.0)),
    (('azimuth', 'elevation'), [2.5e-5, 2.5e-5], _station(5.0, 30.0)),
]


def test_station_jacobian_matches_finite_differences_through_the_spline():
    traj = _trajectory((3.0, 5.0, 5.0, 7.5))
    coef = _coef(traj)
    for fields, time, pose, states, sig, valid in _rows(traj, coef, STATIONS, rate=4.0):
        jac = station_jacobian(traj, fields, time, pose, states, sig, valid).toarray()
        fd = np.zeros_like(jac)
        for k in range(traj.n_coef):
            h = 1e-3
            up, dn = coef.copy(), coef.copy()
            up[k] += h
            dn[k] -= h
            yu, _ = predict(fields, traj.states(up, time), pose)
            yd, _ = predict(fields, traj.states(dn, time), pose)
            d = (yu - yd) / (2 * h) / sig
            fd[:, k] = d.T.ravel()  # rows field-major, as station_jacobian
        # the difference quotient loses ~1e-7 (whitened) to rounding of ECEF metres
        np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-6)


def test_bound_of_axis_aligned_ranges_is_the_polynomial_regression_variance():
    """Three range stations 1e9 m away along the spline frame's axes measure one
    coordinate each; with no interior knot each axis is a quartic, so the bound is
    ``sigma^2 v(t)^T (V^T V)^-1 v(t)`` with the monomial Vandermonde ``V`` (no B-spline)."""
    traj = _trajectory(span=8.0)
    coef = _coef(traj)
    sig = np.array([0.5, 1.0, 2.0])
    stations = [
        (('range',), [sig[a]], StationPose.fixed(ORIGIN + 1e9 * ENU[:, a], ENU, 1))
        for a in range(3)
    ]
    rows = _rows(traj, coef, stations, rate=5.0)
    t_out = np.linspace(0.0, 8.0, 41)
    b = bound(traj, station_information(traj, rows), t_out)
    t = rows[0][1]
    vand = np.vander(t / 8.0, 5, increasing=True)
    inv = np.linalg.inv(vand.T @ vand)
    v_out = np.vander(t_out / 8.0, 5, increasing=True)
    dv_out = np.hstack([np.zeros((t_out.size, 1)), v_out[:, :4] * np.arange(1, 5)]) / 8.0
    reg = np.einsum('mi,ij,mj->m', v_out, inv, v_out)
    reg_v = np.einsum('mi,ij,mj->m', dv_out, inv, dv_out)
    np.testing.assert_allclose(b.position_var, reg * np.sum(sig**2), rtol=1e-4)
    np.testing.assert_allclose(b.velocity_var, reg_v * np.sum(sig**2), rtol=1e-4)
    assert not b.singular


def test_joint_covariance_holds_the_bound_per_time_and_flags_unobserved_ones():
    traj = _trajectory(span=8.0)
    coef = _coef(traj)
    rows = _rows(traj, coef, STATIONS, rate=5.0)
    t = np.linspace(0.5, 7.5, 8)
    b = bound(traj, station_information(traj, rows), t)
    sigma, finite = b.joint_position_covariance(t)
    assert sigma.shape == (24, 24) and finite.all()
    traces = np.array([np.trace(sigma[3 * k : 3 * k + 3, 3 * k : 3 * k + 3]) for k in range(8)])
    np.testing.assert_allclose(traces, b.position_var, rtol=1e-9)
    np.testing.assert_allclose(sigma, sigma.T, atol=1e-12 * np.abs(sigma).max())
    # neighbouring times of a smooth fit are positively correlated
    assert sigma[0, 3] > 0.0
    fields, tr, pose, x, s, v = rows[0]
    info = station_information(traj, [(('range',), tr, pose, x, s[:, :1], v[:, :1])])
    one = bound(traj, info, t)
    assert not one.joint_position_covariance(t)[1].any()


def test_states_no_data_can_fix_have_an_infinite_bound():
    traj = _trajectory(span=8.0)
    coef = _coef(traj)
    rows = _rows(traj, coef, [STATIONS[0]], rate=5.0)[:1]
    # one station's range alone: the spline's three axes are not all determined
    fields, t, pose, x, s, v = rows[0]
    b = bound(traj, station_information(traj, [(('range',), t, pose, x, s[:, :1], v[:, :1])]), t)
    assert b.singular and np.all(np.isinf(b.position_var))


def _gauss_markov_cov(t: np.ndarray, white: float, sigma: float, tc: float) -> np.ndarray:
    return white**2 * np.eye(t.size) + sigma**2 * np.exp(-np.abs(t[:, None] - t[None, :]) / tc)


@cache
def _monte_carlo() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position errors of maximum-likelihood fits (runs, m, 3), the bound's traces at the
    same times, and the bound without telemetry."""
    traj = _trajectory((5.0,), span=10.0)
    coef = _coef(traj)
    rows = _rows(traj, coef, STATIONS, rate=5.0)
    t_tel = np.arange(0.0, 10.0 + 1e-9, 0.5)
    cov_p = _gauss_markov_cov(t_tel, 0.5, 3.0, 4.0)
    cov_v = _gauss_markov_cov(t_tel, 0.05, 0.2, 2.0)
    tel = TelemetryErrorCovariance(t_tel, cov_p, cov_v)
    f_st = station_information(traj, rows)
    f = telemetry_information(traj, tel)
    f[: traj.n_coef, : traj.n_coef] += f_st
    t_out = np.linspace(0.0, 10.0, 21)
    b = bound(traj, f, t_out)
    b_st = bound(traj, f_st, t_out)
    lp, lv = sla.cholesky(cov_p, lower=True), sla.cholesky(cov_v, lower=True)
    x_tel = traj.states(coef, t_tel)
    truth = traj.states(coef, t_out)[:, :3]
    # the solver's Jacobian (only its convergence depends on it; the optimum is that of
    # the residuals above, written with predict alone)
    gp, gv = traj.world_design(t_tel, 0).toarray(), traj.world_design(t_tel, 1).toarray()
    tel_jac = [
        -sla.solve_triangular(chol, g[c::3], lower=True)
        for chol, g in ((lp, gp), (lv, gv))
        for c in range(3)
    ]

    def jac(c: np.ndarray, *_args: object) -> np.ndarray:
        blocks = []
        for fields, t, pose, _x, s, v in rows:
            j = station_jacobian(traj, fields, t, pose, traj.states(c, t), s, v)
            blocks.append(-j.toarray())
        # telemetry rows are ordered (epoch, axis): interleave the per-axis blocks
        for k in range(2):
            per_axis = tel_jac[3 * k : 3 * k + 3]
            blocks.append(np.stack(per_axis, axis=1).reshape(-1, traj.n_coef))
        return np.vstack(blocks)

    rng = np.random.default_rng(7)
    errors = []
    for _ in range(120):
        meas = [
            predict(fields, x, pose)[0] + rng.standard_normal(s.shape) * s
            for fields, _t, pose, x, s, _v in rows
        ]
        tp = x_tel[:, :3] + lp @ rng.standard_normal((t_tel.size, 3))
        tv = x_tel[:, 3:] + lv @ rng.standard_normal((t_tel.size, 3))

        def resid(
            c: np.ndarray, meas: list = meas, tp: np.ndarray = tp, tv: np.ndarray = tv
        ) -> np.ndarray:
            out = []
            for (fields, t, pose, _x, s, _v), y in zip(rows, meas, strict=True):
                pred, _ = predict(fields, traj.states(c, t), pose)
                r = y - pred
                if 'azimuth' in fields:
                    j = fields.index('azimuth')
                    r[:, j] = np.arctan2(np.sin(r[:, j]), np.cos(r[:, j]))
                out.append((r / s).T.ravel())
            xs = traj.states(c, t_tel)
            out.append(sla.solve_triangular(lp, tp - xs[:, :3], lower=True).ravel())
            out.append(sla.solve_triangular(lv, tv - xs[:, 3:], lower=True).ravel())
            return np.concatenate(out)

        fit = least_squares(resid, coef, jac=jac, method='lm', xtol=1e-12, ftol=1e-12)
        errors.append(traj.states(fit.x, t_out)[:, :3] - truth)
    return np.array(errors), b.position_var, b_st.position_var


def test_bound_is_attained_by_maximum_likelihood_in_a_monte_carlo():
    errors, var, _ = _monte_carlo()
    mc = np.mean(np.sum(errors**2, axis=2), axis=0)  # E|e(t)|^2 per output time
    # 120 runs of a 33-parameter Gaussian fit: the pooled mean is good to a few percent
    assert np.mean(mc) == pytest.approx(np.mean(var), rel=0.08)
    np.testing.assert_allclose(mc, var, rtol=0.2)


def test_correlated_telemetry_tightens_the_bound():
    _, var, var_stations = _monte_carlo()
    assert np.all(var < var_stations)


def test_oracle_knots_represent_the_truth_within_tolerance_with_repeated_event_knots():
    d = draw('ascent', 4)
    sc = d.scenario
    world = World(sc)
    t = np.append(np.arange(sc.t_start, sc.t_end, 0.05), sc.t_end)
    oracle = oracle_spline(t, world.target_state(0, t), sc.t_start, sc.t_end, d.events, d.kinks)
    dense = np.linspace(sc.t_start, sc.t_end, 20001)  # 4x denser than the fit's grid
    ep, ev = oracle.errors(dense, world.target_state(0, dense))
    assert ep.max() <= 0.01 and ev.max() <= 0.001, (ep.max(), ev.max())
    assert d.events
    for ax in oracle.trajectory.axes:
        for e in d.events:
            assert np.sum(np.abs(ax.interior - e) < 1e-9) == ax.degree - 1
    unpruned = oracle_spline(
        t, world.target_state(0, t), sc.t_start, sc.t_end, d.events, d.kinks, prune=False
    )
    assert sum(oracle.knots) < sum(unpruned.knots)
    # without the event knots the same tolerance needs many more knots
    blind = oracle_spline(t, world.target_state(0, t), sc.t_start, sc.t_end)
    assert sum(blind.knots) > sum(oracle.knots) + 3 * len(d.events)


def test_time_skew_nuisance_equals_the_delay_folded_into_the_covariance():
    """Eliminating the delays (parameters with a prior) must give the information of the
    telemetry whose covariance holds them: ``C + s_p^2 b_p b_p^T + s_v^2 b_v b_v^T`` over
    all three axes at once (``b`` the truth's velocity / acceleration at the stamps), the
    Woodbury identity, computed here densely."""
    traj = _trajectory((4.0, 6.0), span=10.0)
    coef = _coef(traj)
    t = np.arange(0.5, 9.5 + 1e-9, 0.5)  # delayed stamps stay inside the span
    delays, prior = (0.05, -0.02), (0.05, 0.02)
    cov = TelemetryErrorCovariance(
        t, _gauss_markov_cov(t, 1.0, 2.0, 3.0), 0.03**2 * np.eye(t.size), None, delays, prior
    )

    def vel(tt: np.ndarray) -> np.ndarray:
        return traj.states(coef, tt)[:, 3:]

    def acc(tt: np.ndarray) -> np.ndarray:
        return traj.acceleration(coef, tt)

    aug = telemetry_information(traj, cov, vel, acc)
    n = traj.n_coef
    schur = aug[:n, :n] - aug[:n, n:] @ np.linalg.solve(aug[n:, n:], aug[n:, :n])
    tp, tv = t - delays[0], t - delays[1]
    gp, gv = traj.world_design(tp, 0).toarray(), traj.world_design(tv, 1).toarray()
    design = np.vstack([gp[c::3] for c in range(3)] + [gv[c::3] for c in range(3)])
    full = sla.block_diag(*([cov.position] * 3 + [cov.velocity] * 3))
    bp = np.concatenate([-vel(tp)[:, c] for c in range(3)] + [np.zeros(3 * t.size)])
    bv = np.concatenate([np.zeros(3 * t.size)] + [-acc(tv)[:, c] for c in range(3)])
    full += prior[0] ** 2 * np.outer(bp, bp) + prior[1] ** 2 * np.outer(bv, bv)
    dense = design.T @ np.linalg.solve(full, design)
    np.testing.assert_allclose(schur, dense, rtol=1e-6, atol=1e-9 * np.abs(dense).max())
    known = telemetry_information(
        traj, TelemetryErrorCovariance(t, cov.position, cov.velocity, None, delays)
    )
    assert np.trace(np.linalg.inv(schur)) > np.trace(np.linalg.inv(known))
