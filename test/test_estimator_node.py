"""The estimator: ``estimator/window_states`` messages, the offline ``orbit-tracking
estimate`` and the ``estimator`` node over real DDS, on a 30 s cut of seed 000 scenario 1
with a 6 s incomplete segment (12-18 s, only cw03 and cw07 measure)."""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_windows import write_short_scenario

from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.windows import TRAJECTORY_CSV_COLUMNS, read_trajectory_csv
from orbit_tracking.core.metrics import hermite_states
from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.core.sim.simulator import simulate
from orbit_tracking.tools.cli import main as cli_main

ROOT = Path(__file__).resolve().parents[1]
EPOCH = 1_700_000_000
TIMEBASE_NS = EPOCH * 1_000_000_000


def assert_within_sigmas(t, state, cov, truth, k=5.0):
    """Every position and velocity component within ``k`` of its own sigma of the truth
    (Hermite-interpolated positions; linear velocities, good to ~2 mm/s at 20 Hz)."""
    sig = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    ep = state[:, :3] - hermite_states(truth.time, truth.position, truth.velocity, t)
    ev = state[:, 3:] - np.stack(
        [np.interp(t, truth.time, truth.velocity[:, c]) for c in range(3)], axis=1
    )
    ok = np.all(np.isfinite(ep), axis=1)
    assert ok.mean() > 0.8, 'truth does not cover the estimated states'
    zp = np.abs(ep[ok]) / sig[ok, :3]
    zv = np.abs(ev[ok]) / (sig[ok, 3:] + 2e-3 / k)
    assert zp.max() <= k, f'position error {zp.max():.1f} sigma at t = {t[ok][zp.argmax() // 3]}'
    assert zv.max() <= k, f'velocity error {zv.max():.1f} sigma'
    # inside the short pass's incomplete segment (12-18 s: cw03 and cw07 alone) the
    # covariance also carries the manoeuvres it may hide (gap_manoeuvre_density) along
    # the direction two CW radars leave open: metres, and tens of metres where a window
    # starts inside the segment (its first states are then extrapolated back through
    # the segment's possible steps); elsewhere it is the formal one
    inside = (t > 12.0) & (t < 18.0)
    assert np.all(sig[~inside, :3] < 1.0), 'sigmas too large to mean anything here'
    assert np.all(sig[inside, :3] < 100.0), 'sigmas too large even for the segment'


# -- estimator/window_states ------------------------------------------------------------------


def test_window_states_round_trip_through_a_point_cloud():
    from sensor_msgs.msg import PointField

    from orbit_tracking.ros.conversions import (
        WINDOW_STATE_FIELDS,
        TimeBase,
        cloud_to_window_states,
        window_states_to_cloud,
    )

    tb = TimeBase(TIMEBASE_NS)
    rng = np.random.default_rng(7)
    t = 10.05 + 0.1 * np.arange(40)
    x = rng.normal(0.0, 1e6, (40, 6))
    a = rng.normal(0.0, 1.0, (40, 6, 6))
    cov = a @ np.transpose(a, (0, 2, 1))
    tid = np.repeat(np.array([0, 3], dtype=np.uint32), 20)
    msg = window_states_to_cloud('earth', 10.0, t, tid, x, cov, tb)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (EPOCH + 10, 0)
    assert [f.name for f in msg.fields] == [*WINDOW_STATE_FIELDS, 'target_id']
    assert len(WINDOW_STATE_FIELDS) == 7 + 21 and 'c_05' in WINDOW_STATE_FIELDS
    assert msg.fields[-1].datatype == PointField.UINT32 and msg.point_step % 8 == 0
    back = cloud_to_window_states(msg, tb)
    assert back.world_frame == 'earth' and back.t0 == 10.0
    assert np.allclose(back.time, t, atol=1e-12)
    assert np.array_equal(back.state, x) and np.array_equal(back.target_id, tid)
    assert np.array_equal(back.covariance, cov)

    bad = window_states_to_cloud('earth', 10.0, t, tid, x, cov, tb)
    bad.fields = [f for f in bad.fields if f.name != 'c_34']
    with pytest.raises(ValueError, match='c_34'):
        cloud_to_window_states(bad, tb)
    bad = window_states_to_cloud('earth', 10.0, t, tid, x, cov, tb)
    bad.fields[1].datatype = PointField.FLOAT32
    with pytest.raises(ValueError, match="'x' has datatype"):
        cloud_to_window_states(bad, tb)
    bad.fields[1].datatype = PointField.FLOAT64
    bad.data = bytes(bad.data)[:-8]
    with pytest.raises(ValueError, match='bytes'):
        cloud_to_window_states(bad, tb)
    cov[3, 2, 2] = -1.0
    with pytest.raises(ValueError, match='negative variance'):
        cloud_to_window_states(window_states_to_cloud('earth', 10.0, t, tid, x, cov, tb), tb)
    with pytest.raises(ValueError, match=r'\(40, 5\)'):
        window_states_to_cloud('earth', 10.0, t, tid, x[:, :5], cov, tb)


# -- offline ------------------------------------------------------------------------------------


@pytest.fixture(scope='module')
def short_bag(tmp_path_factory):
    """The short pass simulated into a bag (batched measurement messages) and its truth."""
    folder = tmp_path_factory.mktemp('short')
    scenario = write_short_scenario(folder)
    bag = folder / 'bag'
    assert (
        cli_main(
            ['simulate', '--scenario', str(scenario), '--out', str(bag), '--quiet']
            + ['--batch-period', '0.5']
        )
        == 0
    )
    return scenario, bag


def test_offline_estimate_writes_the_contract_trajectory_within_its_sigmas(
    short_bag, tmp_path, capsys
):
    from orbit_tracking.ros.bag import read_bag
    from orbit_tracking.ros.conversions import TimeBase, cloud_to_window_states

    scenario, bag = short_bag
    out = tmp_path / 'est'
    args = ['estimate', str(bag), '--out', str(out), '--window-length', '20', '--overlap', '6']
    assert cli_main([*args, '--quiet']) == 0
    printed = capsys.readouterr().out
    assert '2 windows: 2 succeeded' in printed and 'inside gaps' in printed
    with open(out / 'trajectory.csv') as fh:
        assert fh.readline().strip() == ','.join(TRAJECTORY_CSV_COLUMNS)
    traj = read_trajectory_csv(out / 'trajectory.csv')
    assert np.array_equal(traj['stamp_ns'], TIMEBASE_NS + 100_000_000 * np.arange(301))
    t = (traj['stamp_ns'] - TIMEBASE_NS) * 1e-9
    cov = np.zeros((t.size, 6, 6))
    cov[:, range(6), range(6)] = traj['sigma'] ** 2
    truth = simulate(load_scenario(scenario)).truth[0]
    assert_within_sigmas(t, traj['state'], cov, truth)

    summary = yaml.safe_load((out / 'summary.yaml').read_text())
    assert [(w['start'], round(w['end'], 6)) for w in summary['windows']] == [
        (0.0, 20.0),
        (14.0, 30.0),
    ]
    assert summary['windows'][0]['segments'][0] == [[12.0, 18.0]]
    assert summary['windows'][0]['used']['cw03'] > 0
    for w in summary['windows']:  # telemetry fused: the model chosen is reported per target
        assert set(w['telemetry_velocity_error']) == {0}, w
        assert w['telemetry_velocity_error'][0] in ('derivative', 'separate')
        assert 'isotropic_spans' in w
        q, q_events = w['jerk_density'], w['jerk_density_near_events']
        assert set(q) == {0} and q[0] > 0.0 and set(q_events) <= {0}, w
        assert all(v >= q[0] for v in q_events.values()), w  # never stiffer near events
    ev = summary['evaluation'][0]
    assert ev['inside_gaps']['n'] == 61 and ev['outside_gaps']['n'] == 240
    assert ev['outside_gaps']['rms_position_m'] < 0.2
    assert 1.0 < ev['outside_gaps']['mean_nees_position'] < 6.0

    msgs = list(read_bag(out / 'bag'))
    states = [m.msg for m in msgs if m.topic == 'trajectory/states']
    windows = [m.msg for m in msgs if m.topic == 'estimator/window_states']
    assert len(states) == 301 and len(windows) == 2
    assert {m.child_frame_id for m in states} == {'target'}
    assert {m.header.frame_id for m in states} == {'earth'}
    s = states[150]
    assert s.pose.pose.orientation.w == 1.0
    assert s.pose.covariance[0] == pytest.approx(traj['sigma'][150, 0] ** 2, rel=1e-6)
    assert s.twist.covariance[0] == pytest.approx(traj['sigma'][150, 3] ** 2, rel=1e-6)
    w = cloud_to_window_states(windows[1], TimeBase(TIMEBASE_NS))
    assert w.t0 == pytest.approx(14.0) and w.time[-1] == pytest.approx(30.0)


