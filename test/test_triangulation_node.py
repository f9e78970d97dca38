"""The triangulation node over real DDS, and the offline ``orbit-tracking triangulate``."""

from __future__ import annotations

import csv
import math
import time

import numpy as np
import pytest

from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.core.sim.simulator import simulate
from orbit_tracking.core.sim.stream import feed_simulation
from orbit_tracking.core.triangulation.pipeline import (
    FIXES_CSV_COLUMNS,
    TriangulationPipeline,
    read_fixes_csv,
)
from orbit_tracking.tools.cli import main as cli_main

EPOCH = 1_700_000_000


def core_fixes(name: str):
    """Fixes of the core pipeline on the same simulated data as the nodes and the bags."""
    pipe = TriangulationPipeline()
    feed_simulation(pipe, simulate(load_scenario(name)))
    return pipe.flush()


def start_triangulation_and_listen(
    start_process, node_command, rclpy_node, spin_until, flush_after=1.0
):
    """Start the triangulation node; return it and the list its fixes arrive in, once the
    test's subscriber sees the node's publisher (no fix lost to discovery)."""
    from geometry_msgs.msg import PoseWithCovarianceStamped

    from orbit_tracking.ros import qos

    tri = start_process(node_command('triangulation_node', lag=0.5, flush_after=flush_after))
    got: list[PoseWithCovarianceStamped] = []
    rclpy_node.create_subscription(
        PoseWithCovarianceStamped, 'triangulation/fixes', got.append, qos.STATE_STREAM
    )
    spin_until(
        rclpy_node,
        lambda: rclpy_node.count_publishers('triangulation/fixes') > 0,
        20,
        'the triangulation node to appear',
    )
    return tri, got


@pytest.mark.dds
def test_scenario_sim_and_triangulation_processes_deliver_the_core_fixes(
    start_process, node_command, rclpy_node, spin_until
):

    tri, got = start_triangulation_and_listen(start_process, node_command, rclpy_node, spin_until)
    sim = start_process(
        node_command(
            'scenario_sim',
            scenario='seed003_q2',
            rate_factor=20.0,
            wait_for_subscribers=1,
            shutdown_when_done=True,
            publish_truth=False,
        )
    )
    expected = core_fixes('seed003_q2')
    spin_until(
        rclpy_node,
        lambda: len(got) >= len(expected),
        60,
        lambda: f'{len(expected)} fixes, got {len(got)}',
    )
    spin_until(rclpy_node, lambda: sim.poll() is not None, 20, 'the simulator to finish')
    for _ in range(10):  # nothing more arrives
        rclpy_node.executor.spin_once(timeout_sec=0.1)
    assert len(got) == len(expected)
    t = np.array([m.header.stamp.sec - EPOCH + 1e-9 * m.header.stamp.nanosec for m in got])
    pos = np.array(
        [[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z] for m in got]
    )
    cov = np.array([np.reshape(m.pose.covariance, (6, 6)) for m in got])
    assert np.allclose(t, [f.time for f in expected], atol=1e-6)
    assert np.allclose(pos, [f.fix.position for f in expected], atol=1e-4)
    assert np.allclose(cov[:, :3, :3], [f.fix.covariance for f in expected], rtol=1e-6)
    assert np.all(cov[:, 3:, 3:][:, [0, 1, 2], [0, 1, 2]] == -1.0)
    assert all(m.header.frame_id == 'eci' for m in got)
    assert tri.poll() is None, 'triangulation node exited'
    assert 'Traceback' not in tri.errors()


def _cloud(station: str, fields, values, sigmas, t: float, datatype=None):
    from sensor_msgs.msg import PointField

    from orbit_tracking.ros.conversions import TimeBase, measurements_to_cloud

    msg = measurements_to_cloud(
        station,
        fields,
        np.array([t]),
        np.zeros(1, np.uint32),
        np.array([values], float),
        np.array([sigmas], float),
        TimeBase(EPOCH * 1_000_000_000),
    )
    if datatype is not None:
        msg.fields[0].datatype = datatype
        assert msg.fields[0].datatype == PointField.FLOAT32
    return msg


