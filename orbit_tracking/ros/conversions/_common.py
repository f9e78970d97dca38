"""Private helpers shared by the conversion modules: the float array type and the
``PointField`` datatypes of cloud fields.

Not part of the package's interface: import from :mod:`orbit_tracking.ros.conversions`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from sensor_msgs.msg import PointField

__all__ = ['FloatArray', '_FLOAT64', '_UINT32', '_dt']

FloatArray = NDArray[np.float64]

_FLOAT64 = PointField.FLOAT64
_UINT32 = PointField.UINT32


def _dt(name: str) -> int:
    return _UINT32 if name == 'target_id' else _FLOAT64
