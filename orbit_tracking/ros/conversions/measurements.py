"""Measurement messages (``sensor_msgs/PointCloud2``) <-> measurement rows.

Layout (``docs/CONTRACT.md``): one point per (epoch, target), FLOAT64 value and
``sigma_<field>`` fields, ``time_offset`` (FLOAT64, s, only when the points have different
epochs) and ``target_id`` (UINT32), little-endian, ``height = 1``, dense;
``header.frame_id`` is the station id and ``header.stamp`` the first point's epoch.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from sensor_msgs.msg import PointCloud2

from orbit_tracking.core.errors import MeasurementError
from orbit_tracking.core.models.measurements import FIELDS, sigma_field
from orbit_tracking.ros.conversions._common import _FLOAT64, _UINT32, FloatArray, _pack_cloud
from orbit_tracking.ros.conversions.time import TimeBase

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
    return _pack_cloud(arr, int(ns[0]), station_id)


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
