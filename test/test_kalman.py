"""The Kalman filter/RTS smoother baseline: at convergence it is the batch MAP solution of
the same model (checked against Gauss-Newton on every state at once, a dense solve),
its covariance is the inverse of that problem's Gauss-Newton Hessian, noise-free
measurements of a constant-acceleration truth are reproduced, and the truth tuning finds
the minimum."""

from __future__ import annotations

import numpy as np
import pytest

from orbit_tracking.core import frames
from orbit_tracking.core.baselines.kalman import KalmanConfig, _start, smooth, tune_on_truth
from orbit_tracking.core.data.observations import FixSeries, Observations, StationObservations
from orbit_tracking.core.data.tables import MeasurementTable
from orbit_tracking.core.estimation.config import EstimationError
from orbit_tracking.core.models.measurements import StationPose, predict, residual

LAT, LON = np.radians(40.9), np.radians(100.3)
ORIGIN = frames.geodetic_to_ecef(LAT, LON, 1000.0)
ENU = frames.enu_rotation(LAT, LON)

# (id, kind, fields, east/north/up offset of the station [m], sigmas)
STATIONS = [
    ('cw', 'cw_radar', ('range', 'range_rate'), (-20e3, 5e3, 0.0), (0.8, 0.05)),
    (
        'pr',
        'pulse_radar',
        ('range', 'azimuth', 'elevation'),
        (10e3, -30e3, 200.0),
        (5.0, 2e-4, 2e-4),
    ),
    ('opt', 'optical', ('azimuth', 'elevation'), (25e3, 20e3, 100.0), (5e-5, 5e-5)),
]
A0 = np.array([30.0, -10.0, 25.0])  # m/s^2, ENU


def _truth(t: np.ndarray) -> np.ndarray:
    """A constant-acceleration flight 15-40 km from the stations: (m, 6) ECEF."""
    p0, v0 = np.array([2e3, 8e3, 15e3]), np.array([400.0, 250.0, 600.0])
    p = p0 + np.outer(t, v0) + 0.5 * np.outer(t * t, A0)
    v = v0 + np.outer(t, A0)
    return np.hstack([p @ ENU.T + ORIGIN, v @ ENU.T])


def _observations(t: np.ndarray, rng: np.random.Generator | None) -> Observations:
    x = _truth(t)
    stations = []
    for k, (sid, kind, fields, enu, sig) in enumerate(STATIONS):
        # stations sample at their own instants (as unsynchronised clocks do)
        ts = t + 0.013 * k
        pose = StationPose.fixed(ORIGIN + ENU @ np.array(enu), ENU, ts.size)
        values, _ = predict(fields, _truth(ts), pose)
        sigmas = np.tile(sig, (ts.size, 1))
        if rng is not None:
            values = values + rng.standard_normal(values.shape) * sigmas
        table = MeasurementTable(
            sid, kind, fields, ts, np.zeros(ts.size, np.uint32), values, sigmas
        )
        stations.append(StationObservations(table, pose))
    noise = rng.standard_normal((t.size, 3)) * 3.0 if rng is not None else 0.0
    fixes = FixSeries(0, t, x[:, :3] + noise, np.tile(np.eye(3) * 9.0, (t.size, 1, 1)))
    return Observations(tuple(stations), {}, {0: fixes})


