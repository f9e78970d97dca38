"""One replay of a regression bag through the running ``triangulation``, ``estimator`` and
``results`` nodes over real DDS with fault classes injected
(:func:`replay_with_faults`; the suite around it is :mod:`orbit_tracking.tools.bench.faults`).

1. The three nodes start as the main job starts them (``orbit_tracking.tools.live``: each
   its own process, its ``config/<node>.yaml`` plus :data:`OVERRIDES` and the bag's epoch as
   ``time_reference``), in the root namespace (the bag's topic names are absolute) of the
   run's own DDS domain, discovery on localhost.
2. This process opens two DDS participants: the *replay* publishes the bag's station and
   telemetry messages as recorded (CDR bytes untouched) at ``rate`` times the recorded
   pace, and watches ``/diagnostics``, ``estimator/window_states`` and
   ``trajectory/states``; the *injector* publishes the bad messages. Both wait until the
   nodes read every topic they will use.
3. The replay stops at a few data times. At a stop the nodes are let settle (their
   ``/diagnostics`` show every message taken); then each fault class of the stop gets its
   *phase*: the injector publishes the class's messages, built from the real messages just
   replayed, and the run waits for a ``/diagnostics`` status of every node that shows them
   taken (:meth:`Participants.settled`). The counters that grew meanwhile are the class's.
4. After the last message the estimator solves what it holds (``~/solve``), the results
   node publishes what it holds (``~/flush``) and the triangulation node fixes the epochs
   its lag holds (``~/flush``); the run keeps every ``trajectory/states``
   message, the final counters, the nodes' exit statuses after SIGINT and the tracebacks
   in their logs (inside a phase: the phase's; elsewhere: the replay's).

A node that exits, or shows nothing new for :data:`SETTLE_S` seconds, ends the run; inside
a phase it is the phase's class's doing. The stops must not look like the end of the data
(a stream heard from last ``silent_after`` seconds ago is taken for quiet, and
``flush_after`` seconds without data for the end of the stream), so the nodes run with
``silent_after`` and ``flush_after`` at :data:`QUIET` seconds and their ends are asked for
(the services above); the clean replay (no class) runs the same way and is the reference.

Which keys of a status are rejection counters, and which are symptoms, is
:mod:`~orbit_tracking.tools.bench.fault_monitor`'s to say; the run records them by name.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from orbit_tracking.tools.bench.fault_catalogue import FaultClass
from orbit_tracking.tools.bench.fault_messages import (
    FIXES,
    NODES,
    RESIDUALS,
    TELEMETRY,
    WINDOWS,
    Reference,
)
from orbit_tracking.tools.bench.fault_monitor import (
    Participants,
    Tick,
    as_int,
    counters,
    grew,
    residual_gate,
    wait_graph_clear,
)
from orbit_tracking.tools.live import log_tail

__all__ = [
    'DEFAULT_BAG',
    'OVERRIDES',
    'DIAGNOSTICS_PERIOD',
    'QUIET',
    'SETTLE_S',
    'STOP_S',
    'Phase',
    'ReplayRun',
    'Segment',
    'load_bag',
    'replay_with_faults',
]

DEFAULT_BAG = Path(__file__).resolve().parents[3] / 'test' / 'data' / 'bags' / 'seed000_s1_20_50'
"""30 s of seed000_s1 (13 stations and telemetry; see test/data/README.md)."""

QUIET = 60.0
"""``silent_after`` and ``flush_after`` of the processing nodes [s]: longer than any stop of
the replay."""

DIAGNOSTICS_PERIOD = 0.25
"""The nodes' ``diagnostics_period`` [s]: a phase waits for a status of every node that
shows its messages taken (at the default 1 s, a phase took 1.3 s)."""

_QUIET = {'silent_after': QUIET, 'flush_after': QUIET, 'diagnostics_period': DIAGNOSTICS_PERIOD}
OVERRIDES: dict[str, dict[str, object]] = {
    'triangulation': dict(_QUIET),
    'estimator': {
        'window_length': 12.0,  # four windows over the bag, as test_regression_bags
        'window_overlap': 4.0,
        'latency': 2.0,
        'output_step': 0.1,
        **_QUIET,
    },
    'results': {'flush_after': 3600.0, 'diagnostics_period': DIAGNOSTICS_PERIOD},
}
"""Parameters set on top of each node's ``config/<node>.yaml``."""

