"""Triangulation core: two-line midpoint, weighted N-line fix and its covariance, gates,
alignment of unsynchronised streams, and consistency (NEES) on the reference scenarios."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.optimize import least_squares

from orbit_tracking.core import frames
from orbit_tracking.core.errors import GeometryError
from orbit_tracking.core.metrics import nees, nees_summary
from orbit_tracking.core.models.measurements import StationPose, predict
from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.core.sim.simulator import World, simulate
from orbit_tracking.core.triangulation.alignment import AlignConfig, low_pass
from orbit_tracking.core.triangulation.intersection import (
    Gates,
    LineOfSight,
    angle_jacobian_local,
    intersect,
    midpoint,
    triangulate,
)
from orbit_tracking.core.triangulation.pipeline import TriangulationPipeline

SIGMA = 2.4e-5  # rad, 5 arc-seconds


def _station(lat_deg: float, lon_deg: float, h: float) -> tuple[np.ndarray, np.ndarray]:
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    return frames.geodetic_to_ecef(lat, lon, h), frames.enu_rotation(lat, lon)


STATIONS = {
    'a': _station(40.80, 100.10, 1200.0),
    'b': _station(40.60, 100.70, 1100.0),
    'c': _station(40.30, 100.20, 1300.0),
    'd': _station(40.95, 100.55, 1000.0),
}
TARGET = frames.geodetic_to_ecef(np.radians(40.6), np.radians(100.35), 35_000.0)


def measure(fields: list[str], target: np.ndarray, pos: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """Noise-free measurements (k,) of a target position from a station pose."""
    values, _ = predict(fields, np.r_[target, 0.0, 0.0, 0.0][None], StationPose.fixed(pos, rot, 1))
    return values[0]


def angle_line(
    sid: str, target: np.ndarray, sigma=(SIGMA, SIGMA), noise=(0.0, 0.0)
) -> LineOfSight:
    """A theodolite line of station ``sid`` toward ``target`` (with optional angle noise)."""
    pos, rot = STATIONS[sid]
    az, el = measure(['azimuth', 'elevation'], target, pos, rot)
    u, jac = angle_jacobian_local('angles', az + noise[0], el + noise[1])
    return LineOfSight(sid, pos, rot @ u, rot @ jac, np.diag(np.square(sigma)))


def test_noise_free_lines_meet_the_truth_to_a_micrometre():
    lines = [angle_line(s, TARGET) for s in 'abcd']
    res = triangulate(lines)
    assert res.success, res.message
    assert np.linalg.norm(res.fix.position - TARGET) < 1e-6
    assert res.fix.miss_distance < 1e-6
    assert res.fix.chi2 < 1e-12


def test_noise_free_satellite_los_lines_meet_the_truth_to_a_micrometre():
    sc = load_scenario('seed003_q2')
    world = World(sc)
    t = 100.0
    target = world.targets[0].state(t)[0]
    lines = []
    for st in sc.stations:
        s = world.station_states(st, np.array([t]))
        values, _ = predict(['los_alpha', 'los_beta'], target[None], s.pose())
        a, b = values[0]
        u, jac = angle_jacobian_local('los', a, b)
        lines.append(
            LineOfSight(
                st.id, s.position[0], s.rotation[0] @ u, s.rotation[0] @ jac, np.eye(2) * 25e-12
            )
        )
    res = triangulate(lines)
    assert res.success, res.message
    assert np.linalg.norm(res.fix.position - target[:3]) < 1e-6


def test_two_line_midpoint_equals_the_n_line_solution_with_equal_weights():
    rng = np.random.default_rng(7)
    for _ in range(20):
        o = rng.normal(size=(2, 3)) * 1e4
        u = rng.normal(size=(2, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        mid, miss = midpoint(o[0], u[0], o[1], u[1])
        infos = np.stack([np.eye(3) - np.outer(v, v) for v in u])
        x, _ = intersect(o, infos)
        assert np.allclose(mid, x, rtol=0, atol=1e-6)
        # the miss distance is the length of the common perpendicular
        n = np.cross(u[0], u[1])
        assert miss == pytest.approx(abs((o[1] - o[0]) @ n) / np.linalg.norm(n), rel=1e-9)


def test_midpoint_of_parallel_lines_raises_geometry_error():
    with pytest.raises(GeometryError, match='parallel'):
        midpoint([0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0])


def test_weighted_fix_matches_a_maximum_likelihood_solve_of_the_angles():
    rng = np.random.default_rng(11)
    sig = {
        'a': (SIGMA, SIGMA),
        'b': (3 * SIGMA, SIGMA),
        'c': (SIGMA, 5 * SIGMA),
        'd': (2 * SIGMA, 2 * SIGMA),
    }
    noise = {s: rng.normal(size=2) * np.array(sig[s]) for s in 'abcd'}
    lines = [angle_line(s, TARGET, sig[s], noise[s]) for s in 'abcd']
    res = triangulate(lines)
    assert res.success

    def resid(x: np.ndarray) -> np.ndarray:
        out = []
        for s in 'abcd':
            pos, rot = STATIONS[s]
            az, el = measure(['azimuth', 'elevation'], x, pos, rot)
            az0, el0 = measure(['azimuth', 'elevation'], TARGET, pos, rot)
            out += [(az0 + noise[s][0] - az) / sig[s][0], (el0 + noise[s][1] - el) / sig[s][1]]
        return np.array(out)

    ml = least_squares(resid, TARGET + 5.0, x_scale=1.0, xtol=1e-14, ftol=1e-14, gtol=1e-14).x
    sigma_fix = np.sqrt(np.trace(res.fix.covariance))
    assert np.linalg.norm(res.fix.position - ml) < 1e-3 * sigma_fix


def test_fix_covariance_matches_monte_carlo_scatter():
    rng = np.random.default_rng(3)
    sig = {'a': (SIGMA, SIGMA), 'b': (3 * SIGMA, SIGMA), 'c': (SIGMA, 2 * SIGMA)}
    fixes, covs = [], []
    for _ in range(3000):
        lines = [
            angle_line(s, TARGET, sig[s], rng.normal(size=2) * np.array(sig[s])) for s in 'abc'
        ]
        res = triangulate(lines, Gates(miss_probability=1.0))
        fixes.append(res.fix.position)
        covs.append(res.fix.covariance)
    err = np.array(fixes) - TARGET
    sample = np.cov(err.T)
    predicted = np.mean(covs, axis=0)
    # eigen-directions of the predicted covariance: variances agree within 8 %
    w, v = np.linalg.eigh(predicted)
    ratio = np.diag(v.T @ sample @ v) / w
    assert np.all(np.abs(ratio - 1.0) < 0.08), ratio
    assert np.linalg.norm(err.mean(axis=0)) < 4 * math.sqrt(w.max() / len(err))
    assert nees_summary(nees(err, np.array(covs))).consistent


def test_pulse_radar_alone_gives_a_fix_with_its_spherical_covariance():
    pos, rot = STATIONS['a']
    rng_m, az, el = measure(['range', 'azimuth', 'elevation'], TARGET, pos, rot)
    s_r, s_a = 5.0, 3e-4
    gen = np.random.default_rng(5)
    fixes, cov = [], None
    for _ in range(2000):
        n = gen.normal(size=3) * [s_r, s_a, s_a]
        u, jac = angle_jacobian_local('angles', az + n[1], el + n[2])
        line = LineOfSight(
            'radar', pos, rot @ u, rot @ jac, np.eye(2) * s_a**2, rng_m + n[0], s_r**2
        )
        res = triangulate([line])
        assert res.success and res.fix.n_lines == 1
        fixes.append(res.fix.position)
        cov = res.fix.covariance
    sample = np.cov((np.array(fixes) - TARGET).T)
    w, v = np.linalg.eigh(cov)
    assert np.all(np.abs(np.diag(v.T @ sample @ v) / w - 1.0) < 0.1)


def test_single_angle_line_gives_no_fix():
    res = triangulate([angle_line('a', TARGET)])
    assert not res.success and res.reason == 'too_few_lines'


def test_parallel_lines_give_no_fix_and_no_exception():
    pos, rot = STATIONS['a']
    u = np.array([0.3, 0.4, np.sqrt(1 - 0.25)])
    jac = np.linalg.svd(np.eye(3) - np.outer(u, u))[0][:, :2]
    a = LineOfSight('a', pos, u, jac, np.eye(2) * SIGMA**2)
    b = LineOfSight('b', pos + 1000.0 * np.array([1.0, 0, 0]), u, jac, np.eye(2) * SIGMA**2)
    res = triangulate([a, b])
    assert not res.success
    assert res.reason in ('degenerate_geometry', 'small_intersection_angle')


def test_nearly_parallel_lines_fail_the_intersection_angle_gate():
    far = TARGET + 2e6 * (TARGET / np.linalg.norm(TARGET))  # 2000 km above: lines ~1 deg apart
    lines = [angle_line(s, far) for s in 'ab']
    res = triangulate(lines, Gates(min_intersection_angle_deg=5.0, max_gdop=1e9))
    assert not res.success and res.reason == 'small_intersection_angle'
    assert res.candidate is not None and res.candidate.max_angle_deg < 5.0


def test_high_gdop_gate():
    far = TARGET + 2e6 * (TARGET / np.linalg.norm(TARGET))
    res = triangulate(
        [angle_line(s, far) for s in 'ab'], Gates(min_intersection_angle_deg=0.0, max_gdop=5.0)
    )
    assert not res.success and res.reason == 'high_gdop'


def test_inconsistent_line_fails_the_miss_distance_gate():
    lines = [angle_line('a', TARGET), angle_line('b', TARGET, noise=(40 * SIGMA, 0.0))]
    res = triangulate(lines)
    assert not res.success and res.reason == 'miss_distance'
    # with the gate off the same lines give a fix whose miss distance is reported
    res = triangulate(lines, Gates(miss_probability=1.0))
    assert res.success and res.fix.miss_distance > 10 * math.sqrt(np.trace(res.fix.covariance) / 3)


def test_gates_validate_their_values():
    with pytest.raises(ValueError, match='miss_probability'):
        Gates(miss_probability=0.0)
    with pytest.raises(ValueError, match='max_gdop'):
        Gates(max_gdop=-1.0)


def test_low_pass_filter_is_the_seed_formula_and_scales_noise_as_documented():
    rng = np.random.default_rng(1)
    x = rng.normal(size=20000)
    y, scale = low_pass(x, 0.95)
    assert y[5] == pytest.approx(0.025 * (x[4] + x[6]) + 0.95 * x[5])
    assert y[0] == x[0] and y[-1] == x[-1]
    assert np.std(y[1:-1]) == pytest.approx(scale[5], rel=0.02)
    assert scale[5] == pytest.approx(math.sqrt(0.95**2 + 0.05**2 / 2))


def _pipeline_for(result, config=None, gates=None, drop_states=()):
    pipe = TriangulationPipeline(config or AlignConfig(), gates)
    for sid, st in result.station_states.items():
        if sid in drop_states:
            continue
        for i in range(len(st.time)):
            pipe.add_pose(
                sid, st.time[i], st.position[i], st.velocity[i], st.rotation[i], st.moving
            )
    for sid, m in result.measurements.items():
        pipe.add_measurements(sid, m.fields, m.time, m.target_id, m.values, m.sigmas)
    return pipe


def _noise_free(name: str):
    sc = load_scenario(name)
    stations = tuple(
        dataclasses.replace(s, sigma={f: 1e-12 for f in s.fields}) for s in sc.stations
    )
    return dataclasses.replace(sc, stations=stations)


def test_unsynchronised_noise_free_streams_align_to_the_truth():
    sc = _noise_free('seed003_q2')
    world = World(sc)
    res = simulate(sc, world)
    pipe = _pipeline_for(res, gates=Gates(miss_probability=1.0))
    fixes = pipe.flush()
    assert len(fixes) == 598  # common epochs 50.4 ... 169.8 (sat09 starts at 50.3754)
    t = np.array([f.time for f in fixes])
    assert np.allclose(np.diff(t), 0.2)
    err = np.array([f.fix.position for f in fixes]) - world.targets[0].state(t)[:, :3]
    # linear interpolation of 0.2 s samples: centimetres early, 0.2 m at the end where the
    # thrust is 120 m/s^2, against a noise of ~20 m per fix in the real scenario
    assert np.abs(err[t < 100.0]).max() < 0.05
    assert np.abs(err).max() < 0.3


def test_smoothing_option_changes_little_and_stays_consistent():
    sc = load_scenario('seed003_q2')
    world = World(sc)
    res = simulate(sc, world)
    plain = _pipeline_for(res).flush()
    smooth = _pipeline_for(res, AlignConfig(smoothing_eps=0.95)).flush()
    assert len(plain) == len(smooth)
    d = np.array([a.fix.position - b.fix.position for a, b in zip(plain, smooth, strict=True)])
    sig = np.array([math.sqrt(np.trace(a.fix.covariance)) for a in plain])
    assert np.median(np.linalg.norm(d, axis=1) / sig) < 0.2  # a 5 % noise change, not more
    s_plain = np.median([np.trace(f.fix.covariance) for f in plain])
    s_smooth = np.median([np.trace(f.fix.covariance) for f in smooth])
    assert s_smooth == pytest.approx(0.95**2 * s_plain, rel=0.03)


def test_station_without_state_gives_no_line_and_is_counted():
    sc = load_scenario('seed000_s1')
    res = simulate(sc)
    pipe = _pipeline_for(res, drop_states=('opt01', 'opt02', 'opt03'))
    fixes = pipe.flush()
    assert not fixes  # only opt04 has a pose: one line per epoch
    assert pipe.counts['no_station_state'] > 0
    assert pipe.counts['too_few_lines'] > 0


def test_a_lone_sample_of_a_station_that_never_sends_a_state_is_counted_when_pruned():
    """One point off the epoch grid from a station nobody declared gives no line at any
    epoch; it is counted once the epochs have passed it, not kept unseen."""
    sc = load_scenario('seed000_s1')
    res = simulate(sc)
    pipe = _pipeline_for(res)
    m = res.measurements['opt01']
    k = len(m) // 2
    t_off = m.time[k : k + 1] + 0.0123  # between epochs
    pipe.add_measurements(
        'zz02', m.fields, t_off, m.target_id[k : k + 1], m.values[k : k + 1], m.sigmas[k : k + 1]
    )
    fixes = pipe.flush()
    assert len(fixes) == len(_pipeline_for(res).flush())
    assert pipe.counts['samples_without_station_state'] == 1


def test_nan_angles_are_counted_and_never_used():
    sc = load_scenario('seed000_s1')
    res = simulate(sc)
    m = res.measurements['opt01']
    values = m.values.copy()
    values[::2, 0] = np.nan
    pipe = TriangulationPipeline()
    st = res.station_states['opt01']
    pipe.add_pose('opt01', st.time[0], st.position[0], st.velocity[0], st.rotation[0], False)
    kept = pipe.add_measurements('opt01', m.fields, m.time, m.target_id, values, m.sigmas)
    assert kept == len(m) - len(values[::2])
    assert pipe.aligner.counts['nan_measurement'] == len(values[::2])


def _nees_figures(name: str, stride: int = 2):
    sc = load_scenario(name)
    world = World(sc)
    res = simulate(sc, world)
    pipe = _pipeline_for(res)
    fixes = pipe.flush()
    t = np.array([f.time for f in fixes])
    outside = np.ones(t.size, bool)
    for a, b in sc.gaps:
        outside &= ~((t >= a) & (t <= b))
    err = np.array([f.fix.position for f in fixes]) - world.targets[0].state(t)[:, :3]
    cov = np.array([f.fix.covariance for f in fixes])
    values = nees(err[outside], cov[outside])
    return (
        nees_summary(values[::stride]),
        np.sqrt(np.mean(np.sum(err[outside] ** 2, axis=1))),
        pipe,
    )


@pytest.mark.parametrize('name', ['seed003_q2', 'seed000_s1'])
def test_fixes_are_consistent_with_their_covariance(name: str):
    summary, rms, pipe = _nees_figures(name)
    print(f'\n{name}: {summary}; RMS 3-D error {rms:.3f} m; counts {dict(pipe.counts)}')
    assert summary.consistent, summary
    assert summary.n > 250


def test_seed000_s2_gap_has_no_fixes_but_counts_why():
    sc = load_scenario('seed000_s2')
    res = simulate(sc)
    pipe = _pipeline_for(res)
    fixes = pipe.flush()
    t = np.array([f.time for f in fixes])
    assert not np.any((t > 45.0 + 0.2) & (t < 75.0 - 0.2))  # one theodolite only in the gap
    assert pipe.counts['too_few_lines'] > 500


def test_ship_sensors_in_the_rolling_deck_frame_give_consistent_fixes():
    """seed004: pulse radar and EO theodolite measure in the unstabilised deck frame of a
    rolling ship; their lines are registered with the state's attitude."""
    sc = load_scenario('seed004_sea')
    sc = dataclasses.replace(sc, t_end=400.0)  # EO in range from ~180 s
    world = World(sc)
    res = simulate(sc, world)
    pipe = _pipeline_for(res)
    fixes = pipe.flush()
    t = np.array([f.time for f in fixes])
    n_lines = np.array([f.fix.n_lines for f in fixes])
    assert np.any(n_lines == 2) and np.any(n_lines == 1)  # radar+EO, radar alone
    err = np.array([f.fix.position for f in fixes]) - world.targets[0].state(t)[:, :3]
    cov = np.array([f.fix.covariance for f in fixes])
    # the radar is sampled at 10 Hz and fixes come at the EO's 25 Hz: take one in six
    for sel in (n_lines == 1, n_lines == 2):
        summary = nees_summary(nees(err[sel], cov[sel])[::6])
        print(f'\nseed004_sea 0-400 s, {n_lines[sel][0]} line(s): {summary}')
        assert summary.consistent, summary