@pytest.mark.dds
def test_triangulation_node_counts_bad_input_and_keeps_running(
    start_process, node_command, rclpy_node, spin_until
):
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2, PointField

    from orbit_tracking.core.sim.simulator import World
    from orbit_tracking.ros import qos
    from orbit_tracking.ros.conversions import TimeBase, station_state_to_odometry

    tri = start_process(
        node_command(
            'triangulation_node',
            stations=['opt01', 'opt02', 'ghost'],
            lag=0.2,
            state_wait_timeout=0.5,
            flush_after=0.5,
            time_reference=float(EPOCH),
        )
    )
    diags: list[dict[str, str]] = []

    def on_diag(msg: DiagnosticArray) -> None:
        for s in msg.status:
            if s.name.startswith('triangulation'):
                diags.append({kv.key: kv.value for kv in s.values})

    rclpy_node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, qos.DIAGNOSTICS)
    pubs = {
        sid: rclpy_node.create_publisher(
            PointCloud2, f'stations/{sid}/measurements', qos.MEASUREMENTS_PUB
        )
        for sid in ('opt01', 'opt02', 'ghost')
    }
    state_pubs = {
        sid: rclpy_node.create_publisher(
            Odometry, f'stations/{sid}/state', qos.STATION_STATE_FIXED
        )
        for sid in ('opt01', 'opt02')
    }
    spin_until(
        rclpy_node,
        lambda: all(p.get_subscription_count() > 0 for p in pubs.values()),
        20,
        'the node to subscribe',
    )
    sc = load_scenario('seed000_s1')
    world = World(sc)
    tb = TimeBase(EPOCH * 1_000_000_000)
    for sid, pub in state_pubs.items():
        s = world.station_states(sc.station(sid), np.array([0.0]))
        pub.publish(
            station_state_to_odometry(
                sid,
                'earth',
                0.0,
                s.position[0],
                s.velocity[0],
                s.rotation[0],
                s.angular_velocity[0],
                tb,
            )
        )
    spin_until(
        rclpy_node,
        lambda: all(p.get_subscription_count() > 0 for p in state_pubs.values()),
        20,
        'the node to subscribe to the station states',
    )
    res = simulate(sc)
    fields = ('azimuth', 'elevation')
    sig = (2.4e-5, 2.4e-5)
    # a wrong field type, NaN angles, a station that never sends its state, good data
    pubs['opt01'].publish(_cloud('opt01', fields, (1.0, 0.2), sig, 1.0, PointField.FLOAT32))
    pubs['opt01'].publish(_cloud('opt01', fields, (math.nan, 0.2), sig, 1.01))
    pubs['opt01'].publish(_cloud('opt01', fields, (1.0, 0.2), (0.0, 1e-5), 1.02))  # zero sigma
    pubs['ghost'].publish(_cloud('opt02', fields, (1.0, 0.2), sig, 1.03))  # wrong frame_id
    for sid in ('opt01', 'opt02'):
        m = res.measurements[sid]
        for i in range(60):
            pubs[sid].publish(_cloud(sid, fields, m.values[i], m.sigmas[i], float(m.time[i])))
            pubs['ghost'].publish(
                _cloud('ghost', fields, m.values[i], m.sigmas[i], float(m.time[i]))
            )
    want = (
        'invalid_messages',
        'nan_measurement',
        'rejected_points',
        'no_station_state',
        'station_mismatch',
    )
    spin_until(
        rclpy_node,
        lambda: (
            bool(diags)
            and all(float(diags[-1].get(k, 0)) > 0 for k in want)
            and int(diags[-1]['fixes']) > 0
        ),
        30,
        lambda: f'diagnostics with {want} and fixes; last {diags[-1] if diags else None}',
    )
    last = diags[-1]
    assert int(last['invalid_messages']) == 1
    assert int(last['rejected_points']) == 1
    assert int(last['nan_measurement']) == 1
    assert int(last['station_mismatch']) == 1
    time.sleep(0.5)
    assert tri.poll() is None, 'the node must keep running'
    assert 'Traceback' not in tri.errors()
    assert 'measurement message rejected' in tri.errors()