def test_offline_estimate_of_a_bag_without_telemetry_triangulates_it_first(tmp_path, capsys):
    scenario = write_short_scenario(tmp_path, telemetry=False)
    bag = tmp_path / 'bag'
    argv = ['simulate', '--scenario', str(scenario), '--out', str(bag), '--quiet']
    assert cli_main([*argv, '--batch-period', '0.5']) == 0
    out = tmp_path / 'est'
    args = ['estimate', str(bag), '--out', str(out), '--window-length', '20', '--overlap', '6']
    assert cli_main([*args, '--quiet']) == 0
    printed = capsys.readouterr().out
    assert 'fixes triangulated from the bag' in printed
    summary = yaml.safe_load((out / 'summary.yaml').read_text())
    assert summary['rough_trajectory'].endswith('fixes triangulated from the bag')
    assert summary['totals']['windows'] == 2
    solved = [w for w in summary['windows'] if 'error' not in w]
    failed = [w for w in summary['windows'] if 'error' in w]
    assert solved, 'no window solved from the triangulated rough trajectory'
    assert all(w['error'] for w in failed)  # a failed window says why, and is not fatal
    assert read_trajectory_csv(out / 'trajectory.csv')['time'].size > 100


def test_offline_estimate_refuses_bad_windows_and_an_existing_output(short_bag, tmp_path, capsys):
    _scenario, bag = short_bag
    out = tmp_path / 'est'
    out.mkdir()
    (out / 'keep.txt').write_text('x')
    assert cli_main(['estimate', str(bag), '--out', str(out), '--quiet']) == 2
    assert 'exists and is not empty; pass --force' in capsys.readouterr().err
    args = ['estimate', str(bag), '--out', str(out), '--window-length', '10', '--overlap', '6']
    assert cli_main([*args, '--force', '--quiet']) == 2
    assert 'overlap' in capsys.readouterr().err
    assert (out / 'keep.txt').exists()  # nothing was deleted for a command that cannot run
    assert cli_main(['estimate', str(tmp_path / 'nope'), '--out', str(tmp_path / 'o')]) == 2