def _ca_model(dt: float, q: float) -> tuple[np.ndarray, np.ndarray]:
    """Written out independently of the module: Bar-Shalom et al. (6.2.3-8), per axis."""
    f = np.array([[1.0, dt, dt * dt / 2.0], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    qm = q * np.array(
        [
            [dt**5 / 20.0, dt**4 / 8.0, dt**3 / 6.0],
            [dt**4 / 8.0, dt**3 / 3.0, dt**2 / 2.0],
            [dt**3 / 6.0, dt**2 / 2.0, dt],
        ]
    )
    return np.kron(f, np.eye(3)), np.kron(qm, np.eye(3))


def _batch_map(obs: Observations, nodes: np.ndarray, cfg: KalmanConfig, x_start: np.ndarray):
    """MAP of all node states at once (prior on the first, process and measurement terms)
    by Gauss-Newton on the stacked problem, from the truth; returns the states (n, 9) and
    the inverse Gauss-Newton Hessian (9n, 9n)."""
    n = nodes.size
    p0 = np.diag(np.repeat(np.square(cfg.init_sigma), 3))
    l0 = np.linalg.inv(np.linalg.cholesky(p0))
    steps = []
    for k in range(1, n):
        f, q = _ca_model(nodes[k] - nodes[k - 1], cfg.jerk_psd)
        steps.append((f, np.linalg.inv(np.linalg.cholesky(q))))
    rows = [(s, np.searchsorted(nodes, s.table.time - 1e-9)) for s in obs.stations]

    def linearised(xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        res, jac = [l0 @ (xs[0] - x_start)], [np.zeros((9, 9 * n))]
        jac[0][:, :9] = l0
        for k, (f, lq) in enumerate(steps, start=1):
            res.append(lq @ (xs[k] - f @ xs[k - 1]))
            j = np.zeros((9, 9 * n))
            j[:, 9 * k : 9 * k + 9] = lq
            j[:, 9 * k - 9 : 9 * k] = -lq @ f
            jac.append(j)
        for s, node in rows:
            pred, h = predict(s.table.fields, xs[node, :6], s.pose, jacobian=True)
            w = residual(s.table.fields, s.table.values, pred) / s.table.sigmas
            for i, k in enumerate(node):
                j = np.zeros((w.shape[1], 9 * n))
                j[:, 9 * k : 9 * k + 6] = -h[i] / s.table.sigmas[i][:, None]
                res.append(w[i])
                jac.append(j)
        return np.concatenate(res), np.vstack(jac)

    xs = np.hstack([_truth(nodes), np.tile(A0 @ ENU.T, (n, 1))])
    for _ in range(8):
        r, j = linearised(xs)
        xs = xs + np.linalg.lstsq(j, -r, rcond=None)[0].reshape(n, 9)
    r, j = linearised(xs)
    return xs, np.linalg.inv(j.T @ j)


def test_smoother_at_convergence_is_the_batch_map_solution_with_its_covariance():
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 3.0, 0.1)
    obs = _observations(t, rng)
    cfg = KalmanConfig(jerk_psd=500.0, passes=30, tolerance=1e-8)
    nodes = np.unique(np.concatenate([s.table.time for s in obs.stations] + [t]))
    track = smooth(obs, 0, nodes, cfg)
    assert track.passes < cfg.passes  # converged
    assert track.rows == sum(len(s.table) for s in obs.stations)
    x_ref, cov_ref = _batch_map(obs, nodes, cfg, _start(obs, 0, float(nodes[0])))
    assert np.max(np.abs(track.state[:, :3] - x_ref[:, :3])) < 1e-6  # m
    assert np.max(np.abs(track.state[:, 3:6] - x_ref[:, 3:6])) < 1e-6  # m/s
    for k in (0, nodes.size // 2, nodes.size - 1):
        block = cov_ref[9 * k : 9 * k + 9, 9 * k : 9 * k + 9]
        # relative to the standard deviations (the dense inverse itself is good to ~1e-4)
        sd = np.sqrt(np.diag(block))
        assert np.max(np.abs(track.covariance[k] - block) / np.outer(sd, sd)) < 1e-3
    # and the estimate is good: within a few sigma of the truth everywhere
    x, c = track.states(nodes)
    e = x - _truth(nodes)
    z = e / np.sqrt(np.diagonal(c, axis1=1, axis2=2))
    assert np.max(np.abs(z)) < 5.0


def test_noise_free_measurements_of_a_constant_acceleration_truth_are_reproduced():
    t = np.arange(0.0, 4.0, 0.1)
    obs = _observations(t, None)
    track = smooth(obs, 0, t, KalmanConfig(jerk_psd=1e-3, passes=30))
    x, _ = track.states(t)
    np.testing.assert_allclose(x, _truth(t), rtol=0.0, atol=1e-4)
    np.testing.assert_allclose(track.state[:, 6:], np.tile(A0 @ ENU.T, (t.size, 1)), atol=1e-4)


def test_outputs_only_at_the_requested_times_and_clear_errors():
    t = np.arange(0.0, 2.0, 0.1)
    obs = _observations(t, np.random.default_rng(1))
    track = smooth(obs, 0, t[::2], KalmanConfig(passes=2))
    assert track.time.size == 10 and track.t0 == 0.0
    with pytest.raises(ValueError, match='output times'):
        track.states([0.05])
    with pytest.raises(ValueError, match='non-decreasing'):
        smooth(obs, 0, t[::-1])
    with pytest.raises(EstimationError, match='no station measurements'):
        smooth(obs, 5, t)
    with pytest.raises(EstimationError, match='start from'):
        smooth(Observations(obs.stations), 0, t)
    for bad in ({'jerk_psd': 0.0}, {'passes': 0}, {'tolerance': 0.0}, {'gate_probability': 1.0}):
        with pytest.raises(ValueError):
            KalmanConfig(**bad)


def test_the_gate_leaves_out_a_wild_row_and_counts_it():
    t = np.arange(0.0, 3.0, 0.1)
    obs = _observations(t, np.random.default_rng(3))
    st = obs.stations[1]
    values = st.table.values.copy()
    values[12, 0] += 5e3  # a 5 km range outlier
    bad = MeasurementTable(
        st.table.station_id,
        st.table.kind,
        st.table.fields,
        st.table.time,
        st.table.target_id,
        values,
        st.table.sigmas,
    )
    stations = (obs.stations[0], StationObservations(bad, st.pose), obs.stations[2])
    wild = Observations(stations, {}, obs.fixes)
    gated = smooth(wild, 0, t, KalmanConfig(gate_probability=1e-6))
    clean = smooth(obs, 0, t, KalmanConfig(gate_probability=1e-6))
    assert gated.rejected == 1 and clean.rejected == 0
    assert np.max(np.abs(gated.state[:, :3] - clean.state[:, :3])) < 5.0


def test_tuning_finds_the_minimum_on_a_log_grid():
    calls = []

    def err(q: float) -> float:
        calls.append(q)
        if q > 1e2:
            raise EstimationError('diverged')
        return (np.log10(q) - 0.6) ** 2

    q, e = tune_on_truth(err)
    assert abs(np.log10(q) - 0.6) <= 0.125 + 1e-12
    assert e == pytest.approx((np.log10(q) - 0.6) ** 2)
    assert len(calls) == 7 + 4
