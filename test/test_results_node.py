"""The results node: streamed windows stitched into final states (core/stitcher.py), the
estimator's per-window residual statistics (core/residuals.py), their messages, and the
``results`` process over real DDS fed with the windows of a real estimate."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_windows import write_short_scenario

from orbit_tracking.core import frames
from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.residuals import ResidualStats, window_residual_stats
from orbit_tracking.core.estimation.stitcher import SampledWindow, TrajectoryStitcher
from orbit_tracking.core.estimation.windows import (
    WindowConfig,
    blend,
    handover_span,
    output_times,
    solve_windows,
    stitch,
)
from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.core.sim.simulator import simulate

ROOT = Path(__file__).resolve().parents[1]
EPOCH = 1_700_000_000
TIMEBASE_NS = EPOCH * 1_000_000_000
STEP = 0.1

# -- a known continuous trajectory, and windows of it ---------------------------------------

SPANS = [(0.0, 60.0), (40.0, 100.0), (80.0, 140.0), (120.0, 150.0)]  # L 60, overlap 20, cut
OFFSETS = [  # each window's (constant) disagreement with the truth [m]
    np.zeros(3),
    np.array([0.01, -0.02, 0.005]),
    np.array([-0.015, 0.01, 0.02]),
    np.array([0.0, 0.03, -0.01]),
]


def truth(t):
    """Position (m, 3) and velocity (m, 3) of a smooth climbing, weaving flight."""
    t = np.atleast_1d(np.asarray(t, dtype=float))[:, None]
    p0 = np.array([-2.1e6, 4.5e6, 3.9e6])
    v0 = np.array([300.0, -150.0, 800.0])
    a = np.array([2.0, -1.0, 15.0])
    amp, om = np.array([50.0, 30.0, 10.0]), np.array([0.05, 0.11, 0.07])
    pos = p0 + v0 * t + 0.5 * a * t**2 + amp * np.sin(om * t)
    vel = v0 + a * t + amp * om * np.cos(om * t)
    return pos, vel


def window_states(k, t, offsets=OFFSETS):
    """Window ``k``'s states and covariances at ``t``: the truth plus its offset."""
    pos, vel = truth(t)
    x = np.hstack([pos + offsets[k], vel])
    sig = np.array([0.1, 0.2, 0.3, 0.01, 0.02, 0.03]) * (1.0 + k)
    return x, np.broadcast_to(np.diag(sig**2), (x.shape[0], 6, 6)).copy()


def sampled(k, target_id=0, spans=SPANS, offsets=OFFSETS):
    t0, t1 = spans[k]
    t = output_times(t0, t1, STEP)
    x, c = window_states(k, t, offsets)
    return SampledWindow(target_id, t0, t1, t, x, c)


def stream(windows, flush=True):
    """Feed windows one by one; returns the emitted (t, x, cov) and, per window, the
    latest time emitted after it."""
    st = TrajectoryStitcher()
    ts, xs, cs, latest = [], [], [], []
    for w in windows:
        for fs in st.add([w]):
            ts.append(fs.time)
            xs.append(fs.state)
            cs.append(fs.covariance)
        latest.append(max((float(t[-1]) for t in ts), default=-math.inf))
    if flush:
        for fs in st.flush():
            ts.append(fs.time)
            xs.append(fs.state)
            cs.append(fs.covariance)
    return st, np.concatenate(ts), np.vstack(xs), np.concatenate(cs), latest


# -- core: the streaming stitch -----------------------------------------------------------------


def test_streamed_windows_recover_a_continuous_truth_and_emit_every_time_once():
    st, t, x, _cov, _ = stream([sampled(k, offsets=[np.zeros(3)] * 4) for k in range(4)])
    grid = output_times(0.0, 150.0, STEP)
    assert np.array_equal(np.round(t * 1e9), np.round(grid * 1e9))  # each once, in order
    pos, vel = truth(grid)
    assert np.abs(x[:, :3] - pos).max() < 1e-9 * np.abs(pos).max()  # rounding of 6e6 m
    assert np.abs(x[:, 3:] - vel).max() < 1e-9
    assert st.counts['states_final'] == grid.size and st.counts['missing_samples'] == 0
    assert st.held() == 0


