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

__all__ = ['FloatArray', '_FLOAT64', '_UINT32', '_dt', '_pack_cloud']

FloatArray = NDArray[np.float64]

_FLOAT64 = PointField.FLOAT64
_UINT32 = PointField.UINT32


def _dt(name: str) -> int:
    return _UINT32 if name == 'target_id' else _FLOAT64


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
