"""The simulator nodes and the recorder over real DDS, in separate processes.

The nodes run as ``python -m orbit_tracking.ros.<node> --ros-args ...`` subprocesses (as
``ros2 run`` would start them); the test process subscribes with the contract's consumer
QoS and decodes with ``orbit_tracking.ros.conversions``. The nodes wait for their
subscribers (``wait_for_subscribers``) so discovery time never loses a message, and stream
at 20 times real time, batched where the message rate would be high.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rosbags.rosbag2 import Reader
from sensor_msgs.msg import PointCloud2

from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.core.sim.simulator import simulate
from orbit_tracking.core.sim.stream import batch_rows
from orbit_tracking.ros.conversions import (
    TimeBase,
    cloud_to_measurements,
    odometry_to_station_state,
)

pytestmark = pytest.mark.dds

TRACEBACK = 'Traceback (most recent call last)'
CLEAN_EXIT = {0, -2, 130}  # exit 0, or killed by / exited on SIGINT

# Reader profiles an outside consumer derives from the contract (independent of ros/qos.py).
KEEP_ALL_VOLATILE = QoSProfile(
    history=HistoryPolicy.KEEP_ALL,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
"""Measurements (nothing overwritten unseen) and moving-station states."""
LATCHED_READER = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
"""Fixed-station states: transient local, so a late joiner still gets them."""


@pytest.fixture(scope='module')
def q2():
    sc = load_scenario('seed003_q2')
    return sc, simulate(sc)


@pytest.fixture(scope='module')
def s1():
    sc = load_scenario('seed000_s1')
    return sc, simulate(sc)


def _stamp_ns(stamp):
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def test_station_sim_delivers_every_measurement_in_order(
    q2, rclpy_node, start_process, node_command, spin_until, ros_namespace
):
    ns = ros_namespace
    sc, ref = q2
    table, states = ref.measurements['sat06'], ref.station_states['sat06']
    assert len(table) == 600 and len(states) == 600
    tb = TimeBase.from_seconds(sc.epoch)
    clouds: list[PointCloud2] = []
    odoms: list[Odometry] = []
    rclpy_node.create_subscription(
        Odometry, f'{ns}/stations/sat06/state', odoms.append, KEEP_ALL_VOLATILE
    )
    rclpy_node.create_subscription(
        PointCloud2, f'{ns}/stations/sat06/measurements', clouds.append, KEEP_ALL_VOLATILE
    )
    # the satellite's state is volatile too: the node waits for readers on both topics
    proc = start_process(
        node_command(
            'station_sim',
            namespace=ns,
            scenario='seed003_q2',
            station_id='sat06',
            rate_factor=20.0,
            wait_for_subscribers=1,
            shutdown_when_done=True,
        )
    )
    spin_until(
        rclpy_node,
        lambda: len(clouds) >= 600 and len(odoms) >= 600,
        30.0,
        lambda: f'600 measurements and states; got {len(clouds)} and {len(odoms)}',
    )
    assert proc.wait(timeout=15) == 0
    for _ in range(10):  # nothing more than the simulation arrives
        rclpy_node.executor.spin_once(timeout_sec=0.01)
    assert (len(clouds), len(odoms)) == (600, 600)
    assert TRACEBACK not in proc.errors()

    stamps = [_stamp_ns(c.header.stamp) for c in clouds]
    assert np.all(np.diff(stamps) > 0), 'measurements out of order'
    batches = [cloud_to_measurements(c, tb) for c in clouds]
    assert all(b.station_id == 'sat06' and b.rejected == 0 and b.time.size == 1 for b in batches)
    assert batches[0].fields == table.fields == ('los_alpha', 'los_beta')
    np.testing.assert_allclose(
        np.concatenate([b.time for b in batches]), table.time, rtol=0, atol=1e-9
    )
    np.testing.assert_array_equal(np.concatenate([b.target_id for b in batches]), table.target_id)
    np.testing.assert_array_equal(np.concatenate([b.values for b in batches]), table.values)
    np.testing.assert_array_equal(np.concatenate([b.sigmas for b in batches]), table.sigmas)

    decoded = [odometry_to_station_state(m, tb) for m in odoms]
    assert all(s.station_id == 'sat06' for s in decoded)
    assert all(m.header.frame_id == 'eci' for m in odoms)
    np.testing.assert_allclose([s.time for s in decoded], states.time, rtol=0, atol=1e-9)
    np.testing.assert_array_equal([s.position for s in decoded], states.position)
    np.testing.assert_allclose([s.velocity for s in decoded], states.velocity, rtol=0, atol=1e-8)
    np.testing.assert_allclose([s.rotation for s in decoded], states.rotation, rtol=0, atol=1e-12)


def test_scenario_sim_batches_every_point_and_latches_fixed_station_states(
    s1, rclpy_node, start_process, node_command, spin_until, ros_namespace
):
    ns = ros_namespace
    sc, ref = s1
    tb = TimeBase.from_seconds(sc.epoch)
    ids = [s.id for s in sc.stations]
    assert len(ids) == 13
    want_points = {sid: len(ref.measurements[sid]) for sid in ids}
    want_msgs = {sid: len(batch_rows(ref.measurements[sid].time, 0.5)) for sid in ids}
    points = dict.fromkeys(ids, 0)
    msgs = dict.fromkeys(ids, 0)
    batches: dict[str, list] = {sid: [] for sid in ids}

    def on_cloud(msg: PointCloud2) -> None:
        b = cloud_to_measurements(msg, tb)
        assert b.rejected == 0
        points[b.station_id] += b.time.size
        msgs[b.station_id] += 1
        batches[b.station_id].append(b)

    for sid in ids:
        rclpy_node.create_subscription(
            PointCloud2, f'{ns}/stations/{sid}/measurements', on_cloud, KEEP_ALL_VOLATILE
        )
    proc = start_process(
        node_command(
            'scenario_sim',
            namespace=ns,
            scenario='seed000_s1',
            rate_factor=20.0,
            batch_period=0.5,
            wait_for_subscribers=1,
            publish_truth=False,
            publish_telemetry=False,
        )
    )
    spin_until(
        rclpy_node,
        lambda: points == want_points,
        30.0,
        lambda: f'every point; missing { ({k: want_points[k] - v for k, v in points.items()}) }',
    )
    assert msgs == want_msgs
    assert sum(want_msgs.values()) < sum(want_points.values()) / 5  # batched: time_offset in use
    for sid in ids:
        t = np.concatenate([b.time for b in batches[sid]])
        np.testing.assert_allclose(t, ref.measurements[sid].time, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(
            np.concatenate([b.values for b in batches[sid]]), ref.measurements[sid].values
        )

    # a late joiner: the states were published once, seconds ago, before it existed
    assert proc.poll() is None, 'the simulator must still be running for this check'
    for sid in ids:  # offered as the contract says
        (state_pub,) = rclpy_node.get_publishers_info_by_topic(f'{ns}/stations/{sid}/state')
        assert state_pub.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
        assert state_pub.qos_profile.reliability == ReliabilityPolicy.RELIABLE
        (meas_pub,) = rclpy_node.get_publishers_info_by_topic(f'{ns}/stations/{sid}/measurements')
        assert meas_pub.qos_profile.durability == DurabilityPolicy.VOLATILE
        assert meas_pub.qos_profile.reliability == ReliabilityPolicy.RELIABLE
    late: dict[str, Odometry] = {}
    for sid in ids:
        rclpy_node.create_subscription(
            Odometry,
            f'{ns}/stations/{sid}/state',
            lambda m: late.__setitem__(m.child_frame_id, m),
            LATCHED_READER,
        )
    spin_until(
        rclpy_node,
        lambda: len(late) == len(ids),
        15.0,
        lambda: f'latched states; got {sorted(late)}',
    )
    for sid in ids:
        s = odometry_to_station_state(late[sid], tb)
        np.testing.assert_array_equal(s.position, ref.station_states[sid].position[0])
        np.testing.assert_allclose(s.rotation, ref.station_states[sid].rotation[0], atol=1e-12)
        assert late[sid].header.frame_id == 'earth'

    proc.send_signal(2)
    assert proc.wait(timeout=15) in CLEAN_EXIT
    assert TRACEBACK not in proc.errors()


def test_record_captures_every_measurement_point(
    s1, tmp_path, start_process, node_command, ros_namespace
):
    ns = ros_namespace
    sc, ref = s1
    tb = TimeBase.from_seconds(sc.epoch)
    out = tmp_path / 'recorded'
    recorder = start_process(
        [
            *(sys.executable, '-m', 'orbit_tracking.tools.cli', 'record'),
            *('--out', str(out), '--idle', '3', '--topics', f'{ns}/*'),
        ],
        label='record',
    )
    sim = start_process(
        node_command(
            'scenario_sim',
            namespace=ns,
            scenario='seed000_s1',
            rate_factor=20.0,
            batch_period=0.5,
            wait_for_subscribers=1,
            shutdown_when_done=True,
        )
    )
    assert sim.wait(timeout=40) == 0
    assert recorder.wait(timeout=20) == 0
    assert TRACEBACK not in recorder.errors() + sim.errors()

    points: dict[str, int] = {}
    states: dict[str, list] = {}
    with Reader(out) as reader:
        conns = {c.topic for c in reader.connections}
        for conn, _, raw in reader.messages():
            assert conn.topic.startswith(f'{ns}/'), conn.topic
            topic = conn.topic.removeprefix(f'{ns}/')
            if topic.endswith('/measurements'):
                b = cloud_to_measurements(deserialize_message(raw, PointCloud2), tb)
                points[b.station_id] = points.get(b.station_id, 0) + b.time.size
            elif topic.startswith('stations/') and topic.endswith('/state'):
                states.setdefault(topic.split('/')[1], []).append(
                    deserialize_message(raw, Odometry)
                )
    assert points == {sid: len(m) for sid, m in ref.measurements.items()}
    # the latched states are captured too (one per fixed station)
    assert {sid: len(v) for sid, v in states.items()} == dict.fromkeys(ref.measurements, 1)
    assert {f'{ns}/truth/state', f'{ns}/telemetry/state'} <= conns
    assert 'recorded' in recorder.output()


@pytest.mark.parametrize(
    ('module', 'params', 'needle'),
    [
        (
            'station_sim',
            {'scenario': 'seed003_q2', 'station_id': 'sat99'},
            "no station(s) ['sat99']",
        ),
        (
            'station_sim',
            {'scenario': 'no_such_scenario', 'station_id': 'sat06'},
            'no_such_scenario',
        ),
        (
            'station_sim',
            {'scenario': 'seed003_q2', 'station_id': 'sat06', 'rate_factor': 0.0},
            'rate_factor',
        ),
        ('scenario_sim', {'scenario': 'seed000_s1', 'rate_factor': 'fast'}, 'rate_factor'),
        ('scenario_sim', {'scenario': 'seed000_s1', 'stations': ['cw01', 'cw99']}, 'cw99'),
    ],
    ids=[
        'unknown_station',
        'unknown_scenario',
        'rate_factor_out_of_range',
        'rate_factor_not_a_number',
        'unknown_station_in_list',
    ],
)
def test_bad_parameter_is_one_fatal_line_and_exit_status_2(
    start_process, node_command, module, params, needle
):
    proc = start_process(node_command(module, **params, shutdown_when_done=True))
    assert proc.wait(timeout=20) == 2
    stderr = proc.errors()
    assert TRACEBACK not in stderr
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, stderr
    assert '[FATAL]' in lines[0] and 'cannot start' in lines[0] and needle in lines[0], lines[0]


def test_simulator_drives_clock_with_the_scenario_stamps(
    rclpy_node, start_process, node_command, spin_until, ros_namespace
):
    from rosgraph_msgs.msg import Clock

    ns = ros_namespace
    clocks: list[int] = []
    best_effort = QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.BEST_EFFORT
    )
    rclpy_node.create_subscription(
        Clock, '/clock', lambda m: clocks.append(_stamp_ns(m.clock)), best_effort
    )
    # the node waits for a reader on its measurement and (moving) state topics
    rclpy_node.create_subscription(
        PointCloud2, f'{ns}/stations/sat06/measurements', lambda _m: None, KEEP_ALL_VOLATILE
    )
    rclpy_node.create_subscription(
        Odometry, f'{ns}/stations/sat06/state', lambda _m: None, KEEP_ALL_VOLATILE
    )
    proc = start_process(
        node_command(
            'station_sim',
            namespace=ns,
            scenario='seed003_q2',
            station_id='sat06',
            rate_factor=40.0,
            publish_clock=True,
            wait_for_subscribers=1,
            shutdown_when_done=True,
        )
    )
    end_ns = 1_700_000_170 * 1_000_000_000
    spin_until(
        rclpy_node,
        lambda: bool(clocks) and clocks[-1] >= end_ns,
        30.0,
        lambda: f'/clock to reach the end of the pass; last {clocks[-1:]}',
    )
    assert proc.wait(timeout=15) == 0
    assert len(clocks) > 50
    assert np.all(np.diff(clocks) >= 0), '/clock went backwards'
    assert clocks[0] >= 1_700_000_050 * 1_000_000_000 and clocks[-1] == end_ns
