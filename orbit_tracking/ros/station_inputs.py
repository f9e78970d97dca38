"""Station inputs shared by the processing nodes (triangulation, estimator).

A node that mixes in :class:`StationInputs` subscribes to ``stations/<id>/measurements``
of the stations it is given (or of every station whose topic appears), and to each
station's ``stations/<id>/state`` once that topic's publisher is known, with a reader
durability matched to it (a transient-local reader does not match a volatile writer).
It validates station states (id and world frame consistent) and owns the node's time
base and world frame.

It also watches time: a stamp more than ``time_reset_tolerance`` seconds older than the
newest one of the same stream (a station's measurements, a moving station's states, or a
stream the node adds) means the source started again (a bag replayed in a loop, a
restarted simulator). The node then resets once (``_on_time_reset``: publish what it holds,
clear buffers and windows), logs one line and counts ``time_resets``; fixed-station states
are given back to it. The other streams join the new time line as their stamps go back
too; until then what they still deliver from the old one is dropped
(``stale_after_reset``).

And it tells a late stream from a quiet one (:meth:`StationInputs._delivering`). Topics
are read one message at a time each, so while the node is busy (a window solve) one
topic's queue can fall seconds of data time behind another's; its data are late, not
missing, and processing must wait for them, so that results depend on the stamps and not
on arrival times. A stream counts as quiet (a dropout, the end of the data) only once the
node has waited ``silent_after`` seconds for data without hearing from it; time the node
spent working does not count as waiting.
"""

from __future__ import annotations

import re
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from orbit_tracking.core.errors import MeasurementError
from orbit_tracking.core.time import format_stamp
from orbit_tracking.ros import qos
from orbit_tracking.ros.conversions import (
    MeasurementBatch,
    StationStateSample,
    TimeBase,
    cloud_to_measurements,
    odometry_to_station_state,
    stamp_ns,
)
from orbit_tracking.ros.parameters import declare

__all__ = ['StationInputs']

_STATION_TOPIC = re.compile(r'^/stations/([A-Za-z][A-Za-z0-9_]*)/measurements$')


