"""Throughput and latency of the live nodes over real DDS (``orbit-tracking bench --suite
dds``).

For each offered rate the benchmark starts the ``triangulation`` and ``estimator`` nodes as
separate processes (``python -m orbit_tracking.ros.<node>``, in a namespace of their own,
``/diagnostics`` remapped into it), waits until they read every topic, and publishes a
simulated pass from this process: each station's single-point measurement messages with
their recorded pacing scaled so that the measurements arrive at the offered rate, and the
telemetry; fixed station states once, latched. Messages are serialised beforehand, so the
publishing loop costs a few microseconds per message.

It then reports, per rate and node, the measurements the node counted
(``measurements_received`` in its ``/diagnostics``) against those sent, the rate at which
it took them (count over the wall time from the first publication until its diagnostics
showed the last one, so within one diagnostics period, 1 s), and for the estimator the
delay from the publication of a window's last measurement to the arrival of its
``estimator/window_states`` (wall clock; it includes the ``latency`` the node waits for
late data, in data seconds divided by the replay speed) and from the publication of the
measurement that made the window due.
"""

from __future__ import annotations

import dataclasses
import math
import os
import platform
import tempfile
import threading
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.core.sim.simulator import simulate
from orbit_tracking.core.sim.stream import EventStream

__all__ = ['DDS_RATES', 'DDS_SCENARIO', 'DDS_WINDOWS', 'DdsRow', 'bench_dds', 'dds_table']

DDS_SCENARIO = 'seed000_s1'
"""13 stations at 20 Hz (260 measurements per data second) before its incomplete segment."""

DDS_RATES = (250.0, 500.0, 1000.0, 2000.0, 4000.0)
"""Offered measurement rates [measurements/s]."""

DDS_WINDOWS = (10.0, 3.0, 1.0)
"""Estimator ``window_length``, ``window_overlap`` and ``latency`` [s]."""


@dataclass(frozen=True)
class DdsRow:
    """One offered rate.

    Attributes
    ----------
    offered : float
        Requested rate [measurements/s]; ``sent_rate`` is what the publisher achieved.
    sent : int
        Measurements (points) published; ``messages`` the messages that carried them.
    tri_received, est_received : int
        Measurements each node counted (``-1``: no diagnostics).
    tri_rate, est_rate : float
        Measurements the node took per wall second (see the module docstring).
    tri_lag_s, est_lag_s : float
        Wall seconds from the last publication until the node's diagnostics showed its
        final count.
    fixes, windows, windows_failed : int
    delay_s, due_delay_s : tuple of float
        Mean and max delay [s] from a window's last measurement, and from the measurement
        that made it due, to its ``estimator/window_states`` (windows closed by the data,
        not the final flush); NaN if none.
    """

    offered: float
    sent: int
    messages: int
    sent_rate: float
    tri_received: int
    tri_rate: float
    tri_lag_s: float
    est_received: int
    est_rate: float
    est_lag_s: float
    fixes: int
    windows: int
    windows_failed: int
    delay_s: tuple[float, float]
    due_delay_s: tuple[float, float]


@dataclass(frozen=True)
class _Outgoing:
    topic: str
    kind: str
    moving: bool
    time: float
    points: int
    raw: bytes


class _Monitor:
    """The diagnostics of both nodes, each with the wall time (``time.monotonic``) it
    arrived (received in the spinning thread, read in the publishing one)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.diags: dict[str, list[tuple[float, dict[str, str]]]] = {'tri': [], 'est': []}

    def on_diag(self, msg: object) -> None:
        now = time.monotonic()
        with self.lock:
            for st in msg.status:  # type: ignore[attr-defined]
                key = {'triangulation: fixes': 'tri', 'estimator: windows': 'est'}.get(st.name)
                if key:
                    self.diags[key].append((now, {kv.key: kv.value for kv in st.values}))

    def last(self, key: str) -> dict[str, str]:
        with self.lock:
            return self.diags[key][-1][1] if self.diags[key] else {}


def _int(d: dict[str, str], key: str) -> int:
    try:
        return int(float(d.get(key, '-1')))
    except ValueError:
        return -1


def _messages(scenario: str, span: float) -> tuple[list[_Outgoing], float, str]:
    """The pass's messages, serialised, in time order; the scenario epoch and name."""
    from rclpy.serialization import serialize_message

    from orbit_tracking.ros.conversions import TimeBase
    from orbit_tracking.ros.messages import event_message, event_topic

    sc = load_scenario(scenario)
    sc = dataclasses.replace(sc, t_end=min(sc.t_end, sc.t_start + span))
    result = simulate(sc)
    tb = TimeBase.from_seconds(sc.epoch)
    out = []
    for ev in EventStream(result, truth=False):
        msg = event_message(result, ev, tb)
        moving = ev.kind == 'station_state' and result.station_states[ev.key].moving
        points = ev.stop - ev.start if ev.kind == 'measurement' else 0
        out.append(
            _Outgoing(event_topic(ev), ev.kind, moving, ev.time, points, serialize_message(msg))
        )
    return out, sc.epoch, sc.name


