"""The live pass seen from the process that runs it: an rclpy node of its own
(:class:`LiveMonitor`) that watches the ROS graph until every node and the recorder are
connected, collects the nodes' ``/diagnostics`` statuses and the ``trajectory/states``
count, and calls the results node's ``~/flush``.

:func:`~orbit_tracking.tools.live.run_live` waits on it before starting the simulator
(:data:`SIMULATOR`) and until the estimator and the results node are through.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

__all__ = ['RECORDER_NODE', 'SIMULATOR', 'LiveMonitor']

SIMULATOR = 'scenario_sim'
"""The node that starts streaming: started last, once every other one listens."""

RECORDER_NODE = 'orbit_tracking_recorder'


@dataclass(frozen=True)
class _Endpoint:
    topic: str
    kind: str  # 'pub' | 'sub'
    node: str


# what must be connected before the simulator may start: nothing published is then lost
_GRAPH: tuple[_Endpoint, ...] = (
    _Endpoint('/telemetry/state', 'sub', 'estimator'),
    _Endpoint('/triangulation/fixes', 'pub', 'triangulation'),
    _Endpoint('/triangulation/fixes', 'sub', 'estimator'),
    _Endpoint('/triangulation/fixes', 'sub', RECORDER_NODE),
    _Endpoint('/estimator/window_states', 'pub', 'estimator'),
    _Endpoint('/estimator/window_states', 'sub', 'results'),
    _Endpoint('/estimator/window_states', 'sub', RECORDER_NODE),
    _Endpoint('/estimator/window_residuals', 'sub', 'results'),
    _Endpoint('/estimator/window_residuals', 'sub', RECORDER_NODE),
    _Endpoint('/trajectory/states', 'pub', 'results'),
    _Endpoint('/trajectory/states', 'sub', RECORDER_NODE),
    _Endpoint('/trajectory/biases', 'sub', RECORDER_NODE),
)
# the nodes' /diagnostics statuses: a node that publishes one is up and spinning
_STATUS = {
    'triangulation': 'triangulation: fixes',
    'estimator': 'estimator: windows',
    'results': 'results: trajectory',
    SIMULATOR: f'{SIMULATOR}: simulator',
}


class LiveMonitor:
    """An rclpy node of our own in this process: the graph, the nodes' ``/diagnostics``,
    the ``trajectory/states`` count and the results node's ``~/flush``."""

    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from rclpy.executors import SingleThreadedExecutor
        from std_srvs.srv import Trigger

        from orbit_tracking.ros import qos

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node('orbit_tracking_live_monitor', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.status: dict[str, dict[str, str]] = {}
        self.messages: dict[str, str] = {}
        self.states = 0
        self.node.create_subscription(
            DiagnosticArray, '/diagnostics', self._on_diagnostics, qos.DIAGNOSTICS
        )
        self.node.create_subscription(
            Odometry, '/trajectory/states', self._on_state, qos.MEASUREMENTS_SUB
        )
        self.flush = self.node.create_client(Trigger, '/results/flush')
        self._trigger = Trigger

    def _on_diagnostics(self, msg: Any) -> None:
        for st in msg.status:
            self.status[st.name] = {kv.key: kv.value for kv in st.values}
            self.messages[st.name] = st.message

    def _on_state(self, _msg: Any) -> None:
        self.states += 1

    def spin(self, seconds: float = 0.1) -> None:
        end = time.monotonic() + seconds
        while True:
            self.executor.spin_once(timeout_sec=max(0.0, min(0.05, end - time.monotonic())))
            if time.monotonic() >= end:
                return

    def missing(self) -> list[_Endpoint]:
        """Endpoints of :data:`_GRAPH` not there yet."""
        out = []
        for e in _GRAPH:
            infos = (
                self.node.get_publishers_info_by_topic(e.topic)
                if e.kind == 'pub'
                else self.node.get_subscriptions_info_by_topic(e.topic)
            )
            if not any(i.node_name == e.node for i in infos):
                out.append(e)
        return out

    def unrecorded(self, node: str) -> tuple[list[str], list[str]] | None:
        """``(topics node publishes, those the recorder does not read yet)``, without
        the infrastructure topics; None while the node is not in the graph."""
        try:
            pubs = self.node.get_publisher_names_and_types_by_node(node, '/')
        except Exception:  # noqa: BLE001 - rclpy raises NodeNameNonExistentError until seen
            return None
        topics = [t for t, _ in pubs if t not in ('/diagnostics', '/rosout', '/parameter_events')]
        missing = [
            t
            for t in topics
            if not any(
                i.node_name == RECORDER_NODE for i in self.node.get_subscriptions_info_by_topic(t)
            )
        ]
        return topics, missing

    def value(self, node: str, key: str, default: float = math.nan) -> float:
        text = self.status.get(_STATUS[node], {}).get(key, '')
        try:
            return float(text)
        except ValueError:
            return default

    def close(self) -> None:
        import rclpy

        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