STOP_S = 30.0
"""Seconds the nodes have, together, to exit after SIGINT: a node still running then is
hung. (Each of them exits within a second on an idle machine; under the test suite's load
on two cores the triangulation node once took more than the 10 s allowed before.)"""

SETTLE_S = 20.0
"""Seconds a node may take to show a message taken before it counts as hung."""

_MARGIN_S = {True: 0.15, False: 0.4}  # a status this long after a publication reflects it
# (counted: the status also shows the message count; not counted: telemetry, states, ...)
_CLEAN_EXIT = {0, -signal.SIGINT, 128 + signal.SIGINT}
_TRACEBACK = 'Traceback (most recent call last)'


@dataclass
class Phase:
    """One fault class's phase of a replay: messages sent, the rejection counters that grew
    per node, the symptom counters that grew, and the tracebacks the nodes logged."""

    sent: int
    grew: dict[str, dict[str, int]] = field(default_factory=dict)
    symptoms: dict[str, dict[str, int]] = field(default_factory=dict)
    tracebacks: dict[str, str] = field(default_factory=dict)


@dataclass
class Segment:
    """The classes of one stop, and the rejection counters per node that grew after their
    phases: while the replay went on to the next stop (or to its end)."""

    faults: tuple[str, ...]
    grew: dict[str, dict[str, int]] = field(default_factory=dict)


@dataclass
class ReplayRun:
    """One replay of the bag with fault classes injected.

    ``aborted`` is (class, what happened) when a node died or hung in a class's phase;
    ``end_problem`` says what went wrong elsewhere (a node that died or hung at the end, a
    traceback outside the phases, an unclean exit). ``states`` maps (child frame, stamp ns)
    to the position (3,) of every ``trajectory/states`` message; ``final`` the rejection
    counters per node at the end (the estimator's with the running residual-gate counts
    the results node relays, ``residual gate <station>/<key>``); ``final_symptoms`` the
    symptom counters.
    """

    faults: tuple[str, ...]
    phases: dict[str, Phase] = field(default_factory=dict)
    segments: list[Segment] = field(default_factory=list)
    aborted: tuple[str, str] | None = None
    end_problem: str = ''
    states: dict[tuple[str, int], np.ndarray] = field(default_factory=dict)
    state_msgs: int = 0
    final: dict[str, dict[str, int]] = field(default_factory=dict)
    final_symptoms: dict[str, dict[str, int]] = field(default_factory=dict)
    exit_codes: dict[str, int] = field(default_factory=dict)
    windows: int = 0
    wall_s: float = 0.0
    timing: dict[str, float] = field(default_factory=dict)
    log_dir: Path | None = None


# -- the bag -------------------------------------------------------------------------------


@dataclass(frozen=True)
class _BagMessage:
    topic: str
    msgtype: str
    log_ns: int
    stamp_ns: int
    raw: bytes
    latched: bool

    @property
    def measurement(self) -> bool:
        return self.topic.endswith('/measurements')


@dataclass(frozen=True)
class _Bag:
    path: Path
    epoch_ns: int
    world_frame: str
    messages: tuple[_BagMessage, ...]
    truth: tuple[tuple[int, np.ndarray], ...]


