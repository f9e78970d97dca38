"""Restart loss of a processing node over real DDS (the fault benchmark's restart rows, and
``test/test_restart.py``); the comparison of two passes is in
:mod:`~orbit_tracking.tools.bench.restart_compare`.

A bag is replayed (``orbit-tracking replay``) through the ``triangulation``, ``estimator``
and ``results`` nodes, each its own process started as the main job starts them (their
``config/<node>.yaml`` plus :data:`RESTART_WINDOWS`), twice: a clean pass, and a pass in
which one of them (``kill_node``, the estimator by default) is killed (SIGKILL by default) a
while after the first windows reached this process, then started again with the same
command line ``restart_after`` seconds later. :func:`measure_restart_loss` compares the
``trajectory/states`` the two passes published (:func:`~orbit_tracking.tools.bench.
restart_compare.compare_passes`).

Messages the player sends while no estimator process runs reach no estimator: with the
journal the restarted node has everything it had accepted before the kill, and the windows
span that short gap in the data as they span any gap. A restarted results node goes on
from its own journal and the estimator's kept windows (docs/NODES.md).

The nodes run in the root namespace (the bag's topic names are absolute) on their own DDS
domain (``domain_id``; default ``1 + pid % 100``) with ``ROS_AUTOMATIC_DISCOVERY_RANGE`` set
to ``LOCALHOST`` here and in the children, so that a benchmark never talks to a running
system.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from orbit_tracking.tools.bench.restart_compare import PassResult, compare_passes

__all__ = [
    'PassResult',
    'RESTART_BAG',
    'RESTART_WINDOWS',
    'compare_passes',
    'measure_restart_loss',
    'run_pass',
]

RESTART_BAG = 'seed000_s1_20_50'
"""Default bag (``test/data/bags`` of the source tree): 30 s of 13 fixed stations and
telemetry, an incomplete segment at 45-50 s."""

RESTART_WINDOWS: Mapping[str, object] = {
    'window_length': 12.0,
    'window_overlap': 4.0,
    'latency': 2.0,
    'output_step': 0.1,
}
"""The estimator's windows: four over 30 s, three hand-overs (as the regression test)."""

_PROCESSING = ('triangulation', 'estimator', 'results')
_OUTPUT_TOPIC = {
    'triangulation': '/triangulation/fixes',
    'estimator': '/estimator/window_states',
    'results': '/trajectory/states',
}


def _bag_facts(bag: Path) -> tuple[int, float, str, bool]:
    """The bag's epoch [ns], newest measurement time [s after it], one measurement topic,
    and whether it has telemetry."""
    from orbit_tracking.ros.bag import bag_custom_data, read_bag
    from orbit_tracking.ros.conversions import TimeBase, cloud_to_measurements

    epoch = TimeBase.from_seconds(float(bag_custom_data(bag)['orbit_tracking.epoch']))
    newest, topic, telemetry = -math.inf, '', False
    for m in read_bag(bag):
        if m.topic.startswith('/stations/') and m.topic.endswith('/measurements'):
            topic = topic or m.topic
            newest = max(newest, float(cloud_to_measurements(m.msg, epoch).time.max()))
        telemetry = telemetry or m.topic == '/telemetry/state'
    return epoch.ref_ns, newest, topic, telemetry


def _checkpointed(journal_dir: Path, t1: float) -> bool:
    """Whether the estimator's journal (read, not locked) holds a checkpoint of a window
    ending at ``t1`` or later."""
    import json

    from orbit_tracking.core.data.journal import scan_journal

    for path in journal_dir.rglob('*.journal'):
        states = [r for r in scan_journal(path).records if r.kind == 'state']
        last = json.loads(states[-1].data).get('last') if states else None
        if last is not None and last[1] >= t1 - 1e-9:
            return True
    return False


def _readers(node: Any, topic: str, node_name: str) -> set[bytes]:
    """Endpoint ids of ``node_name``'s readers of ``topic`` on the ROS graph."""
    return {
        bytes(i.endpoint_gid)
        for i in node.get_subscriptions_info_by_topic(topic)
        if i.node_name == node_name
    }


def _start(cmd: Sequence[str], log: Path, env: Mapping[str, str]) -> subprocess.Popen[bytes]:
    with open(log, 'wb') as fh:
        return subprocess.Popen(
            list(cmd), env=dict(env), stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL
        )


