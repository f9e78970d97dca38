"""Message <-> core conversions (``orbit_tracking.ros.conversions``) against the contract.

No DDS: messages are built and read in process. Layout checks read the PointCloud2 bytes
with an independent decoder (offsets from the PointFields, ``struct``-style numpy views),
not with the module under test.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import PointCloud2, PointField

from orbit_tracking.core import frames
from orbit_tracking.core.errors import MeasurementError
from orbit_tracking.ros.conversions import (
    TimeBase,
    cloud_to_measurements,
    fix_to_msg,
    measurements_to_cloud,
    msg_to_fix,
    odometry_to_station_state,
    odometry_to_target_state,
    station_state_to_odometry,
    target_frame_id,
    target_id_from_frame,
    target_state_to_odometry,
)

EPOCH_NS = 1_700_000_000 * 1_000_000_000
TB = TimeBase(EPOCH_NS)

# value fields of each sensor kind (contract table), pulse radar also with its optional range rate
KIND_FIELDS = {
    'cw_radar': ('range', 'range_rate'),
    'pulse_radar': ('range', 'azimuth', 'elevation'),
    'pulse_radar_range_rate': ('range', 'range_rate', 'azimuth', 'elevation'),
    'optical': ('azimuth', 'elevation'),
    'satellite': ('los_alpha', 'los_beta'),
}
TYPICAL = {  # (value scale, sigma) per field
    'range': (150e3, 0.83),
    'range_rate': (2e3, 0.05),
    'azimuth': (2 * np.pi, 2.424e-5),
    'elevation': (1.2, 2.424e-5),
    'los_alpha': (0.2, 5e-6),
    'los_beta': (0.2, 5e-6),
}
TARGETS = np.array([0, 3, 7], dtype=np.uint32)


def _rows(fields, times, seed=0):
    """Rows for every (epoch, target): time, target_id, values, sigmas."""
    rng = np.random.default_rng(seed)
    t = np.repeat(np.asarray(times, dtype=np.float64), TARGETS.size)
    tid = np.tile(TARGETS, len(times))
    values = np.stack([rng.random(t.size) * TYPICAL[f][0] for f in fields], axis=1)
    sigmas = np.stack(
        [np.full(t.size, TYPICAL[f][1]) * (1 + rng.random(t.size)) for f in fields], axis=1
    )
    return t, tid, values, sigmas


def _column(msg, name):
    """One field of every point, read straight from the bytes (independent of the decoder)."""
    field = next(f for f in msg.fields if f.name == name)
    fmt = {PointField.FLOAT64: 'f8', PointField.UINT32: 'u4', PointField.FLOAT32: 'f4'}[
        field.datatype
    ]
    size = int(fmt[1])
    raw = np.frombuffer(bytes(msg.data), dtype=np.uint8).reshape(
        msg.height * msg.width, msg.point_step
    )
    chunk = np.ascontiguousarray(raw[:, field.offset : field.offset + size])
    return chunk.view(('>' if msg.is_bigendian else '<') + fmt).ravel()


def _stamp_ns(stamp):
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def _by_field(fields, arr):
    return {f: arr[:, j] for j, f in enumerate(fields)}


# -- PointCloud2 layout and round trip ---------------------------------------------------------


@pytest.mark.parametrize('kind', sorted(KIND_FIELDS))
@pytest.mark.parametrize('batched', [False, True], ids=['one_epoch', 'batch'])
def test_measurement_cloud_round_trip_and_layout(kind, batched):
    fields = KIND_FIELDS[kind]
    times = [12.345678901, 12.395678901, 12.445678901, 13.0] if batched else [12.345678901]
    t, tid, values, sigmas = _rows(fields, times)
    msg = measurements_to_cloud('st01', fields, t, tid, values, sigmas, TB)
    # a CDR round trip, as on the wire or in a bag
    msg = deserialize_message(serialize_message(msg), PointCloud2)

    # -- layout, exactly as the contract
    n = t.size
    assert msg.header.frame_id == 'st01'
    assert _stamp_ns(msg.header.stamp) == EPOCH_NS + round(times[0] * 1e9)
    assert (msg.height, msg.width) == (1, n)
    assert msg.is_dense is True
    assert msg.is_bigendian is False
    assert msg.row_step == msg.point_step * n
    assert len(msg.data) == msg.row_step
    expected = {*fields, *(f'sigma_{f}' for f in fields), 'target_id'}
    if batched:
        expected.add('time_offset')
    names = [f.name for f in msg.fields]
    assert sorted(names) == sorted(expected), 'time_offset only in a batch; one sigma per value'
    spans = []
    for f in msg.fields:
        want = PointField.UINT32 if f.name == 'target_id' else PointField.FLOAT64
        assert (f.datatype, f.count) == (want, 1), f.name
        size = 4 if want == PointField.UINT32 else 8
        assert 0 <= f.offset and f.offset + size <= msg.point_step, f.name
        spans.append((f.offset, f.offset + size))
    spans.sort()
    assert all(a[1] <= b[0] for a, b in zip(spans, spans[1:], strict=False)), (
        f'fields overlap: {spans}'
    )

    # -- the bytes hold the input (independent decoding)
    for j, f in enumerate(fields):
        np.testing.assert_array_equal(_column(msg, f), values[:, j])
        np.testing.assert_array_equal(_column(msg, f'sigma_{f}'), sigmas[:, j])
    np.testing.assert_array_equal(_column(msg, 'target_id'), tid)
    if batched:
        np.testing.assert_allclose(_column(msg, 'time_offset'), t - t[0], rtol=0, atol=1e-9)

    # -- and the decoder returns it
    batch = cloud_to_measurements(msg, TB)
    assert batch.station_id == 'st01'
    assert set(batch.fields) == set(fields)
    assert batch.rejected == 0
    np.testing.assert_allclose(batch.time, t, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(batch.target_id, tid)
    assert batch.target_id.dtype == np.uint32
    got_v, got_s = _by_field(batch.fields, batch.values), _by_field(batch.fields, batch.sigmas)
    for j, f in enumerate(fields):
        np.testing.assert_array_equal(got_v[f], values[:, j])
        np.testing.assert_array_equal(got_s[f], sigmas[:, j])


def test_decoded_fields_follow_the_contract_order():
    fields = ('elevation', 'range', 'azimuth')  # any input order
    t, tid, values, sigmas = _rows(fields, [1.0])
    batch = cloud_to_measurements(
        measurements_to_cloud('s', fields, t, tid, values, sigmas, TB), TB
    )
    assert batch.fields == ('range', 'azimuth', 'elevation')
    np.testing.assert_array_equal(batch.values, values[:, [1, 2, 0]])
    np.testing.assert_array_equal(batch.sigmas, sigmas[:, [1, 2, 0]])


def test_target_id_is_optional_and_defaults_to_zero():
    msg = _hand_built_cloud(
        [('range', '<f8', 0), ('sigma_range', '<f8', 8)],
        {'range': [1e5, 2e5], 'sigma_range': [1.0, 1.0]},
    )
    batch = cloud_to_measurements(msg, TB)
    np.testing.assert_array_equal(batch.target_id, [0, 0])
    np.testing.assert_array_equal(batch.time, [5.0, 5.0])


def test_target_ids_past_the_signed_32_bit_range_are_dropped_and_counted():
    msg = _hand_built_cloud(
        [('range', '<f8', 0), ('sigma_range', '<f8', 8), ('target_id', '<u4', 16)],
        {
            'range': [1e5, 2e5, 3e5],
            'sigma_range': [1.0] * 3,
            'target_id': [2**31 - 1, 2**31, 2**32 - 1],
        },
        point_step=24,
    )
    batch = cloud_to_measurements(msg, TB)
    np.testing.assert_array_equal(batch.target_id, [2**31 - 1])
    assert batch.rejected == 2 and batch.reasons == {'target_id_out_of_range': 2}


def test_measurements_to_cloud_rejects_bad_input():
    t, tid, values, sigmas = _rows(('range',), [1.0])
    with pytest.raises(MeasurementError, match='bogus'):
        measurements_to_cloud('s', ('bogus',), t, tid, values, sigmas, TB)
    with pytest.raises(MeasurementError, match='at least one point'):
        measurements_to_cloud('s', ('range',), t[:0], tid[:0], values[:0], sigmas[:0], TB)
    with pytest.raises(MeasurementError, match='must be'):
        measurements_to_cloud('s', ('range', 'range_rate'), t, tid, values, sigmas, TB)


# -- validation of incoming clouds ---------------------------------------------------------------


def _valid_cloud():
    fields = ('range', 'range_rate')
    t, tid, values, sigmas = _rows(fields, [1.0, 1.05])
    return measurements_to_cloud('cw01', fields, t, tid, values, sigmas, TB)


@pytest.mark.parametrize(
    ('name', 'datatype'),
    [
        ('range', PointField.FLOAT32),
        ('sigma_range_rate', PointField.FLOAT32),
        ('target_id', PointField.FLOAT64),
        ('time_offset', PointField.UINT32),
    ],
)
def test_field_with_wrong_datatype_is_refused_by_name(name, datatype):
    msg = _valid_cloud()
    field = next(f for f in msg.fields if f.name == name)
    field.datatype = datatype
    with pytest.raises(
        MeasurementError, match=rf"field '{name}' of station 'cw01' has datatype {datatype}"
    ):
        cloud_to_measurements(msg, TB)


def test_field_with_count_other_than_one_is_refused():
    msg = _valid_cloud()
    next(f for f in msg.fields if f.name == 'range').count = 2
    with pytest.raises(MeasurementError, match="'range'.*count 2"):
        cloud_to_measurements(msg, TB)


@pytest.mark.parametrize('value_field', ['range', 'range_rate'])
def test_value_field_without_its_sigma_is_refused(value_field):
    msg = _valid_cloud()
    msg.fields = [f for f in msg.fields if f.name != f'sigma_{value_field}']
    with pytest.raises(MeasurementError, match=rf"without sigma field.*'sigma_{value_field}'"):
        cloud_to_measurements(msg, TB)


def test_cloud_without_value_field_or_station_is_refused():
    msg = _valid_cloud()
    msg.fields = [f for f in msg.fields if f.name in ('target_id', 'time_offset')]
    with pytest.raises(MeasurementError, match='no measurement field'):
        cloud_to_measurements(msg, TB)
    msg = _valid_cloud()
    msg.header.frame_id = ''
    with pytest.raises(MeasurementError, match='frame_id'):
        cloud_to_measurements(msg, TB)


@pytest.mark.parametrize('cut', [1, 8, 'width'])
def test_truncated_data_raises(cut):
    msg = _valid_cloud()
    if cut == 'width':
        msg.width += 1
        msg.row_step = msg.point_step * msg.width
    else:
        msg.data = bytes(msg.data)[:-cut]
    with pytest.raises(MeasurementError, match='bytes'):
        cloud_to_measurements(msg, TB)


def test_field_beyond_point_step_raises():
    msg = _valid_cloud()
    next(f for f in msg.fields if f.name == 'range').offset = msg.point_step - 4
    with pytest.raises(MeasurementError, match="'range' lies beyond point_step"):
        cloud_to_measurements(msg, TB)


# -- NaN, bad sigmas -----------------------------------------------------------------------------


def test_nan_value_is_not_measured_and_bad_sigmas_are_rejected():
    nan, inf = np.nan, np.inf
    # (range, range_rate, sigma_range, sigma_range_rate): what happens
    points = [
        (1e5, 10.0, 1.0, 0.05),  # 0 kept
        (nan, 10.0, 1.0, 0.05),  # 1 kept: range not measured
        (nan, nan, 1.0, 0.05),  # 2 dropped: nothing measured (not a rejection)
        (1e5, 10.0, nan, 0.05),  # 3 rejected: sigma NaN
        (1e5, 10.0, 0.0, 0.05),  # 4 rejected: sigma 0
        (1e5, 10.0, 1.0, -1.0),  # 5 rejected: sigma negative
        (1e5, 10.0, inf, 0.05),  # 6 rejected: sigma infinite
        (nan, 10.0, nan, 0.05),  # 7 kept: the sigma of an unmeasured value does not matter
        (1e5, nan, 1.0, -1.0),  # 8 kept: likewise
        (inf, 10.0, 1.0, 0.05),  # 9 rejected: an infinite value is not "not measured"
        (nan, 10.0, 1.0, 0.0),  # 10 rejected: the measured value has sigma 0
    ]
    arr = np.array(points)
    n = len(points)
    t = 20.0 + 0.05 * np.arange(n)
    tid = np.arange(n, dtype=np.uint32)
    msg = measurements_to_cloud(
        'cw01', ('range', 'range_rate'), t, tid, arr[:, :2], arr[:, 2:], TB
    )
    batch = cloud_to_measurements(msg, TB)
    kept = [0, 1, 7, 8]
    np.testing.assert_array_equal(batch.target_id, kept)
    np.testing.assert_allclose(batch.time, t[kept], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(batch.values, arr[kept, :2])  # NaN kept as NaN
    assert (
        np.isnan(batch.values[1, 0])
        and np.isnan(batch.values[2, 0])
        and np.isnan(batch.values[3, 1])
    )
    assert batch.rejected == 6
    measured = ~np.isnan(batch.values)
    assert np.all(np.isfinite(batch.sigmas[measured]) & (batch.sigmas[measured] > 0))


def test_every_point_rejected_gives_an_empty_batch():
    t, tid, values, sigmas = _rows(('azimuth', 'elevation'), [3.0])
    sigmas[:, 1] = 0.0
    batch = cloud_to_measurements(
        measurements_to_cloud('o1', ('azimuth', 'elevation'), t, tid, values, sigmas, TB), TB
    )
    assert batch.rejected == t.size
    assert (
        batch.time.shape == (0,) and batch.values.shape == (0, 2) and batch.sigmas.shape == (0, 2)
    )


# -- foreign layouts: big-endian, other offsets, padding ------------------------------------


def _hand_built_cloud(layout, columns, bigendian=False, point_step=None, stamp_s=5.0, frame='ext'):
    """A PointCloud2 as another vendor might write it; ``layout``: [(name, format, offset)]."""
    step = point_step or max(off + np.dtype(fmt).itemsize for _, fmt, off in layout)
    dtype = np.dtype(
        {
            'names': [n for n, _, _ in layout],
            'formats': [f for _, f, _ in layout],
            'offsets': [o for _, _, o in layout],
            'itemsize': step,
        }
    )
    n = len(next(iter(columns.values())))
    arr = np.zeros(n, dtype=dtype)
    for name, values in columns.items():
        arr[name] = values
    dt = {'f8': PointField.FLOAT64, 'u4': PointField.UINT32}
    msg = PointCloud2()
    msg.header.frame_id = frame
    msg.header.stamp = TB.to_stamp(stamp_s)
    msg.height, msg.width = 1, n
    msg.fields = [
        PointField(name=nm, offset=o, datatype=dt[f[1:]], count=1) for nm, f, o in layout
    ]
    msg.is_bigendian = bigendian
    msg.point_step, msg.row_step = step, step * n
    msg.is_dense = True
    msg.data = arr.tobytes()
    return msg


@pytest.mark.parametrize('endian', ['>', '<'])
def test_foreign_layout_and_big_endian_data_are_decoded(endian):
    e = endian
    # target_id first, value and sigma fields apart, padding, 4-byte aligned doubles
    layout = [
        ('target_id', e + 'u4', 0),
        ('los_beta', e + 'f8', 4),
        ('time_offset', e + 'f8', 12),
        ('los_alpha', e + 'f8', 24),
        ('sigma_los_alpha', e + 'f8', 36),
        ('sigma_los_beta', e + 'f8', 44),
    ]
    cols = {
        'target_id': [5, 6, 70000],
        'los_alpha': [0.125, -0.2, 1e-3],
        'los_beta': [-0.3, 0.01, np.nan],
        'sigma_los_alpha': [5e-6, 6e-6, 7e-6],
        'sigma_los_beta': [5e-6, 5e-6, 5e-6],
        'time_offset': [0.0, 0.2, 0.4],
    }
    msg = _hand_built_cloud(layout, cols, bigendian=(endian == '>'), point_step=56)
    batch = cloud_to_measurements(deserialize_message(serialize_message(msg), PointCloud2), TB)
    assert batch.fields == ('los_alpha', 'los_beta')
    np.testing.assert_array_equal(batch.target_id, [5, 6, 70000])
    np.testing.assert_allclose(batch.time, [5.0, 5.2, 5.4], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(batch.values, np.array([cols['los_alpha'], cols['los_beta']]).T)
    np.testing.assert_array_equal(
        batch.sigmas, np.array([cols['sigma_los_alpha'], cols['sigma_los_beta']]).T
    )


def _two_point_cloud():
    layout = [('range', '<f8', 0), ('sigma_range', '<f8', 8)]
    return _hand_built_cloud(layout, {'range': [1.0e5, 2.0e5], 'sigma_range': [1.0, 1.0]})


def _padded_rows(msg):
    msg.height, msg.width = 2, 1
    msg.row_step = 16 + 8
    msg.data = bytes(msg.data[:16]) + b'\0' * 8 + bytes(msg.data[16:]) + b'\0' * 8


def _duplicate_field(msg):
    msg.fields = [*msg.fields, PointField(name='range', offset=8, datatype=8, count=1)]


@pytest.mark.parametrize(
    'damage, words',
    [
        (_padded_rows, 'height must be 1'),
        (lambda m: setattr(m, 'data', bytes(m.data) + b'\0' * 8), 'data holds 40 bytes'),
        (lambda m: setattr(m, 'data', bytes(m.data)[:-1]), 'data holds 31 bytes'),
        (lambda m: setattr(m, 'row_step', 16), 'row_step 16'),
        (lambda m: setattr(m, 'point_step', 0), 'point_step must be > 0'),
        (_duplicate_field, "duplicate field name(s) ['range']"),
        (lambda m: setattr(m, 'width', 10**9), 'at most 100000'),
        (lambda m: setattr(m.fields[1], 'offset', 12), 'beyond point_step'),
    ],
    ids=[
        'padded_rows',
        'extra_bytes',
        'short_data',
        'row_step',
        'point_step',
        'duplicate',
        'too_many_points',
        'field_beyond',
    ],
)
def test_a_cloud_not_laid_out_as_the_contract_says_is_rejected_as_layout(damage, words):
    msg = _two_point_cloud()
    assert cloud_to_measurements(msg, TB).values.shape == (2, 1)
    damage(msg)
    with pytest.raises(MeasurementError, match=re.escape(words)) as info:
        cloud_to_measurements(msg, TB)
    assert info.value.reason == 'layout'


@pytest.mark.parametrize(
    'sec, nanosec', [(5, 1_000_000_000), (5, 4_294_967_295), (-1, 0)], ids=['1e9', 'max', 'neg']
)
def test_an_invalid_stamp_rejects_the_message(sec, nanosec):
    msg = _two_point_cloud()
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    with pytest.raises(MeasurementError) as info:
        cloud_to_measurements(msg, TB)
    assert info.value.reason == 'stamp'


def test_a_message_without_points_is_rejected():
    msg = _two_point_cloud()
    msg.width, msg.row_step, msg.data = 0, 0, b''
    with pytest.raises(MeasurementError) as info:
        cloud_to_measurements(msg, TB)
    assert info.value.reason == 'no_points'


@pytest.mark.parametrize(
    'field, value, sigma, reason',
    [
        ('range', 1e300, 1.0, 'range_out_of_range'),
        ('range', -5.0, 1.0, 'range_out_of_range'),
        ('range', 1.0e5, 1e-300, 'sigma_range_out_of_range'),
        ('range', 1.0e5, 1e300, 'sigma_range_out_of_range'),
        ('range_rate', 1e12, 0.1, 'range_rate_out_of_range'),
        ('elevation', 4.0, 1e-4, 'elevation_out_of_range'),
        ('azimuth', 1e9, 1e-4, 'azimuth_out_of_range'),
        ('los_alpha', 1e30, 1e-5, 'los_alpha_out_of_range'),
    ],
)
def test_implausible_points_are_dropped_and_counted_by_reason(field, value, sigma, reason):
    fields = (field,)
    t = np.array([1.0, 1.1, 1.2])
    good = {
        'range': 1.0e5,
        'range_rate': 10.0,
        'elevation': 0.3,
        'azimuth': 1.0,
        'los_alpha': 0.1,
    }[field]
    values = np.array([[good], [value], [good]])
    sigmas = np.array([[1e-3], [sigma], [1e-3]])
    msg = measurements_to_cloud('s1', fields, t, np.zeros(3, np.uint32), values, sigmas, TB)
    batch = cloud_to_measurements(msg, TB)
    assert batch.rejected == 1 and dict(batch.reasons) == {reason: 1}
    np.testing.assert_allclose(batch.time, [1.0, 1.2], atol=1e-9)


@pytest.mark.parametrize('offset', [1e18, -1e18, 1e300, np.nan, 3600.5])
def test_a_time_offset_beyond_an_hour_drops_its_point(offset):
    layout = [('range', '<f8', 0), ('sigma_range', '<f8', 8), ('time_offset', '<f8', 16)]
    msg = _hand_built_cloud(
        layout,
        {'range': [1.0e5, 2.0e5], 'sigma_range': [1.0, 1.0], 'time_offset': [0.0, offset]},
    )
    batch = cloud_to_measurements(msg, TB)
    assert batch.rejected == 1 and dict(batch.reasons) == {'time_offset_out_of_range': 1}
    np.testing.assert_allclose(batch.time, [5.0], atol=1e-9)


# -- Odometry: station states ------------------------------------------------------------------


def _satellite_state():
    p = np.array([-1732113.220573, 9092044.771852, 1732113.220573])
    v = np.array([-4453.807606, -1566.513180, 4453.807606])
    return p, v, frames.observation_rotation(p[None, :])[0], np.array([0.0, 0.0, 6.9e-4])


def _ground_state():
    lat, lon = np.radians(40.9), np.radians(100.3)
    return (
        frames.geodetic_to_ecef(lat, lon, 1000.0),
        np.zeros(3),
        frames.enu_rotation(lat, lon),
        np.zeros(3),
    )


@pytest.mark.parametrize('which', ['satellite', 'ground', 'tilted'])
def test_station_state_odometry_round_trip(which):
    if which == 'satellite':
        p, v, rot, w = _satellite_state()
    elif which == 'ground':
        p, v, rot, w = _ground_state()
    else:  # a ship's deck: any rotation, moving
        p, v = np.array([3.1e6, 4.2e6, 3.3e6]), np.array([5.0, -3.0, 0.2])
        rot = Rotation.from_euler('zyx', [40.0, 3.0, -5.0], degrees=True).as_matrix()
        w = np.array([0.01, -0.02, 0.003])
    t = 61.2345
    msg = station_state_to_odometry('sat06', 'eci', t, p, v, rot, w, TB)
    msg = deserialize_message(serialize_message(msg), Odometry)

    assert (msg.header.frame_id, msg.child_frame_id) == ('eci', 'sat06')
    assert _stamp_ns(msg.header.stamp) == EPOCH_NS + 61_234_500_000
    pos = msg.pose.pose.position
    np.testing.assert_array_equal([pos.x, pos.y, pos.z], p)  # pose in the world frame
    o = msg.pose.pose.orientation
    assert o.x**2 + o.y**2 + o.z**2 + o.w**2 == pytest.approx(1.0, abs=1e-12)
    # the orientation rotates station-frame vectors into the world frame
    np.testing.assert_allclose(
        Rotation.from_quat([o.x, o.y, o.z, o.w]).as_matrix(), rot, atol=1e-12
    )
    lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
    # the twist is expressed in child_frame_id (the station frame)
    np.testing.assert_allclose([lin.x, lin.y, lin.z], rot.T @ v, rtol=0, atol=1e-9)
    np.testing.assert_array_equal([ang.x, ang.y, ang.z], w)

    back = odometry_to_station_state(msg, TB)
    assert back.station_id == 'sat06'
    assert back.time == pytest.approx(t, abs=1e-9)
    np.testing.assert_array_equal(back.position, p)
    np.testing.assert_allclose(back.velocity, v, rtol=0, atol=1e-9)
    np.testing.assert_allclose(back.rotation, rot, atol=1e-12)
    np.testing.assert_array_equal(back.angular_velocity, w)


def test_station_state_decoder_refuses_bad_messages():
    msg = Odometry()
    msg.child_frame_id = 'cw01'
    msg.pose.pose.orientation.w = 0.0  # all-zero quaternion: not a rotation
    with pytest.raises(ValueError, match='unit quaternion'):
        odometry_to_station_state(msg, TB)
    msg.pose.pose.orientation.w = 1.0
    msg.pose.pose.position.x = float('nan')
    with pytest.raises(ValueError, match='non-finite'):
        odometry_to_station_state(msg, TB)
    msg.pose.pose.position.x = 0.0
    msg.child_frame_id = ''
    with pytest.raises(ValueError, match='child_frame_id'):
        odometry_to_station_state(msg, TB)


# -- Odometry: target states, fixes -------------------------------------------------------------


def _spd(seed, scale):
    a = np.random.default_rng(seed).standard_normal((3, 3))
    return (a @ a.T + np.eye(3)) * scale


def _check_cov6(cov_msg, cov3):
    c = np.asarray(cov_msg).reshape(6, 6)
    np.testing.assert_array_equal(c[:3, :3], cov3)
    np.testing.assert_array_equal(np.diag(c)[3:], [-1.0, -1.0, -1.0])  # rotation: not estimated
    c[3:, 3:] -= np.diag([-1.0, -1.0, -1.0])
    assert not np.any(c[3:, :]) and not np.any(c[:, 3:])


def test_target_state_odometry():
    p, v = np.array([-1.112e6, 6.2e6, 1.133e6]), np.array([-697.0, 817.0, 940.0])
    pc, vc = _spd(1, 25.0), _spd(2, 0.01)
    msg = target_state_to_odometry(3, 'eci', 50.0, p, v, pc, vc, TB)
    msg = deserialize_message(serialize_message(msg), Odometry)
    assert (msg.header.frame_id, msg.child_frame_id) == ('eci', 'target_3')
    assert _stamp_ns(msg.header.stamp) == EPOCH_NS + 50_000_000_000
    o = msg.pose.pose.orientation
    assert (o.x, o.y, o.z, o.w) == (
        0.0,
        0.0,
        0.0,
        1.0,
    )  # identity: the twist is the world velocity
    pos, lin = msg.pose.pose.position, msg.twist.twist.linear
    np.testing.assert_array_equal([pos.x, pos.y, pos.z], p)
    np.testing.assert_array_equal([lin.x, lin.y, lin.z], v)
    _check_cov6(msg.pose.covariance, pc)
    _check_cov6(msg.twist.covariance, vc)

    back = odometry_to_target_state(msg, TB)
    assert back.target_id == 3 and back.time == 50.0
    np.testing.assert_array_equal(back.position, p)
    np.testing.assert_array_equal(back.velocity, v)
    np.testing.assert_array_equal(back.position_cov, pc)
    np.testing.assert_array_equal(back.velocity_cov, vc)


def test_target_frame_ids():
    assert target_frame_id(0) == 'target_0' and target_frame_id(12) == 'target_12'
    assert target_id_from_frame('target_12') == 12
    assert target_id_from_frame('target') == 0
    assert target_id_from_frame('target_2147483647') == 2**31 - 1
    for bad in (
        'sat06',
        'target_',
        'target_x',
        'target_-1',
        'target_2147483648',
        'target_4294967295',
        'target_' + '9' * 5000,
        'target_\u00b2',
    ):
        with pytest.raises(ValueError, match='target_<id>'):
            target_id_from_frame(bad)


def test_fix_message():
    p, cov = np.array([1.2e6, 4.7e6, 4.1e6]), _spd(3, 4.0)
    msg = fix_to_msg('earth', 33.4, p, cov, TB)
    assert isinstance(msg, PoseWithCovarianceStamped)
    msg = deserialize_message(serialize_message(msg), PoseWithCovarianceStamped)
    assert msg.header.frame_id == 'earth'
    assert _stamp_ns(msg.header.stamp) == EPOCH_NS + 33_400_000_000
    o = msg.pose.pose.orientation
    assert (o.x, o.y, o.z, o.w) == (0.0, 0.0, 0.0, 1.0)
    _check_cov6(msg.pose.covariance, cov)
    t, pos, c = msg_to_fix(msg, TB)
    assert t == pytest.approx(33.4, abs=1e-9)
    np.testing.assert_array_equal(pos, p)
    np.testing.assert_array_equal(c, cov)


# -- TimeBase -------------------------------------------------------------------------------


def test_timebase_keeps_nanoseconds_near_1_7e9_s():
    tb = TimeBase.from_seconds(1.7e9)
    assert tb.ref_ns == EPOCH_NS
    rng = np.random.default_rng(7)
    for sec, nsec in zip(
        rng.integers(1_700_000_000 - 1000, 1_700_000_000 + 200_000, 50),
        rng.integers(0, 1_000_000_000, 50),
        strict=True,
    ):
        stamp = Time(sec=int(sec), nanosec=int(nsec))
        t = tb.to_seconds(stamp)
        back = tb.to_stamp(t)
        assert (back.sec, back.nanosec) == (stamp.sec, stamp.nanosec)
    # neighbouring nanoseconds stay apart (float seconds since 1970 could not do this)
    a = tb.to_seconds(Time(sec=1_700_000_100, nanosec=1))
    b = tb.to_seconds(Time(sec=1_700_000_100, nanosec=2))
    assert b - a == pytest.approx(1e-9, rel=1e-3)
    assert 1_700_000_100 + 1e-9 == 1_700_000_100 + 2e-9


@pytest.mark.parametrize(
    't', [0.0, 1e-9, 50.1812, 169.9999999995, 1234.567890123, -0.25, -3.0000000001]
)
def test_timebase_float_to_stamp_round_trip(t):
    stamp = TB.to_stamp(t)
    assert 0 <= stamp.nanosec < 1_000_000_000
    assert _stamp_ns(stamp) == EPOCH_NS + round(t * 1e9)
    assert TB.to_seconds(stamp) == pytest.approx(t, abs=0.5e-9 + 1e-15)