def test_offline_triangulate_writes_fixes_csv_with_the_contract_columns(tmp_path, capsys):
    bag = tmp_path / 'bag'
    assert cli_main(['simulate', '--scenario', 'seed003_q2', '--out', str(bag), '--quiet']) == 0
    out = tmp_path / 'tri'
    assert cli_main(['triangulate', str(bag), '--out', str(out), '--quiet']) == 0
    printed = capsys.readouterr().out
    assert 'mean NEES' in printed and 'inside' in printed
    with open(out / 'fixes.csv', newline='') as fh:
        header = next(csv.reader(fh))
    assert tuple(header) == FIXES_CSV_COLUMNS
    table = read_fixes_csv(out / 'fixes.csv')
    expected = core_fixes('seed003_q2')
    assert len(table['time']) == len(expected)
    assert np.allclose(table['time'] - EPOCH, [f.time for f in expected], atol=1e-6)
    assert np.allclose(table['position'], [f.fix.position for f in expected], atol=1e-5)
    assert np.allclose(table['covariance'], [f.fix.covariance for f in expected], rtol=1e-6)
    assert np.all(table['n_lines'] == 2)
    assert (out / 'bag' / 'metadata.yaml').is_file()
    assert (out / 'summary.yaml').is_file()


def test_offline_triangulate_of_a_missing_bag_is_a_clean_error(tmp_path, capsys):
    code = cli_main(
        ['triangulate', str(tmp_path / 'nope'), '--out', str(tmp_path / 'o'), '--quiet']
    )
    assert code == 2
    assert 'error' in capsys.readouterr().err


@pytest.mark.dds
def test_replaying_a_bag_into_the_node_reproduces_the_offline_fixes(
    tmp_path, start_process, node_command, rclpy_node, spin_until
):
    """Replay regression: a recorded pass played back over DDS gives the same fixes as the
    offline tool on the same bag; the epochs its lag holds at the end come on ``~/flush``
    (the node would wait a minute for them itself)."""
    import sys

    from std_srvs.srv import Trigger

    bag = tmp_path / 'bag'
    assert cli_main(['simulate', '--scenario', 'seed003_q2', '--out', str(bag), '--quiet']) == 0
    assert cli_main(['triangulate', str(bag), '--out', str(tmp_path / 'tri'), '--quiet']) == 0
    offline = read_fixes_csv(tmp_path / 'tri' / 'fixes.csv')
    _tri, got = start_triangulation_and_listen(
        start_process, node_command, rclpy_node, spin_until, flush_after=60.0
    )
    player = start_process(
        [
            sys.executable,
            '-m',
            'orbit_tracking.tools.cli',
            'play',
            str(bag),
            '--rate',
            '20',
            '--topics',
            'stations/*',
            '--wait-for-subscribers',
            '1',
        ],
        label='play',
    )
    assert player.wait(timeout=60) == 0
    assert 'played 2398 messages' in player.output()  # 600 + 599 measurements and states
    seen = -1
    while len(got) != seen:  # until no fix came for 1.5 s: the lag's epochs stay held
        seen = len(got)
        end = time.monotonic() + 1.5
        while time.monotonic() < end:
            rclpy_node.executor.spin_once(timeout_sec=0.05)
    held = len(offline['time']) - len(got)
    assert held >= 1, held
    client = rclpy_node.create_client(Trigger, '/triangulation/flush')
    assert client.wait_for_service(timeout_sec=10.0)
    future = client.call_async(Trigger.Request())
    spin_until(rclpy_node, future.done, 20, 'the ~/flush answer')
    assert future.result().message == f'fixed {held} held epoch(s)'
    spin_until(
        rclpy_node,
        lambda: len(got) >= len(offline['time']),
        20,
        lambda: f'{len(offline["time"])} fixes, got {len(got)}',
    )
    pos = np.array(
        [[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z] for m in got]
    )
    t = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in got])
    assert len(got) == len(offline['time'])
    assert np.allclose(t, offline['time'], atol=1e-6)
    assert np.allclose(pos, offline['position'], atol=1e-4)
