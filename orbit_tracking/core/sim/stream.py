"""Time-ordered event stream of a simulation, shared by the live simulators and the bag
writer so that a bag and a live run carry exactly the same messages.

An :class:`Event` names what to publish (a batch of measurement rows, a station state,
a telemetry or truth sample) and the scenario time at which it becomes available.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.data.tables import MeasurementTable
from orbit_tracking.core.sim.simulator import SimulationResult
from orbit_tracking.core.triangulation.alignment import Aligner
from orbit_tracking.core.triangulation.pipeline import TriangulationPipeline

__all__ = ['Event', 'EventKind', 'EventStream', 'batch_rows', 'feed_simulation']

EventKind = Literal['station_state', 'measurement', 'telemetry', 'truth']

# at equal times a station's state goes out before its measurements
_ORDER: dict[str, int] = {'station_state': 0, 'truth': 1, 'telemetry': 2, 'measurement': 3}


@dataclass(frozen=True)
class Event:
    """One message to emit.

    Attributes
    ----------
    time : float
        Scenario time at which the message is available [s] (for a measurement batch,
        the epoch of its last point).
    kind : str
        ``station_state``, ``measurement``, ``telemetry`` or ``truth``.
    key : str
        Station id, or the target id as a string.
    start, stop : int
        Row range in the source table (``stop - start == 1`` except for measurement
        batches).
    """

    time: float
    kind: EventKind
    key: str
    start: int
    stop: int


def batch_rows(time: NDArray[np.float64], batch_period: float) -> list[tuple[int, int]]:
    """Split sorted epochs into row ranges: each range holds the points of one epoch
    (``batch_period <= 0``) or of consecutive epochs spanning less than ``batch_period``.
    """
    n = time.shape[0]
    if n == 0:
        return []
    out = []
    i = 0
    while i < n:
        if batch_period > 0.0:
            j = int(np.searchsorted(time, time[i] + batch_period - 1e-9, side='left'))
        else:
            j = int(np.searchsorted(time, time[i], side='right'))
        j = max(j, i + 1)
        out.append((i, j))
        i = j
    return out


class EventStream:
    """All events of a simulation result in time order.

    Parameters
    ----------
    result : SimulationResult
    stations : sequence of str, optional
        Station ids to include (default all).
    batch_period : float
        Scenario seconds of epochs packed into one measurement message (0: one message
        per epoch). Batching keeps replay at many times real time lossless.
    telemetry, truth : bool
        Include telemetry / truth events.
    """

    def __init__(
        self,
        result: SimulationResult,
        stations: Sequence[str] | None = None,
        batch_period: float = 0.0,
        telemetry: bool = True,
        truth: bool = True,
    ) -> None:
        self.result = result
        ids = list(result.measurements) if stations is None else list(stations)
        unknown = [s for s in ids if s not in result.measurements]
        if unknown:
            raise KeyError(f'unknown station(s) {unknown}; known {list(result.measurements)}')
        events: list[Event] = []
        t0 = result.scenario.t_start
        for sid in ids:
            st = result.station_states[sid]
            if st.moving:
                events += [
                    Event(float(t), 'station_state', sid, i, i + 1) for i, t in enumerate(st.time)
                ]
            else:
                events.append(Event(t0, 'station_state', sid, 0, 1))
            table: MeasurementTable = result.measurements[sid]
            for a, b in batch_rows(table.time, batch_period):
                events.append(Event(float(table.time[b - 1]), 'measurement', sid, a, b))
        if telemetry:
            for tid, ts in result.telemetry.items():
                events += [
                    Event(float(t), 'telemetry', str(tid), i, i + 1) for i, t in enumerate(ts.time)
                ]
        if truth:
            for tid, ts in result.truth.items():
                events += [
                    Event(float(t), 'truth', str(tid), i, i + 1) for i, t in enumerate(ts.time)
                ]
        events.sort(key=lambda e: (e.time, _ORDER[e.kind], e.key, e.start))
        self.events = events
        self._times = np.array([e.time for e in events])
        self._next = 0

    def __len__(self) -> int:
        return len(self.events)

    def __iter__(self) -> Iterator[Event]:
        return iter(self.events)

    @property
    def done(self) -> bool:
        return self._next >= len(self.events)

    @property
    def next_time(self) -> float | None:
        return None if self.done else float(self._times[self._next])

    def until(self, t: float) -> list[Event]:
        """Events with time <= ``t`` not yet returned (advances the stream)."""
        j = int(np.searchsorted(self._times, t, side='right'))
        out = self.events[self._next : j]
        self._next = max(self._next, j)
        return out

    def reset(self) -> None:
        self._next = 0


def feed_simulation(sink: Aligner | TriangulationPipeline, result: SimulationResult) -> None:
    """Give every station state and measurement of a simulation to an aligner or pipeline
    (what the nodes receive over DDS, all at once)."""
    for sid, st in result.station_states.items():
        for i in range(len(st)):
            sink.add_pose(
                sid, st.time[i], st.position[i], st.velocity[i], st.rotation[i], st.moving
            )
    for sid, m in result.measurements.items():
        sink.add_measurements(sid, m.fields, m.time, m.target_id, m.values, m.sigmas)