def bench_dds(
    scenario: str = DDS_SCENARIO,
    rates: Sequence[float] = DDS_RATES,
    span: float = 30.0,
    windows: tuple[float, float, float] = DDS_WINDOWS,
    progress: bool = True,
    timeout: float = 180.0,
    log_dir: Path | None = None,
) -> list[DdsRow]:
    """Run every offered rate (measurements/s) on ``span`` data seconds of ``scenario``,
    the estimator solving windows of ``windows`` = (length, overlap, latency) seconds.

    Raises
    ------
    RuntimeError
        A node exits, does not come up, or a rate does not finish within ``timeout`` s.

    The nodes' output goes to ``log_dir`` (default a temporary folder, removed).
    """
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import PointCloud2

    from orbit_tracking.ros import qos
    from orbit_tracking.tools.live import _env

    if not rates or min(rates) <= 0.0:
        raise ValueError(f'rates must be positive measurements/s; got {list(rates)}')
    outgoing, epoch, name = _messages(scenario, span)
    if progress:
        print(f'bench dds: {name}, {span:g} s of data, {len(outgoing)} messages', flush=True)
    os.environ.update({k: v for k, v in _env().items() if k.startswith('ROS_')})
    ns = f'/bench_{uuid.uuid4().hex[:8]}'
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('orbit_tracking_bench', namespace=ns, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    monitor = _Monitor()
    window_msgs: list[tuple[float, PointCloud2]] = []
    node.create_subscription(DiagnosticArray, 'diagnostics', monitor.on_diag, qos.DIAGNOSTICS)
    node.create_subscription(
        PointCloud2,
        'estimator/window_states',
        lambda m: window_msgs.append((time.monotonic(), m)),
        qos.MEASUREMENTS_SUB,
    )
    pubs: dict[str, Any] = {}
    for o in outgoing:
        if o.topic in pubs:
            continue
        if o.kind == 'measurement':
            pubs[o.topic] = node.create_publisher(PointCloud2, o.topic, qos.MEASUREMENTS_PUB)
        elif o.kind == 'station_state':
            profile = qos.STATION_STATE_MOVING if o.moving else qos.STATION_STATE_FIXED
            pubs[o.topic] = node.create_publisher(Odometry, o.topic, profile)
        else:
            pubs[o.topic] = node.create_publisher(Odometry, o.topic, qos.STATE_STREAM)
    for o in outgoing:  # fixed station states: once, latched
        if o.kind == 'station_state' and not o.moving:
            pubs[o.topic].publish(o.raw)
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.05)

    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    rows = []
    try:
        with tempfile.TemporaryDirectory(prefix='orbit_tracking_bench_dds_') as tmp:
            logs = Path(log_dir or tmp)
            logs.mkdir(parents=True, exist_ok=True)
            for rate in rates:
                trace = _one_rate(
                    rate,
                    outgoing,
                    pubs,
                    node,
                    monitor,
                    window_msgs,
                    epoch,
                    ns,
                    windows,
                    logs,
                    timeout,
                )
                row = _row(rate, trace, windows[2])
                rows.append(row)
                if progress:
                    print(
                        f'  {rate:g} meas/s: sent {row.sent} at {row.sent_rate:.0f}/s, '
                        f'triangulation {row.tri_received}, estimator {row.est_received}, '
                        f'{row.windows} windows',
                        flush=True,
                    )
    finally:
        stop.set()
        spinner.join(timeout=5.0)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    return rows


@dataclass
class _Trace:
    """What one rate produced: the measurement publications (stamp [s], wall time), the
    windows that arrived, and the diagnostics of both nodes."""

    stamps: np.ndarray
    walls: np.ndarray
    sent: int
    messages: int
    windows: list[tuple[float, float]]
    diags: dict[str, list[tuple[float, dict[str, str]]]]


