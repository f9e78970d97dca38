"""Column tables of what stations and vehicles report: measurements, station states and
target states (truth or telemetry).

These are the types every data path shares (the simulator fills them, the message
conversions and bag readers fill them from real data); they depend on the measurement
models only, never on the simulator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.models.measurements import StationPose

__all__ = ['MeasurementTable', 'StationStates', 'TargetStates']

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class MeasurementTable:
    """One station's measurements: one row per (epoch, target) point.

    Attributes
    ----------
    station_id, kind : str
    fields : tuple of str
        Value fields, the column order of ``values`` and ``sigmas``.
    time : ndarray, shape (n,)
        Measurement epochs, scenario seconds, non-decreasing.
    target_id : ndarray of uint32, shape (n,)
    values : ndarray, shape (n, k)
        Measured values; NaN where a field was not measured at that epoch.
    sigmas : ndarray, shape (n, k)
        One-sigma noise of each value.
    """

    station_id: str
    kind: str
    fields: tuple[str, ...]
    time: FloatArray
    target_id: NDArray[np.uint32]
    values: FloatArray
    sigmas: FloatArray

    def __len__(self) -> int:
        return int(self.time.shape[0])

    def select(self, mask: NDArray[np.bool_]) -> MeasurementTable:
        return MeasurementTable(
            self.station_id,
            self.kind,
            self.fields,
            self.time[mask],
            self.target_id[mask],
            self.values[mask],
            self.sigmas[mask],
        )


@dataclass(frozen=True)
class StationStates:
    """Station origin, velocity and attitude at a series of epochs (world frame).

    ``angular_velocity`` is in the station frame (as ``nav_msgs/Odometry`` twist).
    A fixed station has one row.
    """

    station_id: str
    moving: bool
    time: FloatArray
    position: FloatArray
    velocity: FloatArray
    rotation: FloatArray
    angular_velocity: FloatArray

    def pose(self) -> StationPose:
        return StationPose(self.position, self.velocity, self.rotation)

    def __len__(self) -> int:
        return int(self.time.shape[0])


@dataclass(frozen=True)
class TargetStates:
    """Position and velocity of a target (truth or telemetry) with 1-sigma errors."""

    target_id: int
    time: FloatArray
    position: FloatArray
    velocity: FloatArray
    position_sigma: FloatArray
    velocity_sigma: FloatArray

    def __len__(self) -> int:
        return int(self.time.shape[0])
