"""The estimator node with ``model: rocket`` over real DDS (issue 15): two satellites'
lines of sight streamed by the scenario simulator, each window fitted with seed 003's
rocket model and published within its sigmas of the truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from orbit_tracking.core.metrics import hermite_states

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / 'test' / 'data' / 'scenarios' / 'seed003_q2_60_90.yaml'
EPOCH = 1_700_000_000


@pytest.mark.dds
def test_estimator_node_fits_the_rocket_model_in_each_window(
    start_process, node_command, rclpy_node, spin_until, ros_namespace
):
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger

    from orbit_tracking.ros import qos
    from orbit_tracking.ros.conversions import (
        TimeBase,
        cloud_to_window_states,
        odometry_to_target_state,
    )

    ns = ros_namespace
    est = start_process(
        node_command(
            'estimator_node',
            namespace=ns,
            model='rocket',
            window_length=20.0,
            window_overlap=6.0,
            latency=1.0,
            flush_after=3600.0,
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
    for sid in ('sat06', 'sat09'):  # the simulator waits for two readers of each
        rclpy_node.create_subscription(
            PointCloud2,
            f'{ns}/stations/{sid}/measurements',
            lambda m: None,
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
            scenario=str(SCENARIO),
            rate_factor=10.0,
            batch_period=0.5,
            wait_for_subscribers=2,
            shutdown_when_done=True,
        )
    )
    spin_until(rclpy_node, lambda: len(windows) >= 1, 40, 'the first window')
    spin_until(rclpy_node, lambda: sim.poll() is not None, 20, 'the simulator to finish')
    spin_until(
        rclpy_node,
        lambda: bool(diags) and float(diags[-1]['newest_data_time_s']) >= 89.5,
        20,
        lambda: f'the node to read the whole pass; last diagnostics {diags[-1:]}',
    )
    client = rclpy_node.create_client(Trigger, f'{ns}/estimator/solve')
    assert client.wait_for_service(timeout_sec=10.0)
    future = client.call_async(Trigger.Request())
    spin_until(rclpy_node, future.done, 30, 'the ~/solve response')
    assert future.result().success, future.result().message
    spin_until(rclpy_node, lambda: len(windows) >= 2, 10, 'the window solved on request')

    tb = TimeBase(EPOCH * 1_000_000_000)
    got = [cloud_to_window_states(m, tb) for m in windows]
    assert all(w.world_frame == 'eci' for w in got)
    samples = sorted((odometry_to_target_state(m, tb) for m in truth), key=lambda s: s.time)
    tt = np.array([s.time for s in samples])
    pos = np.array([s.position for s in samples])
    vel = np.array([s.velocity for s in samples])
    for w in got:
        ep = w.state[:, :3] - hermite_states(tt, pos, vel, w.time)
        ok = np.all(np.isfinite(ep), axis=1)
        assert ok.mean() > 0.8
        sig = np.sqrt(np.diagonal(w.covariance, axis1=1, axis2=2))[ok, :3]
        assert np.all(sig < 50.0)  # metres, not a shrug
        assert np.max(np.abs(ep[ok]) / sig) < 5.0
    spin_until(rclpy_node, lambda: int(diags[-1]['windows_solved']) >= 2, 5, 'diagnostics')
    assert int(diags[-1]['windows_failed']) == 0
    assert est.poll() is None, 'the estimator node exited'
    assert 'Traceback' not in est.errors()
