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
    _layout_problem,
    _pack_cloud,
)
from orbit_tracking.ros.conversions.time import TimeBase, checked_stamp_ns

__all__ = ['MeasurementBatch', 'cloud_to_measurements', 'measurements_to_cloud']


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
    """

    station_id: str
    fields: tuple[str, ...]
    time: FloatArray
    target_id: NDArray[np.uint32]
    values: FloatArray
    sigmas: FloatArray
    rejected: int
    reasons: Counter[str] = field(default_factory=Counter)


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
    return _pack_cloud(arr, int(ns[0]), station_id)


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
    station = msg.header.frame_id
    try:
        checked_stamp_ns(msg.header.stamp)
    except ValueError as exc:
        raise MeasurementError(f'station {station!r}: {exc}', 'stamp') from None
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
    arr = np.frombuffer(bytes(msg.data), dtype=dtype, count=n)
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
    t0 = timebase.to_seconds(msg.header.stamp)
    return MeasurementBatch(
        station_id=station,
        fields=fields,
        time=t0 + offs[keep],
        target_id=tids[keep],
        values=values[keep],
        sigmas=sigmas[keep],
        rejected=int(np.count_nonzero(bad)),
        reasons=reasons,
    )