def test_a_corrupt_far_future_stamp_is_rejected_and_does_not_stop_the_fixes():
    sc = load_scenario('seed003_q2')
    res = simulate(sc)
    pipe = TriangulationPipeline(AlignConfig(lag=0.5))
    st = {sid: res.station_states[sid] for sid in res.station_states}
    fixes = []
    # interleave: each station's samples and states epoch by epoch, with one corrupt stamp
    events = sorted(
        (m.time[i], sid, i) for sid, m in res.measurements.items() for i in range(len(m))
    )
    for n, (_t, sid, i) in enumerate(events):
        s, m = st[sid], res.measurements[sid]
        pipe.add_pose(sid, s.time[i], s.position[i], s.velocity[i], s.rotation[i], True)
        tt = m.time[i : i + 1] + (3.15e7 if n == 300 else 0.0)  # one stamp a year ahead
        pipe.add_measurements(
            sid, m.fields, tt, m.target_id[i : i + 1], m.values[i : i + 1], m.sigmas[i : i + 1]
        )
        fixes += pipe.process()
    fixes += pipe.flush()
    assert pipe.counts['time_jump'] == 1
    assert len(fixes) >= 596  # the one lost sample costs at most two epochs
    assert max(f.time for f in fixes) < 171.0


def test_a_new_pass_after_a_long_pause_restarts_the_buffers():
    from orbit_tracking.core.triangulation.alignment import Aligner

    al = Aligner(AlignConfig(max_time_jump=100.0))
    rot = np.eye(3)
    for sid in ('a', 'b'):
        al.add_pose(
            sid, 0.0, np.array([1e6, 0, 0]) * (1 if sid == 'a' else -1), np.zeros(3), rot, False
        )
    vals = np.array([[0.1, 0.2]])
    sig = np.array([[1e-5, 1e-5]])
    for t in np.arange(0.0, 10.0, 0.1):
        for sid in ('a', 'b'):
            al.add_measurements(
                sid, ('azimuth', 'elevation'), np.array([t]), np.zeros(1, np.uint32), vals, sig
            )
    for t in np.arange(5000.0, 5010.0, 0.1):
        for sid in ('a', 'b'):
            al.add_measurements(
                sid, ('azimuth', 'elevation'), np.array([t]), np.zeros(1, np.uint32), vals, sig
            )
    assert al.counts['restarts'] == 1
    assert al.earliest >= 5000.0


