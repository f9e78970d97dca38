"""Estimated station biases on the ROS side: the ``trajectory/biases`` messages, the offline
``orbit-tracking estimate --biases`` (biases.csv and friends) and the estimator node's
``bias_file`` parameter over real DDS, on 30 s of seed 000 scenario 1 with biases."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest
import yaml

from orbit_tracking.core.estimation.bias_files import read_biases_csv
from orbit_tracking.core.estimation.results import BiasEstimate
from orbit_tracking.core.sim.scenario import load_scenario, truth_biases
from orbit_tracking.tools.cli import main as cli_main

EPOCH = 1_700_000_000
TIMEBASE_NS = EPOCH * 1_000_000_000

SHORT_BIASED = """\
base: seed000_s1_bias
name: short_s1_bias
description: seed000_s1_bias cut to 30 s (tests)
span: [0.0, 30.0]
"""


def write_short_biased_scenario(folder: Path, telemetry: bool = True) -> Path:
    """seed000_s1_bias (range biases on cw02, cw05, cw08, angle biases on opt01, opt03)
    cut to 30 s."""
    path = folder / 'short_s1_bias.yaml'
    path.write_text(SHORT_BIASED + ('' if telemetry else 'telemetry: null\n'))
    return path


# -- trajectory/biases --------------------------------------------------------------------------


def test_biases_round_trip_through_a_diagnostic_array():
    from diagnostic_msgs.msg import DiagnosticStatus

    from orbit_tracking.ros.conversions import (
        TimeBase,
        biases_to_diagnostics,
        diagnostics_to_biases,
    )

    biases = (
        BiasEstimate('cw02', 'range', 2.987654321012345, 0.1234, 0.0, 10.0, 'estimated'),
        BiasEstimate('cw02', 'range_rate', -1e-4 / 3, 3e-3, 0.0, 0.1, 'estimated'),
        BiasEstimate('sat06', 'los_theta', 1e-3, 1e-3, 0.0, 1e-3, 'unobservable (x): held'),
        BiasEstimate('sat06', 'clock', 0.004, 1e-4, 0.0, 0.01, 'estimated'),
        BiasEstimate('opt02', 'azimuth', 1.2e-5, 1e-4, 1.2e-5, 1e-4, 'known'),
        BiasEstimate('cw05', 'range', 5.0, 0.5, 0.0, 10.0, 'estimated, at its upper bound 5'),
    )
    tb = TimeBase(TIMEBASE_NS)
    msg = biases_to_diagnostics(biases, 14.0, 30.25, tb)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (EPOCH + 30, 250_000_000)
    assert [(s.name, s.hardware_id) for s in msg.status] == [
        ('cw02', 'cw02'),
        ('sat06', 'sat06'),
        ('opt02', 'opt02'),
        ('cw05', 'cw05'),
    ]
    ok, warn = DiagnosticStatus.OK, DiagnosticStatus.WARN
    assert [s.level for s in msg.status] == [ok, warn, ok, warn]
    kv = {k.key: k.value for k in msg.status[0].values}
    assert list(kv)[:5] == [
        'range_bias',
        'range_bias_sigma',
        'range_bias_prior',
        'range_bias_prior_sigma',
        'range_bias_status',
    ]
    assert float(kv['range_bias']) == 2.987654321012345  # written exactly
    assert kv['window_start'] == f'{EPOCH + 14}.000000000'
    assert kv['window_end'] == f'{EPOCH + 30}.250000000'
    assert {k.key for k in msg.status[1].values} >= {'los_theta_bias', 'clock_bias_sigma'}
    assert 'los_theta' in msg.status[1].message and 'unobservable' in msg.status[1].message

    back = diagnostics_to_biases(msg)
    assert sorted(back, key=repr) == sorted(biases, key=repr)

    # outside software may send only the contract's two keys
    msg.status[0].values = [
        v for v in msg.status[0].values if v.key in ('range_bias', 'range_bias_sigma')
    ]
    (first, *_) = diagnostics_to_biases(msg)
    assert (first.value, first.sigma, first.status) == (biases[0].value, 0.1234, '')
    assert math.isnan(first.prior) and math.isnan(first.prior_sigma)
    msg.status[0].values = msg.status[0].values[:1]
    with pytest.raises(ValueError, match='range_bias without range_bias_sigma'):
        diagnostics_to_biases(msg)
    msg = biases_to_diagnostics(biases[:1], 0.0, 1.0, tb)
    msg.status[0].values[0].value = 'three'
    with pytest.raises(ValueError, match='must be numbers'):
        diagnostics_to_biases(msg)


# -- offline --------------------------------------------------------------------------------------


@pytest.fixture(scope='module')
def biased_bag(tmp_path_factory):
    """The short biased pass without telemetry (so the rough trajectory is triangulated)."""
    folder = tmp_path_factory.mktemp('biased')
    scenario = write_short_biased_scenario(folder, telemetry=False)
    bag = folder / 'bag'
    argv = ['simulate', '--scenario', str(scenario), '--out', str(bag), '--quiet']
    assert cli_main([*argv, '--batch-period', '0.5']) == 0
    return scenario, bag


def test_offline_estimate_with_auto_biases_writes_biases_csv_and_recovers_them(
    biased_bag, tmp_path, capsys
):
    from orbit_tracking.ros.bag import read_bag
    from orbit_tracking.ros.conversions import diagnostics_to_biases

    scenario, bag = biased_bag
    out = tmp_path / 'est'
    args = ['estimate', str(bag), '--out', str(out), '--window-length', '20', '--overlap', '6']
    assert cli_main([*args, '--biases', 'auto', '--quiet']) == 0
    printed = capsys.readouterr().out
    assert '2 windows: 2 succeeded' in printed
    assert 'miss-distance gate off: biases declared' in printed
    assert 'biases cw02: range ' in printed and '(truth 3, z ' in printed

    truth = truth_biases(load_scenario(scenario))
    with open(out / 'biases.csv') as fh:
        assert fh.readline().strip() == 'station,field,bias,sigma'
    rows = read_biases_csv(out / 'biases.csv')
    stations = {s.id: s.fields for s in load_scenario(scenario).stations}
    assert [(s, f) for s, f, _, _ in rows] == [
        (s, f) for s in sorted(stations) for f in stations[s]
    ]
    ranges = {s: (b, sd) for s, f, b, sd in rows if f == 'range'}
    assert len(ranges) == 9
    for sid, (b, sd) in ranges.items():
        z = (b - truth.get((sid, 'range'), 0.0)) / sd
        assert abs(z) < 3.0, (sid, b, sd)
        assert sd < 1.0  # from a prior sigma of 10 m
    assert ranges['cw08'][0] > 2.0  # 4 m simulated

    with open(out / 'biases_by_window.csv', newline='') as fh:
        by_window = list(csv.DictReader(fh))
    assert list(by_window[0]) == [
        't0',
        't1',
        'station',
        'field',
        'bias',
        'sigma',
        'prior',
        'prior_sigma',
        'status',
    ]
    assert {(r['t0'], r['t1'][:14]) for r in by_window} == {
        (f'{EPOCH}.000000000', f'{EPOCH + 20}.000'),
        (f'{EPOCH + 14}.000000000', f'{EPOCH + 30}.000'),
    }
    assert all(r['status'] == 'estimated' and r['prior_sigma'] for r in by_window)

    summary = yaml.safe_load((out / 'summary.yaml').read_text())
    assert summary['config']['biases'] == 'auto' and summary['config']['bias_parameters'] == 26
    sb = summary['biases']
    assert sb['truth_source'].startswith('bag metadata') and sb['max_abs_z_estimated'] < 3.0
    cw02 = next(r for r in sb['final'] if (r['station'], r['field']) == ('cw02', 'range'))
    assert cw02['truth'] == 3.0 and cw02['window'][0] == 14.0
    assert cw02['error'] == pytest.approx(cw02['bias'] - 3.0)

    msgs = [m for m in read_bag(out / 'bag') if m.topic == 'trajectory/biases']
    assert len(msgs) == 2
    last = {(b.station, b.name): b for b in diagnostics_to_biases(msgs[-1].msg)}
    assert last[('cw02', 'range')].value == pytest.approx(ranges['cw02'][0], rel=1e-9)
    meta = yaml.safe_load((out / 'bag' / 'metadata.yaml').read_text())
    topics = meta['rosbag2_bagfile_information']['topics_with_message_count']
    (entry,) = [
        t['topic_metadata'] for t in topics if t['topic_metadata']['name'] == msgs[0].topic
    ]
    qos = entry['offered_qos_profiles']
    qos = yaml.safe_load(qos) if isinstance(qos, str) else qos
    assert qos[0]['durability'] in ('transient_local', 1)


def test_offline_estimate_refuses_a_bad_bias_file_before_touching_the_output(
    biased_bag, tmp_path, capsys
):
    _scenario, bag = biased_bag
    out = tmp_path / 'est'
    out.mkdir()
    (out / 'keep.txt').write_text('x')
    bad = tmp_path / 'bad.yaml'
    bad.write_text('biases:\n  - {station: cw02, name: range, sigma: 0}\n')
    argv = ['estimate', str(bag), '--out', str(out), '--force', '--quiet', '--biases', str(bad)]
    assert cli_main(argv) == 2
    err = capsys.readouterr().err
    assert f'{bad}: biases[0].sigma: expected a number > 0' in err
    assert (out / 'keep.txt').exists()


# -- the node over DDS ------------------------------------------------------------------------


@pytest.mark.dds
def test_estimator_node_with_auto_biases_latches_them_on_trajectory_biases(
    tmp_path, start_process, node_command, rclpy_node, spin_until, ros_namespace
):
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import PointCloud2

    from orbit_tracking.ros import qos
    from orbit_tracking.ros.conversions import diagnostics_to_biases

    ns = ros_namespace
    scenario = write_short_biased_scenario(tmp_path)
    est = start_process(
        node_command(
            'estimator_node',
            namespace=ns,
            window_length=20.0,
            window_overlap=6.0,
            latency=1.0,
            flush_after=3600.0,
            use_telemetry=False,
            time_reference=float(EPOCH),
            bias_file='auto',
        )
    )
    windows: list[PointCloud2] = []
    rclpy_node.create_subscription(
        PointCloud2, f'{ns}/estimator/window_states', windows.append, qos.STATE_STREAM
    )
    spin_until(
        rclpy_node,
        lambda: rclpy_node.count_publishers(f'{ns}/trajectory/biases') > 0,
        20,
        'the estimator node to appear',
    )
    (info,) = rclpy_node.get_publishers_info_by_topic(f'{ns}/trajectory/biases')
    assert info.qos_profile.durability == qos.LATCHED.durability
    start_process(
        node_command(
            'scenario_sim',
            namespace=ns,
            scenario=str(scenario),
            rate_factor=10.0,
            batch_period=0.5,
            wait_for_subscribers=1,
            shutdown_when_done=True,
        )
    )
    spin_until(rclpy_node, lambda: len(windows) >= 1, 40, 'the first window')
    # subscribed only now: transient local hands over the message published before
    got: list[DiagnosticArray] = []
    rclpy_node.create_subscription(
        DiagnosticArray, f'{ns}/trajectory/biases', got.append, qos.LATCHED
    )
    spin_until(rclpy_node, lambda: bool(got), 10, 'the latched trajectory/biases')

    msg = got[0]
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (EPOCH + 20, 0)
    stations = {s.id: s.fields for s in load_scenario(scenario).stations}
    assert sorted(s.name for s in msg.status) == sorted(stations)
    assert all(s.name == s.hardware_id for s in msg.status)
    biases = {(b.station, b.name): b for b in diagnostics_to_biases(msg)}
    assert set(biases) == {(s, f) for s, fs in stations.items() for f in fs}
    truth = truth_biases(load_scenario(scenario))
    for sid in ('cw02', 'cw05', 'cw08'):
        b = biases[(sid, 'range')]
        assert b.status == 'estimated', b
        assert abs(b.value - truth[(sid, 'range')]) < 3.0 * b.sigma, b
    assert est.poll() is None, 'the estimator node exited'
    assert 'Traceback' not in est.errors()
