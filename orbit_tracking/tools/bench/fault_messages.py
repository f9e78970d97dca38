"""Messages of the fault-injection suite (:mod:`orbit_tracking.tools.bench.faults`): what
a fault class starts from (:class:`Reference`), what it publishes (:class:`Injection`), and
the small functions that build bad messages of every input topic of the processing nodes;
the classes themselves are listed in :mod:`~orbit_tracking.tools.bench.fault_catalogue`.

Bad messages are derived from the real ones the replay has just published, so that
everything but the fault is plausible. A measurement point starts from a real point with
every value moved by two of its sigmas: a message that should have been rejected but is
used then shows in the trajectory (and it is never a mere repeat of a real row, which the
estimator would drop as such). Telemetry is moved 50 m and 25 ms (between two real
samples); windows and fixes come from the bag's truth.

Builders are functions of a :class:`Reference` returning a list of :class:`Injection`. The
module builds messages only; it starts nothing and needs no running ROS graph.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2, PointField

__all__ = [
    'CW',
    'EST',
    'FIXES',
    'NODES',
    'OPT',
    'OPT2',
    'RANGES',
    'RES',
    'RESIDUALS',
    'ROGUE',
    'ROGUE2',
    'STATIONS',
    'TELEMETRY',
    'TRI',
    'WINDOWS',
    'LAYOUT',
    'Builder',
    'Injection',
    'Reference',
    'assign',
    'field_of',
    'first_point',
    'fix',
    'mutated',
    'offset',
    'on',
    'one_point',
    'residuals',
    'rogue_no_state',
    'rogue_reset',
    'set_variances',
    'stamped',
    'station_state',
    'target_max',
    'targets_300',
    'telemetry',
    'valued',
    'window',
    'topic_type',
]

NODES = ('triangulation', 'estimator', 'results')
"""The processing nodes under attack (node names, executables)."""

TRI, EST, RES = NODES
STATIONS = (TRI, EST)
"""Readers of every ``stations/<id>/...`` topic: both decode every measurement message and
check its layout, stamps, sigmas and finite values, so both must count those faults."""

RANGES = (EST,)
"""Judges of an implausible range or range rate: the estimator uses them; the
triangulation node intersects lines of sight and leaves a CW radar's values aside."""

CW = 'cw03'
"""A CW radar (range, range rate) of the regression bag that measures over its whole span."""

OPT, OPT2 = 'opt01', 'opt02'
"""Theodolites (azimuth, elevation) of the bag, measuring until 45 s."""

ROGUE, ROGUE2 = 'zz01', 'zz02'
"""Station ids nobody declared (no state is ever published for them)."""

FIXES = '/triangulation/fixes'
TELEMETRY = '/telemetry/state'
WINDOWS = '/estimator/window_states'
RESIDUALS = '/estimator/window_residuals'

_F32, _F64, _U32 = PointField.FLOAT32, PointField.FLOAT64, PointField.UINT32
_NS = 1_000_000_000


