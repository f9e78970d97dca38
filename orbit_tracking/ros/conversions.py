"""Messages <-> core types: the only module where ROS messages and the numerical core meet.

Layouts follow ``docs/CONTRACT.md``:

* measurements: ``sensor_msgs/PointCloud2``, one point per (epoch, target), FLOAT64
  value and ``sigma_<field>`` fields, ``time_offset`` (FLOAT64, s) and ``target_id``
  (UINT32), little-endian, ``height = 1``, dense;
* station states, telemetry, truth and fitted states: ``nav_msgs/Odometry``;
* triangulation fixes: ``geometry_msgs/PoseWithCovarianceStamped``;
* a window's fitted states (internal, ``estimator/window_states``): ``PointCloud2`` with
  :data:`WINDOW_STATE_FIELDS`;
* a window's residual statistics (internal, ``estimator/window_residuals``):
  ``diagnostic_msgs/DiagnosticArray``, one status per station;
* a window's station biases (``trajectory/biases``): ``diagnostic_msgs/DiagnosticArray``,
  one status per station with ``<name>_bias`` and ``<name>_bias_sigma`` keys.

Times: the core computes in float seconds relative to a :class:`TimeBase` (an integer
number of nanoseconds, by default the scenario epoch), so that float64 keeps
sub-nanosecond resolution across a long pass.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from numpy.typing import ArrayLike, NDArray
from sensor_msgs.msg import PointCloud2, PointField

from orbit_tracking.core import frames
from orbit_tracking.core.errors import MeasurementError
from orbit_tracking.core.estimation.residuals import ResidualStats
from orbit_tracking.core.models.measurements import FIELDS, sigma_field
from orbit_tracking.core.models.systematic import ESTIMABLE_BIASES
from orbit_tracking.core.time import format_stamp, parse_stamp

if TYPE_CHECKING:  # the estimator is heavy to import, and only the bias messages need it
    from orbit_tracking.core.estimation.estimator import BiasEstimate

__all__ = [
    'MeasurementBatch',
    'StationStateSample',
    'TargetStateSample',
    'TimeBase',
    'WINDOW_STATE_FIELDS',
    'WindowResiduals',
    'WindowStates',
    'biases_to_diagnostics',
    'cloud_to_measurements',
    'cloud_to_window_states',
    'diagnostic_array',
    'diagnostic_status',
    'diagnostics_to_biases',
    'fix_to_msg',
    'measurements_to_cloud',
    'msg_to_fix',
    'msg_to_window_residuals',
    'odometry_to_station_state',
    'odometry_to_target_state',
    'stamp_ns',
    'station_state_to_odometry',
    'target_frame_id',
    'target_id_from_frame',
    'target_state_to_odometry',
    'window_residuals_to_msg',
    'window_states_to_cloud',
]

FloatArray = NDArray[np.float64]

_FLOAT64 = PointField.FLOAT64
_UINT32 = PointField.UINT32
_UNKNOWN_ROTATION = -1.0  # REP-conventional "not estimated" variance


@dataclass(frozen=True)
class TimeBase:
    """Maps ``builtin_interfaces/Time`` stamps to float seconds and back.

    Parameters
    ----------
    ref_ns : int
        Stamp (integer nanoseconds) of float time 0.
    """

    ref_ns: int

    @classmethod
    def from_seconds(cls, epoch_s: float) -> TimeBase:
        return cls(int(round(epoch_s * 1e9)))

    @classmethod
    def whole_second_of(cls, stamp_ns_: int) -> TimeBase:
        """A time base at the whole second of a stamp (what nodes use when no reference
        is configured: the first stamp they receive)."""
        return cls((stamp_ns_ // 1_000_000_000) * 1_000_000_000)

    def to_seconds(self, stamp: Time) -> float:
        return ((int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)) - self.ref_ns) * 1e-9

    def to_ns(self, t: float) -> int:
        return self.ref_ns + int(round(t * 1e9))

    def to_stamp(self, t: float) -> Time:
        ns = self.to_ns(t)
        return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def stamp_ns(stamp: Time) -> int:
    """Integer nanoseconds of a stamp."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


@dataclass(frozen=True)
class MeasurementBatch:
    """Decoded content of one measurement message.

    Attributes
    ----------
    station_id : str
        ``header.frame_id``.
    fields : tuple of str
        Value fields present, in the contract's order.
    time : ndarray, shape (n,)
        Epoch of each accepted point (stamp + time_offset) in TimeBase seconds.
    target_id : ndarray of uint32, shape (n,)
    values, sigmas : ndarray, shape (n, k)
        NaN values were not measured.
    rejected : int
        Points dropped because a measured value's sigma was not finite and positive
        or a value was infinite.
    """

    station_id: str
    fields: tuple[str, ...]
    time: FloatArray
    target_id: NDArray[np.uint32]
    values: FloatArray
    sigmas: FloatArray
    rejected: int