def test_offline_estimate_takes_the_nodes_parameter_file(short_bag, tmp_path, capsys):
    """``estimate --params-file`` runs with the settings a node started with that file
    would have; the command line overrides it; a misspelt key is an error, not a default."""
    _scenario, bag = short_bag
    params = tmp_path / 'estimator.yaml'
    body = {'window_length': 20.0, 'window_overlap': 6.0, 'flush_after': 9.0}
    params.write_text(yaml.safe_dump({'estimator': {'ros__parameters': body}}))
    out = tmp_path / 'est'
    args = ['estimate', str(bag), '--out', str(out), '--params-file', str(params)]
    assert cli_main([*args, '--quiet']) == 0
    assert yaml.safe_load((out / 'summary.yaml').read_text())['totals']['windows'] == 2
    assert cli_main([*args, '--force']) == 0
    assert 'not used offline: flush_after' in capsys.readouterr().out
    assert cli_main([*args, '--force', '--quiet', '--window-length', '30']) == 0
    assert yaml.safe_load((out / 'summary.yaml').read_text())['totals']['windows'] == 1
    body['windw_length'] = 30.0
    params.write_text(yaml.safe_dump({'/estimator': {'ros__parameters': body}}))
    assert cli_main([*args, '--force', '--quiet']) == 2
    assert 'not an estimator node parameter: windw_length' in capsys.readouterr().err
    params.write_text(yaml.safe_dump({'triangulation': {'ros__parameters': body}}))
    assert cli_main([*args, '--force', '--quiet']) == 2
    assert "no ros__parameters for node 'estimator'" in capsys.readouterr().err


def test_offline_settings_take_the_types_of_the_core():
    """A YAML ``5`` for a float setting is 5.0; a fraction for a count, or a word for a
    switch, is an error and not a truncated or truthy default."""
    from orbit_tracking.tools.estimator_parameters import estimator_configs

    est, win, _ = estimator_configs({'gate_sigma': 5, 'window_length': 50, 'refine_rounds': 2.0})
    assert isinstance(est.gate_sigma, float) and est.refine_rounds == 2
    assert win.length == 50.0
    for bad in ({'refine_rounds': 2.5}, {'use_telemetry': 'yes'}, {'gate_sigma': 'five'}):
        with pytest.raises(ValueError):
            estimator_configs(bad)


def _another_value(name, value):
    """A valid value of node parameter ``name`` other than its default ``value``."""
    strings = {
        'knot_method': 'uniform',
        'solver': 'CLARABEL',
        'telemetry_velocity_error': 'separate',
        'telemetry_delays': 'on',
    }
    if isinstance(value, bool):
        return not value
    if isinstance(value, int):
        return value + 1
    if isinstance(value, float):
        return value * 1.5 if value else 0.5
    assert name in strings, f'give the test another value of string parameter {name}'
    return strings[name]


def test_the_offline_settings_are_the_nodes_for_every_parameter(tmp_path):
    """Every estimator node parameter (config/estimator.yaml lists them all) set away from
    its default gives the same core settings in the node and in the offline tools
    (``estimator_configs``: ``estimate --params-file``, the demo's cross-check), and each
    one alone changes them: a parameter file cannot change the node but not the offline
    run. Only the stream handling of a live node is left out, by name."""
    import rclpy

    from orbit_tracking.core.estimation.windows import WindowConfig
    from orbit_tracking.ros.estimator_node import EstimatorNode
    from orbit_tracking.tools.estimator_parameters import (
        NODE_ONLY_PARAMETERS,
        estimator_configs,
        read_parameters_file,
    )

    defaults = yaml.safe_load((ROOT / 'config' / 'estimator.yaml').read_text())
    mapped = {
        k: _another_value(k, v)
        for k, v in defaults['estimator']['ros__parameters'].items()
        if k not in NODE_ONLY_PARAMETERS
    }
    assert len(mapped) > 30
    for name, value in mapped.items():
        est, win, _ = estimator_configs({name: value})
        assert (est, win) != (EstimatorConfig(), WindowConfig()), f'{name} maps to nothing'
    path = tmp_path / 'estimator.yaml'
    path.write_text(yaml.safe_dump({'/**': {'ros__parameters': mapped}}))
    rclpy.init(args=['--ros-args', '--params-file', str(path)])
    try:
        node = EstimatorNode()
        try:
            got = node.est_cfg, node.win_cfg
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    offline = estimator_configs(read_parameters_file(path))
    assert got == offline[:2]
    assert got[0] != EstimatorConfig()


# -- the node ----------------------------------------------------------------------------------


