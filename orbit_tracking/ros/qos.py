"""QoS profiles of the topic contract, defined once for every node."""

from __future__ import annotations

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from rclpy.topic_endpoint_info import TopicEndpointInfo

__all__ = [
    'CLOCK',
    'matching_reader',
    'DIAGNOSTICS',
    'LATCHED',
    'MEASUREMENTS_PUB',
    'MEASUREMENTS_SUB',
    'STATE_STREAM',
    'STATION_STATE_FIXED',
    'STATION_STATE_MOVING',
    'WINDOWS_SUB',
    'window_stream',
]

MEASUREMENTS_PUB = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=5000,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
"""Stations publish reliably; the deep history lets a slow reader catch up."""

MEASUREMENTS_SUB = QoSProfile(
    history=HistoryPolicy.KEEP_ALL,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
"""The processing chain reads keep-all, so no measurement is overwritten unseen."""

STATION_STATE_FIXED = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
"""A fixed station's state is latched: late joiners still get it."""

STATION_STATE_MOVING = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=200,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)


STATE_STREAM = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1000,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
"""Telemetry, truth, fixes and fitted states."""

LATCHED = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
"""``trajectory/path`` and ``trajectory/biases``."""

DIAGNOSTICS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=50,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)


def window_stream(depth: int) -> QoSProfile:
    """``estimator/window_states`` and ``estimator/window_residuals`` as the estimator
    offers them: reliable, transient local, the last ``depth`` messages kept. A results node
    that (re)joins gets the windows it missed, those in flight when it was killed included:
    a journal on the reader's side cannot hold a message it never took."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=int(depth),
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


WINDOWS_SUB = QoSProfile(
    history=HistoryPolicy.KEEP_ALL,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
"""The results node's reader of the window topics: keep-all, and transient local so that the
estimator's kept windows reach it when it (re)joins. A volatile writer does not match it."""

CLOCK = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.BEST_EFFORT,
    durability=DurabilityPolicy.VOLATILE,
)
"""As rclpy's own /clock subscription (best effort, depth 1)."""


def matching_reader(publishers: list[TopicEndpointInfo]) -> QoSProfile | None:
    """A keep-all reliable reader profile that matches every publisher of a topic.

    Transient-local when all publishers offer it (so a latched fixed-station state is
    received even though it was published before we subscribed), volatile otherwise (a
    transient-local reader would not match a volatile writer). None if there is no
    publisher yet.
    """
    if not publishers:
        return None
    latched = all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in publishers)
    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )
