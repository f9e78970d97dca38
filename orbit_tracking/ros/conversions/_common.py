"""Private helpers shared by the conversion modules: the float array type, the
``PointField`` datatypes of cloud fields, and the packing of a structured array into a
``PointCloud2``.

Not part of the package's interface: import from :mod:`orbit_tracking.ros.conversions`.
"""

from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Time
from numpy.typing import NDArray
from sensor_msgs.msg import PointCloud2, PointField

__all__ = ['FloatArray', '_FLOAT64', '_UINT32', '_dt', '_layout_problem', '_pack_cloud']

FloatArray = NDArray[np.float64]

_FLOAT64 = PointField.FLOAT64
_UINT32 = PointField.UINT32


_SIZES = {1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 8: 8}
"""Bytes of each ``PointField`` datatype (INT8 .. FLOAT64)."""


def _dt(name: str) -> int:
    return _UINT32 if name == 'target_id' else _FLOAT64


def _layout_problem(msg: PointCloud2, max_points: int) -> str | None:
    """What is wrong with the byte layout of an incoming cloud, or None.

    The contract's layout: one row (``height`` 1), ``row_step = width * point_step``, exactly
    ``row_step`` data bytes (no extra or missing bytes), at most ``max_points`` points,
    unique field names, each field inside ``point_step``. Anything else is a broken or
    hostile writer; guessing what it meant could turn bytes into wrong values."""
    width, height, step = int(msg.width), int(msg.height), int(msg.point_step)
    if height != 1:
        return f'height must be 1 (one row of points); got {height}'
    if width > max_points:
        return f'{width} points in one message; at most {max_points} are accepted'
    if step <= 0:
        return f'point_step must be > 0; got {step}'
    if int(msg.row_step) != width * step:
        return f'row_step {msg.row_step} != width * point_step = {width * step}'
    if len(msg.data) != width * step:
        return f'data holds {len(msg.data)} bytes; width * point_step = {width * step}'
    names = [f.name for f in msg.fields]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        return f'duplicate field name(s) {dup}'
    for f in msg.fields:
        size = _SIZES.get(int(f.datatype), 8) * max(int(f.count), 1)
        if int(f.offset) < 0 or int(f.offset) + size > step:
            return f'field {f.name!r} lies beyond point_step'
    return None


def _pack_cloud(arr: np.ndarray, stamp_ns: int, frame_id: str) -> PointCloud2:
    """One-row (``height`` 1), little-endian, dense cloud of the structured array ``arr``:
    a ``PointField`` per dtype field at its offset, the stamp ``stamp_ns`` [ns]."""
    msg = PointCloud2()
    msg.header.stamp = Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
    msg.header.frame_id = frame_id
    msg.height = 1
    msg.width = arr.shape[0]
    dtype = arr.dtype
    msg.fields = [
        PointField(name=name, offset=int(dtype.fields[name][1]), datatype=_dt(name), count=1)
        for name in dtype.names
    ]
    msg.is_bigendian = False
    msg.point_step = dtype.itemsize
    msg.row_step = dtype.itemsize * arr.shape[0]
    msg.data = arr.tobytes()
    msg.is_dense = True
    return msg
