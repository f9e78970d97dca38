"""A bag player node: publishes a rosbag2's messages on their topics with the QoS the bag
recorded, at ``rate`` times the recorded pace (``ros2 bag play`` is not on PyPI).

Messages go out as the stored CDR bytes (no deserialisation). Topic names stored without
a leading slash resolve into the player's namespace, like those of the simulators.

With ``loop`` the bag starts again after its last message (time goes back: the processing
nodes reset). With ``clock`` the player also publishes ``/clock``
(``rosgraph_msgs/Clock``) with the bag's message stamps, read from the serialised
``header.stamp`` of every message type that begins with a header and interpolated between
messages by their recorded pace, never going back within one pass of the bag, so that
nodes run with ``use_sim_time:=true`` follow bag time.
"""

from __future__ import annotations

import fnmatch
import struct
import time
from collections.abc import Sequence
from pathlib import Path

from builtin_interfaces.msg import Time
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from rosbags.interfaces import Connection
from rosbags.rosbag2 import Reader
from rosgraph_msgs.msg import Clock

from orbit_tracking.ros import qos
from orbit_tracking.ros.bag import message_class
from orbit_tracking.ros.runner import StreamGate

__all__ = ['BagPlayerNode']

_DEFAULT_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1000,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)


def _profile(conn: object) -> QoSProfile:
    """The first offered QoS the bag recorded for a connection (reliable depth 1000 if none)."""
    profiles = getattr(getattr(conn, 'ext', None), 'offered_qos_profiles', None) or []
    if not profiles:
        return _DEFAULT_QOS
    q = profiles[0]
    latched = getattr(q.durability, 'name', '') == 'TRANSIENT_LOCAL'
    best_effort = getattr(q.reliability, 'name', '') == 'BEST_EFFORT'
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=max(int(q.depth), 1) if latched else max(int(q.depth), 1000),
        reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


def _has_header(msg_cls: type) -> bool:
    """Whether a message type's first field is a ``std_msgs/Header``."""
    fields = list(msg_cls.get_fields_and_field_types().items())  # type: ignore[attr-defined]
    return bool(fields) and fields[0] == ('header', 'std_msgs/Header')


def header_stamp_ns(raw: bytes) -> int | None:
    """``header.stamp`` [ns] of a CDR-serialised message that begins with a header (the
    stamp's ``int32 sec, uint32 nanosec`` follow the 4-byte encapsulation header)."""
    if len(raw) < 12:
        return None
    order = '<' if raw[1] & 1 else '>'  # CDR_LE = 0x0001, CDR_BE = 0x0000
    sec, nsec = struct.unpack_from(order + 'iI', raw, 4)
    return sec * 1_000_000_000 + nsec