def test_estimator_parameter_file_sets_every_declared_parameter():
    """config/estimator.yaml names exactly the node's parameters (rclpy silently ignores a
    misspelt key), and the node starts with it."""
    import rclpy

    from orbit_tracking.ros.estimator_node import EstimatorNode

    path = ROOT / 'config' / 'estimator.yaml'
    params = yaml.safe_load(path.read_text())['estimator']['ros__parameters']
    assert 'segments' in path.read_text()  # documented, commented out: no empty list in YAML
    context_args = ['--ros-args', '--params-file', str(path)]
    rclpy.init(args=context_args)
    try:
        node = EstimatorNode()
        try:
            declared = {
                name: node.get_parameter(name).value
                for name in node.list_parameters([], 0).names
                if name not in ('use_sim_time', 'start_type_description_service', 'segments')
            }
            assert node.est_cfg.segments == ()
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    assert declared == params


def test_the_nodes_defaults_are_the_cores():
    """Every default is written twice (EstimatorConfig and the node's declaration, then the
    YAML file and NODES.md): the node started without a parameter file runs exactly the
    core's default configuration, so the offline tools and the benchmarks measure it."""
    import rclpy

    from orbit_tracking.ros.estimator_node import EstimatorNode

    rclpy.init(args=[])
    try:
        node = EstimatorNode()
        try:
            got = node.est_cfg
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    assert got == EstimatorConfig()


# -- the node over DDS ------------------------------------------------------------------------