def test_streamed_stitch_is_the_offline_blend_and_spreads_each_seam_over_its_hand_over():
    _st, t, x, cov, _ = stream([sampled(k) for k in range(4)])
    grid = output_times(0.0, 150.0, STEP)
    fns = [lambda tt, k=k: window_states(k, tt) for k in range(4)]
    tt, xo, co = blend(SPANS, fns, grid)
    assert np.allclose(t, tt, rtol=0.0, atol=1e-12)
    assert np.allclose(x, xo, rtol=0.0, atol=1e-8) and np.allclose(cov, co, rtol=1e-12)
    # the error against the continuous truth is each window's own offset outside the
    # hand-overs, and moves from one to the next linearly inside them
    err = x[:, :3] - truth(t)[0]
    for k in range(3):
        h0, h1 = handover_span(SPANS[k], SPANS[k + 1])
        before = (t > SPANS[k + 1][0] - 5.0) & (t <= h0)
        after = (t >= h1) & (t < SPANS[k][1] + 5.0)
        assert np.allclose(err[before], OFFSETS[k], atol=1e-8)
        assert np.allclose(err[after], OFFSETS[k + 1], atol=1e-8)
        # no jump at the seam: one step changes the error by at most the disagreement
        # times dt / (hand-over length), not by the whole disagreement
        inside = (t >= h0 - STEP) & (t <= h1 + STEP)
        steps = np.abs(np.diff(err[inside], axis=0))
        bound = np.abs(OFFSETS[k + 1] - OFFSETS[k]) * STEP / (h1 - h0)
        assert np.all(steps <= bound + 1e-8), (k, steps.max(axis=0), bound)
        assert np.abs(OFFSETS[k + 1] - OFFSETS[k]).max() > 10 * bound.max()


def test_a_state_is_emitted_only_once_no_later_window_can_change_it():
    windows = [sampled(k) for k in range(4)]
    st = TrajectoryStitcher()
    assert st.add([windows[0]]) == []  # the next window decides how the first one ends
    assert st.held() == output_times(0.0, 60.0, STEP).size
    for k in range(1, 4):
        (fs,) = st.add([windows[k]])
        h0 = handover_span(SPANS[k - 1], SPANS[k])[0]
        assert fs.time[-1] < h0 <= fs.time[-1] + STEP + 1e-9  # everything before h0
        assert st.final_until(0) == pytest.approx(h0)
    (rest,) = st.flush()
    assert rest.time[0] >= handover_span(SPANS[2], SPANS[3])[0]
    assert rest.time[-1] == pytest.approx(150.0) and st.held() == 0
    # a window after the flush that reaches back: its samples at emitted times are
    # dropped and counted, never emitted a second time
    late = sampled(0, spans=[(140.0, 170.0)], offsets=[np.ones(3)])
    assert st.add([late]) == []
    assert st.counts['states_already_final'] == output_times(140.0, 150.0, STEP).size
    (tail,) = st.flush()
    assert tail.time[0] > 150.0 and tail.time[-1] == pytest.approx(170.0)


def test_stitcher_keeps_targets_apart_and_refuses_a_window_that_does_not_end_later():
    st = TrajectoryStitcher()
    st.add([sampled(0, 0), sampled(0, 7)])
    out = st.add([sampled(1, 0), sampled(1, 7)])
    assert [fs.target_id for fs in out] == [0, 7]
    assert np.array_equal(out[0].state, out[1].state)
    with pytest.raises(ValueError, match='does not end after'):
        st.add([sampled(1, 0)])
    with pytest.raises(ValueError, match='share its span'):
        st.add([sampled(2, 0), sampled(3, 7)])
    st.reset()
    assert st.add([sampled(0)]) == [] and st.targets == [0]
    t = output_times(0.0, 10.0, STEP)
    with pytest.raises(ValueError, match='outside the window'):
        SampledWindow(0, 1.0, 10.0, t, *window_states(0, t))
    with pytest.raises(ValueError, match='strictly increasing'):
        SampledWindow(0, 0.0, 10.0, t[::-1], *window_states(0, t))