@dataclass(frozen=True)
class Reference:
    """What a fault class builds its messages from.

    Attributes
    ----------
    t : float
        Data time the replay stands at [s after ``epoch_ns``].
    epoch_ns : int
        Stamp [ns] of data time 0 (the nodes' ``time_reference``).
    latest : mapping of topic to message
        The latest real message the replay published on each topic (deserialised).
    truth : sequence of (stamp ns, state (6,))
        The pass's truth (position [m], velocity [m/s]), in time order.
    world_frame : str
    """

    t: float
    epoch_ns: int
    latest: Mapping[str, Any]
    truth: Sequence[tuple[int, np.ndarray]]
    world_frame: str = 'earth'

    def stamp(self, t: float | None = None) -> Time:
        """The stamp of data time ``t`` (default: where the replay stands)."""
        ns = self.epoch_ns + int(round((self.t if t is None else t) * 1e9))
        return Time(sec=ns // _NS, nanosec=ns % _NS)

    def measurements(self, sid: str) -> PointCloud2:
        return self.latest[f'/stations/{sid}/measurements']

    def state(self, sid: str) -> Odometry:
        return self.latest[f'/stations/{sid}/state']


@dataclass(frozen=True)
class Injection:
    """One bad message: its topic (absolute) and the message."""

    topic: str
    msg: Any


Builder = Callable[[Reference], list[Injection]]
"""A fault class's message builder."""


def topic_type(topic: str) -> type:
    """The message type of one of the nodes' input topics."""
    if topic.endswith('/measurements') or topic == WINDOWS:
        return PointCloud2
    if topic == FIXES:
        return PoseWithCovarianceStamped
    if topic == RESIDUALS:
        return DiagnosticArray
    return Odometry


# -- measurement points ------------------------------------------------------------------

_VALUE_FIELDS = ('range', 'range_rate', 'azimuth', 'elevation', 'los_alpha', 'los_beta')


def _columns(msg: PointCloud2) -> dict[str, np.ndarray]:
    """The fields of a (contract-layout, little-endian) cloud as float64 / uint32 columns."""
    names = [f.name for f in msg.fields]
    dtype = np.dtype(
        {
            'names': names,
            'formats': ['<u4' if f.datatype == _U32 else '<f8' for f in msg.fields],
            'offsets': [f.offset for f in msg.fields],
            'itemsize': msg.point_step,
        }
    )
    arr = np.frombuffer(bytes(msg.data), dtype=dtype, count=msg.width * msg.height)
    return {n: arr[n].copy() for n in names}


def _point(ref: Reference, sid: str) -> dict[str, float]:
    """The first point of ``sid``'s latest message, every value moved by two sigmas: a
    plausible measurement that is not one of the real rows."""
    cols = _columns(ref.measurements(sid))
    out: dict[str, float] = {}
    for name in _VALUE_FIELDS:
        if name in cols:
            sigma = float(cols[f'sigma_{name}'][0])
            out[name] = float(cols[name][0]) + 2.0 * sigma
            out[f'sigma_{name}'] = sigma
    return out


def _point_fields(dtype: np.dtype) -> list[PointField]:
    """A ``PointField`` per field of a structured dtype: ``target_id`` UINT32, the rest
    FLOAT64."""
    return [
        PointField(
            name=name,
            offset=int(dtype.fields[name][1]),
            datatype=_U32 if name == 'target_id' else _F64,
            count=1,
        )
        for name in dtype.names
    ]


def _cloud(
    ref: Reference,
    sid: str,
    points: Sequence[Mapping[str, float]],
    *,
    frame: str | None = None,
    stamp: Time | None = None,
    time_offsets: Sequence[float] | None = None,
    target_ids: Sequence[int] | None = None,
) -> PointCloud2:
    """A measurement message in the contract's layout (values, sigmas, ``time_offset``,
    ``target_id``; little-endian, one row) with ``points``; stamp and frame default to
    ``sid``'s latest real message."""
    value_names = [n for n in _VALUE_FIELDS if n in points[0]]
    names = [*value_names, *(f'sigma_{n}' for n in value_names), 'time_offset', 'target_id']
    n = len(points)
    dtype = np.dtype(
        {
            'names': names,
            'formats': ['<f8'] * (len(names) - 1) + ['<u4'],
            'offsets': [8 * i for i in range(len(names))],
            'itemsize': 8 * len(names),
        }
    )
    arr = np.zeros(n, dtype=dtype)
    for i, p in enumerate(points):
        for name in names[:-2]:
            arr[name][i] = p[name]
    arr['time_offset'] = np.zeros(n) if time_offsets is None else np.asarray(time_offsets)
    arr['target_id'] = np.zeros(n) if target_ids is None else np.asarray(target_ids)
    real = ref.measurements(sid)
    msg = PointCloud2()
    msg.header.stamp = real.header.stamp if stamp is None else stamp
    msg.header.frame_id = sid if frame is None else frame
    msg.height, msg.width = 1, n
    msg.fields = _point_fields(dtype)
    msg.is_bigendian = False
    msg.point_step = dtype.itemsize
    msg.row_step = dtype.itemsize * n
    msg.data = arr.tobytes()
    msg.is_dense = True
    return msg


def one_point(
    ref: Reference, sid: str, edit: Mapping[str, float] | None = None, **kw: Any
) -> PointCloud2:
    """One perturbed point of ``sid`` with the values in ``edit`` replaced."""
    p = _point(ref, sid)
    p.update(edit or {})
    return _cloud(ref, sid, [p], **kw)


def on(sid: str, msg: PointCloud2) -> list[Injection]:
    return [Injection(f'/stations/{sid}/measurements', msg)]


def field_of(msg: PointCloud2, name: str) -> PointField:
    return next(f for f in msg.fields if f.name == name)


def mutated(sid: str, layout: str) -> Builder:
    """A builder: one perturbed point of ``sid``, then the :data:`LAYOUT` fault ``layout``
    applied to the message."""

    def build(ref: Reference) -> list[Injection]:
        msg = one_point(ref, sid)
        LAYOUT[layout](msg)
        return on(sid, msg)

    return build


def valued(sid: str, **edit: float) -> Builder:
    """A builder: one point of ``sid`` carrying only the values in ``edit``; its other
    value fields are NaN (not measured). A plausible value beside the bad one would be
    data the nodes must use, and the trajectory would rightly move."""

    def build(ref: Reference) -> list[Injection]:
        p = _point(ref, sid)
        p.update({f: math.nan for f in _VALUE_FIELDS if f in p and f not in edit})
        p.update(edit)
        return on(sid, _cloud(ref, sid, [p]))

    return build


def stamped(sid: str, sec: int, nanosec: int | None = None) -> Builder:
    """A builder: one perturbed point of ``sid`` with header stamp ``sec`` (and ``nanosec``,
    default the real message's)."""

    def build(ref: Reference) -> list[Injection]:
        real = ref.measurements(sid).header.stamp
        nsec = real.nanosec if nanosec is None else nanosec
        return on(sid, one_point(ref, sid, stamp=Time(sec=sec, nanosec=nsec)))

    return build


def offset(sid: str, dt: float) -> Builder:
    return lambda ref: on(sid, one_point(ref, sid, time_offsets=[dt]))


# -- layout faults -----------------------------------------------------------------------


def _drop(msg: PointCloud2, names: Sequence[str]) -> None:
    msg.fields = [f for f in msg.fields if f.name not in names]


LAYOUT: dict[str, Callable[[PointCloud2], None]] = {
    'range_float32': lambda m: assign(field_of(m, 'range'), datatype=_F32),
    'range_count_2': lambda m: assign(field_of(m, 'range'), count=2),
    'beyond_point_step': lambda m: assign(field_of(m, 'target_id'), offset=m.point_step - 2),
    'point_step_zero': lambda m: assign(m, point_step=0, row_step=0),
    'width_height_overflow': lambda m: assign(m, width=2**32 - 1, height=2**32 - 1),
    'huge_width': lambda m: assign(m, width=10**9),
    'truncated': lambda m: assign(m, data=bytes(m.data)[:-1]),
    'without_sigma_field': lambda m: _drop(m, ['sigma_range_rate']),
    'without_value_fields': lambda m: _drop(m, _VALUE_FIELDS),
    'empty_frame_id': lambda m: assign(m.header, frame_id=''),
    'other_station': lambda m: assign(m.header, frame_id='cw05'),
    'zero_points': lambda m: assign(m, width=0, row_step=0, data=b''),
    # the bytes stay little-endian: a writer with a wrong flag
    'big_endian_flag': lambda m: assign(m, is_bigendian=True),
    'trailing_bytes': lambda m: assign(m, data=bytes(m.data) + b'\x7f' * 16),
    # two points, a row_step of one
    'row_step_too_small': lambda m: assign(
        m, width=2, data=bytes(m.data) * 2, row_step=m.point_step
    ),
    # two rows of one point, each padded by 8 bytes
    'padded_rows': lambda m: assign(
        m, height=2, row_step=m.point_step + 8, data=(bytes(m.data) + bytes(8)) * 2
    ),
    # a second 'range' over sigma_range
    'duplicate_range_field': lambda m: assign(
        m,
        fields=[
            *m.fields,
            PointField(
                name='range', offset=field_of(m, 'sigma_range').offset, datatype=_F64, count=1
            ),
        ],
    ),
}
"""Layout faults of a measurement message, by name: each changes the message in place."""


# -- identity faults ---------------------------------------------------------------------


def rogue_reset(ref: Reference) -> list[Injection]:
    """A station nobody declared: a message with the current stamp, then one stamped 1 s
    after the Unix epoch (issue 13: both nodes reset and then dropped every real message)."""
    p = _point(ref, CW)
    now = ref.measurements(CW).header.stamp
    first = _cloud(ref, CW, [p], frame=ROGUE, stamp=now)
    second = _cloud(ref, CW, [p], frame=ROGUE, stamp=Time(sec=1, nanosec=0))
    topic = f'/stations/{ROGUE}/measurements'
    return [Injection(topic, first), Injection(topic, second)]


def rogue_no_state(ref: Reference) -> list[Injection]:
    msg = _cloud(ref, OPT, [_point(ref, OPT)], frame=ROGUE2)
    return [Injection(f'/stations/{ROGUE2}/measurements', msg)]


def target_max(ref: Reference) -> list[Injection]:
    return on(OPT, _cloud(ref, OPT, [_point(ref, OPT)], target_ids=[2**32 - 1]))


def targets_300(ref: Reference) -> list[Injection]:
    out = []
    for sid in (OPT, OPT2):
        p = _point(ref, sid)
        out += on(sid, _cloud(ref, sid, [p] * 300, target_ids=list(range(1, 301))))
    return out


# -- station states ----------------------------------------------------------------------


def station_state(change: Callable[[Odometry], None]) -> Builder:
    """A builder: ``OPT``'s real (latched) state with ``change`` applied."""

    def build(ref: Reference) -> list[Injection]:
        msg = copy.deepcopy(ref.state(OPT))
        change(msg)
        return [Injection(f'/stations/{OPT}/state', msg)]

    return build


def assign(obj: Any, **values: Any) -> None:
    for k, v in values.items():
        setattr(obj, k, v)


# -- telemetry and fixes -----------------------------------------------------------------


def telemetry(change: Callable[[Odometry], None]) -> Builder:
    """A builder: the latest real telemetry message moved 50 m and 25 ms (between two real
    samples, so it is no repeated epoch), with ``change`` applied (accepted, it would pull
    the trajectory)."""

    def build(ref: Reference) -> list[Injection]:
        msg = copy.deepcopy(ref.latest[TELEMETRY])
        ns = msg.header.stamp.sec * _NS + msg.header.stamp.nanosec + 25_000_000
        msg.header.stamp = Time(sec=ns // _NS, nanosec=ns % _NS)  # between two real samples
        msg.pose.pose.position.x += 50.0
        change(msg)
        return [Injection(TELEMETRY, msg)]

    return build


def set_variances(msg: Any, diag: Sequence[float], block: int = 0) -> None:
    c = np.asarray(msg.covariance, dtype=np.float64).reshape(6, 6).copy()
    for i, v in enumerate(diag):
        c[block + i, block + i] = v
    msg.covariance = c.ravel()


def fix(change: Callable[[PoseWithCovarianceStamped], None]) -> Builder:
    """A builder: a position fix at the truth position of the current data time (10 m
    sigma), with ``change`` applied."""

    def build(ref: Reference) -> list[Injection]:
        stamp_ns, x = _truth_at(ref, ref.t)
        msg = PoseWithCovarianceStamped()
        msg.header.stamp = Time(sec=stamp_ns // _NS, nanosec=stamp_ns % _NS)
        msg.header.frame_id = ref.world_frame
        p = msg.pose.pose.position
        p.x, p.y, p.z = (float(v) for v in x[:3])
        msg.pose.pose.orientation.w = 1.0
        c = np.zeros((6, 6))
        c[:3, :3] = np.eye(3) * 100.0
        c[3:, 3:] = -np.eye(3)
        msg.pose.covariance = c.ravel()
        change(msg)
        return [Injection(FIXES, msg)]

    return build


def _truth_at(ref: Reference, t: float) -> tuple[int, np.ndarray]:
    """The truth sample nearest data time ``t``: (stamp ns, state (6,))."""
    want = ref.epoch_ns + int(round(t * 1e9))
    i = min(range(len(ref.truth)), key=lambda k: abs(ref.truth[k][0] - want))
    return ref.truth[i]


# -- window states and residuals -----------------------------------------------------------

_WINDOW_FIELDS = (
    'time_offset',
    'x',
    'y',
    'z',
    'vx',
    'vy',
    'vz',
    *(f'c_{i}{j}' for i in range(6) for j in range(i, 6)),
)


def _window_cloud(
    ref: Reference,
    change: Callable[[np.ndarray], None] | None = None,
    *,
    shift_s: float = 0.0,
    targets: int = 1,
) -> PointCloud2:
    """A plausible ``estimator/window_states``: the truth every 0.1 s over the 6 s before
    the current data time (``targets`` copies with ids 0, 1, ...), 1 m / 0.1 m/s sigmas, a
    ``window_length`` field; the data array passes through ``change`` before packing."""
    t1 = math.floor(ref.t * 10.0) / 10.0
    t0 = t1 - 6.0
    rows = [(s, x) for s, x in ref.truth if t0 - 1e-6 <= (s - ref.epoch_ns) * 1e-9 <= t1 + 1e-6]
    names = [*_WINDOW_FIELDS, 'target_id', 'window_length']
    offsets = [8 * i for i in range(len(names))]
    dtype = np.dtype(
        {
            'names': names,
            'formats': ['<f8'] * len(_WINDOW_FIELDS) + ['<u4', '<f8'],
            'offsets': offsets,
            'itemsize': offsets[-1] + 8,
        }
    )
    arr = np.zeros(len(rows) * targets, dtype=dtype)
    t0_ns = ref.epoch_ns + int(round(t0 * 1e9))
    for k in range(targets):
        for i, (s, x) in enumerate(rows):
            j = k * len(rows) + i
            arr['time_offset'][j] = (s - t0_ns) * 1e-9
            for name, v in zip(('x', 'y', 'z', 'vx', 'vy', 'vz'), x, strict=True):
                arr[name][j] = v
            for d in range(6):
                arr[f'c_{d}{d}'][j] = 1.0 if d < 3 else 0.01
            arr['target_id'][j] = k
    arr['window_length'] = t1 - t0
    if change is not None:
        change(arr)
    start = t0_ns + int(round(shift_s * 1e9))
    msg = PointCloud2()
    msg.header.stamp = Time(sec=start // _NS, nanosec=start % _NS)
    msg.header.frame_id = ref.world_frame
    msg.height, msg.width = 1, arr.size
    msg.fields = _point_fields(dtype)
    msg.is_bigendian = False
    msg.point_step = dtype.itemsize
    msg.row_step = dtype.itemsize * arr.size
    msg.data = arr.tobytes()
    msg.is_dense = True
    return msg


def window(
    change: Callable[[np.ndarray], None] | None = None,
    after: Callable[[PointCloud2], None] | None = None,
    **kw: Any,
) -> Builder:
    def build(ref: Reference) -> list[Injection]:
        msg = _window_cloud(ref, change, **kw)
        if after is not None:
            after(msg)
        return [Injection(WINDOWS, msg)]

    return build


def first_point(name: str, value: float) -> Callable[[np.ndarray], None]:
    def change(arr: np.ndarray) -> None:
        arr[name][0] = value

    return change


def residuals(
    edit: Mapping[str, str | None] | None = None, name: str = CW, shift_s: float = 0.0
) -> Builder:
    """A builder: ``estimator/window_residuals`` for a window ending at the current data
    time, one station status with ``edit`` applied to its key-values (None removes a key)."""

    def build(ref: Reference) -> list[Injection]:
        t1 = math.floor(ref.t * 10.0) / 10.0 + shift_s
        t0 = t1 - 6.0

        def text(t: float) -> str:
            ns = ref.epoch_ns + int(round(t * 1e9))
            return f'{ns // _NS}.{ns % _NS:09d}'

        values: dict[str, str | None] = {
            'window_start': text(t0),
            'window_end': text(t1),
            'counted_after': '',
            'rows': '100',
            'rejected': '0',
            'not_measured': '0',
            'range_count': '100',
            'range_mean': '0.1',
            'range_rms': '1.0',
            'range_rejected': '0',
        }
        values.update(edit or {})
        st = DiagnosticStatus(name=name, hardware_id=name, level=DiagnosticStatus.OK)
        st.message = 'injected'
        st.values = [KeyValue(key=k, value=v) for k, v in values.items() if v is not None]
        msg = DiagnosticArray()
        msg.header.stamp = ref.stamp(t0)
        msg.status = [st]
        return [Injection(RESIDUALS, msg)]

    return build
