"""Internal estimator -> results messages of one window: its fitted states
(``estimator/window_states``, ``sensor_msgs/PointCloud2`` with :data:`WINDOW_STATE_FIELDS`)
and its residual statistics (``estimator/window_residuals``,
``diagnostic_msgs/DiagnosticArray``, one status per station).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from numpy.typing import ArrayLike, NDArray
from sensor_msgs.msg import PointCloud2

from orbit_tracking.core.estimation.residuals import ResidualStats
from orbit_tracking.core.models.limits import MAX_TARGET_ID
from orbit_tracking.core.time import format_stamp, parse_stamp
from orbit_tracking.ros.conversions._common import FloatArray, _dt, _layout_problem, _pack_cloud
from orbit_tracking.ros.conversions.diagnostics import diagnostic_array, diagnostic_status
from orbit_tracking.ros.conversions.time import TimeBase, checked_stamp_ns

__all__ = [
    'MAX_WINDOW_POINTS',
    'WINDOW_STATE_FIELDS',
    'WindowResiduals',
    'WindowStates',
    'cloud_to_window_states',
    'msg_to_window_residuals',
    'window_residuals_to_msg',
    'window_states_to_cloud',
]

MAX_WINDOW_POINTS = 200_000
"""Most states one ``estimator/window_states`` message may hold (every target of a window
at the output step: 60 s at 0.1 s for 32 targets is 19 200)."""

MAX_WINDOW_LENGTH_S = 86_400.0
"""Longest window [s] a window states message may declare."""

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
    return _pack_cloud(arr, t0_ns, world_frame)


def cloud_to_window_states(msg: PointCloud2, timebase: TimeBase) -> WindowStates:
    """Decode and validate ``estimator/window_states``.

    Raises
    ------
    ValueError
        An invalid stamp, a layout other than the contract's (see ``_layout_problem``; at
        most :data:`MAX_WINDOW_POINTS` points), a missing field or one of the wrong
        datatype or count, non-finite values, a covariance with a negative
        variance, a target id beyond
        :data:`~orbit_tracking.core.models.limits.MAX_TARGET_ID`, or a ``window_length``
        that is not one positive value.
    """
    checked_stamp_ns(msg.header.stamp)
    problem = _layout_problem(msg, MAX_WINDOW_POINTS)
    if problem:
        raise ValueError(f'window states layout: {problem}')
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
    if np.any(arr['target_id'] > MAX_TARGET_ID):
        raise ValueError(f'window states message holds a target id beyond {MAX_TARGET_ID}')
    time = t0 + off
    if 'window_length' in names:
        length = arr['window_length'].astype(np.float64)
        if m and not (
            np.all(np.isfinite(length)) and np.all(length == length[0]) and length[0] > 0.0
        ):
            raise ValueError('window_length must be one positive value for every point')
        t1 = t0 + float(length[0]) if m else t0
        if m and not (
            length[0] <= MAX_WINDOW_LENGTH_S and np.all((off >= -1e-6) & (off <= length[0] + 1e-6))
        ):
            raise ValueError(
                f'window of {length[0]:g} s with state offsets in [{off.min():g}, '
                f'{off.max():g}] s: the length must be at most {MAX_WINDOW_LENGTH_S:g} s and '
                'every state inside the window'
            )
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