def run_pass(
    bag: str | Path,
    work_dir: str | Path,
    *,
    rate: float = 1.0,
    journal: bool = True,
    kill_after_windows: int | None = None,
    kill_at: float | None = None,
    kill_after_checkpoint: bool = False,
    kill_delay: float = 0.0,
    restart_after: float = 1.0,
    max_gap: float | None = None,
    kill_signal: int = signal.SIGKILL,
    kill_node: str = 'estimator',
    estimator_params: Mapping[str, object] | None = None,
    results_params: Mapping[str, object] | None = None,
    domain_id: int | None = None,
    timeout: float = 300.0,
    progress: Callable[[str], None] | None = None,
) -> PassResult:
    """Replay ``bag`` through the three nodes and collect what they publish.

    Parameters
    ----------
    bag : path-like
        rosbag2 folder with ``orbit_tracking.epoch`` in its metadata.
    work_dir : path-like
        Logs and the estimator's journal (``<work_dir>/journal``) go here.
    rate : float
        Replay speed.
    journal : bool
        Run the estimator and the results node with ``journal_dir`` (else without).
    kill_after_windows : int, optional
        Kill the estimator ``kill_delay`` wall seconds after this many windows arrived
        here, and start it again ``restart_after`` seconds later; None: a clean pass.
    kill_at : float, optional
        Wait, before the delay, until the newest measurement received here is at least
        this data time [s after the bag's epoch] as well.
    kill_after_checkpoint : bool
        Wait, before the delay, until the estimator's journal holds the checkpoint of the
        last of those windows (it is written once the readers acknowledged the window):
        the restart resumes the window schedule. Else the kill may come first, and the
        window is solved again after the restart.
    max_gap : float, optional
        With ``kill_node='estimator'``: most data seconds the player runs on while no
        estimator runs. Once the data heard here reach the kill's data time plus this, or
        ``max_gap / rate`` wall seconds after the kill (whichever comes first: what this
        process hears lags under load), the player is paused (SIGSTOP) until the restarted
        estimator's first status and its reader are seen here, then resumed (SIGCONT), so
        the data the estimator misses do not grow with the machine's load.
        None: the player never waits.
    kill_signal : int
        ``signal.SIGKILL`` (default) or ``signal.SIGTERM``.
    kill_node : str
        The node killed and started again: ``estimator`` (default), ``results`` or
        ``triangulation``.
    estimator_params, results_params : mapping, optional
        Parameters on top of the defaults of this module.
    domain_id : int, optional
        DDS domain of the pass (default ``1 + pid % 100``).

    Raises
    ------
    RuntimeError
        A node exited on its own, or the pass did not end within ``timeout`` seconds.
    """
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger

    from orbit_tracking.core.time import format_stamp
    from orbit_tracking.ros import qos
    from orbit_tracking.ros.conversions import (
        TimeBase,
        cloud_to_window_states,
        odometry_to_target_state,
        stamp_ns,
    )
    from orbit_tracking.tools.live import NODES, _env, _stop, node_command, package_location

    if kill_node not in _PROCESSING:
        raise ValueError(f'kill_node must be one of {_PROCESSING}; got {kill_node!r}')
    if max_gap is not None and kill_node != 'estimator':
        raise ValueError('max_gap is for estimator kills only')
    bag = Path(bag)
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda _text: None)
    epoch_ns, newest, probe_topic, has_telemetry = _bag_facts(bag)
    tb = TimeBase(epoch_ns)
    domain = int(domain_id) if domain_id is not None else 1 + os.getpid() % 100
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    where = package_location()
    env = {**_env(where), 'ROS_DOMAIN_ID': str(domain)}  # the source tree on PYTHONPATH
    ref = {'time_reference': tb.ref_ns * 1e-9}
    overrides: dict[str, dict[str, object]] = {
        'triangulation': dict(ref),
        'estimator': {
            **ref,
            **RESTART_WINDOWS,
            # no journal: the file's '' (an empty -p value does not parse)
            **({'journal_dir': str(work / 'journal')} if journal else {}),
            **(estimator_params or {}),
        },
        # the tail is flushed on request (~/flush) once the last window is in
        'results': {
            **ref,
            'flush_after': 3600.0,
            **({'journal_dir': str(work / 'journal')} if journal else {}),
            **(results_params or {}),
        },
    }
    spec = {s.executable: s for s in NODES}
    commands = {exe: node_command(spec[exe], where, overrides[exe]) for exe in _PROCESSING}

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node('orbit_tracking_bench_restart', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    states: list[Any] = []
    windows: list[Any] = []
    results: dict[str, str] = {}
    estimator: dict[str, str] = {}
    estimator_heard_ns = [0]  # header stamp (system time) of the estimator's newest status
    data_now = [-math.inf]

    def on_diag(msg: DiagnosticArray) -> None:
        for st in msg.status:
            if st.name == 'results: trajectory':
                results.clear()
                results.update({kv.key: kv.value for kv in st.values})
            elif st.name == 'estimator: windows':
                estimator_heard_ns[0] = max(estimator_heard_ns[0], stamp_ns(msg.header.stamp))
                estimator.clear()
                estimator.update({kv.key: kv.value for kv in st.values})

    def on_probe(msg: PointCloud2) -> None:
        data_now[0] = max(data_now[0], (stamp_ns(msg.header.stamp) - epoch_ns) * 1e-9)

    node.create_subscription(Odometry, '/trajectory/states', states.append, qos.MEASUREMENTS_SUB)
    node.create_subscription(
        PointCloud2, '/estimator/window_states', windows.append, qos.WINDOWS_SUB
    )
    node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, qos.DIAGNOSTICS)
    node.create_subscription(PointCloud2, probe_topic, on_probe, qos.MEASUREMENTS_SUB)
    if has_telemetry:  # a second reader, so that the player's wait covers telemetry too
        node.create_subscription(
            Odometry, '/telemetry/state', lambda _m: None, qos.MEASUREMENTS_SUB
        )
    client = node.create_client(Trigger, '/results/flush')
    procs: dict[str, subprocess.Popen[bytes]] = {}
    logs: dict[str, Path] = {}
    t_start = time.monotonic()
    out = PassResult(np.zeros(0, np.int64), np.zeros((0, 6)), np.zeros((0, 6)), [], epoch_ns)

    def start(label: str, cmd: Sequence[str]) -> None:
        logs[label] = work / f'{label}.log'
        procs[label] = _start(cmd, logs[label], env)

    def spin_until(pred: Callable[[], bool], limit: float, what: str) -> None:
        end = time.monotonic() + limit
        while not pred():
            dead = {
                k: p.returncode
                for k, p in procs.items()
                if k not in ('replay', f'{kill_node}_killed') and p.poll() is not None
            }
            if dead:
                raise RuntimeError(f'node process(es) exited {dead} while waiting for {what}')
            if time.monotonic() > end:
                raise RuntimeError(f'timed out after {limit:.0f} s waiting for {what}')
            executor.spin_once(timeout_sec=0.05)

    try:
        for exe in _PROCESSING:
            start(exe, commands[exe])
        spin_until(
            lambda: (
                node.count_publishers('/estimator/window_states') >= 1
                and node.count_subscribers('/estimator/window_states') >= 2
                and node.count_publishers('/trajectory/states') >= 1
                and node.count_publishers('/triangulation/fixes') >= 1
            ),
            90,
            'the nodes to come up',
        )
        say(
            f'nodes up after {time.monotonic() - t_start:.1f} s; replaying {bag.name} at {rate:g}x'
        )
        start(
            'replay',
            [sys.executable, '-m', 'orbit_tracking.tools.cli', 'replay', str(bag)]
            + ['--rate', str(rate), '--topics', '/stations/*', '/telemetry/state']
            + ['--wait-for-subscribers', '2', '--wait-timeout', '90'],
        )
        deadline = t_start + timeout
        if kill_after_windows is not None:
            if kill_at is not None:
                spin_until(
                    lambda: data_now[0] >= kill_at,
                    max(deadline - time.monotonic(), 1.0),
                    f'data time {kill_at:g} s before the kill',
                )
            spin_until(
                lambda: len(windows) >= kill_after_windows,
                max(deadline - time.monotonic(), 1.0),
                f'{kill_after_windows} window(s) before the kill',
            )
            if kill_after_checkpoint and kill_node == 'estimator':
                t1 = cloud_to_window_states(windows[kill_after_windows - 1], tb).t1
                spin_until(
                    lambda: _checkpointed(work / 'journal', t1),
                    30,
                    f'the journal checkpoint of the window ending at {t1:.3f} s',
                )
            end = time.monotonic() + kill_delay
            spin_until(lambda: time.monotonic() >= end, kill_delay + 1.0, 'the kill delay')
            out.windows_before_kill = len(windows)
            old_readers = _readers(node, probe_topic, kill_node)
            procs[kill_node].send_signal(kill_signal)
            procs[kill_node].wait(10)
            killed_at = time.monotonic()
            killed_ns = time.time_ns()  # a status stamped later is the new process's
            out.kill_data_s = data_now[0]
            procs[f'{kill_node}_killed'] = procs.pop(kill_node)
            say(
                f'{kill_node} killed ({signal.Signals(kill_signal).name}) at data time '
                f'{out.kill_data_s:.2f} s, after {len(windows)} window(s)'
            )

            def new_reader() -> bool:  # what the player sends before it matched the new
                # reader is lost to it (seconds under load); seen here is the proxy for that
                return bool(_readers(node, probe_topic, kill_node) - old_readers)

            paused = [False]
            resumed = [False]
            pause_lock = threading.Lock()

            def pause() -> None:
                """SIGSTOP the player once (not after it was resumed)."""
                with pause_lock:
                    if not (paused[0] or resumed[0]) and procs['replay'].poll() is None:
                        procs['replay'].send_signal(signal.SIGSTOP)
                        paused[0] = True

            # The data this process hears lag behind what the player sent when it is short
            # of CPU; the player cannot have sent more than max_gap / rate wall seconds of
            # data beyond the kill, so a timer pauses it then at the latest.
            timer = None
            if max_gap is not None:
                timer = threading.Timer(max_gap / rate, pause)
                timer.daemon = True
                timer.start()

            def hold(pred: Callable[[], bool]) -> Callable[[], bool]:
                """``pred``, pausing the player once the data pass ``max_gap``."""

                def check() -> bool:
                    if max_gap is not None and data_now[0] >= out.kill_data_s + max_gap:
                        pause()
                    return pred()

                return check

            end = time.monotonic() + restart_after
            spin_until(
                hold(lambda: time.monotonic() >= end), restart_after + 1.0, 'the restart delay'
            )
            start(f'{kill_node}_2', commands[kill_node])
            spin_until(
                hold(lambda: node.count_publishers(_OUTPUT_TOPIC[kill_node]) >= 1),
                60,
                f'the restarted {kill_node}',
            )
            if max_gap is not None:  # the player resumes once the new estimator is up
                spin_until(
                    hold(lambda: estimator_heard_ns[0] > killed_ns and new_reader()),
                    60,
                    f'the restarted estimator: its first status and reader of {probe_topic}',
                )
            if timer is not None:
                timer.cancel()
            with pause_lock:
                resumed[0] = True
                if paused[0]:
                    procs['replay'].send_signal(signal.SIGCONT)
            if paused[0]:
                out.paused_data_s = data_now[0]
                say(f'the player waited at data time {out.paused_data_s:.2f} s')
            if kill_node == 'estimator':
                estimator.clear()
                spin_until(
                    lambda: float(estimator.get('measurement_messages', 0)) > 0,
                    60,
                    'the first measurement message at the restarted estimator',
                )
            elif kill_node == 'results':
                results.clear()
                spin_until(lambda: bool(results), 60, 'the restarted results node')
            out.restart_wall_s = time.monotonic() - killed_at
            out.ready_data_s = data_now[0]
            say(
                f'{kill_node} back {out.restart_wall_s:.1f} s after the kill, at data time '
                f'{out.ready_data_s:.2f} s'
            )
        last_end = [-math.inf]

        def ended() -> bool:
            for m in windows[len(out.windows) :]:
                out.windows.append(cloud_to_window_states(m, tb))
                last_end[0] = max(last_end[0], out.windows[-1].t1)
            return procs['replay'].poll() is not None and last_end[0] >= newest - 1e-6

        spin_until(
            ended,
            max(deadline - time.monotonic(), 1.0),
            f'the replay to end and the last window (cut at {newest:.3f} s)',
        )
        # the results node must have taken the last window before the tail is flushed
        last_stamp = format_stamp(epoch_ns, last_end[0])
        spin_until(
            lambda: results.get('last_window_end') == last_stamp,
            30,
            f'the results node to take the last window (ending {last_stamp})',
        )
        if not client.wait_for_service(timeout_sec=20.0):
            raise RuntimeError('the results node offers no ~/flush')
        future = client.call_async(Trigger.Request())
        spin_until(future.done, 30, 'the results ~/flush response')
        quiet = [time.monotonic(), len(states)]

        def settled() -> bool:
            if len(states) != quiet[1]:
                quiet[:] = [time.monotonic(), len(states)]
            return time.monotonic() - quiet[0] > 1.5

        spin_until(settled, 30, 'the last states')
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGCONT)  # a paused player takes its SIGINT
            _stop(proc)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    out.wall_s = time.monotonic() - t_start
    out.logs = {k: p.read_text(errors='replace') for k, p in logs.items()}
    out.results = dict(results)
    out.estimator = dict(estimator)
    samples = [odometry_to_target_state(m, tb) for m in states]
    out.stamps = np.array([stamp_ns(m.header.stamp) for m in states], dtype=np.int64)
    out.state = np.array([np.concatenate([s.position, s.velocity]) for s in samples]).reshape(
        -1, 6
    )
    out.sigma = np.sqrt(
        np.array(
            [np.concatenate([np.diag(s.position_cov), np.diag(s.velocity_cov)]) for s in samples]
        ).reshape(-1, 6)
    )
    return out