def _one_rate(
    rate: float,
    outgoing: list[_Outgoing],
    pubs: dict[str, Any],
    node: Any,
    monitor: _Monitor,
    window_msgs: list[tuple[float, Any]],
    epoch: float,
    ns: str,
    windows: tuple[float, float, float],
    logs: Path,
    timeout: float,
) -> _Trace:
    from orbit_tracking.ros.conversions import TimeBase, cloud_to_window_states
    from orbit_tracking.tools.live import _node, _start, _stop

    length, overlap, latency = windows
    remap = ['-r', f'__ns:={ns}', '-r', f'/diagnostics:={ns}/diagnostics']
    common = {'time_reference': epoch}
    procs = {
        'triangulation': _start(
            _node('triangulation_node', {'lag': 0.5, 'flush_after': 1.0, **common}) + remap,
            logs / f'triangulation_{rate:g}.log',
        ),
        'estimator': _start(
            _node(
                'estimator_node',
                {
                    'window_length': length,
                    'window_overlap': overlap,
                    'latency': latency,
                    'flush_after': 2.0,  # after the triangulation's: its tail fixes come last
                    **common,
                },
            )
            + remap,
            logs / f'estimator_{rate:g}.log',
        ),
    }
    with monitor.lock:
        monitor.diags = {'tri': [], 'est': []}
    window_msgs.clear()
    meas = [o for o in outgoing if o.kind == 'measurement']
    sent = sum(o.points for o in meas)
    t_first, last_meas = outgoing[0].time, meas[-1].time
    speed = rate / (sent / max(last_meas - meas[0].time, 1e-9))  # data s per wall s

    def check(what: str, deadline: float) -> None:
        for label, proc in procs.items():
            if proc.poll() is not None:
                log = (logs / f'{label}_{rate:g}.log').read_text(errors='replace')
                raise RuntimeError(f'bench dds: the {label} node exited:\n{log[-3000:]}')
        if time.monotonic() > deadline:
            raise RuntimeError(f'bench dds: {what} in time')

    stamps, walls = [], []
    try:
        # both nodes read every topic and report: nothing is lost to discovery
        deadline = time.monotonic() + 60.0
        while not (
            all(
                p.get_subscription_count() >= (1 if t == 'telemetry/state' else 2)
                for t, p in pubs.items()
            )
            and monitor.last('tri')
            and monitor.last('est')
            and node.count_publishers(f'{ns}/estimator/window_states') > 0
        ):
            check('the nodes did not subscribe', deadline)
            time.sleep(0.1)
        time.sleep(1.0)  # endpoint matching follows graph discovery closely
        start = time.monotonic()
        for o in outgoing:
            if o.kind == 'station_state' and not o.moving:
                continue
            wait = start + (o.time - t_first) / speed - time.monotonic()
            if wait > 0.0005:
                time.sleep(wait)
            pubs[o.topic].publish(o.raw)
            if o.kind == 'measurement':
                stamps.append(o.time)
                walls.append(time.monotonic())
        # until both nodes took everything and the estimator flushed its last window, or
        # nothing moved for 15 s (then what arrived is reported)
        deadline = time.monotonic() + timeout
        state: object = None
        changed = time.monotonic()
        while True:
            tri_d, est_d = monitor.last('tri'), monitor.last('est')
            got = (_int(tri_d, 'measurements_received'), _int(est_d, 'measurements_received'))
            n_win = _int(est_d, 'windows_solved') + _int(est_d, 'windows_failed')
            end = float(est_d.get('last_window_end') or 'nan')
            if (got, n_win) != state:
                state, changed = (got, n_win), time.monotonic()
            if min(got) >= sent and end >= last_meas - 1e-3:
                time.sleep(0.5)  # the flushed window's message
                break
            if time.monotonic() - changed > 15.0:
                break
            check('the nodes did not finish', deadline)
            time.sleep(0.1)
    finally:
        for proc in procs.values():
            _stop(proc)
    tb = TimeBase.from_seconds(epoch)
    with monitor.lock:
        diags = {k: list(v) for k, v in monitor.diags.items()}
    return _Trace(
        np.asarray(stamps),
        np.asarray(walls),
        sent,
        len(meas),
        [(arrival, cloud_to_window_states(m, tb).t1) for arrival, m in window_msgs],
        diags,
    )