def _cloud_dtype(fields: Sequence[str], with_time_offset: bool) -> np.dtype:
    names, formats, offsets = [], [], []
    off = 0
    for f in (*fields, *(sigma_field(f) for f in fields)):
        names.append(f)
        formats.append('<f8')
        offsets.append(off)
        off += 8
    if with_time_offset:
        names.append('time_offset')
        formats.append('<f8')
        offsets.append(off)
        off += 8
    names.append('target_id')
    formats.append('<u4')
    offsets.append(off)
    off += 4
    itemsize = (off + 7) // 8 * 8  # keep doubles 8-byte aligned from point to point
    return np.dtype({'names': names, 'formats': formats, 'offsets': offsets, 'itemsize': itemsize})


def measurements_to_cloud(
    station_id: str,
    fields: Sequence[str],
    time: FloatArray,
    target_id: NDArray[np.uint32],
    values: FloatArray,
    sigmas: FloatArray,
    timebase: TimeBase,
) -> PointCloud2:
    """Pack measurement rows into one PointCloud2.

    The header stamp is the first row's epoch; a ``time_offset`` field is added only when
    rows have different epochs (a batch).
    """
    fields = tuple(fields)
    bad = [f for f in fields if f not in FIELDS]
    if bad:
        raise MeasurementError(f'unknown measurement field(s) {bad}')
    n = time.shape[0]
    if n == 0:
        raise MeasurementError('a measurement message needs at least one point')
    if values.shape != (n, len(fields)) or sigmas.shape != values.shape:
        raise MeasurementError(
            f'values {values.shape} and sigmas {sigmas.shape} must be ({n}, {len(fields)})'
        )
    ns = np.array([timebase.to_ns(float(t)) for t in time], dtype=np.int64)
    batched = bool(np.any(ns != ns[0]))
    dtype = _cloud_dtype(fields, batched)
    arr = np.zeros(n, dtype=dtype)
    for j, f in enumerate(fields):
        arr[f] = values[:, j]
        arr[sigma_field(f)] = sigmas[:, j]
    if batched:
        arr['time_offset'] = (ns - ns[0]) * 1e-9
    arr['target_id'] = target_id
    msg = PointCloud2()
    first_ns = int(ns[0])
    msg.header.stamp = Time(sec=first_ns // 1_000_000_000, nanosec=first_ns % 1_000_000_000)
    msg.header.frame_id = station_id
    msg.height = 1
    msg.width = n
    msg.fields = [
        PointField(name=name, offset=int(dtype.fields[name][1]), datatype=_dt(name), count=1)
        for name in dtype.names
    ]
    msg.is_bigendian = False
    msg.point_step = dtype.itemsize
    msg.row_step = dtype.itemsize * n
    msg.data = arr.tobytes()
    msg.is_dense = True
    return msg


def _dt(name: str) -> int:
    return _UINT32 if name == 'target_id' else _FLOAT64


def cloud_to_measurements(msg: PointCloud2, timebase: TimeBase) -> MeasurementBatch:
    """Decode and validate one measurement message.

    Raises
    ------
    MeasurementError
        The message as a whole is unusable: no value field, a field of the wrong type
        or count, a value field without its sigma field, inconsistent sizes.
        Individual bad points are dropped and counted in ``rejected`` instead.
    """
    station = msg.header.frame_id
    if not station:
        raise MeasurementError('measurement message has an empty header.frame_id (station id)')
    by_name = {f.name: f for f in msg.fields}
    for f in msg.fields:
        want = _UINT32 if f.name == 'target_id' else _FLOAT64
        if (
            f.name in FIELDS
            or f.name.startswith('sigma_')
            or f.name in ('time_offset', 'target_id')
        ) and (f.datatype != want or f.count != 1):
            raise MeasurementError(
                f'field {f.name!r} of station {station!r} has datatype {f.datatype} and count '
                f'{f.count}; expected datatype {want} '
                f'({"UINT32" if want == _UINT32 else "FLOAT64"}) and count 1'
            )
    fields = tuple(f for f in FIELDS if f in by_name)
    if not fields:
        raise MeasurementError(
            f'message of station {station!r} has no measurement field; expected any of {FIELDS}'
        )
    missing = [sigma_field(f) for f in fields if sigma_field(f) not in by_name]
    if missing:
        raise MeasurementError(
            f'station {station!r}: value field(s) without sigma field {missing}'
        )
    n = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    if (
        step <= 0
        or len(msg.data) < n * step
        or int(msg.row_step) * int(msg.height) > len(msg.data)
    ):
        raise MeasurementError(
            f'station {station!r}: data has {len(msg.data)} bytes, expected '
            f'width*height*point_step = {n * step}'
        )
    for f in msg.fields:
        size = 4 if f.datatype == _UINT32 else 8
        if f.offset + size > step:
            raise MeasurementError(f'station {station!r}: field {f.name!r} lies beyond point_step')
    endian = '>' if msg.is_bigendian else '<'
    names = [*fields, *(sigma_field(f) for f in fields)]
    formats = [f'{endian}f8'] * len(names)
    offsets = [by_name[nm].offset for nm in names]
    for extra, fmt in (('time_offset', 'f8'), ('target_id', 'u4')):
        if extra in by_name:
            names.append(extra)
            formats.append(endian + fmt)
            offsets.append(by_name[extra].offset)
    dtype = np.dtype({'names': names, 'formats': formats, 'offsets': offsets, 'itemsize': step})
    row_bytes = int(msg.row_step) if msg.height > 1 else n * step
    raw = bytes(msg.data)
    if msg.height > 1 and int(msg.row_step) != int(msg.width) * step:
        rows = [raw[r * row_bytes : r * row_bytes + msg.width * step] for r in range(msg.height)]
        raw = b''.join(rows)
    arr = np.frombuffer(raw, dtype=dtype, count=n)
    values = np.stack([arr[f].astype(np.float64) for f in fields], axis=1)
    sigmas = np.stack([arr[sigma_field(f)].astype(np.float64) for f in fields], axis=1)
    offs = arr['time_offset'].astype(np.float64) if 'time_offset' in names else np.zeros(n)
    tids = arr['target_id'].astype(np.uint32) if 'target_id' in names else np.zeros(n, np.uint32)
    measured = ~np.isnan(values)
    bad_sigma = measured & ~(np.isfinite(sigmas) & (sigmas > 0.0))
    bad = np.any(bad_sigma | np.isinf(values), axis=1) | ~np.isfinite(offs)
    empty = ~np.any(measured, axis=1)
    keep = ~bad & ~empty
    t0 = timebase.to_seconds(msg.header.stamp)
    return MeasurementBatch(
        station_id=station,
        fields=fields,
        time=t0 + offs[keep],
        target_id=tids[keep],
        values=values[keep],
        sigmas=sigmas[keep],
        rejected=int(np.count_nonzero(bad)),
    )


@dataclass(frozen=True)
class StationStateSample:
    """A station pose decoded from ``stations/<id>/state``."""

    station_id: str
    time: float
    position: FloatArray
    velocity: FloatArray
    rotation: FloatArray
    angular_velocity: FloatArray

    @property
    def moving(self) -> bool:
        """A station with any velocity or turn rate is treated as moving (its states are
        interpolated in time); a still one keeps its latest pose for every epoch."""
        return bool(
            np.linalg.norm(self.velocity) > 1e-6 or np.linalg.norm(self.angular_velocity) > 1e-9
        )


def station_state_to_odometry(
    station_id: str,
    world_frame: str,
    t: float,
    position: FloatArray,
    velocity: FloatArray,
    rotation: FloatArray,
    angular_velocity: FloatArray,
    timebase: TimeBase,
) -> Odometry:
    """Station pose as Odometry: pose in the world frame, twist in the station frame."""
    msg = Odometry()
    msg.header.stamp = timebase.to_stamp(t)
    msg.header.frame_id = world_frame
    msg.child_frame_id = station_id
    _set_point(msg.pose.pose.position, position)
    q = frames.matrix_to_quaternion(rotation)
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = (float(v) for v in q)
    v_body = rotation.T @ velocity
    _set_vector(msg.twist.twist.linear, v_body)
    _set_vector(msg.twist.twist.angular, angular_velocity)
    return msg


def odometry_to_station_state(msg: Odometry, timebase: TimeBase) -> StationStateSample:
    """Decode a station state; raises ``ValueError`` on a non-unit quaternion or NaN."""
    p = _point(msg.pose.pose.position)
    o = msg.pose.pose.orientation
    rot = frames.quaternion_to_matrix([o.x, o.y, o.z, o.w])
    v = rot @ _vector(msg.twist.twist.linear)
    w = _vector(msg.twist.twist.angular)
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(v))):
        raise ValueError(f'station state of {msg.child_frame_id!r} has non-finite values')
    if not msg.child_frame_id:
        raise ValueError('station state has an empty child_frame_id (station id)')
    return StationStateSample(
        msg.child_frame_id, timebase.to_seconds(msg.header.stamp), p, v, rot, w
    )