def _feed_with_lagging_states(lag_s: float, delivering: bool, quiet: str = '') -> tuple:
    """seed003_q2 streamed in 0.2 s steps with the satellites' states ``lag_s`` seconds of
    data time behind their measurements (their topic queued behind while a node was busy);
    station ``quiet`` stops sending measurements at 100 s (a dropout)."""
    res = simulate(load_scenario('seed003_q2'))
    pipe = TriangulationPipeline(AlignConfig(lag=0.5))
    newest: dict[str, float] = {}
    fixes = []
    states, meas = res.station_states, res.measurements
    horizons = []
    for step in np.arange(50.0, 171.0, 0.2):
        for sid, m in meas.items():
            if sid == quiet and step >= 100.0:
                newest.pop(sid, None)  # not heard any more
                continue
            sel = (m.time >= step) & (m.time < step + 0.2)
            if sel.any():
                newest[sid] = float(m.time[sel][0])
            pipe.add_measurements(
                sid, m.fields, m.time[sel], m.target_id[sel], m.values[sel], m.sigmas[sel]
            )
        for sid, st in states.items():
            sel = np.flatnonzero((st.time >= step - lag_s) & (st.time < step - lag_s + 0.2))
            for i in sel:
                pipe.add_pose(
                    sid, st.time[i], st.position[i], st.velocity[i], st.rotation[i], True
                )
                newest[f'{sid}/state'] = float(st.time[i])
        fixes += pipe.process(delivering=dict(newest) if delivering else None)
        horizons.append((step, pipe.aligner.horizon(dict(newest) if delivering else None)))
    for sid, st in states.items():
        for i in np.flatnonzero(st.time >= 171.0 - lag_s):
            pipe.add_pose(sid, st.time[i], st.position[i], st.velocity[i], st.rotation[i], True)
    fixes += pipe.flush()
    return fixes, pipe, horizons