@pytest.mark.dds
def test_estimator_node_solves_windows_from_a_live_pass_close_to_truth(
    tmp_path, start_process, node_command, rclpy_node, spin_until, ros_namespace
):
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger

    from orbit_tracking.core.data.tables import TargetStates
    from orbit_tracking.ros import qos
    from orbit_tracking.ros.conversions import (
        TimeBase,
        cloud_to_window_states,
        msg_to_window_residuals,
        odometry_to_target_state,
    )

    ns = ros_namespace
    scenario = write_short_scenario(tmp_path)
    est = start_process(
        node_command(
            'estimator_node',
            namespace=ns,
            window_length=20.0,
            window_overlap=6.0,
            latency=1.0,
            flush_after=3600.0,  # the second window only on request (~/solve)
            use_telemetry=False,
            time_reference=float(EPOCH),
        )
    )
    windows: list[PointCloud2] = []
    truth: list[Odometry] = []
    diags: list[dict[str, str]] = []

    def on_diag(msg: DiagnosticArray) -> None:
        diags.extend(
            {kv.key: kv.value for kv in s.values}
            for s in msg.status
            if s.name == 'estimator: windows'
        )

    rclpy_node.create_subscription(
        PointCloud2, f'{ns}/estimator/window_states', windows.append, qos.STATE_STREAM
    )
    rclpy_node.create_subscription(
        Odometry, f'{ns}/truth/state', truth.append, qos.MEASUREMENTS_SUB
    )
    rclpy_node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, qos.DIAGNOSTICS)
    residuals: list[DiagnosticArray] = []
    rclpy_node.create_subscription(
        DiagnosticArray, f'{ns}/estimator/window_residuals', residuals.append, qos.STATE_STREAM
    )
    # The simulator waits for two readers of every measurement topic, the node and us, so
    # that it starts streaming only once it has discovered this process: its truth/state
    # is volatile and what it publishes before that is lost to us.
    points = []
    for st in load_scenario(scenario).stations:
        rclpy_node.create_subscription(
            PointCloud2,
            f'{ns}/stations/{st.id}/measurements',
            lambda m: points.append(m.width),
            qos.MEASUREMENTS_SUB,
        )
    spin_until(
        rclpy_node,
        lambda: rclpy_node.count_publishers(f'{ns}/estimator/window_states') > 0,
        20,
        'the estimator node to appear',
    )
    sim = start_process(
        node_command(
            'scenario_sim',
            namespace=ns,
            scenario=str(scenario),
            rate_factor=10.0,
            batch_period=0.5,
            wait_for_subscribers=2,
            shutdown_when_done=True,
        )
    )
    # the first window is solved once the stamps pass 20 s + latency
    spin_until(rclpy_node, lambda: len(windows) >= 1, 40, 'the first window')
    spin_until(rclpy_node, lambda: sim.poll() is not None, 20, 'the simulator to finish')
    spin_until(
        rclpy_node,
        # the pass's last epoch is 30.0 s (stations with an epoch offset stop before it);
        # solving on an earlier newest stamp would end the second window short of it
        lambda: bool(diags) and float(diags[-1]['newest_data_time_s']) >= 30.0 - 1e-6,
        20,
        lambda: f'the node to read the whole pass; last diagnostics {diags[-1:]}',
    )
    client = rclpy_node.create_client(Trigger, f'{ns}/estimator/solve')
    assert client.wait_for_service(timeout_sec=10.0)
    future = client.call_async(Trigger.Request())
    spin_until(rclpy_node, future.done, 30, 'the ~/solve response')
    assert future.result().success, future.result().message
    spin_until(rclpy_node, lambda: len(windows) >= 2, 10, 'the window solved on request')

    tb = TimeBase(TIMEBASE_NS)
    got = [cloud_to_window_states(m, tb) for m in windows]
    assert [round(w.t0, 6) for w in got] == [0.0, 14.0]
    assert got[0].time[-1] == pytest.approx(20.0) and got[1].time[-1] == pytest.approx(30.0)
    assert [w.t1 for w in got] == pytest.approx([20.0, 30.0], abs=1e-9)  # window_length
    # per-window residual statistics: the second window counts only the rows after the
    # first one's end, so over both every measurement row counts once
    spin_until(rclpy_node, lambda: len(residuals) >= 2, 5, 'the window residuals')
    res = [msg_to_window_residuals(m, tb) for m in residuals]
    assert [r[0].counted_after for r in res] == [None, pytest.approx(20.0)]
    assert {r.stats.station for r in res[0]} == {st.id for st in load_scenario(scenario).stations}
    rows = Counter()
    for r in (*res[0], *res[1]):
        rows[r.stats.station] += r.stats.rows
        assert np.all((r.stats.rms > 0.5) & (r.stats.rms < 2.0)), r
    assert sum(rows.values()) == 6480  # = every point of the pass (one target)
    assert sum(points) == 6480  # every point of the pass reached this process too
    assert all(w.world_frame == 'earth' and np.all(w.target_id == 0) for w in got)
    assert np.allclose(got[0].time * 10.0, np.round(got[0].time * 10.0), atol=1e-6)
    samples = sorted((odometry_to_target_state(m, tb) for m in truth), key=lambda s: s.time)
    ref = TargetStates(
        0,
        np.array([s.time for s in samples]),
        np.array([s.position for s in samples]),
        np.array([s.velocity for s in samples]),
        np.zeros((len(samples), 3)),
        np.zeros((len(samples), 3)),
    )
    for w in got:
        assert_within_sigmas(w.time, w.state, w.covariance, ref)

    spin_until(
        rclpy_node,
        lambda: int(diags[-1]['windows_solved']) == 2,
        5,
        lambda: f'diagnostics counting both windows; last {diags[-1]}',
    )
    last = diags[-1]
    assert int(last['windows_failed']) == 0
    assert last['solving_window'] == ''  # nothing on the worker once both are out
    assert int(last['used_cw03']) > 0 and int(last['used_opt01']) > 0
    assert 0.5 < float(last['last_chi2_dof']) < 2.0
    assert math.isclose(float(last['last_window_end']), 30.0, abs_tol=1e-6)
    assert est.poll() is None, 'the estimator node exited'
    log = est.errors()
    assert 'Traceback' not in log
    assert log.count('GN iterations') == 2 and 'solved in' in log