def test_states_to_local_is_the_launch_frame_of_the_contract():
    lat, lon, az = math.radians(40.9), math.radians(100.3), math.radians(150.0)
    o = frames.geodetic_to_ecef(lat, lon, 1000.0)
    r = frames.launch_rotation(lat, lon, az)
    rng = np.random.default_rng(5)
    x = np.hstack([o + rng.normal(0, 1e5, (5, 3)), rng.normal(0, 1e3, (5, 3))])
    a = rng.normal(size=(5, 6, 6))
    cov = a @ a.transpose(0, 2, 1)
    xl, cl = frames.states_to_local(x, cov, o, r)
    # independent: y is the geodetic up, x horizontal along the azimuth (north to east)
    up = np.array([math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)])
    east = np.array([-math.sin(lon), math.cos(lon), 0.0])
    north = np.cross(up, east)
    ex = math.sin(az) * east + math.cos(az) * north
    ez = np.cross(ex, up)
    for j, e in enumerate((ex, up, ez)):
        assert np.allclose(xl[:, j], (x[:, :3] - o) @ e, atol=1e-6)
        assert np.allclose(xl[:, 3 + j], x[:, 3:] @ e, atol=1e-9)
        assert np.allclose(cl[:, j, j], np.einsum('i,mij,j->m', e, cov[:, :3, :3], e))
    assert np.allclose(np.trace(cl, axis1=1, axis2=2), np.trace(cov, axis1=1, axis2=2))


# -- a real estimate of a short pass --------------------------------------------------------------


@pytest.fixture(scope='module')
def short_estimate(tmp_path_factory):
    """The 30 s seed 000 pass in 12 s windows overlapping 4 s, solved by the core."""
    scenario = write_short_scenario(tmp_path_factory.mktemp('results'))
    sc = load_scenario(scenario)
    obs = Observations.from_simulation(simulate(sc))
    ests = solve_windows(
        obs, EstimatorConfig(use_telemetry=False), WindowConfig(length=12.0, overlap=4.0)
    )
    assert [(e.t0, e.t1) for e in ests] == [(0.0, 12.0), (8.0, 20.0), (16.0, 28.0), (24.0, 30.0)]
    return scenario, sc, obs, ests


def estimate_windows(ests):
    """Each estimate sampled as the estimator node publishes it."""
    out = []
    for e in ests:
        t = output_times(e.t0, e.t1, STEP)
        x, c = e.targets[0].states(t)
        out.append(SampledWindow(0, e.t0, e.t1, t, x, c))
    return out


def test_streamed_estimate_windows_give_the_offline_trajectory(short_estimate):
    *_, ests = short_estimate
    _st, t, x, cov, _ = stream(estimate_windows(ests))
    to, xo, co = stitch(ests, output_times(0.0, 30.0, STEP))
    assert np.allclose(t, to, rtol=0.0, atol=1e-12)
    assert np.abs(x - xo).max() < 1e-6 and np.allclose(cov, co, rtol=1e-9, atol=1e-15)


def test_window_residual_statistics_count_each_measurement_once_over_the_windows(
    short_estimate,
):
    *_, obs, ests = short_estimate
    whole = window_residual_stats(ests[0], obs)
    assert whole['cw03'].rows == int(np.count_nonzero(_station(obs, 'cw03').time <= 12.0))
    for sid, s in whole.items():  # the whole window: the estimator's own counts
        assert int(s.rejected.sum()) == ests[0].rejected.get((sid, 'residual_gate'), 0)
        assert s.not_measured == ests[0].rejected.get((sid, 'not_measured'), 0)
        assert int(s.count.sum()) == ests[0].used[sid]
    total: dict[str, ResidualStats] = {}
    after = None
    for e in ests:
        for sid, s in window_residual_stats(e, obs, after).items():
            total[sid] = s if sid not in total else total[sid].merged(s)
        after = e.t1
    for s in obs.stations:
        assert total[s.table.station_id].rows == len(s.table)  # every row, once
    rms = np.concatenate([s.rms for s in total.values()])
    assert np.all((rms > 0.7) & (rms < 1.3)), rms  # whitened: about one
    assert total['cw03'].fields == ('range', 'range_rate')