class BagPlayerNode(Node):
    """Replay ``bag`` at ``rate`` times real time.

    Parameters
    ----------
    bag : path-like
        rosbag2 folder.
    rate : float
        Playback speed factor (> 0).
    patterns : sequence of str, optional
        fnmatch patterns of the topics to play (default all).
    wait_for_subscribers : int
        Before playing, wait (up to ``wait_timeout`` s) until every non-latched topic has
        this many subscribers.
    loop : bool
        Start again at the beginning after the last message (``done`` never completes).
    clock : bool
        Publish ``/clock`` with the message stamps (a ``/clock`` topic of the bag is then
        not played).
    """

    def __init__(
        self,
        bag: str | Path,
        rate: float = 1.0,
        patterns: Sequence[str] | None = None,
        wait_for_subscribers: int = 0,
        wait_timeout: float = 30.0,
        start_delay: float = 0.5,
        loop: bool = False,
        clock: bool = False,
    ) -> None:
        super().__init__('orbit_tracking_player')
        if not rate > 0.0:
            raise ValueError(f'rate must be positive; got {rate}')
        self.rate = rate
        self.done = Future()
        self._reader = Reader(Path(bag))
        self._reader.open()
        conns = [
            c
            for c in self._reader.connections
            if not patterns
            or any(
                fnmatch.fnmatch('/' + c.topic.lstrip('/'), '/' + p.lstrip('/')) for p in patterns
            )
        ]
        if clock:
            conns = [c for c in conns if '/' + c.topic.lstrip('/') != '/clock']
        if not conns:
            raise ValueError(f'no topic of {bag} matches {list(patterns or [])}')
        self.pubs: dict[int, Publisher] = {}
        self.latched: set[int] = set()
        self._stamped: set[int] = set()
        for c in conns:
            profile = _profile(c)
            if profile.durability == DurabilityPolicy.TRANSIENT_LOCAL:
                self.latched.add(c.id)
            cls = message_class(c.msgtype)
            if _has_header(cls):
                self._stamped.add(c.id)
            self.pubs[c.id] = self.create_publisher(cls, c.topic, profile)
        self._conns = conns
        self._messages = self._reader.messages(connections=conns)
        self._next: tuple[Connection, int, bytes] | None = next(self._messages, None)
        self._t0_log = self._next[1] if self._next else 0
        self.count = 0
        self.loop = loop
        self.loops = 0
        self.clock_pub = self.create_publisher(Clock, '/clock', qos.CLOCK) if clock else None
        self._clock_ns: int | None = None
        self._last_stamped: tuple[int, int] | None = None  # (log ns, stamp ns)
        self._gate = StreamGate(start_delay, wait_for_subscribers, wait_timeout)
        self._t0_wall: float | None = None
        self.get_logger().info(
            f'playing {len(conns)} topic(s) of {bag} at {rate:g}x '
            f'({self._reader.message_count} messages in the bag)'
            + (', in a loop' if loop else '')
            + (', publishing /clock' if clock else '')
        )
        self.timer = self.create_timer(0.005, self._tick)

    def _ready(self, now: float) -> bool:
        pubs = [p for cid, p in self.pubs.items() if cid not in self.latched]
        return self._gate.ready(now, pubs)

    def _tick(self) -> None:
        now = time.monotonic()
        if self._t0_wall is None:
            if not self._ready(now):
                return
            self._t0_wall = now
        due = self._t0_log + int((now - self._t0_wall) * self.rate * 1e9)
        while self._next is not None and self._next[1] <= due:
            conn, t_log, raw = self._next
            self.pubs[conn.id].publish(bytes(raw))
            self.count += 1
            cid = conn.id
            stamp = header_stamp_ns(raw) if self.clock_pub and cid in self._stamped else None
            if stamp is not None:
                self._last_stamped = (t_log, stamp)
                self._advance_clock(stamp)
            self._next = next(self._messages, None)
        if self.clock_pub is not None:
            self._tick_clock(due)
        if self._next is None and self.loop and self.count:
            self._restart(now)
        elif self._next is None and not self.done.done():
            self.get_logger().info(f'played {self.count} messages')
            self.done.set_result(True)
            self.timer.cancel()

    def _restart(self, now: float) -> None:
        """Back to the first message: the recorded pace and the clock start again."""
        self.loops += 1
        self._messages = self._reader.messages(connections=self._conns)
        self._next = next(self._messages, None)
        self._t0_wall = now
        self._clock_ns = None
        self._last_stamped = None
        self.get_logger().info(f'end of the bag after {self.count} messages: loop {self.loops}')

    def _advance_clock(self, stamp: int) -> None:
        if self.clock_pub is not None and (self._clock_ns is None or stamp > self._clock_ns):
            self._clock_ns = stamp
            t = Time(sec=stamp // 1_000_000_000, nanosec=stamp % 1_000_000_000)
            self.clock_pub.publish(Clock(clock=t))

    def _tick_clock(self, due: int) -> None:
        """Between messages, move the clock from the last stamp toward the next message's
        stamp at the recorded pace."""
        nxt, last = self._next, self._last_stamped
        if nxt is None or last is None or nxt[0].id not in self._stamped:
            return
        stamp = header_stamp_ns(nxt[2])
        if stamp is None or nxt[1] <= last[0]:
            return
        frac = min(max((due - last[0]) / (nxt[1] - last[0]), 0.0), 1.0)
        self._advance_clock(last[1] + int(frac * (stamp - last[1])))

    def close(self) -> None:
        self._reader.close()
