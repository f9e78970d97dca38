"""Station inputs shared by the processing nodes (triangulation, estimator).

A node that mixes in :class:`StationInputs` subscribes to ``stations/<id>/measurements``
of the stations it is given (or of every station whose topic appears), and to each
station's ``stations/<id>/state`` once that topic's publisher is known, with a reader
durability matched to it (a transient-local reader does not match a volatile writer).
It validates station states (id and world frame consistent) and owns the node's time
base and world frame.

It also watches time: a stamp more than ``time_reset_tolerance`` seconds older than the
newest one of the same stream (a station's measurements, a moving station's states, or a
stream the node adds) may mean the source started again (a bag replayed in a loop, a
restarted simulator). One voice is not evidence: a stream that goes back is *held* (its
messages kept, unused) until more than half of the active streams (those heard within
``silent_after`` of the last of them heard, so a pause changes nothing, plus those held)
have gone back too; then the node resets once
(``_on_time_reset``: publish what it holds, clear buffers and windows), logs one line,
counts ``time_resets`` and processes the held messages on the new time line; fixed-station
states are given back to it. A lone stream that goes back while the others go on (a broken
clock, a hostile publisher) only loses its own data: when it returns to the common time
line, or holds more than ``_MAX_HELD`` messages, what it held is dropped and counted
(``time_back_unconfirmed``). Every message held is counted at once too
(``time_back_held``, ``time_ahead_held``), so a jump shows in ``/diagnostics`` without
waiting ``silent_after``. With a single active stream, its going back is the majority.
After a reset, the other streams join the new time line as their stamps go back too; until
then what they still deliver from the old one is dropped (``stale_after_reset``). A stream
whose stamps run more than ``_MAX_LEAD_S`` (600 s) ahead of every other active stream is
held the same way: taken (without a reset) once most streams are there too, else dropped
(``time_ahead_unconfirmed``), so one stamp years ahead cannot become the newest data time.
A new stream whose first stamp lies more than ``_MAX_LEAD_S`` before every active stream
counts as one that went back (held; dropped as ``time_back_unconfirmed`` unless most
streams follow it), so a station with its clock at 1970 is not taken on a time line of its
own.

Every message is checked at the boundary (stamp, layout, plausible values: see
:func:`~orbit_tracking.ros.conversions.cloud_to_measurements`); rejections are counted by
reason (``invalid_messages_<reason>``, ``rejected_points_<reason>``). At most
``max_targets`` distinct target ids are taken (first come); points of further ids are
dropped (``too_many_targets``), so a flood of ids cannot grow the node without bound; and
at most ``max_stations`` stations are subscribed to as their topics appear (further ones
are counted as ``too_many_stations``). No
callback can take the node down: an unexpected exception is logged with its traceback and
counted (``internal_error``).

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
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from typing import Any

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from orbit_tracking.core.errors import MeasurementError
from orbit_tracking.core.models.limits import TargetLimit
from orbit_tracking.core.time import format_stamp
from orbit_tracking.ros import qos
from orbit_tracking.ros.conversions import (
    MeasurementBatch,
    StationStateSample,
    TimeBase,
    checked_stamp_ns,
    cloud_to_measurements,
    odometry_to_station_state,
    read_message,
)
from orbit_tracking.ros.guard import guarded
from orbit_tracking.ros.parameters import declare

__all__ = ['StationInputs']

_STATION_TOPIC = re.compile(r'^/stations/([A-Za-z][A-Za-z0-9_]*)/measurements$')

_MAX_HELD = 2000
"""Messages a stream that jumped may hold while the node waits for the others."""

_MAX_LEAD_S = 600.0
"""Data seconds a stream may run ahead of every other active stream before its stamps
count as a jump (far more than one topic's queue can lead another's while the node is
busy)."""


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
            'A stamp this many seconds older than the newest of its stream means the stream '
            'went back; once most active streams have (a bag replayed in a loop, a restarted '
            'source) the node resets: held data are published, buffers and windows cleared. '
            'A stream going back alone only loses its own data.',
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
        self.max_targets = declare(
            self,
            'max_targets',
            32,
            'Distinct target ids the node takes (first come); points of further ids are '
            'dropped and counted (too_many_targets). Bounds the memory and publishers a '
            'flood of ids could create.',
            read_only=True,
            min_value=1,
            max_value=4096,
        )
        self.targets = TargetLimit(self.max_targets)
        self.max_stations = declare(
            self,
            'max_stations',
            128,
            'Stations the node subscribes to as their topics appear (when no stations are '
            'listed); the topics of further station ids are ignored and counted '
            '(too_many_stations). Bounds the subscriptions a flood of topics could create.',
            read_only=True,
            min_value=1,
            max_value=4096,
        )
        self._ignored_stations: set[str] = set()
        self._held: list[tuple[str, int, Callable[[], None]]] = []  # (stream, stamp, redo)
        # stream that jumped -> (its newest stamp on the new line, idle clock then, ahead)
        self._back: dict[str, tuple[int, float, bool]] = {}
        self._heard: dict[str, float] = {}  # stream -> idle clock at its last message
        self._busy_s = 0.0
        self._busy_since: float | None = None
        self._streams: dict[str, tuple[int, int]] = {}  # stream -> (generation, newest ns)
        self._generation = 0
        self._generation_newest: int | None = None
        self._fixed_states: dict[str, StationStateSample] = {}
        for sid in station_filter:
            self._subscribe(sid)
        self.create_timer(0.5, lambda: self._guarded('housekeeping', self._housekeeping))
        self._discover()

    def _stations_text(self) -> str:
        return (
            f'stations {self.station_filter}'
            if self.station_filter
            else 'every station that appears'
        )

    def _housekeeping(self) -> None:
        self._discover()
        self._check_reset()  # the streams still on the old line may have fallen quiet

    def _discover(self) -> None:
        """Subscribe to stations as their topics appear (all, or those listed), and to each
        station's state once its publisher is known, with a matching durability."""
        ns = self.get_namespace().rstrip('/')
        if not self.station_filter:
            for topic, _types in self.get_topic_names_and_types():
                m = _STATION_TOPIC.match(topic[len(ns) :]) if topic.startswith(ns + '/') else None
                sid = m.group(1) if m else None
                if sid is None or sid in self.subs or sid in self._ignored_stations:
                    continue
                if len(self.subs) < self.max_stations:
                    self._subscribe(sid)
                else:
                    self._ignored_stations.add(sid)
                    self._reject(
                        'too_many_stations',
                        f'station {sid[:80]!r} not subscribed: already max_stations = '
                        f'{self.max_stations} stations',
                    )
        for sid in self.subs:
            if sid in self.state_subs:
                continue
            topic = f'{ns}/stations/{sid}/state'
            profile = qos.matching_reader(self.get_publishers_info_by_topic(topic))
            if profile is not None:
                self.state_subs[sid] = self.create_subscription(
                    Odometry,
                    topic,
                    lambda m, s=sid: self._guarded('station state', self._on_state, m, s),
                    profile,
                )

    def _subscribe(self, sid: str) -> None:
        # raw: the bytes are read by conversions.read_message (no message object per point
        # batch; rclpy only for what the direct reader declines)
        self.subs[sid] = self.create_subscription(
            PointCloud2,
            f'stations/{sid}/measurements',
            lambda m, s=sid: self._guarded('measurements', self._on_measurements, m, s),
            qos.MEASUREMENTS_SUB,
            raw=True,
        )
        self.get_logger().info(f'subscribed to station {sid}')

    def _timebase(self, stamp_ns_: int) -> TimeBase:
        if self.timebase is None:
            self.timebase = TimeBase.whole_second_of(stamp_ns_)
        return self.timebase

    def _guarded(self, what: str, fn: Callable[..., object], *args: object) -> None:
        guarded(self, self.counts, what, fn, *args)

    def _stamp_of(self, msg: Any, what: str) -> int | None:
        """The checked stamp [ns] of an incoming message, or None (rejected, counted)."""
        try:
            return checked_stamp_ns(msg.header.stamp)
        except ValueError as exc:
            self._reject('invalid_stamp', f'{what} rejected: {exc}')
            return None

    def _on_state(self, msg: Odometry, sid: str) -> None:
        ns = self._stamp_of(msg, f'station {sid} state')
        if ns is None:
            return
        tb = self._timebase(ns)
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
        if st.moving and not self._in_time(
            f'{sid}/state', ns, lambda: self._use_state(msg, sid, st)
        ):
            return
        self._use_state(msg, sid, st)

    def _use_state(self, msg: Odometry, sid: str, st: StationStateSample) -> None:
        if not st.moving:  # given back to the node after a time reset
            self._fixed_states[sid] = st
        self.world_frame = msg.header.frame_id
        self._add_pose(sid, st)

    def _on_measurements(self, data: bytes | PointCloud2, sid: str) -> None:
        """One message of a station's measurements topic: its serialised bytes (the raw
        subscription) or, from in-process callers, the message itself."""
        self.counts['measurement_messages'] += 1
        try:
            msg = (
                read_message(data, 'sensor_msgs/msg/PointCloud2', PointCloud2)
                if isinstance(data, bytes | bytearray | memoryview)
                else data
            )
        except ValueError as exc:
            self.counts['invalid_messages_cdr'] += 1
            self._reject('invalid_messages', f'measurement message rejected: {exc}')
            return
        self.counts['measurements_received'] += int(msg.width) * int(msg.height)
        try:
            tb = self._timebase(checked_stamp_ns(msg.header.stamp))
            batch = cloud_to_measurements(msg, tb)
        except ValueError as exc:
            reason = exc.reason if isinstance(exc, MeasurementError) else 'stamp'
            self.counts[f'invalid_messages_{reason}'] += 1
            self._reject('invalid_messages', f'measurement message rejected: {exc}')
            return
        if batch.rejected:
            self.counts['rejected_points'] += batch.rejected
        for why, n in batch.reasons.items():
            self.counts[f'rejected_points_{why}'] += n
        if batch.station_id != sid:
            self._reject(
                'station_mismatch',
                f'message on stations/{sid}/measurements has frame_id {batch.station_id!r}; '
                'ignored',
            )
            return
        batch = self._admit_targets(batch)
        if batch.time.size == 0:
            return
        stamp = checked_stamp_ns(msg.header.stamp)
        if self._in_time(sid, stamp, lambda: self._add_measurements(sid, batch)):
            self._add_measurements(sid, batch)

    def _admit(self, ids: set[int]) -> bool:
        """Whether every target id in ``ids`` is admitted (``max_targets``, first come)."""
        return bool(np.all(self.targets.admit(sorted(ids))))

    def _admit_targets(self, batch: MeasurementBatch) -> MeasurementBatch:
        """Drop the points of target ids beyond the first ``max_targets`` seen."""
        keep = self.targets.admit(batch.target_id)
        if np.all(keep):
            return batch
        self._reject(
            'too_many_targets',
            f'station {batch.station_id}: {int((~keep).sum())} point(s) of target ids beyond '
            f'the first max_targets = {self.max_targets} dropped',
            int((~keep).sum()),
        )
        return replace(
            batch,
            time=batch.time[keep],
            target_id=batch.target_id[keep],
            values=batch.values[keep],
            sigmas=batch.sigmas[keep],
        )

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
        ref = self.timebase.ref_ns
        return {stream: (self._streams[stream][1] - ref) * 1e-9 for stream in self._active()}

    def _active(self) -> list[str]:
        """Streams of the current time line heard within ``silent_after`` of waiting."""
        now = self._idle_clock()
        return [
            stream
            for stream, heard in self._heard.items()
            if now - heard <= self.silent_after and self._streams[stream][0] == self._generation
        ]

    # -- time going back ------------------------------------------------------------
    def _quorum(self) -> list[str]:
        """The streams a jump is weighed against: those of the current time line that
        have not jumped and were heard within ``silent_after`` of the last one of them
        heard. While data flow these are the active streams; in a pause (between passes,
        a replay stopped) they are the streams active before it, so that a lone voice in
        a pause is still one voice among them, not the majority of an empty room."""
        heard = {
            s: t
            for s, t in self._heard.items()
            if s not in self._back and self._streams[s][0] == self._generation
        }
        if not heard:
            return []
        last = max(heard.values())
        return [s for s, t in heard.items() if last - t <= self.silent_after]

    def _in_time(self, stream: str, stamp: int, redo: Callable[[], None] | None = None) -> bool:
        """Whether a message of ``stream`` stamped ``stamp`` [ns] is to be used now (see the
        module docstring for the rule). A message of a stream that jumped off the common
        time line (back, or more than ``_MAX_LEAD_S`` ahead of every other active stream)
        is held (``redo`` runs it once most streams confirm the jump) and False returned.

        Each stream is compared with itself: messages of one topic arrive in order, while
        different topics may lag each other by a queue's worth.
        """
        tol = int(self.time_reset_tolerance * 1e9)
        gen, newest = self._streams.get(stream, (self._generation, stamp))
        if gen == self._generation:
            back = stamp < newest - tol or (stream not in self._streams and self._behind(stamp))
            ahead = not back and self._ahead(stream, stamp)
            if back or ahead:
                self._hold(stream, stamp, redo, ahead)
                return False
            if stream in self._back:  # back on the common time line: it was a lone voice
                self._drop_held(stream)
        else:
            ref = self._generation_newest
            if ref is not None and stamp > ref + tol:  # still the old time line
                self.counts['stale_after_reset'] += 1
                return False
        self._accept(stream, stamp)
        return True

    def _accept(self, stream: str, stamp: int) -> None:
        gen, newest = self._streams.get(stream, (self._generation, stamp))
        if gen != self._generation:
            newest = stamp
        self._streams[stream] = (self._generation, max(newest, stamp))
        self._heard[stream] = self._idle_clock()
        ref = self._generation_newest
        self._generation_newest = stamp if ref is None else max(ref, stamp)

    def _ahead(self, stream: str, stamp: int) -> bool:
        """Whether ``stamp`` lies more than ``_MAX_LEAD_S`` past the newest stamp of every
        other active stream (a clock set years ahead, a hostile stamp)."""
        others = [self._streams[s][1] for s in self._quorum() if s != stream]
        return bool(others) and stamp > max(others) + int(_MAX_LEAD_S * 1e9)

    def _behind(self, stamp: int) -> bool:
        """Whether the first stamp of a new stream lies more than ``_MAX_LEAD_S`` before
        the newest stamp of every active stream: it starts behind the common time line, as
        if it had gone back (a clock at 1970, a replay started while another runs)."""
        others = [self._streams[s][1] for s in self._quorum()]
        return bool(others) and stamp < min(others) - int(_MAX_LEAD_S * 1e9)

    def _hold(self, stream: str, stamp: int, redo: Callable[[], None] | None, ahead: bool) -> None:
        way = 'ahead' if ahead else 'back'
        self.counts[f'time_{way}_held'] += 1  # seen at once, whatever becomes of it
        if stream not in self._back:
            newest = self._streams.get(stream, (0, self._generation_newest or stamp))[1]
            self.get_logger().warning(
                f'stream {stream} jumped {way} in time by {abs(stamp - newest) * 1e-9:.3f} s '
                f'(to stamp {format_stamp(stamp, 0.0)}): its messages are held until most '
                f'streams follow it, else dropped when it returns or falls quiet '
                f'({self.counts[f"time_{way}_held"]} held so far)',
                throttle_duration_sec=5.0,
            )
        last = self._back.get(stream, (stamp, 0.0, ahead))[0]
        self._back[stream] = (max(last, stamp), self._idle_clock(), ahead)
        if redo is not None:
            self._held.append((stream, stamp, redo))
            if sum(1 for h in self._held if h[0] == stream) > _MAX_HELD:
                self._drop_held(stream)
                return
        self._check_reset()

    def _drop_held(self, stream: str) -> None:
        """A stream that jumped alone: forget that and drop what it held."""
        _, _, ahead = self._back.pop(stream)
        dropped = sum(1 for h in self._held if h[0] == stream)
        self._held = [h for h in self._held if h[0] != stream]
        self._reject(
            'time_ahead_unconfirmed' if ahead else 'time_back_unconfirmed',
            f'stream {stream} jumped {"ahead" if ahead else "back"} in time while most '
            f'others did not: {dropped} of its messages dropped',
            max(dropped, 1),
        )

    def _check_reset(self) -> None:
        """Once more than half of the active streams have jumped, take the new time line:
        reset if they went back, carry on if they went ahead; a stream that jumped and then
        fell quiet for ``silent_after`` no longer counts."""
        now = self._idle_clock()
        for stream in [k for k, v in self._back.items() if now - v[1] > self.silent_after]:
            self._drop_held(stream)
        if not self._back:
            return
        active = set(self._quorum()) | set(self._back)
        if 2 * len(self._back) <= len(active):
            return
        back, held = self._back, self._held
        self._back, self._held = {}, []
        if all(v[2] for v in back.values()):  # ahead together: a later time line, no reset
            for stream, stamp, redo in held:
                self._accept(stream, stamp)
                redo()
            return
        first = min(back, key=lambda k: back[k][0])
        newest = self._streams[first][1] if first in self._streams else self._generation_newest
        self._time_reset(first, back[first][0] if newest is None else newest, back[first][0])
        for stream in back:
            starts = [h[1] for h in held if h[0] == stream] or [back[stream][0]]
            self._streams[stream] = (self._generation, min(starts))
        for stream, stamp, redo in held:
            if self._in_time(stream, stamp):
                redo()

    def _time_reset(self, stream: str, newest: int, stamp: int) -> None:
        self._generation += 1
        self._generation_newest = None
        self.counts['time_resets'] += 1
        done = self._on_time_reset()
        for sid, st in self._fixed_states.items():
            self._add_pose(sid, st)
        self.get_logger().warning(
            f'time went back {(newest - stamp) * 1e-9:.3f} s on {stream} and most active '
            f'streams (to stamp {format_stamp(stamp, 0.0)}): reset '
            f'#{self.counts["time_resets"]}, {done}, buffers cleared'
        )

    # -- implemented by the node ----------------------------------------------------
    def _add_measurements(self, sid: str, batch: MeasurementBatch) -> None:
        raise NotImplementedError

    def _add_pose(self, sid: str, state: StationStateSample) -> None:
        raise NotImplementedError

    def _reject(self, key: str, text: str, n: int = 1) -> None:
        """Count ``n`` rejections under ``key`` and log ``text`` (throttled)."""
        raise NotImplementedError

    def _on_time_reset(self) -> str:
        """Publish what is held, clear buffers and windows; say what was published."""
        raise NotImplementedError