def measure_restart_loss(
    bag: str | Path | None = None,
    *,
    rate: float = 1.0,
    journal: bool = True,
    kill_after_windows: int = 1,
    kill_at: float | None = None,
    kill_after_checkpoint: bool = True,
    kill_delay: float = 0.0,
    restart_after: float = 1.0,
    kill_signal: int = signal.SIGKILL,
    kill_node: str = 'estimator',
    clean: PassResult | None = None,
    clean_rate: float = 10.0,
    estimator_params: Mapping[str, object] | None = None,
    results_params: Mapping[str, object] | None = None,
    work_dir: str | Path | None = None,
    domain_id: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """States lost to a kill and restart of a processing node (``kill_node``, default the
    estimator) mid-pass.

    Runs a clean pass (at ``clean_rate``: the results do not depend on the replay speed;
    or takes ``clean``), then a pass at ``rate`` in which the estimator is killed once
    ``kill_after_windows`` windows have arrived, the data have reached ``kill_at`` and (with
    ``kill_after_checkpoint`` and the journal) the journal holds the last window's
    checkpoint, plus ``kill_delay`` s, and started again ``restart_after`` s later; then
    compares them (:func:`compare_passes`). See :func:`run_pass` for the parameters.

    Returns
    -------
    dict
        The comparison, plus ``bag``, ``rate``, ``journal``, ``signal``, ``kill_data_s``,
        ``ready_data_s`` (data time when the new process was up), ``restart_wall_s``,
        ``windows_clean``, ``windows_killed``, the results node's ``flushes``,
        ``states_already_final``, ``estimator_gone`` and ``duplicate_windows``, the
        restarted estimator's journal line and each pass's wall time.
    """
    if bag is None:
        from orbit_tracking.tools.live import package_location

        root = package_location().source_root
        if root is None:
            raise FileNotFoundError('no source tree with test/data/bags: give the bag')
        bag = root / 'test' / 'data' / 'bags' / RESTART_BAG
    bag = Path(bag)
    with tempfile.TemporaryDirectory(prefix='orbit_tracking_restart_') as tmp:
        work = Path(work_dir) if work_dir is not None else Path(tmp)
        common: dict[str, Any] = {
            'estimator_params': estimator_params,
            'results_params': results_params,
            'domain_id': domain_id,
            'progress': progress,
        }
        if clean is None:
            clean = run_pass(bag, work / 'clean', rate=clean_rate, journal=journal, **common)
        killed = run_pass(
            bag,
            work / 'killed',
            rate=rate,
            journal=journal,
            kill_after_windows=kill_after_windows,
            kill_at=kill_at,
            kill_after_checkpoint=kill_after_checkpoint and journal,
            kill_delay=kill_delay,
            restart_after=restart_after,
            kill_signal=kill_signal,
            kill_node=kill_node,
            **common,
        )
    out: dict[str, Any] = {
        'bag': bag.name,
        'node': kill_node,
        'rate': rate,
        'journal': journal,
        'signal': signal.Signals(kill_signal).name,
        **compare_passes(clean, killed),
        'kill_data_s': round(killed.kill_data_s, 3),
        'ready_data_s': round(killed.ready_data_s, 3),
        'restart_wall_s': round(killed.restart_wall_s, 2),
        'windows_clean': len(clean.windows),
        'windows_killed': len(killed.windows),
    }
    for key in ('flushes', 'states_already_final', 'estimator_gone'):
        out[key] = killed.results.get(key, '')
    out['duplicate_windows'] = killed.results.get('rejected_duplicate_window', '0')
    out['journal_log'] = next(
        (
            line.strip()
            for line in killed.logs.get('estimator_2', '').splitlines()
            if 'journal' in line and 'replayed' in line
        ),
        '',
    )
    out['wall_s'] = {'clean': round(clean.wall_s, 1), 'killed': round(killed.wall_s, 1)}
    out['passes'] = {'clean': clean, 'killed': killed}
    return out