@dataclass(frozen=True)
class TargetStateSample:
    """A target state (truth, telemetry, fitted) decoded from Odometry."""

    target_id: int
    time: float
    position: FloatArray
    velocity: FloatArray
    position_cov: FloatArray
    velocity_cov: FloatArray


def target_frame_id(target_id: int) -> str:
    """``child_frame_id`` of a target's states: ``target_<id>``."""
    return f'target_{int(target_id)}'


def target_id_from_frame(frame: str) -> int:
    """Inverse of :func:`target_frame_id`; plain ``target`` is target 0."""
    if frame == 'target':
        return 0
    if frame.startswith('target_') and frame[7:].isdigit():
        return int(frame[7:])
    raise ValueError(f"target frame must be 'target' or 'target_<id>'; got {frame!r}")


def target_state_to_odometry(
    target_id: int,
    world_frame: str,
    t: float,
    position: FloatArray,
    velocity: FloatArray,
    position_cov: FloatArray,
    velocity_cov: FloatArray,
    timebase: TimeBase,
) -> Odometry:
    """Target state as Odometry: identity orientation so the twist is the world velocity;
    rotation and angular-rate variances are -1 (not estimated)."""
    msg = Odometry()
    msg.header.stamp = timebase.to_stamp(t)
    msg.header.frame_id = world_frame
    msg.child_frame_id = target_frame_id(target_id)
    _set_point(msg.pose.pose.position, position)
    msg.pose.pose.orientation.w = 1.0
    _set_vector(msg.twist.twist.linear, velocity)
    msg.pose.covariance = _cov6(position_cov)
    msg.twist.covariance = _cov6(velocity_cov)
    return msg


