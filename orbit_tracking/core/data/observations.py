"""What the estimator is given: station measurements with the station pose of every row,
on-board telemetry and triangulated fixes, cut to a time window.

The live node builds an :class:`Observations` from its buffers, the offline tool from a
bag, the benchmarks straight from a simulation run (:meth:`Observations.from_simulation`
takes anything with its three tables, so this module does not depend on the simulator).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.data.tables import MeasurementTable, StationStates, TargetStates
from orbit_tracking.core.models.measurements import StationPose

__all__ = [
    'FixSeries',
    'Observations',
    'RecordedTables',
    'StationObservations',
    'pose_at',
    'states_pose',
]

FloatArray = NDArray[np.float64]


class RecordedTables(Protocol):
    """What :meth:`Observations.from_simulation` reads: the measurement table and the
    states of every station, and the telemetry of every target (a
    :class:`~orbit_tracking.core.sim.simulator.SimulationResult` is one)."""

    @property
    def measurements(self) -> Mapping[str, MeasurementTable]: ...

    @property
    def station_states(self) -> Mapping[str, StationStates]: ...

    @property
    def telemetry(self) -> Mapping[int, TargetStates]: ...


@dataclass(frozen=True)
class StationObservations:
    """One station's measurement rows and its pose at each row's epoch."""

    table: MeasurementTable
    pose: StationPose

    def __post_init__(self) -> None:
        if len(self.pose) != len(self.table):
            raise ValueError(
                f'station {self.table.station_id}: {len(self.table)} measurement rows but '
                f'{len(self.pose)} poses'
            )

    def select(self, mask: NDArray[np.bool_]) -> StationObservations:
        return StationObservations(self.table.select(mask), self.pose.take(np.flatnonzero(mask)))


@dataclass(frozen=True)
class FixSeries:
    """Position fixes of one target: time (n,), position (n, 3), covariance (n, 3, 3)."""

    target_id: int
    time: FloatArray
    position: FloatArray
    covariance: FloatArray

    def __len__(self) -> int:
        return int(self.time.shape[0])

    def select(self, mask: NDArray[np.bool_]) -> FixSeries:
        return FixSeries(
            self.target_id, self.time[mask], self.position[mask], self.covariance[mask]
        )


def _cut_states(s: TargetStates, mask: NDArray[np.bool_]) -> TargetStates:
    return TargetStates(
        s.target_id,
        s.time[mask],
        s.position[mask],
        s.velocity[mask],
        s.position_sigma[mask],
        s.velocity_sigma[mask],
    )


def _span(
    times: Iterable[NDArray[np.float64]], t0: float = -math.inf, t1: float = math.inf
) -> tuple[float, float]:
    """Earliest and latest of ``times`` in [t0, t1]; (nan, nan) if none is."""
    lo, hi = math.inf, -math.inf
    for t in times:
        t = t[(t >= t0) & (t <= t1)]
        if t.size:
            lo, hi = min(lo, float(t.min())), max(hi, float(t.max()))
    return (lo, hi) if lo <= hi else (math.nan, math.nan)


@dataclass(frozen=True)
class Observations:
    """Everything measured about the targets (times in scenario / TimeBase seconds).

    Attributes
    ----------
    stations : tuple of StationObservations
    telemetry : mapping of target id to TargetStates
        On-board position and velocity with their reported 1-sigma.
    fixes : mapping of target id to FixSeries
    """

    stations: tuple[StationObservations, ...]
    telemetry: Mapping[int, TargetStates] = field(default_factory=dict)
    fixes: Mapping[int, FixSeries] = field(default_factory=dict)

    @property
    def target_ids(self) -> list[int]:
        ids: set[int] = set(self.telemetry) | set(self.fixes)
        for s in self.stations:
            ids |= {int(i) for i in np.unique(s.table.target_id)}
        return sorted(ids)

    def measured_span(self, t0: float = -math.inf, t1: float = math.inf) -> tuple[float, float]:
        """Earliest and latest epoch in [t0, t1] of any station row or telemetry sample:
        what the estimator fits to (fixes only start it). (nan, nan) if there is none."""
        tel = [v.time for v in self.telemetry.values()]
        return _span([*(s.table.time for s in self.stations), *tel], t0, t1)

    def window(self, t0: float, t1: float) -> Observations:
        """Rows with ``t0 <= t <= t1``."""
        st = []
        for s in self.stations:
            m = (s.table.time >= t0) & (s.table.time <= t1)
            if np.any(m):
                st.append(s.select(m))
        tel = {
            k: _cut_states(v, (v.time >= t0) & (v.time <= t1)) for k, v in self.telemetry.items()
        }
        fx = {k: v.select((v.time >= t0) & (v.time <= t1)) for k, v in self.fixes.items()}
        return Observations(
            tuple(st),
            {k: v for k, v in tel.items() if len(v)},
            {k: v for k, v in fx.items() if len(v)},
        )

    def without_telemetry(self) -> Observations:
        return Observations(self.stations, {}, self.fixes)

    @classmethod
    def from_simulation(
        cls, result: RecordedTables, fixes: Mapping[int, FixSeries] | None = None
    ) -> Observations:
        """Observations of a simulation run (station poses interpolated per row)."""
        stations = []
        for sid, table in result.measurements.items():
            if not len(table):
                continue
            states = result.station_states[sid]
            stations.append(StationObservations(table, pose_at(states_pose(states), table.time)))
        return cls(tuple(stations), dict(result.telemetry), dict(fixes or {}))


@dataclass(frozen=True)
class _Poses:
    time: FloatArray
    pose: StationPose
    moving: bool


def states_pose(states: StationStates) -> _Poses:
    """Pose samples of a :class:`~orbit_tracking.core.data.tables.StationStates`."""
    return _Poses(np.asarray(states.time), states.pose(), bool(states.moving))


def pose_at(poses: _Poses, t: FloatArray) -> StationPose:
    """Station pose at epochs ``t``: the single pose of a fixed station, else Hermite
    position and normalised-linear attitude between the two bracketing samples (the
    samples come at the measurement rate, so the attitude step is tiny)."""
    m = t.shape[0]
    p = poses.pose
    if not poses.moving or len(p) == 1:
        return StationPose.fixed(p.position[0], p.rotation[0], m)
    ts = poses.time
    i = np.clip(np.searchsorted(ts, t, side='right') - 1, 0, ts.size - 2)
    h = ts[i + 1] - ts[i]
    s = np.clip((t - ts[i]) / h, 0.0, 1.0)
    h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
    h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
    pos = (
        h00[:, None] * p.position[i]
        + (h10 * h)[:, None] * p.velocity[i]
        + h01[:, None] * p.position[i + 1]
        + (h11 * h)[:, None] * p.velocity[i + 1]
    )
    vel = (1 - s)[:, None] * p.velocity[i] + s[:, None] * p.velocity[i + 1]
    rot = (1 - s)[:, None, None] * p.rotation[i] + s[:, None, None] * p.rotation[i + 1]
    u, _, vt = np.linalg.svd(rot)
    return StationPose(pos, vel, u @ vt)
