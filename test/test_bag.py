"""``orbit-tracking simulate`` writes real rosbag2 folders that carry the contract's messages.

Each bag is read back *raw* with ``rosbags.rosbag2.Reader`` and every message is
deserialised with ``rclpy.serialization.deserialize_message`` into the rclpy classes, as
any ROS 2 tool would; the content is then compared with the core simulation.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import yaml
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message
from rosbags.rosbag2 import Reader
from sensor_msgs.msg import PointCloud2

from orbit_tracking.core.models.measurements import StationPose, predict, residual
from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.core.sim.simulator import SimulationResult, World, simulate
from orbit_tracking.ros.conversions import (
    TimeBase,
    cloud_to_measurements,
    odometry_to_station_state,
    odometry_to_target_state,
)
from orbit_tracking.tools.cli import main

MSG_CLASSES = {'sensor_msgs/msg/PointCloud2': PointCloud2, 'nav_msgs/msg/Odometry': Odometry}


class BagContents:
    """A bag read back raw: every message deserialised by rclpy, decoded clouds cached.

    Attributes
    ----------
    msgs : dict
        ``{topic: [rclpy message]}``, topics without a leading ``/`` (nodes use relative names).
    log_ns : dict
        ``{topic: [log time ns]}``.
    types : dict
        ``{topic: msgtype}``.
    """

    def __init__(self, path: Path) -> None:
        msgs: dict[str, list] = defaultdict(list)
        log_ns: dict[str, list[int]] = defaultdict(list)
        self.types: dict[str, str] = {}
        with Reader(path) as reader:
            for conn, t_ns, raw in reader.messages():
                topic = conn.topic.lstrip('/')
                self.types[topic] = conn.msgtype
                msgs[topic].append(deserialize_message(raw, MSG_CLASSES[conn.msgtype]))
                log_ns[topic].append(t_ns)
        self.msgs, self.log_ns = dict(msgs), dict(log_ns)
        self._decoded: dict[tuple[str, int], tuple] = {}

    def measurements(self, station_id: str, tb: TimeBase):
        """``(time, target_id, values, sigmas, fields)`` of a station, all messages decoded."""
        key = (station_id, tb.ref_ns)
        if key not in self._decoded:
            batches = [
                cloud_to_measurements(m, tb)
                for m in self.msgs[f'stations/{station_id}/measurements']
            ]
            assert sum(b.rejected for b in batches) == 0
            self._decoded[key] = (
                np.concatenate([b.time for b in batches]),
                np.concatenate([b.target_id for b in batches]),
                np.concatenate([b.values for b in batches]),
                np.concatenate([b.sigmas for b in batches]),
                batches[0].fields,
            )
        return self._decoded[key]


def qos_profiles(meta: dict) -> dict[str, list[dict]]:
    """``{topic: offered QoS profiles}`` of a metadata.yaml (a list; a YAML string in old bags)."""
    out = {}
    for entry in meta['rosbag2_bagfile_information']['topics_with_message_count']:
        tm = entry['topic_metadata']
        prof = tm.get('offered_qos_profiles') or []
        out[tm['name'].lstrip('/')] = yaml.safe_load(prof) if isinstance(prof, str) else prof
    return out


def expected_message_counts(result: SimulationResult) -> dict[str, int]:
    counts = {}
    for sid, m in result.measurements.items():
        counts[f'stations/{sid}/measurements'] = len(np.unique(m.time))  # one message per epoch
        counts[f'stations/{sid}/state'] = len(result.station_states[sid])
    if result.truth:
        counts['truth/state'] = sum(len(t) for t in result.truth.values())
    if result.telemetry:
        counts['telemetry/state'] = sum(len(t) for t in result.telemetry.values())
    return counts


def simulate_bag(tmp: Path, scenario: str, *extra: str) -> Path:
    out = tmp / 'bag'
    assert main(['simulate', '--scenario', scenario, '--out', str(out), '--quiet', *extra]) == 0
    return out


@pytest.fixture(scope='module')
def q2_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate_bag(tmp_path_factory.mktemp('q2'), 'seed003_q2')


@pytest.fixture(scope='module')
def s1_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate_bag(tmp_path_factory.mktemp('s1'), 'seed000_s1')


@pytest.fixture(scope='module')
def s1_contents(s1_bag: Path) -> BagContents:
    return BagContents(s1_bag)


def check_bag_equals_simulation(bag: BagContents, scenario: str) -> None:
    sc = load_scenario(scenario)
    result = simulate(sc)
    tb = TimeBase.from_seconds(sc.epoch)
    msgs, log_ns, types = bag.msgs, bag.log_ns, bag.types

    assert {t: len(v) for t, v in msgs.items()} == expected_message_counts(result)
    for topic, times in log_ns.items():
        assert np.all(np.diff(times) >= 0), f'{topic}: log times out of order'

    for sid, table in result.measurements.items():
        topic = f'stations/{sid}/measurements'
        assert types[topic] == 'sensor_msgs/msg/PointCloud2'
        clouds = msgs[topic]
        # one epoch per message: the log time is the measurement epoch, the stamp
        assert [tb.ref_ns + round(t * 1e9) for t in np.unique(table.time)] == log_ns[topic]
        assert all(c.header.frame_id == sid for c in clouds)
        t, tid, values, sigmas, fields = bag.measurements(sid, tb)
        assert fields == table.fields
        np.testing.assert_allclose(t, table.time, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(tid, table.target_id)
        np.testing.assert_array_equal(values, table.values)
        np.testing.assert_array_equal(sigmas, table.sigmas)

        states = [odometry_to_station_state(m, tb) for m in msgs[f'stations/{sid}/state']]
        ref = result.station_states[sid]
        assert all(s.station_id == sid for s in states)
        np.testing.assert_allclose([s.time for s in states], ref.time, rtol=0, atol=1e-9)
        np.testing.assert_array_equal([s.position for s in states], ref.position)
        np.testing.assert_allclose([s.velocity for s in states], ref.velocity, rtol=0, atol=1e-8)
        np.testing.assert_allclose([s.rotation for s in states], ref.rotation, rtol=0, atol=1e-12)

    truth = [odometry_to_target_state(m, tb) for m in msgs['truth/state']]
    for tid, ref in result.truth.items():
        mine = [s for s in truth if s.target_id == tid]
        np.testing.assert_allclose([s.time for s in mine], ref.time, rtol=0, atol=1e-9)
        np.testing.assert_array_equal([s.position for s in mine], ref.position)
        np.testing.assert_array_equal([s.velocity for s in mine], ref.velocity)


def test_simulate_writes_an_mcap_bag_equal_to_the_core_simulation(q2_bag):
    meta = yaml.safe_load((q2_bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['storage_identifier'] == 'mcap'
    assert [p.suffix for p in q2_bag.iterdir() if p.name != 'metadata.yaml'] == ['.mcap']
    bag = BagContents(q2_bag)
    msgs = bag.msgs
    # the reference scenario: sat06 sees 600 epochs (50.1812 s + k 0.2 s <= 170 s), sat09 599
    assert len(msgs['stations/sat06/measurements']) == 600
    assert len(msgs['stations/sat09/measurements']) == 599
    check_bag_equals_simulation(bag, 'seed003_q2')


def test_simulate_sqlite3_bag(tmp_path):
    path = simulate_bag(tmp_path, 'seed003_q2', '--storage', 'sqlite3')
    meta = yaml.safe_load((path / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['storage_identifier'] == 'sqlite3'
    assert [p.suffix for p in path.iterdir() if p.name != 'metadata.yaml'] == ['.db3']
    check_bag_equals_simulation(BagContents(path), 'seed003_q2')


def test_ground_bag_equals_the_core_simulation(s1_contents):
    check_bag_equals_simulation(s1_contents, 'seed000_s1')


def _durability(profile: dict) -> str:
    d = profile['durability']
    return {1: 'transient_local', 2: 'volatile'}.get(d, d) if isinstance(d, int) else str(d)


def _reliability(profile: dict) -> str:
    r = profile['reliability']
    return {1: 'reliable', 2: 'best_effort'}.get(r, r) if isinstance(r, int) else str(r)


def test_bag_metadata_carries_the_contract_qos(s1_bag, q2_bag):
    ground = qos_profiles(yaml.safe_load((s1_bag / 'metadata.yaml').read_text()))
    states = [t for t in ground if t.endswith('/state') and t.startswith('stations/')]
    assert len(states) == 13
    for topic in states:  # fixed stations: latched
        (profile,) = ground[topic]
        assert (_durability(profile), _reliability(profile), profile['depth']) == (
            'transient_local',
            'reliable',
            1,
        ), topic
    for topic in (t for t in ground if t.endswith('/measurements')):
        (profile,) = ground[topic]
        assert (_durability(profile), _reliability(profile)) == ('volatile', 'reliable'), topic

    space = qos_profiles(yaml.safe_load((q2_bag / 'metadata.yaml').read_text()))
    for topic in ('stations/sat06/state', 'stations/sat09/state'):  # moving: volatile
        (profile,) = space[topic]
        assert (_durability(profile), _reliability(profile)) == ('volatile', 'reliable'), topic


def test_measurements_in_bag_are_unbiased_with_honest_sigmas(s1_contents):
    """(z - h(truth)) / sigma from the bag alone (plus the truth trajectory): mean 0, std 1."""
    sc = load_scenario('seed000_s1')
    world = World(sc)
    tb = TimeBase.from_seconds(sc.epoch)
    msgs = s1_contents.msgs
    checked = 0
    for st in sc.stations:
        t, tid, values, sigmas, fields = s1_contents.measurements(st.id, tb)
        (state,) = [odometry_to_station_state(m, tb) for m in msgs[f'stations/{st.id}/state']]
        truth = np.empty((t.size, 6))
        for target in np.unique(tid):
            sel = tid == target
            truth[sel] = world.target_state(int(target), t[sel])
        pose = StationPose.fixed(state.position, state.rotation, t.size)
        predicted, _ = predict(fields, truth, pose)
        z = residual(fields, values, predicted) / sigmas
        for j, field in enumerate(fields):
            zj = z[:, j][~np.isnan(values[:, j])]
            n = zj.size
            assert n > 500, f'{st.id} {field}: only {n} measurements'
            assert abs(zj.mean()) < 4.0 / np.sqrt(n), (
                f'{st.id} {field}: mean {zj.mean():.4f} (n={n})'
            )
            assert abs(zj.std(ddof=1) - 1.0) < 0.05, (
                f'{st.id} {field}: std {zj.std(ddof=1):.4f} (n={n})'
            )
            checked += 1
    assert checked == 26