def odometry_to_target_state(msg: Odometry, timebase: TimeBase) -> TargetStateSample:
    pc = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(6, 6)[:3, :3]
    vc = np.asarray(msg.twist.covariance, dtype=np.float64).reshape(6, 6)[:3, :3]
    return TargetStateSample(
        target_id_from_frame(msg.child_frame_id),
        timebase.to_seconds(msg.header.stamp),
        _point(msg.pose.pose.position),
        _vector(msg.twist.twist.linear),
        pc,
        vc,
    )


def fix_to_msg(
    world_frame: str, t: float, position: FloatArray, cov: FloatArray, timebase: TimeBase
) -> PoseWithCovarianceStamped:
    """A position fix with its 3x3 covariance (rotation block: -1 on the diagonal)."""
    msg = PoseWithCovarianceStamped()
    msg.header.stamp = timebase.to_stamp(t)
    msg.header.frame_id = world_frame
    _set_point(msg.pose.pose.position, position)
    msg.pose.pose.orientation.w = 1.0
    msg.pose.covariance = _cov6(cov)
    return msg


def msg_to_fix(
    msg: PoseWithCovarianceStamped, timebase: TimeBase
) -> tuple[float, FloatArray, FloatArray]:
    """``(t, position (3,), covariance (3, 3))`` of a fix."""
    cov = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(6, 6)[:3, :3]
    return timebase.to_seconds(msg.header.stamp), _point(msg.pose.pose.position), cov


WINDOW_STATE_FIELDS: tuple[str, ...] = (
    'time_offset',
    'x',
    'y',
    'z',
    'vx',
    'vy',
    'vz',
    *(f'c_{i}{j}' for i in range(6) for j in range(i, 6)),
)
"""FLOAT64 fields of ``estimator/window_states`` (then ``target_id``, UINT32): the
offset [s] of the point's time from ``header.stamp``, world position [m] and velocity
[m/s], and the 21 upper-triangle entries ``c_<i><j>`` (i <= j) of their 6x6 covariance in
the order (x, y, z, vx, vy, vz)."""

_UPPER = np.triu_indices(6)


