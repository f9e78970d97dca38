"""Measurement and state messages read from their bytes (``parse_cloud``) and many at once
(``clouds_to_measurements``), against rclpy's deserialisation and the one-message decoder.

The message set: every sensor kind, one epoch and batches, foreign and big-endian point
layouts, and the damaged and hostile messages of the contract's checks (bad stamps, empty
station, wrong datatypes, a value without its sigma, rows of padding, short data, no points,
implausible points); station and target states, and a broken one.
"""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import PointCloud2, PointField
from test_conversions import KIND_FIELDS, TB, _hand_built_cloud, _rows

from orbit_tracking.core.errors import MeasurementError
from orbit_tracking.ros.conversions import (
    WireCloud,
    cloud_to_measurements,
    clouds_to_measurements,
    fix_to_msg,
    measurements_to_cdr,
    measurements_to_cloud,
    odometry_to_station_state,
    odometry_to_target_state,
    parse_cloud,
    parse_odometry,
    read_message,
    station_state_to_odometry,
    target_state_to_odometry,
)


def _good(station: str, kind: str, times: list[float], seed: int) -> PointCloud2:
    fields = KIND_FIELDS[kind]
    t, tid, values, sigmas = _rows(fields, times, seed=seed)
    return measurements_to_cloud(station, fields, t, tid, values, sigmas, TB)


def _damaged() -> list[PointCloud2]:
    out = []
    m = _good('st01', 'cw_radar', [3.0], 1)
    m.header.stamp.nanosec = 1_000_000_000
    out.append(m)
    m = _good('', 'optical', [3.0], 2)
    out.append(m)
    m = _good('st02', 'optical', [3.0], 3)
    m.fields[0].datatype = PointField.FLOAT32
    out.append(m)
    m = _good('st02', 'optical', [3.0], 4)
    m.fields = [f for f in m.fields if f.name != 'sigma_azimuth']
    out.append(m)
    m = _good('st03', 'cw_radar', [3.0, 3.1], 5)
    m.data = bytes(m.data)[:-3]
    out.append(m)
    m = _good('st03', 'cw_radar', [3.0], 6)
    m.width, m.row_step, m.data = 0, 0, b''
    out.append(m)
    m = _good('st04', 'satellite', [3.0, 3.05], 7)
    m.height, m.row_step = 2, m.row_step // 2
    out.append(m)
    layout = [('range', '>f8', 0), ('sigma_range', '>f8', 8), ('target_id', '>u4', 16)]
    cols = {
        'range': [1.0e5, -3.0, 2.0e5],
        'sigma_range': [1.0, 1.0, 1e300],
        'target_id': [1, 2, 3],
    }
    out.append(_hand_built_cloud(layout, cols, frame='st05', bigendian=True, point_step=24))
    return out


def _messages() -> list[PointCloud2]:
    """Good messages of several stations interleaved with damaged ones."""
    out = []
    for i in range(40):
        kind = sorted(KIND_FIELDS)[i % len(KIND_FIELDS)]
        times = [1.0 + i] if i % 3 else [1.0 + i, 1.0 + i + 0.05, 1.0 + i + 0.1]
        out.append(_good(f'st{i % len(KIND_FIELDS):02d}', kind, times, seed=i))
    for j, m in enumerate(_damaged()):
        out.insert(3 * j + 1, m)
    return out


@pytest.mark.parametrize('i', range(48))
def test_parse_cloud_reads_what_rclpy_reads(i: int) -> None:
    msg = _messages()[i]
    raw = serialize_message(msg)
    want = deserialize_message(raw, PointCloud2)
    got = parse_cloud(raw)
    assert got is not None
    assert (got.header.stamp.sec, got.header.stamp.nanosec) == (
        want.header.stamp.sec,
        want.header.stamp.nanosec,
    )
    assert got.header.frame_id == want.header.frame_id
    assert [tuple(f) for f in got.fields] == [
        (f.name, f.offset, f.datatype, f.count) for f in want.fields
    ]
    for name in ('height', 'width', 'is_bigendian', 'point_step', 'row_step', 'is_dense'):
        assert getattr(got, name) == getattr(want, name), name
    assert got.data == bytes(want.data)


def test_parse_cloud_declines_cut_or_foreign_bytes_instead_of_raising() -> None:
    raw = bytes(serialize_message(_messages()[0]))
    for cut in range(len(raw)):
        got = parse_cloud(raw[:cut])
        # a cut inside the trailing is_dense byte or the data is never a message
        assert got is None, cut
    assert parse_cloud(b'\x00\x00' + raw[2:]) is None  # big-endian CDR: left to rclpy
    assert parse_cloud(raw[:4] + b'\xff' * (len(raw) - 4)) is None


def _rows_of(batches):
    """All rows of decoded batches, sorted (station, time, target, values, sigmas)."""
    rows = []
    for b in batches:
        for k in range(b.time.size):
            rows.append(
                (
                    b.station_id,
                    b.fields,
                    b.time[k],
                    int(b.target_id[k]),
                    *b.values[k],
                    *b.sigmas[k],
                )
            )
    return sorted(rows, key=repr)


@pytest.mark.parametrize('wire', [False, True], ids=['rclpy', 'parse_cloud'])
def test_many_messages_at_once_give_the_rows_and_counts_of_one_at_a_time(wire: bool) -> None:
    msgs = _messages()
    if wire:
        msgs = [parse_cloud(serialize_message(m)) for m in msgs]
    one, reasons = [], []
    for m in msgs:
        try:
            one.append(cloud_to_measurements(m, TB))
        except MeasurementError as exc:
            reasons.append(exc.reason)
    batches, errors = clouds_to_measurements(msgs, TB)
    assert [e.reason for e in errors] == reasons
    assert sorted(reasons) == [
        'fields',
        'fields',
        'frame_id',
        'layout',
        'layout',
        'no_points',
        'stamp',
    ]
    assert sum(b.messages for b in batches) == len(one)
    assert sum(b.rejected for b in batches) == sum(b.rejected for b in one) == 2
    total = sum((b.reasons for b in one), start=type(one[0].reasons)())
    assert sum((b.reasons for b in batches), start=type(total)()) == total
    got, want = _rows_of(batches), _rows_of(one)
    assert len(got) == len(want) > 60
    assert repr(got) == repr(want)  # bit for bit, NaN included
    # one batch per station and point layout (one epoch, or a batch with time_offset)
    assert len(batches) == 11
    assert all(np.all(np.diff(b.time) >= 0) for b in batches if b.station_id != 'st05')


def _odometries() -> list[Odometry]:
    rng = np.random.default_rng(5)
    out = []
    for k, (station, world) in enumerate([('cw01', 'earth'), ('sat06', 'eci'), ('x', 'w')]):
        rot = Rotation.from_euler('zyx', rng.uniform(-3, 3, 3)).as_matrix()
        p, v, w = rng.normal(0, 5e6, 3), rng.normal(0, 300, 3), rng.normal(0, 0.01, 3)
        out.append(station_state_to_odometry(station, world, 3.0 + k, p, v, rot, w, TB))
    for tid in (0, 7, 2**31 - 1):
        pc, vc = np.diag(rng.uniform(1, 9, 3)), np.diag(rng.uniform(0.1, 1, 3))
        p, v = rng.normal(0, 5e6, 3), rng.normal(0, 300, 3)
        out.append(target_state_to_odometry(tid, 'earth', 9.5, p, v, pc, vc, TB))
    bad = Odometry()  # an empty station id, a zero quaternion, NaN
    bad.pose.pose.position.x = float('nan')
    out.append(bad)
    return out


@pytest.mark.parametrize('i', range(7))
def test_parse_odometry_decodes_as_rclpy_does(i: int) -> None:
    raw = serialize_message(_odometries()[i])
    want = deserialize_message(raw, Odometry)
    got = parse_odometry(raw)
    assert got is not None
    assert (got.header.stamp.sec, got.header.stamp.nanosec, got.header.frame_id) == (
        want.header.stamp.sec,
        want.header.stamp.nanosec,
        want.header.frame_id,
    )
    assert got.child_frame_id == want.child_frame_id
    for path in (
        'pose.pose.position',
        'pose.pose.orientation',
        'twist.twist.linear',
        'twist.twist.angular',
    ):
        a, b = got, want
        for part in path.split('.'):
            a, b = getattr(a, part), getattr(b, part)
        names = ('x', 'y', 'z', 'w') if path.endswith('orientation') else ('x', 'y', 'z')
        assert repr([getattr(a, n) for n in names]) == repr([getattr(b, n) for n in names])
    np.testing.assert_array_equal(got.pose.covariance, want.pose.covariance)
    np.testing.assert_array_equal(got.twist.covariance, want.twist.covariance)
    # and the decoders give the same samples, or the same refusal
    for decode in (odometry_to_station_state, odometry_to_target_state):
        try:
            expected = repr(decode(want, TB))
        except ValueError as exc:
            expected = f'ValueError: {exc}'
        try:
            actual = repr(decode(got, TB))
        except ValueError as exc:
            actual = f'ValueError: {exc}'
        assert actual == expected


def test_parse_odometry_declines_cut_or_foreign_bytes() -> None:
    raw = bytes(serialize_message(_odometries()[0]))
    assert all(parse_odometry(raw[:cut]) is None for cut in range(len(raw) - 4))
    assert parse_odometry(b'\x00\x00' + raw[2:]) is None