class StationInputs(Node):
    """Mixin base of a node fed by station topics.

    Subclasses implement ``_add_measurements(sid, batch)`` (a decoded, validated message),
    ``_add_pose(sid, state)``, ``_reject(key, text)`` and ``_on_time_reset()``, keep a
    ``counts`` Counter, and call :meth:`_start_station_inputs` from ``__init__``.
    """

    timebase: TimeBase | None
    world_frame: str
    station_filter: list[str]
    subs: dict[str, Any]
    state_subs: dict[str, Any]
    counts: Counter[str]

    def _declare_station_filter(self) -> list[str]:
        """The ``stations`` parameter: station ids to use (empty = every one that appears)."""
        ids = declare(
            self,
            'stations',
            [''],
            'Station ids to use; [""] uses every station that appears.',
            read_only=True,
        )
        return [s for s in ids if s]

    def _start_station_inputs(self, station_filter: list[str], time_reference: float) -> None:
        self.station_filter = station_filter
        self.timebase = TimeBase.from_seconds(time_reference) if time_reference > 0.0 else None
        self.world_frame = ''
        self.subs = {}
        self.state_subs = {}
        self.time_reset_tolerance = declare(
            self,
            'time_reset_tolerance',
            5.0,
            'A stamp this many seconds older than the newest of its stream (a bag replayed '
            'in a loop, a restarted source) resets the node: held data are published, '
            'buffers and windows cleared.',
            read_only=True,
            min_value=0.01,
            max_value=1e9,
        )
        self.silent_after = declare(
            self,
            'silent_after',
            2.0,
            'Wall seconds the node waits for data without hearing from a stream (a '
            "station's measurements or states, telemetry, fixes) before it stops holding "
            'fixes and windows back for it; a stream that still delivers, however late, '
            'is waited for.',
            read_only=True,
            min_value=0.1,
            max_value=3600.0,
        )
        self._heard: dict[str, float] = {}  # stream -> idle clock at its last message
        self._busy_s = 0.0
        self._busy_since: float | None = None
        self._streams: dict[str, tuple[int, int]] = {}  # stream -> (generation, newest ns)
        self._generation = 0
        self._generation_newest: int | None = None
        self._fixed_states: dict[str, StationStateSample] = {}
        for sid in station_filter:
            self._subscribe(sid)
        self.create_timer(0.5, self._discover)
        self._discover()

    def _stations_text(self) -> str:
        return (
            f'stations {self.station_filter}'
            if self.station_filter
            else 'every station that appears'
        )

    def _discover(self) -> None:
        """Subscribe to stations as their topics appear (all, or those listed), and to each
        station's state once its publisher is known, with a matching durability."""
        ns = self.get_namespace().rstrip('/')
        if not self.station_filter:
            for topic, _types in self.get_topic_names_and_types():
                m = _STATION_TOPIC.match(topic[len(ns) :]) if topic.startswith(ns + '/') else None
                if m and m.group(1) not in self.subs:
                    self._subscribe(m.group(1))
        for sid in self.subs:
            if sid in self.state_subs:
                continue
            topic = f'{ns}/stations/{sid}/state'
            profile = qos.matching_reader(self.get_publishers_info_by_topic(topic))
            if profile is not None:
                self.state_subs[sid] = self.create_subscription(
                    Odometry, topic, lambda m, s=sid: self._on_state(m, s), profile
                )

    def _subscribe(self, sid: str) -> None:
        self.subs[sid] = self.create_subscription(
            PointCloud2,
            f'stations/{sid}/measurements',
            lambda m, s=sid: self._on_measurements(m, s),
            qos.MEASUREMENTS_SUB,
        )
        self.get_logger().info(f'subscribed to station {sid}')

    def _timebase(self, stamp_ns_: int) -> TimeBase:
        if self.timebase is None:
            self.timebase = TimeBase.whole_second_of(stamp_ns_)
        return self.timebase

    def _on_state(self, msg: Odometry, sid: str) -> None:
        tb = self._timebase(stamp_ns(msg.header.stamp))
        try:
            st = odometry_to_station_state(msg, tb)
        except ValueError as exc:
            self._reject('invalid_state', f'station state rejected: {exc}')
            return
        if st.station_id != sid:
            self._reject(
                'station_mismatch',
                f'state on stations/{sid}/state names station {st.station_id!r}; ignored',
            )
            return
        if self.world_frame and msg.header.frame_id != self.world_frame:
            self._reject(
                'frame_mismatch',
                f'station {sid} state in frame {msg.header.frame_id!r}, '
                f'expected {self.world_frame!r}',
            )
            return
        if st.moving and not self._in_time(f'{sid}/state', stamp_ns(msg.header.stamp)):
            return
        if not st.moving:  # given back to the node after a time reset
            self._fixed_states[sid] = st
        self.world_frame = msg.header.frame_id
        self._add_pose(sid, st)

    def _on_measurements(self, msg: PointCloud2, sid: str) -> None:
        self.counts['measurement_messages'] += 1
        self.counts['measurements_received'] += msg.width * msg.height
        tb = self._timebase(stamp_ns(msg.header.stamp))
        try:
            batch = cloud_to_measurements(msg, tb)
        except MeasurementError as exc:
            self._reject('invalid_messages', f'measurement message rejected: {exc}')
            return
        if batch.rejected:
            self.counts['rejected_points'] += batch.rejected
        if batch.station_id != sid:
            self._reject(
                'station_mismatch',
                f'message on stations/{sid}/measurements has frame_id {batch.station_id!r}; '
                'ignored',
            )
            return
        if not self._in_time(sid, stamp_ns(msg.header.stamp)):
            return
        self._add_measurements(sid, batch)

    # -- late or quiet streams -------------------------------------------------------
    @contextmanager
    def _working(self) -> Iterator[None]:
        """Mark heavy work (a solve): messages queue meanwhile, which is not silence."""
        if self._busy_since is not None:  # nested
            yield
            return
        self._busy_since = time.monotonic()
        try:
            yield
        finally:
            self._busy_s += time.monotonic() - self._busy_since
            self._busy_since = None

    def _idle_clock(self) -> float:
        """Wall time [s] not spent in :meth:`_working` blocks."""
        now = time.monotonic() if self._busy_since is None else self._busy_since
        return now - self._busy_s

    def _delivering(self) -> dict[str, float]:
        """Streams heard within ``silent_after`` seconds of waiting, each with the newest
        stamp received on it (internal seconds). Stream names: a station id (its
        measurements), ``<id>/state`` (a moving station's states), or a name the node
        gave to :meth:`_in_time` (``telemetry``, ``fixes``)."""
        if self.timebase is None:
            return {}
        now = self._idle_clock()
        ref = self.timebase.ref_ns
        return {
            stream: (self._streams[stream][1] - ref) * 1e-9
            for stream, heard in self._heard.items()
            if now - heard <= self.silent_after and self._streams[stream][0] == self._generation
        }

    # -- time going back ------------------------------------------------------------
    def _in_time(self, stream: str, stamp: int) -> bool:
        """Whether a message of ``stream`` stamped ``stamp`` [ns] is to be used, after
        resetting the node if it starts a new time line (see the module docstring).

        Each stream is compared with itself: messages of one topic arrive in order, while
        different topics may lag each other by a queue's worth.
        """
        tol = int(self.time_reset_tolerance * 1e9)
        gen, newest = self._streams.get(stream, (self._generation, stamp))
        if stamp < newest - tol:
            if gen == self._generation:  # the first stream to go back: a new time line
                self._time_reset(stream, newest, stamp)
            gen, newest = self._generation, stamp
        elif gen != self._generation:
            ref = self._generation_newest
            if ref is not None and stamp > ref + tol:  # still the old time line
                self.counts['stale_after_reset'] += 1
                return False
            gen = self._generation
        self._streams[stream] = (gen, max(newest, stamp))
        self._heard[stream] = self._idle_clock()
        ref = self._generation_newest
        self._generation_newest = stamp if ref is None else max(ref, stamp)
        return True

    def _time_reset(self, stream: str, newest: int, stamp: int) -> None:
        self._generation += 1
        self._generation_newest = None
        self.counts['time_resets'] += 1
        done = self._on_time_reset()
        for sid, st in self._fixed_states.items():
            self._add_pose(sid, st)
        self.get_logger().warning(
            f'time went back {(newest - stamp) * 1e-9:.3f} s on {stream} (to stamp '
            f'{format_stamp(stamp, 0.0)}): reset #{self.counts["time_resets"]}, {done}, '
            'buffers cleared'
        )

    # -- implemented by the node ----------------------------------------------------
    def _add_measurements(self, sid: str, batch: MeasurementBatch) -> None:
        raise NotImplementedError

    def _add_pose(self, sid: str, state: StationStateSample) -> None:
        raise NotImplementedError

    def _reject(self, key: str, text: str) -> None:
        raise NotImplementedError

    def _on_time_reset(self) -> str:
        """Publish what is held, clear buffers and windows; say what was published."""
        raise NotImplementedError
