"""This process's side of a fault replay (:mod:`orbit_tracking.tools.bench.fault_replay`):
its two DDS participants (:class:`Participants`) and how a node's ``/diagnostics`` status
is read (:func:`counters`).

The *replay* participant publishes the bag's messages, watches ``/diagnostics``,
``estimator/window_states`` and ``trajectory/states`` (spun in a thread of its own) and
calls the nodes' ``~/solve`` and ``~/flush``; the *injector* publishes the bad messages.
Both join the replay's DDS domain without installing signal handlers, so that two replays
can run side by side in one process.

A *rejection counter* is any integer key of a node's status that is not activity (messages
taken, fixes, windows, states), not a symptom (time resets, data dropped after one,
restarts, internal errors, failed windows) and not a per-window value (``last_*``,
``used_*``, the estimator's ``rejected_<station>_<why>`` of its last window). Names may
change; what grew is recorded by name.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from orbit_tracking.tools.bench.fault_messages import NODES, RESIDUALS, WINDOWS, topic_type

__all__ = [
    'INIT_LOCK',
    'Participants',
    'Tick',
    'as_int',
    'counters',
    'grew',
    'residual_gate',
    'wait_graph_clear',
]

_STATUS = {
    'triangulation: fixes': 'triangulation',
    'estimator: windows': 'estimator',
    'results: trajectory': 'results',
}
_ACTIVITY = frozenset(
    {
        'measurement_messages',
        'measurements_received',
        'telemetry_messages',
        'samples_without_angles',  # every CW radar sample, at the triangulation node
        'fixes',
        'windows_solved',
        'windows_received',
        'windows_used',
        'states_published',
        'states_held',
        'flushes',
        'targets',  # the ids the results node has seen
        'estimator_gone',
    }
)
_SYMPTOMS = frozenset(
    {
        'time_resets',
        'stale_after_reset',
        'restarts',
        'internal_error',
        'rejected_internal_error',
        'windows_failed',
        'residuals_failed',
        'states_already_final',
        'missing_samples',
        'windows_repeated',
    }
)
_NOT_COUNTERS = ('last_', 'used_', 'withheld_', 'buffer_', 'processing_', 'fix_age_', 'newest_')
INIT_LOCK = threading.Lock()
"""Held while rclpy contexts are made or shut down (two replays may run in threads)."""


@dataclass
class Tick:
    """One ``/diagnostics`` status of a node: its header stamp [s] (the node's system
    clock when it published) and its key-values (for the results node with its residual
    statuses as ``residuals <station>/<key>``)."""

    stamp: float
    values: dict[str, str]


def as_int(text: str) -> int:
    """A status value as an integer (-1 if it is none)."""
    try:
        return int(text)
    except ValueError:
        return -1


def _windows_done(t: Tick) -> int:
    return as_int(t.values.get('windows_solved', '0')) + as_int(
        t.values.get('windows_failed', '0')
    )


class Participants:
    """The run's two participants in ``domain``: the replay (player, monitor, service
    clients; spun in a thread) and the injector (publishers only)."""

    def __init__(
        self,
        topics: Sequence[tuple[str, str, bool]],
        bad_topics: Sequence[str],
        domain: int,
    ) -> None:
        """``topics``: the bag's (topic, message type, latched); ``bad_topics``: those of
        the bad messages; ``domain``: the replay's DDS domain."""
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        from sensor_msgs.msg import PointCloud2
        from std_srvs.srv import Trigger

        from orbit_tracking.ros import qos
        from orbit_tracking.ros.bag import message_class

        self.lock = threading.Lock()
        self.ticks: dict[str, list[Tick]] = {n: [] for n in NODES}
        self.states: dict[tuple[str, int], np.ndarray] = {}
        self.state_msgs = 0
        self.windows = 0
        self.injected_windows: set[bytes] = set()
        self.contexts, self.nodes = [], []
        with INIT_LOCK:
            for name in (f'fault_replay_{domain}', f'fault_injector_{domain}'):
                ctx = rclpy.Context()
                rclpy.init(
                    context=ctx,
                    domain_id=domain,
                    signal_handler_options=SignalHandlerOptions.NO,
                )
                self.contexts.append(ctx)
                self.nodes.append(rclpy.create_node(name, context=ctx))
        self.node, self.injector = self.nodes
        self.executor = SingleThreadedExecutor(context=self.contexts[0])
        self.executor.add_node(self.node)

        def profile(topic: str, latched: bool) -> Any:
            if latched:
                return qos.STATION_STATE_FIXED
            if topic in (WINDOWS, RESIDUALS):  # as the estimator offers them
                return qos.window_stream(16)
            return qos.MEASUREMENTS_PUB if topic.endswith('/measurements') else qos.STATE_STREAM

        self.pubs: dict[str, Any] = {}
        for topic, msgtype, latched in topics:
            if topic not in self.pubs:
                self.pubs[topic] = self.node.create_publisher(
                    message_class(msgtype), topic, profile(topic, latched)
                )
        # a bad station state must reach readers matched to the bag's latched writer
        self.bad_pubs: dict[str, Any] = {}
        for topic in bad_topics:
            if topic not in self.bad_pubs:
                latched = topic.startswith('/stations/') and topic.endswith('/state')
                self.bad_pubs[topic] = self.injector.create_publisher(
                    topic_type(topic), topic, profile(topic, latched)
                )
        self.node.create_subscription(
            DiagnosticArray, '/diagnostics', self._on_diag, qos.DIAGNOSTICS
        )
        self.node.create_subscription(PointCloud2, WINDOWS, self._on_window, qos.MEASUREMENTS_SUB)
        self.node.create_subscription(
            Odometry, '/trajectory/states', self._on_state, qos.MEASUREMENTS_SUB
        )
        self.solve = self.node.create_client(Trigger, '/estimator/solve')
        self.flush = self.node.create_client(Trigger, '/results/flush')
        self.tri_flush = self.node.create_client(Trigger, '/triangulation/flush')
        self._trigger = Trigger
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        import rclpy

        self._stop.set()
        self._thread.join(timeout=5.0)
        self.executor.shutdown()
        with INIT_LOCK:
            for node, ctx in zip(self.nodes, self.contexts, strict=True):
                node.destroy_node()
                rclpy.try_shutdown(context=ctx)

    # -- callbacks (the spinning thread) --
    def _on_diag(self, msg: Any) -> None:
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        node, values = None, {}
        for st in msg.status:
            kv = {k.key: k.value for k in st.values}
            if st.name in _STATUS:
                node = _STATUS[st.name]
                values.update(kv)
            elif st.name.startswith('results: residuals '):
                sid = st.name[len('results: residuals ') :]
                values.update({f'residuals {sid}/{k}': v for k, v in kv.items()})
        if node is not None:
            with self.lock:
                self.ticks[node].append(Tick(stamp, values))

    def _on_window(self, msg: Any) -> None:
        if bytes(msg.data) not in self.injected_windows:
            with self.lock:
                self.windows += 1

    def _on_state(self, msg: Any) -> None:
        p = msg.pose.pose.position
        key = (msg.child_frame_id, msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
        with self.lock:
            self.states[key] = np.array([p.x, p.y, p.z])
            self.state_msgs += 1

    # -- queries (the main thread) --
    def last(self, node: str) -> Tick | None:
        with self.lock:
            return self.ticks[node][-1] if self.ticks[node] else None

    def settled(
        self, node: str, after: float, expect: Mapping[str, int], margin: float = 0.15
    ) -> Tick | None:
        """The first status of ``node`` published ``margin`` seconds or more after
        ``after`` (system time) that shows ``expect`` (key >= value; keys the node does not
        report are not waited for) and, for the estimator, no window solved since its
        previous status (a status published right after a solve can precede the messages
        that queued meanwhile)."""
        with self.lock:
            ticks = list(self.ticks[node])
        for i, t in enumerate(ticks):
            if t.stamp < after + margin:
                continue
            if any(as_int(t.values.get(k, str(v))) < v for k, v in expect.items()):
                continue
            if node == 'estimator' and (i == 0 or _windows_done(ticks[i - 1]) != _windows_done(t)):
                continue
            return t
        return None

    def call(self, client: Any, timeout: float) -> str | None:
        """Call a Trigger service; its answer, or None if there is none in time."""
        if not client.wait_for_service(timeout_sec=min(timeout, 10.0)):
            return None
        future = client.call_async(self._trigger.Request())
        deadline = time.monotonic() + timeout
        while not future.done():
            if time.monotonic() > deadline:
                return None
            time.sleep(0.02)
        return str(future.result().message)


def counters(node: str, values: Mapping[str, str]) -> tuple[dict[str, int], dict[str, int]]:
    """(rejection counters, symptom counters) of one status (see the module docstring)."""
    stations = values.get('stations', '').split()
    rejections, symptoms = {}, {}
    for k, v in values.items():
        if k in _ACTIVITY or k.startswith(_NOT_COUNTERS) or k.startswith('residuals '):
            continue
        if node == 'estimator' and any(k.startswith(f'rejected_{s}_') for s in stations):
            continue  # the last window's residual gate, not a running count
        n = as_int(v)
        if n < 0 or str(n) != v:
            continue
        (symptoms if k in _SYMPTOMS else rejections)[k] = n
    return rejections, symptoms


def residual_gate(values: Mapping[str, str]) -> dict[str, int]:
    """The running residual-gate counts per station the results node relays."""
    out = {}
    for k, v in values.items():
        if k.startswith('residuals ') and k.endswith('rejected') and as_int(v) >= 0:
            out['residual gate ' + k[len('residuals ') :]] = as_int(v)
    return out


def grew(before: Mapping[str, int], after: Mapping[str, int]) -> dict[str, int]:
    return {k: v - before.get(k, 0) for k, v in after.items() if v > before.get(k, 0)}


def wait_graph_clear(domain: int, timeout: float = 30.0) -> None:
    """Wait until the nodes of a previous replay in ``domain`` have left the graph."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    ctx = rclpy.Context()
    with INIT_LOCK:
        rclpy.init(context=ctx, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
        node = rclpy.create_node(f'fault_graph_probe_{domain}', context=ctx)
    try:
        time.sleep(0.3)  # discovery
        deadline = time.monotonic() + timeout
        while set(NODES) & set(node.get_node_names()) and time.monotonic() < deadline:
            time.sleep(0.2)
    finally:
        with INIT_LOCK:
            node.destroy_node()
            rclpy.try_shutdown(context=ctx)
