"""Measurement messages (``sensor_msgs/PointCloud2``) <-> measurement rows.

Layout (``docs/CONTRACT.md``): one point per (epoch, target), FLOAT64 value and
``sigma_<field>`` fields, ``time_offset`` (FLOAT64, s, only when the points have different
epochs) and ``target_id`` (UINT32), little-endian, ``height = 1``, dense;
``header.frame_id`` is the station id and ``header.stamp`` the first point's epoch.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from sensor_msgs.msg import PointCloud2

from orbit_tracking.core.errors import MeasurementError
from orbit_tracking.core.models.limits import (
    MAX_POINTS,
    MAX_TARGET_ID,
    MAX_TIME_OFFSET_S,
    implausible_rows,
)
from orbit_tracking.core.models.measurements import FIELDS, sigma_field
from orbit_tracking.ros.conversions._common import (
    _FLOAT64,
    _UINT32,
    FloatArray,
    _dt,
    _layout_problem,
    _pack_cloud,
)
from orbit_tracking.ros.conversions.time import TimeBase, checked_stamp_ns
from orbit_tracking.ros.conversions.wire import WireCloud, cloud_cdr

__all__ = [
    'MeasurementBatch',
    'checked_stamp_ns_of',
    'cloud_to_measurements',
    'clouds_to_measurements',
    'measurements_to_cdr',
    'measurements_to_cloud',
]


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
        Points dropped as implausible (a value or sigma outside the limits of
        :mod:`orbit_tracking.core.models.limits`, a ``time_offset`` beyond
        ``MAX_TIME_OFFSET_S``); points without any measured value are dropped too but not
        counted here.
    reasons : Counter
        Dropped points per reason (the empty ones as ``no_value``).
    messages : int
        Messages decoded into this batch (more than one from
        :func:`clouds_to_measurements`).
    """

    station_id: str
    fields: tuple[str, ...]
    time: FloatArray
    target_id: NDArray[np.uint32]
    values: FloatArray
    sigmas: FloatArray
    rejected: int
    reasons: Counter[str] = field(default_factory=Counter)
    messages: int = 1


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
    arr, ns0 = _measurement_points(fields, time, target_id, values, sigmas, timebase)
    return _pack_cloud(arr, ns0, station_id)


def measurements_to_cdr(
    station_id: str,
    fields: Sequence[str],
    time: FloatArray,
    target_id: NDArray[np.uint32],
    values: FloatArray,
    sigmas: FloatArray,
    timebase: TimeBase,
) -> bytes:
    """:func:`measurements_to_cloud` already serialised (the bytes ``serialize_message`` would
    give), for a bag writer: no message object is built."""
    arr, ns0 = _measurement_points(fields, time, target_id, values, sigmas, timebase)
    return cloud_cdr(arr, ns0, station_id, [_dt(name) for name in arr.dtype.names or ()])


def _measurement_points(
    fields: Sequence[str],
    time: FloatArray,
    target_id: NDArray[np.uint32],
    values: FloatArray,
    sigmas: FloatArray,
    timebase: TimeBase,
) -> tuple[np.ndarray, int]:
    """The structured point array of a measurement message and its stamp [ns]."""
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
    return arr, int(ns[0])


_Group = tuple[str, tuple[str, ...], np.dtype, list[bytes], list[float], list[int]]
"""Messages of one station and layout: station, fields, dtype, point bytes, stamps, widths."""


def cloud_to_measurements(msg: PointCloud2, timebase: TimeBase) -> MeasurementBatch:
    """Decode and validate one measurement message.

    Raises
    ------
    MeasurementError
        The message as a whole is unusable; its ``reason`` says why: ``stamp`` (not a valid
        stamp), ``frame_id`` (empty), ``fields`` (no value field, a field of the wrong
        type or count, a value field without its sigma field), ``layout`` (see
        ``_layout_problem``: not one dense row of exactly the declared size), ``no_points``.
        Individual bad points are dropped instead and counted in ``rejected`` and
        ``reasons`` (:func:`~orbit_tracking.core.models.limits.implausible_rows`,
        ``time_offset_out_of_range``, ``target_id_out_of_range`` (beyond
        :data:`~orbit_tracking.core.models.limits.MAX_TARGET_ID`), ``sigma_invalid``,
        ``no_value``).
    """
    checked_stamp_ns_of(msg)
    station, fields, dtype = _checked_layout(msg)
    arr = np.frombuffer(bytes(msg.data), dtype=dtype, count=int(msg.width))
    t0 = np.full(arr.shape[0], timebase.to_seconds(msg.header.stamp))
    return _points(station, fields, arr, t0)