@dataclass(frozen=True)
class WindowStates:
    """Decoded ``estimator/window_states``: one window's fitted states.

    Attributes
    ----------
    world_frame : str
    t0 : float
        Window start (``header.stamp``) in TimeBase seconds.
    t1 : float
        Window end [s]: ``t0 + window_length`` when the message has that field, else its
        latest state time.
    time : ndarray, shape (m,)
        Time of each state [s] (TimeBase).
    target_id : ndarray of uint32, shape (m,)
    state : ndarray, shape (m, 6)
        World position [m] and velocity [m/s].
    covariance : ndarray, shape (m, 6, 6)
    """

    world_frame: str
    t0: float
    time: FloatArray
    target_id: NDArray[np.uint32]
    state: FloatArray
    covariance: FloatArray
    t1: float


def _window_dtype(with_length: bool = False) -> np.dtype:
    names = [*WINDOW_STATE_FIELDS, 'target_id']
    formats = ['<f8'] * len(WINDOW_STATE_FIELDS) + ['<u4']
    offsets = [8 * i for i in range(len(names))]
    if with_length:
        names.append('window_length')
        formats.append('<f8')
        offsets.append(offsets[-1] + 8)  # after target_id, 8-byte aligned
    itemsize = (offsets[-1] + (8 if with_length else 4) + 7) // 8 * 8
    return np.dtype({'names': names, 'formats': formats, 'offsets': offsets, 'itemsize': itemsize})