def test_a_late_state_stream_that_still_delivers_holds_the_fixes_back():
    """States 8 s of data time behind their measurements (more than ``stale_after``): with
    the delivering streams known, no epoch is fixed before its states arrive and every fix
    of the offline pass is made; without that information they were lost."""
    offline = TriangulationPipeline(AlignConfig(lag=0.5))
    res = simulate(load_scenario('seed003_q2'))
    for sid, st in res.station_states.items():
        for i in range(st.time.size):
            offline.add_pose(sid, st.time[i], st.position[i], st.velocity[i], st.rotation[i], True)
    for sid, m in res.measurements.items():
        offline.add_measurements(sid, m.fields, m.time, m.target_id, m.values, m.sigmas)
    reference = {round(f.time, 6): f.fix.position for f in offline.flush()}

    fixes, pipe, _ = _feed_with_lagging_states(8.0, delivering=True)
    assert pipe.counts['no_station_state'] == 0
    assert len(fixes) == len(reference) == 598
    for f in fixes:
        np.testing.assert_allclose(f.fix.position, reference[round(f.time, 6)], atol=1e-9)

    lossy, pipe_old, _ = _feed_with_lagging_states(8.0, delivering=False)
    assert len(lossy) < 598 and pipe_old.counts['no_station_state'] > 0


def test_a_quiet_station_stops_holding_the_others_back():
    """A station that stops sending (a dropout) no longer bounds the horizon once the
    others are ``stale_after`` seconds past it, while the late states still do."""
    fixes, pipe, horizons = _feed_with_lagging_states(3.0, delivering=True, quiet='sat06')
    late = [(step, h) for step, h in horizons if step >= 120.0]
    assert late and all(h > 100.0 for _, h in late)
    assert all(h <= step - 3.0 + 0.2 for step, h in late)  # bounded by the late states
    assert fixes and pipe.counts['no_station_state'] == 0