def clouds_to_measurements(
    clouds: Sequence[PointCloud2 | WireCloud], timebase: TimeBase
) -> tuple[list[MeasurementBatch], list[MeasurementError]]:
    """Decode many measurement messages at once: the same checks, rows and counts as
    :func:`cloud_to_measurements` message by message, but the points of all messages of one
    station and layout decoded and checked in one pass.

    Returns
    -------
    batches : list of MeasurementBatch
        One per (station, field layout), in order of first appearance; the rows of each in
        message order. A message's points keep its own stamp. ``rejected`` and ``reasons``
        add up those of its messages.
    errors : list of MeasurementError
        One per message that is unusable as a whole (what :func:`cloud_to_measurements`
        raises for it), in message order.
    """
    layouts: dict[tuple[object, ...], tuple[str, tuple[str, ...], np.dtype] | MeasurementError]
    layouts = {}
    groups: dict[tuple[object, ...], _Group] = {}
    errors: list[MeasurementError] = []
    for msg in clouds:
        try:
            checked_stamp_ns_of(msg)
        except MeasurementError as exc:
            errors.append(exc)
            continue
        data = bytes(msg.data)
        key = (
            msg.header.frame_id,
            msg.fields
            if isinstance(msg, WireCloud)
            else tuple((f.name, f.offset, f.datatype, f.count) for f in msg.fields),
            bool(msg.is_bigendian),
            int(msg.point_step),
            int(msg.height),
            int(msg.width),
            int(msg.row_step),
            len(data),
        )
        layout = layouts.get(key)
        if layout is None:
            try:
                layout = _checked_layout(msg)
            except MeasurementError as exc:
                layout = exc
            layouts[key] = layout
        if isinstance(layout, MeasurementError):
            errors.append(layout)
            continue
        group = groups.setdefault(key[:5], (*layout, [], [], []))
        group[3].append(data)
        group[4].append(timebase.to_seconds(msg.header.stamp))
        group[5].append(int(msg.width))
    batches = []
    for station, fields, dtype, datas, t0s, widths in groups.values():
        arr = np.frombuffer(b''.join(datas), dtype=dtype, count=sum(widths))
        t0 = np.repeat(np.array(t0s), widths)
        batches.append(_points(station, fields, arr, t0, messages=len(datas)))
    return batches, errors


def checked_stamp_ns_of(msg: PointCloud2 | WireCloud) -> int:
    """The stamp of a measurement message in integer nanoseconds.

    Raises
    ------
    MeasurementError
        With reason ``stamp``: not a valid stamp.
    """
    try:
        return checked_stamp_ns(msg.header.stamp)
    except ValueError as exc:
        raise MeasurementError(f'station {msg.header.frame_id!r}: {exc}', 'stamp') from None


def _checked_layout(msg: PointCloud2 | WireCloud) -> tuple[str, tuple[str, ...], np.dtype]:
    """Station id, value fields and the structured dtype of a message's points, after the
    message-level checks (see :func:`cloud_to_measurements`)."""
    station = msg.header.frame_id
    if not station:
        raise MeasurementError(
            'measurement message has an empty header.frame_id (station id)', 'frame_id'
        )
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
                f'({"UINT32" if want == _UINT32 else "FLOAT64"}) and count 1',
                'fields',
            )
    fields = tuple(f for f in FIELDS if f in by_name)
    if not fields:
        raise MeasurementError(
            f'message of station {station!r} has no measurement field; expected any of {FIELDS}',
            'fields',
        )
    missing = [sigma_field(f) for f in fields if sigma_field(f) not in by_name]
    if missing:
        raise MeasurementError(
            f'station {station!r}: value field(s) without sigma field {missing}', 'fields'
        )
    problem = _layout_problem(msg, MAX_POINTS)
    if problem:
        raise MeasurementError(f'station {station!r}: {problem}', 'layout')
    n = int(msg.width)
    if n == 0:
        raise MeasurementError(f'station {station!r}: message without points', 'no_points')
    endian = '>' if msg.is_bigendian else '<'
    names = [*fields, *(sigma_field(f) for f in fields)]
    formats = [f'{endian}f8'] * len(names)
    offsets = [by_name[nm].offset for nm in names]
    for extra, fmt in (('time_offset', 'f8'), ('target_id', 'u4')):
        if extra in by_name:
            names.append(extra)
            formats.append(endian + fmt)
            offsets.append(by_name[extra].offset)
    dtype = np.dtype(
        {'names': names, 'formats': formats, 'offsets': offsets, 'itemsize': msg.point_step}
    )
    return station, fields, dtype


def _points(
    station: str, fields: tuple[str, ...], arr: np.ndarray, t0: FloatArray, messages: int = 1
) -> MeasurementBatch:
    """The point-level checks and rows of decoded points ``arr`` whose messages were
    stamped ``t0`` (per point, TimeBase seconds)."""
    n = arr.shape[0]
    names = arr.dtype.names or ()
    values = np.stack([arr[f].astype(np.float64) for f in fields], axis=1)
    sigmas = np.stack([arr[sigma_field(f)].astype(np.float64) for f in fields], axis=1)
    offs = arr['time_offset'].astype(np.float64) if 'time_offset' in names else np.zeros(n)
    tids = arr['target_id'].astype(np.uint32) if 'target_id' in names else np.zeros(n, np.uint32)
    reasons: Counter[str] = Counter()
    bad = ~(np.abs(offs) <= MAX_TIME_OFFSET_S)  # NaN included
    if np.any(bad):
        reasons['time_offset_out_of_range'] = int(bad.sum())
    bad_id = (tids > MAX_TARGET_ID) & ~bad
    if np.any(bad_id):
        reasons['target_id_out_of_range'] = int(bad_id.sum())
        bad |= bad_id
    rest = np.flatnonzero(~bad)
    implausible, why = implausible_rows(fields, values[rest], sigmas[rest])
    bad[rest[implausible]] = True
    reasons.update(why)
    empty = ~np.any(~np.isnan(values), axis=1) & ~bad
    if np.any(empty):
        reasons['no_value'] = int(empty.sum())
    keep = ~bad & ~empty
    return MeasurementBatch(
        station_id=station,
        fields=fields,
        time=t0[keep] + offs[keep],
        target_id=tids[keep],
        values=values[keep],
        sigmas=sigmas[keep],
        rejected=int(np.count_nonzero(bad)),
        reasons=reasons,
        messages=messages,
    )