def _station(obs, sid):
    return next(s.table for s in obs.stations if s.table.station_id == sid)


# -- messages -------------------------------------------------------------------------------


def test_window_messages_carry_the_window_end_and_residual_statistics_round_trip(short_estimate):
    from orbit_tracking.ros.conversions import (
        TimeBase,
        cloud_to_window_states,
        msg_to_window_residuals,
        window_residuals_to_msg,
        window_states_to_cloud,
    )

    *_, obs, ests = short_estimate
    tb = TimeBase(TIMEBASE_NS)
    w = estimate_windows(ests)[3]  # the cut window: its end (30 s) is no window length away
    msg = window_states_to_cloud('earth', w.t0, w.time, 0, w.state, w.covariance, tb, t1=w.t1)
    assert msg.fields[-1].name == 'window_length' and msg.point_step % 8 == 0
    back = cloud_to_window_states(msg, tb)
    assert back.t0 == pytest.approx(24.0) and back.t1 == pytest.approx(30.0, abs=1e-12)
    without = window_states_to_cloud(
        'earth', 24.0, w.time[:-5], 0, w.state[:-5], w.covariance[:-5], tb
    )
    assert cloud_to_window_states(without, tb).t1 == pytest.approx(w.time[-6])

    stats = window_residual_stats(ests[1], obs, after=12.0)
    arr = window_residuals_to_msg(stats, 8.0, 20.0, 12.0, tb)
    assert [s.name for s in arr.status] == sorted(stats)
    cw = next(s for s in arr.status if s.name == 'cw03')
    kv = {k.key: k.value for k in cw.values}
    assert cw.hardware_id == 'cw03' and kv['window_start'] == '1700000008.000000000'
    assert kv['window_end'] == '1700000020.000000000'
    assert kv['counted_after'] == '1700000012.000000000'
    assert int(kv['rows']) == stats['cw03'].rows
    for key in ('rejected', 'not_measured', 'range_rms', 'range_mean', 'range_count'):
        assert key in kv
    got = {r.stats.station: r for r in msg_to_window_residuals(arr, tb)}
    for sid, s in stats.items():
        r = got[sid]
        assert (r.t0, r.t1, r.counted_after) == (8.0, 20.0, 12.0)
        assert r.stats.fields == s.fields and r.stats.rows == s.rows
        assert np.array_equal(r.stats.count, s.count)
        assert np.allclose(r.stats.rms, s.rms, rtol=1e-8)
        assert np.allclose(r.stats.mean, s.mean, rtol=1e-8, atol=1e-12)
    arr.status[0].values = [v for v in arr.status[0].values if v.key != 'window_end']
    with pytest.raises(ValueError, match='window_end'):
        msg_to_window_residuals(arr, tb)


# -- the node -------------------------------------------------------------------------------


def _node_parameters(path=None, **overrides):
    import rclpy

    from orbit_tracking.ros.results_node import ResultsNode

    args = ['--ros-args']
    if path is not None:
        args += ['--params-file', str(path)]
    for k, v in overrides.items():
        args += ['-p', f'{k}:={v}']
    rclpy.init(args=args)
    try:
        node = ResultsNode()
        try:
            return node, {
                name: node.get_parameter(name).value
                for name in node.list_parameters([], 0).names
                if name not in ('use_sim_time', 'start_type_description_service', 'launch_site')
            }
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_results_parameter_file_sets_every_declared_parameter():
    path = ROOT / 'config' / 'results.yaml'
    params = yaml.safe_load(path.read_text())['results']['ros__parameters']
    assert 'launch_site' in path.read_text()  # documented, commented out
    _node, declared = _node_parameters(path)
    assert declared == params