@pytest.mark.parametrize('station', ['st01', 'a', 'abc', 'radar_long_name_7'])
@pytest.mark.parametrize('kind', sorted(KIND_FIELDS))
@pytest.mark.parametrize('epochs', [1, 4])
def test_measurements_to_cdr_serialises_the_message_of_measurements_to_cloud(
    station, kind, epochs
) -> None:
    fields = KIND_FIELDS[kind]
    t, tid, values, sigmas = _rows(fields, [7.25 + 0.05 * k for k in range(epochs)], seed=3)
    msg = measurements_to_cloud(station, fields, t, tid, values, sigmas, TB)
    want = bytes(serialize_message(msg))
    for _ in range(2):  # the second time from the kept layout
        raw = measurements_to_cdr(station, fields, t, tid, values, sigmas, TB)
        # rclpy leaves its alignment padding uninitialised: compare the message, and the
        # bytes everywhere but in the padding
        assert deserialize_message(raw, PointCloud2) == msg
        assert len(raw) == len(want)
        assert raw[-1 - len(msg.data) :] == want[-1 - len(msg.data) :]


def test_read_message_reads_directly_or_through_rclpy_and_refuses_garbage() -> None:
    cloud = _messages()[0]
    raw = bytes(serialize_message(cloud))
    assert isinstance(read_message(raw, 'sensor_msgs/msg/PointCloud2'), WireCloud)
    # a little-endian message the direct reader declines (is_dense 2) goes to rclpy
    odd = raw[:-1] + b'\x02'
    assert parse_cloud(odd) is None
    assert isinstance(read_message(odd, 'sensor_msgs/msg/PointCloud2'), PointCloud2)
    # a type without a direct reader
    fix = fix_to_msg('earth', 1.0, np.ones(3), np.eye(3), TB)
    got = read_message(
        bytes(serialize_message(fix)), 'geometry_msgs/msg/PoseWithCovarianceStamped'
    )
    assert got == fix
    with pytest.raises(ValueError, match='not a sensor_msgs/msg/PointCloud2'):
        read_message(raw[:30], 'sensor_msgs/msg/PointCloud2')


def _bag_of(tmp_path, msgs) -> str:
    from orbit_tracking.core import frames
    from orbit_tracking.ros.bag import BagWriter

    folder = tmp_path / 'bag'
    lat, lon = np.radians(40.9), np.radians(100.3)
    p, rot = frames.geodetic_to_ecef(lat, lon, 1000.0), frames.enu_rotation(lat, lon)
    with BagWriter(folder) as bag:
        for k in range(6):
            sid = f'st{k:02d}'
            state = station_state_to_odometry(
                sid, 'earth', 0.5, p, np.zeros(3), rot, np.zeros(3), TB
            )
            bag.write(f'stations/{sid}/state', state, TB.to_ns(0.5))
        for j, m in enumerate(msgs):
            # the topic of the station it names (a damaged one with an empty name: st00's)
            sid = m.header.frame_id or 'st00'
            bag.write(f'stations/{sid}/measurements', m, TB.to_ns(1.0 + 0.01 * j))
    return str(folder)


def test_reading_a_bag_in_chunks_gives_the_rows_and_counts_of_one_message_at_a_time(
    tmp_path, monkeypatch
) -> None:
    """read_for_estimation decodes each station's messages together, a chunk at a time: the
    same buffer and counts as the messages one by one (bag_inputs without deferring), for
    any chunk size."""
    from orbit_tracking.tools import bag_inputs as bi

    msgs = _messages() * 3
    bag = _bag_of(tmp_path, msgs)

    def one_by_one():
        ctx, counts = bi.BagContext(), Counter()
        rows = [
            item.data
            for item in bi.bag_inputs(bag, ctx, counts, False, '')
            if item.kind == 'measurements'
        ]
        return _rows_of(rows), +counts

    def chunked(size):
        monkeypatch.setattr(bi, '_DEFER_CHUNK', size)
        ctx = bi.BagContext()
        buf, counts = bi.read_for_estimation(bag, ctx, False)
        obs = buf.observations()
        rows = []
        for s in obs.stations:
            t = s.table
            for k in range(len(t)):
                rows.append(
                    (t.station_id, t.time[k], int(t.target_id[k]), *t.values[k], *t.sigmas[k])
                )
        return sorted(rows, key=repr), counts

    want_rows, want_counts = one_by_one()
    assert want_counts['invalid_messages'] == 21 and want_counts['rejected_points'] == 6
    # the buffer drops exact repeats (the message set three times): compare distinct rows
    want = sorted({(r[0], *r[2:]) for r in want_rows}, key=repr)
    for size in (1, 5, 4096):
        rows, counts = chunked(size)
        assert counts == want_counts, size
        assert repr(rows) == repr(want), size