def load_bag(path: Path = DEFAULT_BAG) -> _Bag:
    """A bag's station and telemetry messages (what the nodes read), in log-time order, its
    truth and its epoch (``orbit_tracking.epoch`` of its labels)."""
    from rclpy.serialization import deserialize_message
    from rosbags.rosbag2 import Reader

    from orbit_tracking.ros.bag import bag_custom_data, message_class
    from orbit_tracking.ros.player import header_stamp_ns

    labels = bag_custom_data(path)
    epoch_ns = int(round(float(labels['orbit_tracking.epoch']) * 1e9))
    out, truth = [], []
    with Reader(Path(path)) as reader:
        for conn, t_log, raw in reader.messages():
            topic = '/' + conn.topic.lstrip('/')
            data = bytes(raw)
            stamp = header_stamp_ns(data) or 0
            if topic == '/truth/state':
                m = deserialize_message(data, message_class(conn.msgtype))
                p, v = m.pose.pose.position, m.twist.twist.linear
                truth.append((stamp, np.array([p.x, p.y, p.z, v.x, v.y, v.z])))
            elif topic.startswith('/stations/') or topic == TELEMETRY:
                profiles = getattr(getattr(conn, 'ext', None), 'offered_qos_profiles', None)
                latched = bool(profiles) and (
                    getattr(profiles[0].durability, 'name', '') == 'TRANSIENT_LOCAL'
                )
                out.append(_BagMessage(topic, conn.msgtype, t_log, stamp, data, latched))
    return _Bag(
        Path(path),
        epoch_ns,
        labels.get('orbit_tracking.world_frame', 'earth'),
        tuple(sorted(out, key=lambda m: m.log_ns)),
        tuple(truth),
    )


class _Abort(Exception):
    """A node died or hung."""


def _read(ticks: dict[str, Tick]) -> dict[str, tuple[dict[str, int], dict[str, int]]]:
    """(rejection counters, symptom counters) of every node in one status each; the
    estimator's with the running residual-gate counts the results node relays."""
    out = {n: counters(n, ticks[n].values) for n in NODES}
    out['estimator'][0].update(residual_gate(ticks['results'].values))
    return out


# -- one replay ------------------------------------------------------------------------------


