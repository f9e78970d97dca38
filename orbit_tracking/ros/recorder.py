"""A recorder node: subscribes to the contract's topics over DDS and writes a rosbag2.

Subscriptions are created as topics appear (polled every 0.5 s), with the durability of
their publishers (transient-local when every publisher offers it, so latched station
states are captured; volatile otherwise) and keep-all reliable history so nothing is lost.
Messages are written as received (serialised bytes), with the receive time as log time.
"""

from __future__ import annotations

import fnmatch
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile

from orbit_tracking.ros.bag import BagWriter, message_class
from orbit_tracking.ros.qos import matching_reader

__all__ = ['DEFAULT_TOPICS', 'RecorderNode']

DEFAULT_TOPICS: tuple[str, ...] = (
    '/stations/*/measurements',
    '/stations/*/state',
    '/telemetry/state',
    '/truth/state',
    '/triangulation/fixes',
    '/trajectory/*',
    '/diagnostics',
)
"""Glob patterns of the topics recorded by default (the contract's topics)."""


class RecorderNode(Node):
    """Record matching topics into ``out`` until stopped.

    Parameters
    ----------
    out : path-like
        New bag folder.
    patterns : sequence of str
        fnmatch patterns of fully qualified topic names.
    storage : {'mcap', 'sqlite3'}
    custom_data : mapping of str to str, optional
        Written into the bag's metadata (rosbag2 ``custom_data``), e.g. the scenario labels
        of :func:`~orbit_tracking.tools.simulate.scenario_custom_data`.
    """

    def __init__(
        self,
        out: str | Path,
        patterns: Sequence[str] = DEFAULT_TOPICS,
        storage: str = 'mcap',
        custom_data: Mapping[str, str] | None = None,
    ) -> None:
        super().__init__('orbit_tracking_recorder')
        self.bag = BagWriter(out, storage)
        for key, value in (custom_data or {}).items():
            self.bag.set_custom_data(key, value)
        self.patterns = tuple(patterns)
        self.subs: dict[str, object] = {}
        self.counts: dict[str, int] = {}
        self.last_message = time.monotonic()
        self.first_message: float | None = None
        self.create_timer(0.5, self._discover)
        self._discover()

    def _discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self.subs or not any(fnmatch.fnmatch(topic, p) for p in self.patterns):
                continue
            if len(types) != 1:
                self.get_logger().warning(f'{topic} has several types {types}; not recorded')
                continue
            msgtype = types[0]
            infos = self.get_publishers_info_by_topic(topic)
            profile = matching_reader(infos)
            if profile is None:
                continue  # the topic has subscribers only so far; look again later
            latched = profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
            offered = infos[0].qos_profile
            cls = message_class(msgtype)
            self.subs[topic] = self.create_subscription(
                cls,
                topic,
                lambda data, t=topic, m=msgtype, q=offered: self._write(t, m, data, q),
                profile,
                raw=True,
            )
            self.counts[topic] = 0
            self.get_logger().info(
                f'recording {topic} [{msgtype}]' + (' (latched)' if latched else '')
            )

    def _write(self, topic: str, msgtype: str, data: bytes, offered: QoSProfile) -> None:
        now = time.monotonic()
        self.last_message = now
        if self.first_message is None:
            self.first_message = now
        self.bag.write_raw(topic, msgtype, data, self.get_clock().now().nanoseconds, offered)
        self.counts[topic] += 1

    def close(self) -> None:
        self.bag.close()