def _row(rate: float, tr: _Trace, latency: float) -> DdsRow:
    t0, t_end = float(tr.walls[0]), float(tr.walls[-1])

    def taken(key: str) -> tuple[int, float, float]:
        hist = tr.diags[key]
        if not hist:
            return -1, math.nan, math.nan
        final = _int(hist[-1][1], 'measurements_received')
        t_reach = next(t for t, d in hist if _int(d, 'measurements_received') == final)
        return final, final / max(t_reach - t0, 1e-9), max(t_reach - t_end, 0.0)

    def last(key: str) -> dict[str, str]:
        return tr.diags[key][-1][1] if tr.diags[key] else {}

    delays, due = [], []
    last_meas = float(tr.stamps[-1])
    for arrival, t1 in tr.windows:
        if t1 >= last_meas - 1e-6:  # the final flush: closed by silence, not by data
            continue
        i = int(np.searchsorted(tr.stamps, t1 + 1e-9, side='right')) - 1
        if i >= 0:
            delays.append(arrival - tr.walls[i])
        j = int(np.searchsorted(tr.stamps, t1 + latency - 1e-9, side='left'))
        if j < tr.stamps.size:
            due.append(arrival - tr.walls[j])

    def stats(x: list[float]) -> tuple[float, float]:
        return (float(np.mean(x)), float(np.max(x))) if x else (math.nan, math.nan)

    tri_n, tri_rate, tri_lag = taken('tri')
    est_n, est_rate, est_lag = taken('est')
    return DdsRow(
        offered=rate,
        sent=tr.sent,
        messages=tr.messages,
        sent_rate=tr.sent / max(t_end - t0, 1e-9),
        tri_received=tri_n,
        tri_rate=tri_rate,
        tri_lag_s=tri_lag,
        est_received=est_n,
        est_rate=est_rate,
        est_lag_s=est_lag,
        fixes=_int(last('tri'), 'fixes'),
        windows=len(tr.windows),
        windows_failed=max(_int(last('est'), 'windows_failed'), 0),
        delay_s=stats(delays),
        due_delay_s=stats(due),
    )


def dds_table(
    rows: Sequence[DdsRow],
    scenario: str,
    span: float,
    windows: tuple[float, float, float],
    wall_s: float,
    command: str,
) -> str:
    """Markdown table of :func:`bench_dds`, with its caption and the machine it ran on."""
    length, overlap, latency = windows

    def num(x: float, fmt: str) -> str:
        return format(x, fmt) if math.isfinite(x) else '—'

    def got(n: int, sent: int) -> str:
        return 'none' if n < 0 else (f'{n}' if n == sent else f'{n} ({sent - n} lost)')

    lines = [
        f'Live nodes over DDS: {span:g} s of `{scenario}` ({rows[0].messages if rows else 0} '
        'single-point measurement messages, plus telemetry) published by one process at each '
        'offered rate into the `triangulation` and `estimator` nodes, each in its own process '
        f'(estimator windows {length:g} s, overlap {overlap:g} s, latency {latency:g} s of '
        'data). received: measurements the node counted in its `/diagnostics`; taken: received '
        'per wall second from the first publication until the diagnostics showed the last one '
        '(they come once a second); lag: wall seconds from the last publication to then; '
        "window delay: from the publication of a window's last measurement (and of the "
        'measurement that made it due) to the arrival of its `estimator/window_states`, mean / '
        'max over the windows closed by data.',
        '',
        '| offered [meas/s] | sent [meas/s] | triangulation received | taken [meas/s] | lag [s] '
        '| estimator received | taken [meas/s] | lag [s] | fixes | windows (failed) '
        '| window delay [s] | after due [s] |',
        '|---|---|---|---|---|---|---|---|---|---|---|---|',
    ]
    for r in rows:
        lines.append(
            f'| {r.offered:g} | {r.sent_rate:.0f} | {got(r.tri_received, r.sent)} | '
            f'{num(r.tri_rate, ".0f")} | {num(r.tri_lag_s, ".1f")} | '
            f'{got(r.est_received, r.sent)} | {num(r.est_rate, ".0f")} | '
            f'{num(r.est_lag_s, ".1f")} | {r.fixes} | {r.windows} ({r.windows_failed}) | '
            f'{num(r.delay_s[0], ".2f")} / {num(r.delay_s[1], ".2f")} | '
            f'{num(r.due_delay_s[0], ".2f")} / {num(r.due_delay_s[1], ".2f")} |'
        )

    def best(key: str) -> str:
        ok = [
            r.offered
            for r in rows
            if getattr(r, f'{key}_received') == r.sent and getattr(r, f'{key}_lag_s') <= 1.5
        ]
        return f'{max(ok):g} meas/s' if ok else 'none of the rates'

    lines += [
        '',
        'Highest offered rate taken without loss and without falling behind (lag within '
        f'1.5 s): triangulation {best("tri")}, estimator {best("est")}.',
        '',
        f'Measured by `{command}` on {platform.machine()} ({platform.python_implementation()} '
        f'{platform.python_version()}, {os.cpu_count()} cores, '
        f'{_rmw()}) in {wall_s:.0f} s.',
    ]
    return '\n'.join(lines)


def _rmw() -> str:
    from rclpy.utilities import get_rmw_implementation_identifier

    return str(get_rmw_implementation_identifier())