class _Replay:
    def __init__(
        self,
        bag: _Bag,
        faults: Sequence[FaultClass],
        log_dir: Path,
        rate: float,
        domain: int,
        source: Path | None,
    ) -> None:
        self.bag = bag
        self.source = source
        self.faults = list(faults)
        self.log_dir = log_dir
        self.rate = rate
        self.domain = domain
        self.run = ReplayRun(tuple(f.name for f in faults), log_dir=log_dir)
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.logs: dict[str, Path] = {}
        self.i = 0  # next bag message
        self.latest: dict[str, bytes] = {}
        self.station_sent = 0  # station measurement messages published (both participants)
        self.telemetry_sent = 0  # telemetry messages published (both participants)
        self.injected_windows = 0
        self.snapshot: dict[str, Tick] = {}
        self.log_marks: dict[str, int] = {}  # log bytes already scanned for tracebacks
        self.t0 = time.monotonic()

    # -- processes --
    def start_nodes(self) -> None:
        from orbit_tracking.tools.live import NODES as SPECS
        from orbit_tracking.tools.live import PackageLocation, node_command, package_location

        where = package_location()
        if self.source is not None:
            where = PackageLocation(None, self.source / 'config', self.source)
        env = dict(os.environ)
        env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
        env['ROS_DOMAIN_ID'] = str(self.domain)
        env['PYTHONUNBUFFERED'] = '1'
        env['RCUTILS_COLORIZED_OUTPUT'] = '0'
        env['PYTHONFAULTHANDLER'] = '1'  # SIGABRT on a hung node: every thread's stack
        if where.source_root is not None:  # python -m must find this very tree
            path = (str(where.source_root), env.get('PYTHONPATH', ''))
            env['PYTHONPATH'] = os.pathsep.join(p for p in path if p)
        spec = {s.executable: s for s in SPECS}
        for node in NODES:
            params = {**OVERRIDES[node], 'time_reference': self.bag.epoch_ns * 1e-9}
            self.logs[node] = self.log_dir / f'{node}.log'
            with open(self.logs[node], 'wb') as log:
                self.procs[node] = subprocess.Popen(
                    node_command(spec[node], where, params),
                    env=env,
                    stdin=subprocess.DEVNULL,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                )

    def alive(self) -> None:
        for node, proc in self.procs.items():
            if proc.poll() is not None:
                raise _Abort(f'{node} exited with status {proc.returncode}')

    def stop_nodes(self) -> None:
        """SIGINT every node; one still running :data:`STOP_S` seconds later gets SIGABRT
        (its log then shows every thread's stack: the nodes run with faulthandler on),
        then SIGKILL."""
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + STOP_S
        for node, proc in self.procs.items():
            try:
                proc.wait(timeout=max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                proc.send_signal(signal.SIGABRT)
                try:
                    proc.wait(timeout=5.0)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(timeout=10.0)
            self.run.exit_codes[node] = int(proc.returncode)

    def scan(self) -> dict[str, str]:
        """Tracebacks the nodes logged since the last scan (node -> text)."""
        out = {}
        for n in NODES:
            try:
                with open(self.logs[n], 'rb') as fh:
                    fh.seek(self.log_marks.get(n, 0))
                    text = fh.read().decode(errors='replace')
                    self.log_marks[n] = fh.tell()
            except OSError:
                continue
            if _TRACEBACK in text:
                out[n] = text[text.index(_TRACEBACK) :][:3000]
        return out

    def outside(self) -> None:
        """A traceback logged outside any phase is a problem of the replay as a whole."""
        for n, text in self.scan().items():
            self.run.end_problem = self.run.end_problem or f'traceback in {n}: {text[:1500]}'

    # -- waiting --
    def wait(self, what: str, predicate: Callable[[], bool], timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while not predicate():
            self.alive()
            if time.monotonic() > deadline:
                raise _Abort(f'timed out after {timeout:.0f} s waiting for {what}')
            time.sleep(0.02)

    def settle(
        self, ros: Participants, after: float, nodes: Sequence[str] = NODES, counted: bool = True
    ) -> dict[str, Tick]:
        """A status of each of ``nodes`` published after ``after`` (system time) that shows
        it took every message sent so far (see :meth:`Participants.settled`)."""
        start = time.monotonic()
        out: dict[str, Tick] = {}
        while True:
            self.alive()
            for node in nodes:
                if node not in out:
                    t = ros.settled(node, after, self.expect(ros, node), _MARGIN_S[counted])
                    if t is not None:
                        out[node] = t
            if len(out) == len(nodes):
                return out
            if time.monotonic() - start > SETTLE_S:
                late = ' and '.join(n for n in nodes if n not in out)
                raise _Abort(
                    f'{late} hung: no /diagnostics status showing the messages taken within '
                    f'{SETTLE_S:.0f} s'
                )
            time.sleep(0.02)

    def expect(self, ros: Participants, node: str) -> dict[str, int]:
        if node == 'results':
            with ros.lock:
                return {'windows_received': ros.windows + self.injected_windows}
        # the triangulation node takes no telemetry (it reports no telemetry_messages, so
        # that key is not waited for there)
        return {
            'measurement_messages': self.station_sent,
            'telemetry_messages': self.telemetry_sent,
        }

    # -- replaying --
    def play(self, ros: Participants, until_s: float | None) -> None:
        """Publish the bag's messages at ``rate`` times their recorded pace, up to the first
        measurement stamped at or after ``until_s`` (data seconds; None: to the end)."""
        msgs = self.bag.messages
        until = None if until_s is None else self.bag.epoch_ns + int(round(until_s * 1e9))
        wall0, log0 = time.monotonic(), None
        while self.i < len(msgs):
            m = msgs[self.i]
            if until is not None and m.measurement and m.stamp_ns >= until:
                break
            log0 = m.log_ns if log0 is None else log0
            wait = wall0 + (m.log_ns - log0) * 1e-9 / self.rate - time.monotonic()
            if wait > 0.0005:
                time.sleep(wait)
            ros.pubs[m.topic].publish(m.raw)
            self.latest[m.topic] = m.raw
            self.station_sent += m.measurement
            self.telemetry_sent += m.topic == TELEMETRY
            self.i += 1

    def reference(self, t: float) -> Reference:
        from rclpy.serialization import deserialize_message

        from orbit_tracking.ros.bag import message_class

        types = {m.topic: m.msgtype for m in self.bag.messages}
        latest = {
            topic: deserialize_message(raw, message_class(types[topic]))
            for topic, raw in self.latest.items()
        }
        return Reference(t, self.bag.epoch_ns, latest, self.bag.truth, self.bag.world_frame)

    def phase(self, ros: Participants, fault: FaultClass, t: float) -> None:
        self.outside()
        before = _read(self.snapshot)
        msgs = fault.build(self.reference(t))
        counted = True
        for inj in msgs:
            if inj.topic == WINDOWS:
                ros.injected_windows.add(bytes(inj.msg.data))
                self.injected_windows += 1
            elif inj.topic.endswith('/measurements'):
                self.station_sent += 1
            elif inj.topic == TELEMETRY:
                self.telemetry_sent += 1
            else:
                counted = False
        phase = self.run.phases[fault.name] = Phase(len(msgs))
        sent_at = time.time()
        for inj in msgs:
            ros.bad_pubs[inj.topic].publish(inj.msg)
        try:
            self.snapshot = self.settle(ros, sent_at, counted=counted)
        finally:
            phase.tracebacks = self.scan()
        after = _read(self.snapshot)
        for n in NODES:
            phase.grew[n] = grew(before[n][0], after[n][0])
            phase.symptoms[n] = grew(before[n][1], after[n][1])

    def close_segment(self, ticks: dict[str, Tick]) -> None:
        """What grew from the end of the last stop's phases until ``ticks``."""
        if self.run.segments:
            before, after = _read(self.snapshot), _read(ticks)
            self.run.segments[-1].grew = {n: grew(before[n][0], after[n][0]) for n in NODES}

    def plan(self) -> list[tuple[float, list[FaultClass]]]:
        """The stops: each class's :attr:`~FaultClass.at`, in time order."""
        times = sorted({f.at for f in self.faults})
        return [(t, [f for f in self.faults if f.at == t]) for t in times]

    def connect(self, ros: Participants) -> None:
        """Wait until every node is up and reads every topic we publish on."""
        readers = {TELEMETRY: 1, FIXES: 1, WINDOWS: 2, RESIDUALS: 1}  # WINDOWS: and ours
        latched = {m.topic for m in self.bag.messages if m.latched}

        def ready() -> bool:
            pubs = [(t, p) for t, p in ros.pubs.items() if t not in latched]
            pubs += list(ros.bad_pubs.items())
            return (
                all(ros.last(n) is not None for n in NODES)
                and all(p.get_subscription_count() >= readers.get(t, 2) for t, p in pubs)
                and ros.node.count_publishers('/trajectory/states') >= 1
                and ros.solve.service_is_ready()
                and ros.flush.service_is_ready()
                and ros.tri_flush.service_is_ready()
            )

        self.wait('the nodes to come up and read every topic', ready, 90.0)
        time.sleep(0.5)  # endpoint matching follows graph discovery closely

    def finish(self, ros: Participants) -> None:
        """The end of the stream: every message taken, the last windows solved and
        stitched, the held states published; the final counters."""
        final = self.settle(ros, time.time())
        if self.telemetry_sent and 'telemetry_messages' not in final['estimator'].values:
            raise _Abort('the estimator counts no telemetry_messages: cannot wait for its tail')
        # every station and telemetry message is taken (counted: telemetry has more
        # messages per second and can lag behind the stations under load, and ~/solve does
        # not wait for late streams); the fixes are not counted: one more status,
        # published while the node idled, and their queue is empty too
        final.update(self.settle(ros, final['estimator'].stamp, ('estimator',)))
        est = as_int(final['estimator'].values.get('windows_solved', '0'))
        answer = ros.call(ros.solve, 60.0)
        if answer is None:
            raise _Abort('the estimator did not answer ~/solve within 60 s (hung)')
        solved = est + answer.count(' solved')
        self.wait('the last windows', lambda: ros.windows >= solved, 20.0)
        after_solve = time.time()
        final.update(self.settle(ros, after_solve, ('estimator', 'results')))
        held = as_int(final['results'].values.get('states_published', '0'))
        answer = ros.call(ros.flush, 30.0)
        if answer is None:
            raise _Abort('the results node did not answer ~/flush within 30 s (hung)')
        words = answer.split()
        flushed = held + (as_int(words[1]) if len(words) > 1 and words[0] == 'published' else 0)

        def all_states() -> bool:
            with ros.lock:
                return ros.state_msgs >= flushed

        self.wait('the final trajectory/states', all_states, 30.0)
        # the triangulation node's own end of stream: it fixes what its lag holds and
        # counts what it could not use
        if ros.call(ros.tri_flush, 30.0) is None:
            raise _Abort('the triangulation node did not answer ~/flush within 30 s (hung)')
        final.update(self.settle(ros, time.time(), ('triangulation',)))
        self.close_segment(final)
        for n, (rejections, symptoms) in _read(final).items():
            self.run.final[n] = rejections
            self.run.final_symptoms[n] = symptoms

    def execute(self) -> ReplayRun:
        self.start_nodes()
        topics = [(m.topic, m.msgtype, m.latched) for m in self.bag.messages]
        bad = [t for f in self.faults for t in f.topics]
        ros = Participants(topics, bad, self.domain)
        current = ''
        try:
            try:
                self.connect(ros)
            except _Abort as exc:
                raise RuntimeError(f'fault replay: {exc}; logs in {self.log_dir}') from None
            self.run.timing['up'] = time.monotonic() - self.t0
            for t, faults in self.plan():
                self.play(ros, t)
                if any(set(f.topics) & {WINDOWS, RESIDUALS} for f in faults):
                    # a bad window must meet a results node that has a time line: the
                    # first real window may come late on a loaded machine (seen: 2.6 s)
                    self.wait('the first window', lambda: ros.windows >= 1, 60.0)
                ticks = self.settle(ros, time.time())
                self.close_segment(ticks)
                self.snapshot = ticks
                for f in faults:
                    current = f.name
                    self.phase(ros, f, t)
                current = ''
                self.run.segments.append(Segment(tuple(f.name for f in faults)))
            self.play(ros, None)
            self.run.timing['replayed'] = time.monotonic() - self.t0
            self.finish(ros)
            self.run.timing['finished'] = time.monotonic() - self.t0
        except _Abort as exc:
            if current:
                self.run.aborted = (current, str(exc))
            else:
                self.run.end_problem = str(exc)
        finally:
            with ros.lock:
                self.run.states = dict(ros.states)
                self.run.state_msgs = ros.state_msgs
                self.run.windows = ros.windows
            ros.close()
            self.stop_nodes()
        if not self.run.aborted:
            self.outside()  # the end, and the shutdown on SIGINT
            for n in NODES:
                code = self.run.exit_codes.get(n)
                if code not in _CLEAN_EXIT and not self.run.end_problem:
                    tail = log_tail(self.logs[n], 2500)
                    self.run.end_problem = f'{n} exited with status {code} on SIGINT:\n{tail}'
        self.run.wall_s = time.monotonic() - self.t0
        return self.run


def replay_with_faults(
    faults: Sequence[FaultClass],
    log_dir: Path,
    bag: _Bag | None = None,
    rate: float = 10.0,
    domain: int | None = None,
    source: Path | None = None,
) -> ReplayRun:
    """One replay of ``bag`` (default :data:`DEFAULT_BAG`, from :func:`load_bag`) through
    the three nodes with ``faults`` injected (none: the clean replay), in DDS domain
    ``domain`` (default ``ROS_DOMAIN_ID``, else ``1 + pid % 100``); node logs go to
    ``log_dir``. The nodes come from ``source`` (a copy of the source tree: ``orbit_tracking``
    and ``config``) if given, else from where this package runs. See the module
    docstring."""
    if domain is None:
        domain = int(os.environ.get('ROS_DOMAIN_ID') or 1 + os.getpid() % 100)
    log_dir.mkdir(parents=True, exist_ok=True)
    wait_graph_clear(domain)
    replay = _Replay(bag or load_bag(), faults, log_dir, rate, domain, source)
    return replay.execute()
