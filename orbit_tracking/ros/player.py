"""A bag player node: publishes a rosbag2's messages on their topics with the QoS the bag
recorded, at ``rate`` times the recorded pace (``ros2 bag play`` is not on PyPI).

Messages go out as the stored CDR bytes (no deserialisation). Topic names stored without
a leading slash resolve into the player's namespace, like those of the simulators.
"""

from __future__ import annotations

import fnmatch
import time
from collections.abc import Sequence
from pathlib import Path

from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from rosbags.rosbag2 import Reader

from orbit_tracking.ros.bag import message_class
from orbit_tracking.ros.runner import ready_to_stream

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
    """

    def __init__(
        self,
        bag: str | Path,
        rate: float = 1.0,
        patterns: Sequence[str] | None = None,
        wait_for_subscribers: int = 0,
        wait_timeout: float = 30.0,
        start_delay: float = 0.5,
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
        if not conns:
            raise ValueError(f'no topic of {bag} matches {list(patterns or [])}')
        self.pubs: dict[int, Publisher] = {}
        self.latched: set[int] = set()
        for c in conns:
            profile = _profile(c)
            if profile.durability == DurabilityPolicy.TRANSIENT_LOCAL:
                self.latched.add(c.id)
            self.pubs[c.id] = self.create_publisher(message_class(c.msgtype), c.topic, profile)
        self._messages = self._reader.messages(connections=conns)
        self._next: tuple[object, int, bytes] | None = next(self._messages, None)
        self._t0_log = self._next[1] if self._next else 0
        self.count = 0
        self.wait_for_subscribers = wait_for_subscribers
        self.wait_timeout = wait_timeout
        self.start_delay = start_delay
        self._created = time.monotonic()
        self._t0_wall: float | None = None
        self.get_logger().info(
            f'playing {len(conns)} topic(s) of {bag} at {rate:g}x '
            f'({self._reader.message_count} messages in the bag)'
        )
        self.timer = self.create_timer(0.005, self._tick)

    def _ready(self, now: float) -> bool:
        pubs = [p for cid, p in self.pubs.items() if cid not in self.latched]
        return ready_to_stream(
            now - self._created,
            self.start_delay,
            self.wait_for_subscribers,
            self.wait_timeout,
            pubs,
        )

    def _tick(self) -> None:
        now = time.monotonic()
        if self._t0_wall is None:
            if not self._ready(now):
                return
            self._t0_wall = now
        due = self._t0_log + int((now - self._t0_wall) * self.rate * 1e9)
        while self._next is not None and self._next[1] <= due:
            conn, _t, raw = self._next
            self.pubs[conn.id].publish(bytes(raw))  # type: ignore[attr-defined]
            self.count += 1
            self._next = next(self._messages, None)
        if self._next is None and not self.done.done():
            self.get_logger().info(f'played {self.count} messages')
            self.done.set_result(True)
            self.timer.cancel()

    def close(self) -> None:
        self._reader.close()