def window_states_to_cloud(
    world_frame: str,
    t0: float,
    time: ArrayLike,
    target_id: ArrayLike,
    state: ArrayLike,
    covariance: ArrayLike,
    timebase: TimeBase,
    t1: float | None = None,
) -> PointCloud2:
    """Pack one window's fitted states into ``estimator/window_states``.

    Parameters
    ----------
    world_frame : str
        ``header.frame_id``.
    t0 : float
        Window start [s]; ``header.stamp``, and ``time_offset = time - t0``.
    time : ndarray, shape (m,)
    target_id : int or ndarray of uint32, shape (m,)
    state : ndarray, shape (m, 6)
    covariance : ndarray, shape (m, 6, 6)
    t1 : float, optional
        Window end [s]; given, it is carried in a ``window_length`` field (``t1 - t0``,
        FLOAT64, after ``target_id``) so that the results node hands over between windows
        exactly where the offline tool does.

    Raises
    ------
    ValueError
        Inconsistent shapes, non-finite values, an empty frame id.
    """
    t = np.atleast_1d(np.asarray(time, dtype=np.float64))
    m = t.size
    x = np.asarray(state, dtype=np.float64)
    c = np.asarray(covariance, dtype=np.float64)
    if not world_frame:
        raise ValueError('window states need a world frame (header.frame_id)')
    if x.shape != (m, 6) or c.shape != (m, 6, 6):
        raise ValueError(
            f'window states need state (m, 6) and covariance (m, 6, 6) for {m} times; got '
            f'{x.shape} and {c.shape}'
        )
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(x)) and np.all(np.isfinite(c))):
        raise ValueError('window states must be finite')
    if t1 is not None and not t1 > t0:
        raise ValueError(f'window end must lie after its start; got [{t0}, {t1}]')
    dtype = _window_dtype(with_length=t1 is not None)
    arr = np.zeros(m, dtype=dtype)
    t0_ns = timebase.to_ns(t0)
    arr['time_offset'] = t - (t0_ns - timebase.ref_ns) * 1e-9
    if t1 is not None:
        arr['window_length'] = t1 - (t0_ns - timebase.ref_ns) * 1e-9
    for j, name in enumerate(('x', 'y', 'z', 'vx', 'vy', 'vz')):
        arr[name] = x[:, j]
    upper = c[:, _UPPER[0], _UPPER[1]]
    for k, name in enumerate(WINDOW_STATE_FIELDS[7:]):
        arr[name] = upper[:, k]
    arr['target_id'] = np.broadcast_to(np.asarray(target_id, dtype=np.uint32), (m,))
    msg = PointCloud2()
    msg.header.stamp = Time(sec=t0_ns // 1_000_000_000, nanosec=t0_ns % 1_000_000_000)
    msg.header.frame_id = world_frame
    msg.height = 1
    msg.width = m
    msg.fields = [
        PointField(name=name, offset=int(dtype.fields[name][1]), datatype=_dt(name), count=1)
        for name in dtype.names
    ]
    msg.is_bigendian = False
    msg.point_step = dtype.itemsize
    msg.row_step = dtype.itemsize * m
    msg.data = arr.tobytes()
    msg.is_dense = True
    return msg


def cloud_to_window_states(msg: PointCloud2, timebase: TimeBase) -> WindowStates:
    """Decode and validate ``estimator/window_states``.

    Raises
    ------
    ValueError
        A missing field or one of the wrong datatype or count, data shorter than
        ``width * height * point_step``, non-finite values, a covariance with a negative
        variance, or a ``window_length`` that is not one positive value.
    """
    by_name = {f.name: f for f in msg.fields}
    names = [*WINDOW_STATE_FIELDS, 'target_id']
    missing = [n for n in names if n not in by_name]
    if missing:
        raise ValueError(f'window states message lacks field(s) {missing}')
    if 'window_length' in by_name:
        names.append('window_length')
    for n in names:
        f = by_name[n]
        want = _dt(n)
        if f.datatype != want or f.count != 1:
            raise ValueError(
                f'window states field {n!r} has datatype {f.datatype} and count {f.count}; '
                f'expected datatype {want} and count 1'
            )
    m = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    if step <= 0 or len(msg.data) < m * step:
        raise ValueError(
            f'window states data has {len(msg.data)} bytes, expected width*height*point_step '
            f'= {m * step}'
        )
    if any(by_name[n].offset + _size(n) > step for n in names):
        raise ValueError('a window states field lies beyond point_step')
    endian = '>' if msg.is_bigendian else '<'
    dtype = np.dtype(
        {
            'names': names,
            'formats': [endian + ('u4' if n == 'target_id' else 'f8') for n in names],
            'offsets': [by_name[n].offset for n in names],
            'itemsize': step,
        }
    )
    arr = np.frombuffer(bytes(msg.data), dtype=dtype, count=m)
    t0 = timebase.to_seconds(msg.header.stamp)
    x = np.column_stack([arr[n].astype(np.float64) for n in ('x', 'y', 'z', 'vx', 'vy', 'vz')])
    c = np.zeros((m, 6, 6))
    for k, n in enumerate(WINDOW_STATE_FIELDS[7:]):
        i, j = int(_UPPER[0][k]), int(_UPPER[1][k])
        c[:, i, j] = c[:, j, i] = arr[n]
    off = arr['time_offset'].astype(np.float64)
    if not (np.all(np.isfinite(off)) and np.all(np.isfinite(x)) and np.all(np.isfinite(c))):
        raise ValueError('window states message holds non-finite values')
    if np.any(np.diagonal(c, axis1=1, axis2=2) < 0.0):
        raise ValueError('window states message holds a negative variance')
    time = t0 + off
    if 'window_length' in names:
        length = arr['window_length'].astype(np.float64)
        if m and not (
            np.all(np.isfinite(length)) and np.all(length == length[0]) and length[0] > 0.0
        ):
            raise ValueError('window_length must be one positive value for every point')
        t1 = t0 + float(length[0]) if m else t0
    else:
        t1 = float(time.max()) if m else t0
    return WindowStates(
        msg.header.frame_id,
        t0,
        time,
        arr['target_id'].astype(np.uint32),
        x,
        c,
        t1,
    )


def _size(name: str) -> int:
    return 4 if name == 'target_id' else 8


@dataclass(frozen=True)
class WindowResiduals:
    """One station's status of ``estimator/window_residuals``, decoded.

    Attributes
    ----------
    t0, t1 : float
        Window span [s] (TimeBase).
    counted_after : float or None
        The statistics count the window's rows after this time [s] (the previous window's
        end); None: every row of the window.
    stats : ResidualStats
    """

    t0: float
    t1: float
    counted_after: float | None
    stats: ResidualStats


def window_residuals_to_msg(
    stats: Mapping[str, ResidualStats],
    t0: float,
    t1: float,
    counted_after: float | None,
    timebase: TimeBase,
) -> DiagnosticArray:
    """``estimator/window_residuals``: one ``DiagnosticStatus`` per station (``name`` and
    ``hardware_id`` = station id) with the window's whitened-residual statistics.

    ``header.stamp`` is the window start. Keys: ``window_start``, ``window_end`` and
    ``counted_after`` (stamps in decimal seconds, ``counted_after`` empty when every row of
    the window counts), ``rows``, ``rejected``, ``not_measured``, and per field
    ``<field>_count``, ``<field>_mean``, ``<field>_rms``, ``<field>_rejected``.
    """
    ref = timebase.ref_ns
    statuses = []
    for sid, st in sorted(stats.items()):
        values: dict[str, object] = {
            'window_start': format_stamp(ref, t0),
            'window_end': format_stamp(ref, t1),
            'counted_after': '' if counted_after is None else format_stamp(ref, counted_after),
            'rows': st.rows,
            'rejected': int(st.rejected.sum()),
            'not_measured': st.not_measured,
        }
        for j, f in enumerate(st.fields):
            values[f'{f}_count'] = int(st.count[j])
            values[f'{f}_mean'] = float(st.mean[j])
            values[f'{f}_rms'] = float(st.rms[j])
            values[f'{f}_rejected'] = int(st.rejected[j])
        text = ', '.join(f'{f} {r:.2f}' for f, r in zip(st.fields, st.rms, strict=True))
        statuses.append(
            diagnostic_status(
                sid,
                DiagnosticStatus.OK,
                f'{st.rows} rows, {int(st.rejected.sum())} values rejected; whitened RMS {text}',
                values,
                hardware_id=sid,
            )
        )
    return diagnostic_array(timebase.to_stamp(t0), statuses)


def msg_to_window_residuals(msg: DiagnosticArray, timebase: TimeBase) -> list[WindowResiduals]:
    """Decode ``estimator/window_residuals``.

    Raises
    ------
    ValueError
        A status without a station name or a required key, an unreadable number, a
        window whose end is not after its start, or statuses of different windows.
    """
    out = []
    for st in msg.status:
        sid = st.name
        if not sid:
            raise ValueError('window residuals status has an empty name (station id)')
        kv = {k.key: k.value for k in st.values}
        try:
            ref = timebase.ref_ns
            t0 = (parse_stamp(kv['window_start']) - ref) * 1e-9
            t1 = (parse_stamp(kv['window_end']) - ref) * 1e-9
            after_text = kv.get('counted_after', '')
            after = (parse_stamp(after_text) - ref) * 1e-9 if after_text else None
            fields = tuple(k[: -len('_count')] for k in kv if k.endswith('_count'))
            count = {f: int(kv[f'{f}_count']) for f in fields}
            mean = {f: float(kv[f'{f}_mean']) for f in fields}
            rms = {f: float(kv[f'{f}_rms']) for f in fields}
            rejected = {f: int(kv.get(f'{f}_rejected', '0')) for f in fields}
            rows, not_measured = int(kv['rows']), int(kv.get('not_measured', '0'))
        except KeyError as exc:
            raise ValueError(f'window residuals of station {sid!r} lack key {exc}') from None
        if not t1 > t0:
            raise ValueError(f'window residuals of station {sid!r}: window end before its start')
        bad = [
            f
            for f in fields
            if count[f] < 0
            or rejected[f] < 0
            or (count[f] and not (math.isfinite(mean[f]) and math.isfinite(rms[f])))
        ]
        if bad or rows < 0 or not_measured < 0:
            raise ValueError(f'window residuals of station {sid!r}: invalid values for {bad}')
        stats = ResidualStats.from_moments(
            sid, fields, rows, count, mean, rms, rejected, not_measured
        )
        out.append(WindowResiduals(t0, t1, after, stats))
    if len({(w.t0, w.t1) for w in out}) > 1:
        raise ValueError('window residuals message mixes statuses of different windows')
    return out


def diagnostic_status(
    name: str, level: int | bytes, message: str, values: dict[str, object], hardware_id: str = ''
) -> DiagnosticStatus:
    """A DiagnosticStatus with ``values`` as KeyValue strings (``level``: OK/WARN/ERROR)."""
    st = DiagnosticStatus()
    st.name = name
    st.level = level if isinstance(level, bytes) else bytes([level])
    st.message = message
    st.hardware_id = hardware_id
    st.values = [KeyValue(key=str(k), value=_fmt(v)) for k, v in values.items()]
    return st


def diagnostic_array(stamp: Time, statuses: Sequence[DiagnosticStatus]) -> DiagnosticArray:
    arr = DiagnosticArray()
    arr.header.stamp = stamp
    arr.status = list(statuses)
    return arr


_BIAS_SUFFIXES = ('bias', 'bias_sigma', 'bias_prior', 'bias_prior_sigma', 'bias_status')


def _bias_warns(status: str) -> bool:
    """An unobservable bias (held at its prior) or one that ended on a bound."""
    return status.startswith('unobservable') or ' bound' in status


def biases_to_diagnostics(
    biases: Sequence[BiasEstimate], t0: float, t1: float, timebase: TimeBase
) -> DiagnosticArray:
    """``trajectory/biases``: one window's station biases as a ``DiagnosticArray``.

    One ``DiagnosticStatus`` per station (in order of first appearance), ``name`` =
    ``hardware_id`` = station id, with the ``KeyValue``s ``<name>_bias``,
    ``<name>_bias_sigma``, ``<name>_bias_prior``, ``<name>_bias_prior_sigma`` (numbers
    written exactly, ``repr``) and ``<name>_bias_status`` per bias, then ``window_start``
    and ``window_end`` (stamps in decimal seconds). Level WARN when a bias of the station
    is unobservable (held at its prior) or ended on a bound, else OK.

    Parameters
    ----------
    biases : sequence of BiasEstimate
        An estimate's ``biases``.
    t0, t1 : float
        The window [TimeBase s]; ``header.stamp`` is the stamp of ``t1``.
    timebase : TimeBase
    """
    per_station: dict[str, list[BiasEstimate]] = {}
    for b in biases:
        per_station.setdefault(b.station, []).append(b)
    statuses = []
    window = {
        'window_start': format_stamp(timebase.ref_ns, t0),
        'window_end': format_stamp(timebase.ref_ns, t1),
    }
    for sid, bs in per_station.items():
        values: dict[str, object] = {}
        for b in bs:
            values[f'{b.name}_bias'] = repr(float(b.value))
            values[f'{b.name}_bias_sigma'] = repr(float(b.sigma))
            values[f'{b.name}_bias_prior'] = repr(float(b.prior))
            values[f'{b.name}_bias_prior_sigma'] = repr(float(b.prior_sigma))
            values[f'{b.name}_bias_status'] = b.status
        values.update(window)
        odd = [f'{b.name}: {b.status}' for b in bs if _bias_warns(b.status)]
        level = DiagnosticStatus.WARN if odd else DiagnosticStatus.OK
        message = '; '.join(odd) if odd else ', '.join(f'{b.name} {b.status}' for b in bs)
        statuses.append(diagnostic_status(sid, level, message, values, hardware_id=sid))
    return diagnostic_array(timebase.to_stamp(t1), statuses)


def diagnostics_to_biases(msg: DiagnosticArray) -> tuple[BiasEstimate, ...]:
    """The biases of a ``trajectory/biases`` message (inverse of
    :func:`biases_to_diagnostics`).

    The station is a status's ``hardware_id`` (its ``name`` if empty); a bias is every
    ``<name>_bias`` key of a known bias name. Missing ``_bias_prior`` /
    ``_bias_prior_sigma`` read as NaN, a missing ``_bias_status`` as ``''``; other keys
    are ignored.

    Raises
    ------
    ValueError
        A ``<name>_bias`` without its ``<name>_bias_sigma``, or a value that is not a
        number.
    """
    from orbit_tracking.core.estimation.estimator import BiasEstimate

    out = []
    for st in msg.status:
        sid = st.hardware_id or st.name
        kv = {k.key: k.value for k in st.values}
        for name in ESTIMABLE_BIASES:
            if f'{name}_bias' not in kv:
                continue
            if f'{name}_bias_sigma' not in kv:
                raise ValueError(f'station {sid}: {name}_bias without {name}_bias_sigma')
            try:
                value, sigma, prior, prior_sigma = (
                    float(kv.get(f'{name}_{suffix}', 'nan')) for suffix in _BIAS_SUFFIXES[:4]
                )
            except ValueError:
                raise ValueError(
                    f'station {sid}: {name} bias values must be numbers; got '
                    f'{[kv.get(f"{name}_{s}") for s in _BIAS_SUFFIXES[:4]]}'
                ) from None
            out.append(
                BiasEstimate(
                    sid, name, value, sigma, prior, prior_sigma, kv.get(f'{name}_bias_status', '')
                )
            )
    return tuple(out)


def _fmt(v: object) -> str:
    if isinstance(v, float):
        return f'{v:.9g}'
    return str(v)


def _cov6(cov3: FloatArray) -> NDArray[np.float64]:
    c = np.zeros((6, 6))
    c[:3, :3] = np.asarray(cov3, dtype=np.float64).reshape(3, 3)
    c[3, 3] = c[4, 4] = c[5, 5] = _UNKNOWN_ROTATION
    return c.ravel()


def _set_point(p: object, xyz: FloatArray) -> None:
    p.x, p.y, p.z = (float(v) for v in xyz)  # type: ignore[attr-defined]


def _set_vector(v: object, xyz: FloatArray) -> None:
    v.x, v.y, v.z = (float(c) for c in xyz)  # type: ignore[attr-defined]


def _point(p: object) -> FloatArray:
    return np.array([p.x, p.y, p.z], dtype=np.float64)  # type: ignore[attr-defined]


_vector = _point