def test_results_node_needs_a_launch_point_for_launch_frame_output():
    with pytest.raises(ValueError, match='launch point'):
        _node_parameters(output_frame='launch')
    with pytest.raises(ValueError, match='output_frame'):
        _node_parameters(output_frame='ecef')
    node, _ = _node_parameters(output_frame='launch', launch_site='[40.9,100.3,1000.0,150.0]')
    assert node.launch is not None and np.allclose(
        node.launch[1], frames.launch_rotation(*np.radians([40.9, 100.3, 150.0]))
    )


# -- the node over DDS -------------------------------------------------------------------------


@pytest.mark.dds
def test_results_node_publishes_the_stitched_estimate_once_final_in_world_and_launch_frames(
    short_estimate, start_process, node_command, rclpy_node, spin_until, ros_namespace
):
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry, Path
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger

    from orbit_tracking.ros import qos
    from orbit_tracking.ros.conversions import (
        TimeBase,
        odometry_to_target_state,
        window_residuals_to_msg,
        window_states_to_cloud,
    )

    scenario, sc, obs, ests = short_estimate
    tb = TimeBase(TIMEBASE_NS)
    ns_world, ns_launch = ros_namespace, ros_namespace + '_launch'
    common = {'time_reference': float(EPOCH), 'flush_after': 3600.0}
    world = start_process(node_command('results_node', namespace=ns_world, **common))
    launch = start_process(
        node_command(
            'results_node',
            namespace=ns_launch,
            output_frame='launch',
            scenario=str(scenario),
            path_step=1.0,
            **common,
        )
    )
    states: dict[str, list[Odometry]] = {ns_world: [], ns_launch: []}
    paths: dict[str, list[Path]] = {ns_world: [], ns_launch: []}
    diags: dict[str, list[dict[str, dict[str, str]]]] = {'earth': [], 'launch': []}
    pubs, res_pubs = {}, {}
    for ns in (ns_world, ns_launch):
        rclpy_node.create_subscription(
            Odometry, f'{ns}/trajectory/states', states[ns].append, qos.MEASUREMENTS_SUB
        )
        rclpy_node.create_subscription(
            Path, f'{ns}/trajectory/path', paths[ns].append, qos.LATCHED
        )
        pubs[ns] = rclpy_node.create_publisher(
            PointCloud2, f'{ns}/estimator/window_states', qos.window_stream(16)
        )
        res_pubs[ns] = rclpy_node.create_publisher(
            DiagnosticArray, f'{ns}/estimator/window_residuals', qos.window_stream(16)
        )

    def on_diag(msg: DiagnosticArray) -> None:
        """The results nodes' statuses, by output frame (both publish the same names)."""
        d = {s.name: {kv.key: kv.value for kv in s.values} for s in msg.status}
        d['_hardware_id'] = {s.name: s.hardware_id for s in msg.status}
        frame = d.get('results: trajectory', {}).get('output_frame')
        if frame in diags:
            diags[frame].append(d)

    rclpy_node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, qos.DIAGNOSTICS)
    spin_until(
        rclpy_node,
        lambda: all(p.get_subscription_count() > 0 for p in (*pubs.values(), *res_pubs.values())),
        20,
        'both results nodes to subscribe',
    )
    spin_until(
        rclpy_node,
        lambda: all(rclpy_node.count_publishers(f'{ns}/trajectory/states') > 0 for ns in pubs),
        10,
        'the results nodes to publish',
    )

    windows = estimate_windows(ests)
    expected = 0
    after = None
    for k, (e, w) in enumerate(zip(ests, windows, strict=True)):
        cloud = window_states_to_cloud(
            'earth', e.t0, w.time, 0, w.state, w.covariance, tb, t1=e.t1
        )
        res = window_residuals_to_msg(window_residual_stats(e, obs, after), e.t0, e.t1, after, tb)
        after = e.t1
        for ns in pubs:
            pubs[ns].publish(cloud)
            res_pubs[ns].publish(res)
        if k:  # final: every time before the hand-over start with this window
            h0 = handover_span((ests[k - 1].t0, ests[k - 1].t1), (e.t0, e.t1))[0]
            expected = int(np.count_nonzero(output_times(0.0, 30.0, STEP) < h0))
        spin_until(
            rclpy_node,
            lambda n=expected: all(len(states[ns]) >= n for ns in states),
            10,
            lambda n=expected: f'{n} final states; got {[len(s) for s in states.values()]}',
        )
        time.sleep(0.3)  # and not one more: the rest of the window is not final yet
        rclpy_node.executor.spin_once(timeout_sec=0.05)
        assert [len(s) for s in states.values()] == [expected, expected]

    # the end of the stream: on request for one node, for the other because the
    # estimator (here: our publisher) goes away
    client = rclpy_node.create_client(Trigger, f'{ns_world}/results/flush')
    assert client.wait_for_service(timeout_sec=10.0)
    future = client.call_async(Trigger.Request())
    spin_until(rclpy_node, future.done, 10, 'the ~/flush response')
    assert (
        future.result().success
        and future.result().message == f'published {301 - expected} held state(s)'
    )
    rclpy_node.destroy_publisher(pubs.pop(ns_launch))
    spin_until(
        rclpy_node,
        lambda: all(len(s) >= 301 for s in states.values()),
        15,
        lambda: f'all 301 states; got {[len(s) for s in states.values()]}',
    )

    # world frame: the offline stitch, each epoch once
    grid = output_times(0.0, 30.0, STEP)
    t_ref, x_ref, c_ref = stitch(ests, grid)
    got = [odometry_to_target_state(m, tb) for m in states[ns_world]]
    assert [round(g.time, 6) for g in got] == [round(t, 6) for t in t_ref]
    assert {m.child_frame_id for m in states[ns_world]} == {'target'}
    assert {m.header.frame_id for m in states[ns_world]} == {'earth'}
    pos = np.array([g.position for g in got])
    vel = np.array([g.velocity for g in got])
    assert np.abs(pos - x_ref[:, :3]).max() < 1e-6 and np.abs(vel - x_ref[:, 3:]).max() < 1e-9
    assert np.allclose([g.position_cov for g in got], c_ref[:, :3, :3], rtol=1e-9, atol=1e-15)
    assert np.allclose([g.velocity_cov for g in got], c_ref[:, 3:, 3:], rtol=1e-9, atol=1e-15)
    m = states[ns_world][100]
    assert m.pose.pose.orientation.w == 1.0 and m.pose.covariance[21] == -1.0
    assert m.twist.covariance[35] == -1.0

    # launch frame: the same states seen from the launch point, covariance rotated too
    origin, rot = sc.launch_frame
    xl, cl = frames.states_to_local(x_ref, c_ref, origin, rot)
    got_l = [odometry_to_target_state(m, tb) for m in states[ns_launch]]
    assert {m.header.frame_id for m in states[ns_launch]} == {'launch'}
    assert np.abs(np.array([g.position for g in got_l]) - xl[:, :3]).max() < 1e-6
    assert np.abs(np.array([g.velocity for g in got_l]) - xl[:, 3:]).max() < 1e-9
    assert np.allclose([g.position_cov for g in got_l], cl[:, :3, :3], rtol=1e-9, atol=1e-15)
    # altitude over the launch point: y grows as the vehicle climbs
    assert got_l[-1].position[1] > got_l[0].position[1] > 0.0

    # paths: latched, the whole trajectory once final (the launch one decimated to 1 s)
    spin_until(
        rclpy_node,
        lambda: all(p and len(p[-1].poses) in (301, 31) for p in paths.values()),
        5,
        lambda: f'complete paths; got {[len(p[-1].poses) if p else 0 for p in paths.values()]}',
    )
    pw, pl = paths[ns_world][-1], paths[ns_launch][-1]
    assert pw.header.frame_id == 'earth' and len(pw.poses) == 301
    assert pl.header.frame_id == 'launch' and len(pl.poses) == 31
    assert pw.poses[150].pose.position.x == pytest.approx(pos[150, 0], abs=1e-6)
    assert len(paths[ns_world]) >= 4  # updated as states became final
    late = Path()
    rclpy_node.create_subscription(
        Path, f'{ns_world}/trajectory/path', lambda p: setattr(late, 'poses', p.poses), qos.LATCHED
    )
    spin_until(rclpy_node, lambda: len(late.poses) == 301, 5, 'the latched path for a late reader')

    # diagnostics: the node's own counters and one status per station, each row once
    def complete(d):
        return d['results: trajectory']['states_published'] == '301' and (
            'results: residuals cw03' in d
        )

    spin_until(
        rclpy_node,
        lambda: all(ds and complete(ds[-1]) for ds in diags.values()),
        5,
        lambda: f'the results diagnostics; last {[ds[-1:] for ds in diags.values()]}',
    )
    d = diags['earth'][-1]
    tr = d['results: trajectory']
    assert tr['windows_used'] == '4' and tr['states_held'] == '0' and tr['flushes'] == '1'
    assert diags['launch'][-1]['results: trajectory']['output_frame'] == 'launch'
    cw = d['results: residuals cw03']
    assert d['_hardware_id']['results: residuals cw03'] == 'cw03'
    assert int(cw['rows']) == len(_station(obs, 'cw03')) and cw['windows'] == '4'
    assert 0.7 < float(cw['range_rms']) < 1.3 and 0.7 < float(cw['range_rate_rms']) < 1.3

    # bad input is counted and logged; time going back restarts the trajectory once the
    # next window confirms the new time line (one stray window does not)
    bad = window_states_to_cloud('earth', 0.0, grid[:5], 0, x_ref[:5], c_ref[:5], tb)
    bad.fields = bad.fields[1:]
    pubs[ns_world].publish(bad)

    def cloud(k: int, shift: float = 0.0):
        e, w = ests[k], windows[k]
        return window_states_to_cloud(
            'earth', e.t0 + shift, w.time + shift, 0, w.state, w.covariance, tb, t1=e.t1 + shift
        )

    n_paths = len(paths[ns_world])
    pubs[ns_world].publish(cloud(0))
    time.sleep(0.3)
    rclpy_node.executor.spin_once(timeout_sec=0.05)
    assert all(p.poses for p in paths[ns_world][n_paths:])  # held, not restarted yet
    pubs[ns_world].publish(cloud(1))
    spin_until(
        rclpy_node,
        lambda: any(p.poses == [] for p in paths[ns_world][n_paths:]),
        5,
        'the path cleared by the restart',
    )
    # a window far in the future, then one that continues the time line: dropped
    pubs[ns_world].publish(cloud(0, shift=1e6))
    pubs[ns_world].publish(cloud(2))

    def counted() -> bool:
        tr = diags['earth'][-1]['results: trajectory']
        return (
            tr.get('restarts') == '1'
            and tr.get('rejected_invalid_window') == '1'
            and tr.get('rejected_window_jump_unconfirmed') == '1'
        )

    spin_until(
        rclpy_node,
        counted,
        5,
        lambda: f'the restart and the rejections counted; last {diags["earth"][-1:]}',
    )
    assert world.poll() is None and launch.poll() is None
    log = world.errors()
    assert 'Traceback' not in log and 'Traceback' not in launch.errors()
    assert 'restarting the trajectory' in log and 'window states rejected' in log
    assert log.count('states final') == 7  # 4 windows, 2 after the restart, 1 after the jump
    assert 'jumps from the last one' in log
    assert 'the estimator went away' in launch.errors()
