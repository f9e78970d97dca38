"""``results``: the estimator's overlapping windows stitched into one trajectory.

Subscribes to ``estimator/window_states`` (each solved window's states, ``PointCloud2``)
and ``estimator/window_residuals`` (its residual statistics per station), hands over from
one window to the next with the offline tool's blend, and publishes each state once it is
final (no later window can change it; the rule is in
:mod:`orbit_tracking.core.estimation.stitcher`):

* ``trajectory/states`` (``nav_msgs/Odometry``, every target or the ``target_id`` one) and
  ``trajectory/target_<id>/states``;
* ``trajectory/path`` (``nav_msgs/Path``, transient local: the ``target_id`` target, or the
  lowest id seen) and ``trajectory/target_<id>/path``;
* ``/diagnostics``: ``results: trajectory`` (windows, states, rejected messages) and one
  ``results: residuals <station>`` per station (whitened-residual statistics of the pass).

States are in the world frame of the windows, or with ``output_frame:=launch`` in the
launch frame (``launch_site`` or the ``scenario``'s launch point).

When the estimator's publisher goes away (it exits), the states held wait
``estimator_gone_grace`` seconds for it to come back (a restart), so that its next window
hands over from the last one as usual. With ``journal_dir`` a results node killed and
started again goes on where it was (:mod:`~orbit_tracking.ros.results_journal`).

Example::

    ros2 run orbit_tracking results --ros-args -p output_frame:=launch -p scenario:=seed000_s1

The module is over the project's ~600-line guide: about 100 lines are parameter
declarations (each with its description and range), about 120 the two diagnostics
statuses and 25 the journal's resume; the stitching is :class:`~orbit_tracking.core.
estimation.stitcher.TrajectoryStitcher` and the choice of windows :class:`~orbit_tracking.
core.estimation.stitcher.TimeLine`.
"""

from __future__ import annotations

import math
import time
from collections import Counter, deque
from collections.abc import Callable

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry, Path
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from orbit_tracking.core import frames
from orbit_tracking.core.estimation.residuals import ResidualStats
from orbit_tracking.core.estimation.stitcher import (
    FinalStates,
    SampledWindow,
    TimeLine,
    TrajectoryStitcher,
    split_window,
)
from orbit_tracking.core.models.limits import TargetLimit
from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.core.time import format_stamp
from orbit_tracking.ros import qos
from orbit_tracking.ros.conversions import (
    TimeBase,
    WindowResiduals,
    WindowStates,
    checked_stamp_ns,
    cloud_to_window_states,
    diagnostic_array,
    diagnostic_status,
    msg_to_window_residuals,
    target_frame_id,
    target_state_to_odometry,
)
from orbit_tracking.ros.guard import guarded
from orbit_tracking.ros.parameters import declare, diagnostics_timer
from orbit_tracking.ros.results_journal import ResultsJournal
from orbit_tracking.ros.runner import run_node

__all__ = ['OUTPUT_FRAMES', 'ResultsNode', 'main']

OUTPUT_FRAMES = ('world', 'launch')
"""Values of the ``output_frame`` parameter."""

_SAME_TIME = 1e-6  # s: two windows ending within this are the same window
_NO_WAIT = Duration(seconds=0)
_SEEN_MAX = 64  # windows of the time line remembered, to know the estimator's kept ones
_SEEN_NS = 1000  # ns: a window whose start and end are this close to one seen is that one
_MAX_RESIDUAL_STATIONS = 256  # residual sums kept for at most this many station ids
_RMS_WARN = 3.0  # whitened RMS above this: the sigmas (or the model) do not fit the data


def _child_frame(target_id: int) -> str:
    """``target`` for target 0 (as the offline tool writes it), ``target_<id>`` otherwise;
    both read back with ``target_id_from_frame``."""
    return 'target' if target_id == 0 else target_frame_id(target_id)


class ResultsNode(Node):
    def __init__(self) -> None:
        super().__init__('results')
        output_frame = declare(
            self,
            'output_frame',
            'world',
            "Frame of the published states: world (the windows' world frame) or launch "
            '(the launch frame of launch_site or scenario; needs the earth world frame).',
            read_only=True,
        )
        if output_frame not in OUTPUT_FRAMES:
            raise ValueError(f'output_frame must be one of {OUTPUT_FRAMES}; got {output_frame!r}')
        scenario = declare(
            self,
            'scenario',
            '',
            'Scenario (name or YAML path) whose launch point defines the launch frame; '
            'alternative to launch_site.',
            read_only=True,
        )
        site = list(
            declare(
                self,
                'launch_site',
                [],
                'Launch point as [latitude_deg, longitude_deg, height_m, azimuth_deg] '
                '(geodetic WGS-84; azimuth from north toward east); alternative to scenario.',
                read_only=True,
                param_type=Parameter.Type.DOUBLE_ARRAY,
            )
        )
        self.target_id = declare(
            self,
            'target_id',
            -1,
            'Target on trajectory/states and trajectory/path; -1 = every target on the states '
            'and the lowest id seen on the path.',
            read_only=True,
            min_value=-1,
            max_value=2**31 - 1,
        )
        self.time_reference = declare(
            self,
            'time_reference',
            0.0,
            'Stamp [s] of internal time 0; 0 = the whole second of the first stamp received.',
            read_only=True,
            min_value=0.0,
        )
        self.flush_after = declare(
            self,
            'flush_after',
            120.0,
            'Wall seconds without a new window after which the states still held are '
            'published (end of the stream). Keep it above the wall time between two '
            'windows (window_length - window_overlap, over the replay rate, plus the solve).',
            read_only=True,
            min_value=0.1,
            max_value=86400.0,
        )
        self.estimator_gone_grace = declare(
            self,
            'estimator_gone_grace',
            10.0,
            'Wall seconds the states held wait for an estimator whose publisher went away to '
            'come back (a restart: its windows then hand over as usual) before they are '
            'published; 0 = at once.',
            read_only=True,
            min_value=0.0,
            max_value=86400.0,
        )
        self.path_step = declare(
            self,
            'path_step',
            0.0,
            'Smallest time step [s] between the poses of the paths; 0 = every state.',
            read_only=True,
            min_value=0.0,
            max_value=3600.0,
        )
        self.path_max_poses = declare(
            self,
            'path_max_poses',
            20000,
            'Most poses a path holds: beyond it every other pose is dropped (the whole pass '
            'stays covered, more coarsely), so a night-long pass keeps the latched path '
            'message bounded.',
            read_only=True,
            min_value=100,
            max_value=10_000_000,
        )
        max_targets = declare(
            self,
            'max_targets',
            32,
            'Distinct target ids published (first come; each has its own topics); states '
            'of further ids are dropped and counted (too_many_targets), and a window with '
            'more ids than this is refused whole.',
            read_only=True,
            min_value=1,
            max_value=4096,
        )
        max_window_jump = declare(
            self,
            'max_window_jump',
            3600.0,
            'A window starting more than this many seconds after the last one, or ending '
            'before it (time went back), is held until the next window confirms the new '
            'time line (or the stream ends); one stray window cannot restart the trajectory.',
            read_only=True,
            min_value=1.0,
            max_value=1e9,
        )
        self.timeline: TimeLine[tuple[WindowStates, list[SampledWindow], TimeBase]] = TimeLine(
            max_window_jump
        )
        self.targets = TargetLimit(max_targets)
        self.launch = self._launch_frame(output_frame, scenario, site)
        self.timebase = (
            TimeBase.from_seconds(self.time_reference) if self.time_reference > 0.0 else None
        )
        self.world_frame = ''
        self.stitcher = TrajectoryStitcher()
        self.counts: Counter[str] = Counter()
        self.paths: dict[int, list[PoseStamped]] = {}
        self.state_pubs: dict[int, Publisher] = {}
        self.path_pubs: dict[int, Publisher] = {}
        self.last_window: tuple[float, float] | None = None
        self.last_window_wall = time.monotonic()
        self.flushed = True
        self.had_publisher = False
        self.gone_since: float | None = None  # wall time the estimator's publisher went away
        self.residual_end = -math.inf
        self.residual_totals: dict[str, ResidualStats] = {}
        self.residual_last: dict[str, WindowResiduals] = {}
        self.residual_windows: Counter[str] = Counter()
        self.seen: deque[tuple[int, int]] = deque(maxlen=_SEEN_MAX)
        """(start, end) stamps [ns] of the windows the time line took, newest last."""
        self.expect_repeats = True
        """Until the first new window after the start: the estimator's kept windows arrive
        first (``window_history``), and those this time line took before a restart (its
        journal) are repeats, not a time line going back."""

        self.states_pub = self.create_publisher(Odometry, 'trajectory/states', qos.STATE_STREAM)
        self.path_pub = self.create_publisher(Path, 'trajectory/path', qos.LATCHED)
        self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', qos.DIAGNOSTICS)
        self.create_subscription(
            PointCloud2, 'estimator/window_states', self._on_window, qos.WINDOWS_SUB
        )
        self.create_subscription(
            DiagnosticArray,
            'estimator/window_residuals',
            lambda m: self._guarded('window residuals', self._on_residuals, m),
            qos.WINDOWS_SUB,
        )
        self.create_service(Trigger, '~/flush', self._on_flush)
        self.journal = ResultsJournal(self)
        self.create_timer(0.5, self._tick)
        self.held_final: list[tuple[list[FinalStates], TimeBase]] | None = None
        self.hold_until = 0.0
        if self.journal.enabled:  # marks what readers acknowledged (a restart resends the rest)
            self.create_timer(0.05, self._journal_tick)
        diagnostics_timer(self, self._publish_diagnostics)
        where = "the windows' world frame"
        if self.launch is not None:
            where = f'the launch frame ({self.launch[2]})'
        self.get_logger().info(
            f'stitching estimator/window_states into trajectory/states in {where}; states '
            f'held at the end of the stream are published after {self.flush_after:g} s '
            'without a window (or on ~/flush)'
        )
        self._resume()

    def _resume(self) -> None:
        """With a journal, go on where the last process on it was (see
        :mod:`~orbit_tracking.ros.results_journal`)."""
        j = self.journal
        if not j.enabled:
            return
        if j.problem:
            self.get_logger().warning(f'journal {j.journal.path}: {j.problem}')
        if j.readers and j.reader_wait > 0.0:
            # what the new process publishes waits for the readers of the old one: a
            # volatile reader that has not matched it yet would never get it
            self.held_final = []
            self.hold_until = time.monotonic() + j.reader_wait
        self.seen.extend(j.seen)
        n = 0
        for msg in j.windows():
            self._add_window(msg)
            n += 1
        marks = ', '.join(
            f'target {tid} up to {format_stamp(ns, 0.0)}' for tid, ns in sorted(j.marks.items())
        )
        self.get_logger().info(
            f'journal {j.journal.path}: {n} window(s) replayed'
            + (f'; states published before: {marks}' if marks else '; starting afresh')
        )

    def _launch_frame(
        self, output_frame: str, scenario: str, site: list[float]
    ) -> tuple[np.ndarray, np.ndarray, str] | None:
        """``(origin (3,), rotation (3, 3), description)`` of the launch frame, or None for
        world-frame output."""
        if output_frame != 'launch':
            if scenario or site:
                self.get_logger().warning(
                    'scenario / launch_site set but output_frame is world: not used'
                )
            return None
        if bool(scenario) == bool(site):
            raise ValueError(
                'output_frame launch needs the launch point: set either scenario or launch_site'
            )
        if scenario:
            sc = load_scenario(scenario)
            if sc.launch is None:
                raise ValueError(f'scenario {sc.name} defines no launch point')
            lat, lon = sc.launch['latitude_deg'], sc.launch['longitude_deg']
            h, az = sc.launch['height_m'], sc.launch['azimuth_deg']
        else:
            if len(site) != 4 or not all(math.isfinite(v) for v in site):
                raise ValueError(
                    'launch_site must be [latitude_deg, longitude_deg, height_m, azimuth_deg]; '
                    f'got {site}'
                )
            lat, lon, h, az = (float(v) for v in site)
            if not (-90.0 <= lat <= 90.0 and -360.0 <= lon <= 360.0 and -360.0 <= az <= 360.0):
                raise ValueError(
                    f'launch_site latitude, longitude or azimuth out of range: {site}'
                )
        la, lo = math.radians(lat), math.radians(lon)
        return (
            frames.geodetic_to_ecef(la, lo, h),
            frames.launch_rotation(la, lo, math.radians(az)),
            f'lat {lat:g} deg, lon {lon:g} deg, h {h:g} m, A0 {az:g} deg',
        )

    # -- windows -------------------------------------------------------------------
    def _tb(self, stamp_ns_: int) -> TimeBase:
        if self.timebase is None:
            self.timebase = TimeBase.whole_second_of(stamp_ns_)
        return self.timebase

    def _guarded(self, what: str, fn: Callable[..., object], *args: object) -> None:
        guarded(self, self.counts, what, fn, *args)

    def _on_window(self, msg: PointCloud2) -> None:
        self.counts['windows_received'] += 1
        self._guarded('window states', self._add_window, msg)

    def _add_window(self, msg: PointCloud2) -> None:
        try:
            tb = self._tb(checked_stamp_ns(msg.header.stamp))
            ws = cloud_to_window_states(msg, tb)
            if ws.time.size == 0:
                raise ValueError('the window holds no state')
            if not ws.world_frame:
                raise ValueError('empty header.frame_id (world frame)')
            n_ids = np.unique(ws.target_id).size
            if n_ids > self.targets.max_targets:  # no estimator sends that: a stray message
                self._reject(
                    'too_many_targets',
                    f'window of {n_ids} target ids, more than max_targets = '
                    f'{self.targets.max_targets}: refused whole',
                    int(ws.time.size),
                )
                return
            keep = self.targets.admit(ws.target_id)
            if not np.all(keep):
                self._reject(
                    'too_many_targets',
                    f'{int((~keep).sum())} state(s) of target ids beyond the first '
                    f'max_targets = {self.targets.max_targets} dropped',
                    int((~keep).sum()),
                )
            windows = split_window(
                ws.t0,
                ws.t1,
                ws.time[keep],
                ws.target_id[keep],
                ws.state[keep],
                ws.covariance[keep],
            )
        except ValueError as exc:
            self._reject('invalid_window', f'window states rejected: {exc}')
            return
        t0, t1 = ws.t0, ws.t1
        key = (tb.ref_ns + round(t0 * 1e9), tb.ref_ns + round(t1 * 1e9))
        if not self.journal.replaying:
            if self.expect_repeats and self._seen_before(key):
                self.counts['windows_repeated'] += 1
                self.get_logger().info(
                    f'window [{self._stamp(t0)}, {self._stamp(t1)}] taken before the restart: '
                    'skipped',
                    throttle_duration_sec=5.0,
                )
                return
            self.expect_repeats = False
        last = self.stitcher.last_end
        if abs(t1 - last) <= _SAME_TIME:
            self._reject('duplicate_window', f'window ending at {self._stamp(t1)} received twice')
            return
        use, dropped = self.timeline.offer((t0, t1), (ws, windows, tb), last)
        if dropped is not None:
            self._reject(
                'window_jump_unconfirmed',
                f'window [{self._stamp(dropped[0].t0)}, {self._stamp(dropped[0].t1)}] jumped '
                'away from the time line and no window followed it: dropped',
            )
        if not use:
            self.get_logger().warning(
                f'window [{self._stamp(t0)}, {self._stamp(t1)}] jumps from the last one '
                f'(ending {self._stamp(last)}): held until the next window confirms it'
            )
        for item in use:
            self._use_window(*item)
        # journaled once taken: a restart of the time line (in _use_window) clears the
        # journal, and a window lost by a kill before this line comes again from the
        # estimator's history
        if not self._seen_before(key):
            self.seen.append(key)
        self.journal.received(msg, key[1] * 1e-9, self.seen)

    def _seen_before(self, key: tuple[int, int]) -> bool:
        return any(
            abs(a - key[0]) <= _SEEN_NS and abs(b - key[1]) <= _SEEN_NS for a, b in self.seen
        )

    def _use_window(self, ws: WindowStates, windows: list[SampledWindow], tb: TimeBase) -> None:
        t0, t1 = ws.t0, ws.t1
        last = self.stitcher.last_end
        if t1 <= last + _SAME_TIME:
            self._restart(
                f'time went back: window [{self._stamp(t0)}, {self._stamp(t1)}] ends before '
                f'the previous one ({self._stamp(last)})'
            )
        if self.world_frame and ws.world_frame != self.world_frame:
            self._reject(
                'frame_mismatch',
                f'window in frame {ws.world_frame!r}, the earlier ones in {self.world_frame!r}',
            )
            return
        if self.launch is not None and ws.world_frame != 'earth':
            self._reject(
                'frame_mismatch',
                f'window in frame {ws.world_frame!r}: the launch frame needs earth (ECEF)',
            )
            return
        self.world_frame = ws.world_frame
        late = self.stitcher.counts['states_already_final']
        final = self.stitcher.add(windows)
        late = self.stitcher.counts['states_already_final'] - late
        if late:
            self.get_logger().warning(
                f'window [{self._stamp(t0)}, {self._stamp(t1)}] reaches back to {late} states '
                'already published (after a flush: is flush_after shorter than the time '
                'between windows?); they are kept as published',
                throttle_duration_sec=5.0,
            )
        self.counts['windows_used'] += 1
        self.last_window = (t0, t1)
        self.last_window_wall = time.monotonic()
        self.flushed = False
        n = self._publish(final, tb)
        self.get_logger().info(
            f'window [{t0:.2f}, {t1:.2f}] s (stamps {self._stamp(t0)}-{self._stamp(t1)}, '
            f'{len(windows)} target(s)): {n} states final, {self.stitcher.held()} held'
        )

    def _flush(self, why: str) -> int:
        held = self.timeline.release()  # the stream ended on it: nothing will confirm it
        if held is not None:
            self._use_window(*held)
        self.flushed = True
        if self.timebase is None:
            return 0
        n = self._publish(self.stitcher.flush(), self.timebase)
        if n:
            self.counts['flushes'] += 1
            self.get_logger().info(f'{why}: published the {n} states held')
        return n

    def _restart(self, why: str) -> None:
        """Time went back (a bag replayed in a loop, a restarted estimator): what is held
        belongs to the old pass and is published; then everything starts anew."""
        self.get_logger().warning(f'{why}: restarting the trajectory')
        self._flush('before the restart')
        self.paths.clear()
        for tid, pub in self.path_pubs.items():
            pub.publish(self._path_msg(tid))  # empty: RViz and late joiners drop the old pass
        self.path_pub.publish(self._path_msg(-1))
        self.stitcher.reset()
        self.journal.clear()
        self.seen.clear()
        self.world_frame = ''
        self.last_window = None
        self.counts['restarts'] += 1

    def _tick(self) -> None:
        now = time.monotonic()
        self._watch_estimator(now)
        if self.flushed:
            return
        if self.gone_since is not None and now - self.gone_since >= self.estimator_gone_grace:
            self._flush(f'the estimator went away {now - self.gone_since:.1f} s ago')
        elif now - self.last_window_wall >= self.flush_after:
            self._flush(f'no window for {self.flush_after:g} s')

    def _watch_estimator(self, now: float) -> None:
        """Notice the estimator's publisher going away and coming back (a restart): the
        states held wait ``estimator_gone_grace`` seconds for it, so that its next window
        hands over from the last one instead of meeting states already published."""
        n = self.count_publishers('estimator/window_states')
        if n > 0:
            if self.gone_since is not None:
                self.get_logger().info(
                    f'the estimator is back after {now - self.gone_since:.1f} s'
                    + ('' if self.flushed else f'; {self.stitcher.held()} states still held')
                )
            self.gone_since = None
            self.had_publisher = True
        elif (self.had_publisher or self.counts['windows_received']) and self.gone_since is None:
            self.gone_since = now
            self.counts['estimator_gone'] += 1
            if not self.flushed:
                self.get_logger().info(
                    f'the estimator went away: holding {self.stitcher.held()} states up to '
                    f'{self.estimator_gone_grace:g} s for it to come back'
                )

    def _on_flush(self, _req: Trigger.Request, resp: Trigger.Response) -> Trigger.Response:
        n = self._flush('flush requested')
        resp.success = True
        resp.message = f'published {n} held state(s)'
        return resp

    # -- output --------------------------------------------------------------------
    def _publish(self, final: list[FinalStates], tb: TimeBase) -> int:
        if self.held_final is not None:  # restarted: the readers are not all back yet
            self.held_final.append((final, tb))
            return sum(len(fs) for fs in final)
        n = 0
        until: dict[int, int] = {}
        for fs in final:
            tid = fs.target_id
            stamps = tb.ref_ns + np.round(fs.time * 1e9).astype(np.int64)
            new = self.journal.unpublished(tid, stamps)
            if not np.all(new):  # published by the process before (journal)
                fs = FinalStates(tid, fs.time[new], fs.state[new], fs.covariance[new])
                stamps = stamps[new]
                if not len(fs):
                    continue
            until[tid] = int(stamps[-1])
            x, cov = fs.state, fs.covariance
            frame = self.world_frame
            if self.launch is not None:
                x, cov = frames.states_to_local(x, cov, self.launch[0], self.launch[1])
                frame = 'launch'
            pub = self._target_pub(tid)
            on_main = self.target_id < 0 or tid == self.target_id
            path = self.paths.setdefault(tid, [])
            for i in range(len(fs)):
                t = float(fs.time[i])
                msg = target_state_to_odometry(
                    tid, frame, t, x[i, :3], x[i, 3:], cov[i, :3, :3], cov[i, 3:, 3:], tb
                )
                msg.child_frame_id = _child_frame(tid)
                pub.publish(msg)
                if on_main:
                    self.states_pub.publish(msg)
                if not path or t - self._path_time(path[-1], tb) >= self.path_step - 1e-9:
                    ps = PoseStamped()
                    ps.header = msg.header
                    ps.pose = msg.pose.pose
                    path.append(ps)
                    if len(path) > self.path_max_poses:  # thin out, keeping the newest
                        path[:] = path[(len(path) - 1) % 2 :: 2]
            n += len(fs)
            self.path_pubs[tid].publish(self._path_msg(tid))
            if tid == self._path_target():
                self.path_pub.publish(self._path_msg(tid))
        self.counts['states_published'] += n
        self.journal.published(until, self._states_acked, self.states_pub.get_subscription_count())
        return n

    def _journal_tick(self) -> None:
        self._release_held()
        holding = self.held_final is not None
        readers = None if holding else self.states_pub.get_subscription_count()
        self.journal.commit(self._states_acked, readers)

    def _release_held(self) -> None:
        """After a restart: publish what was held once the readers of the last process
        are back, or ``restart_reader_wait`` seconds have passed."""
        if self.held_final is None:
            return
        n = self.states_pub.get_subscription_count()
        if n < self.journal.readers and time.monotonic() < self.hold_until:
            return
        held, self.held_final = self.held_final, None
        count = sum(self._publish(final, tb) for final, tb in held)
        self.get_logger().info(
            f'{n} of the {self.journal.readers} reader(s) of trajectory/states before the '
            f'restart matched: published the {count} states held for them'
        )

    def _states_acked(self) -> bool:
        """Whether every reader of the state topics has acknowledged what went out."""
        pubs = [self.states_pub, *self.state_pubs.values()]
        return all(p.wait_for_all_acked(_NO_WAIT) for p in pubs)

    @staticmethod
    def _path_time(ps: PoseStamped, tb: TimeBase) -> float:
        return tb.to_seconds(ps.header.stamp)

    def _path_target(self) -> int:
        if self.target_id >= 0:
            return self.target_id
        return min(self.paths) if self.paths else -1

    def _path_msg(self, tid: int) -> Path:
        msg = Path()
        poses = self.paths.get(tid, [])
        msg.header.frame_id = (
            'launch' if self.launch is not None else (self.world_frame or 'earth')
        )
        if poses:
            msg.header.stamp = poses[-1].header.stamp
        msg.poses = list(poses)
        return msg

    def _target_pub(self, tid: int) -> Publisher:
        pub = self.state_pubs.get(tid)
        if pub is None:
            pub = self.state_pubs[tid] = self.create_publisher(
                Odometry, f'trajectory/target_{tid}/states', qos.STATE_STREAM
            )
            self.path_pubs[tid] = self.create_publisher(
                Path, f'trajectory/target_{tid}/path', qos.LATCHED
            )
        return pub

    # -- residuals -----------------------------------------------------------------
    def _on_residuals(self, msg: DiagnosticArray) -> None:
        try:
            tb = self._tb(checked_stamp_ns(msg.header.stamp))
            items = msg_to_window_residuals(msg, tb)
            if len(set(self.residual_totals) | {it.stats.station for it in items}) > (
                _MAX_RESIDUAL_STATIONS
            ):
                raise ValueError(f'more than {_MAX_RESIDUAL_STATIONS} stations')
        except ValueError as exc:
            self._reject('invalid_residuals', f'window residuals rejected: {exc}')
            return
        if not items:
            return
        t1 = items[0].t1
        ends = [self.stitcher.last_end]
        if self.timeline.held is not None:
            ends.append(self.timeline.held[0][1])
        ends = [e for e in ends if math.isfinite(e)]
        if ends and not any(abs(t1 - e) <= self.timeline.max_jump for e in ends):
            self._reject(
                'residuals_off_time_line',
                f'residuals of a window ending {self._stamp(t1)}, more than max_window_jump '
                f'from every window received (the last ending {self._stamp(ends[0])}): '
                'refused',
            )
            return
        if t1 <= self.residual_end + _SAME_TIME:
            if abs(t1 - self.residual_end) <= _SAME_TIME:
                self._reject(
                    'duplicate_residuals',
                    f'residuals of the window ending {self._stamp(t1)} twice',
                )
                return
            # time went back (logged with the window states): the sums start anew
            self.residual_totals.clear()
            self.residual_last.clear()
            self.residual_windows.clear()
        self.residual_end = t1
        for it in items:
            sid = it.stats.station
            old = self.residual_totals.get(sid)
            self.residual_totals[sid] = it.stats if old is None else old.merged(it.stats)
            self.residual_last[sid] = it
            self.residual_windows[sid] += 1

    # -- diagnostics ---------------------------------------------------------------
    def _stamp(self, t: float) -> str:
        if not math.isfinite(t):
            return str(t)
        return format_stamp(self.timebase.ref_ns if self.timebase else 0, t)

    def _reject(self, key: str, text: str, n: int = 1) -> None:
        self.counts[key] += n
        self.get_logger().warning(f'{text} ({self.counts[key]} so far)', throttle_duration_sec=5.0)

    def _publish_diagnostics(self) -> None:
        c = self.counts
        sc = self.stitcher.counts
        rejected = {
            k: v
            for k, v in sorted(c.items())
            if k
            in (
                'invalid_window',
                'duplicate_window',
                'frame_mismatch',
                'invalid_residuals',
                'duplicate_residuals',
                'internal_error',
                'too_many_targets',
                'window_jump_unconfirmed',
                'residuals_off_time_line',
            )
        }
        main = self._path_target()
        values: dict[str, object] = {
            'windows_received': c['windows_received'],
            'windows_used': c['windows_used'],
            'windows_repeated': c['windows_repeated'],
            'states_published': c['states_published'],
            'states_held': self.stitcher.held(),
            'states_already_final': sc['states_already_final'],
            'missing_samples': sc['missing_samples'],
            **{f'rejected_{k}': v for k, v in rejected.items()},
            'flushes': c['flushes'],
            'restarts': c['restarts'],
            'estimator_gone': c['estimator_gone'],
            **(
                {'journal_write_errors': self.journal.write_errors} if self.journal.enabled else {}
            ),
            'last_window_start': ''
            if self.last_window is None
            else self._stamp(self.last_window[0]),
            'last_window_end': ''
            if self.last_window is None
            else self._stamp(self.last_window[1]),
            'final_until': self._stamp(self.stitcher.final_until(main)) if main >= 0 else '',
            'targets': ' '.join(str(t) for t in self.stitcher.targets),
            'world_frame': self.world_frame,
            'output_frame': 'launch' if self.launch is not None else self.world_frame,
        }
        bad = sum(rejected.values())
        status = diagnostic_status(
            'results: trajectory',
            DiagnosticStatus.WARN if bad else DiagnosticStatus.OK,
            f'{c["windows_used"]} windows, {c["states_published"]} states published, '
            f'{values["states_held"]} held' + (f', {bad} messages rejected' if bad else ''),
            values,
        )
        statuses = [status, *(self._residual_status(sid) for sid in sorted(self.residual_totals))]
        self.diag_pub.publish(diagnostic_array(self.get_clock().now().to_msg(), statuses))

    def _residual_status(self, sid: str) -> DiagnosticStatus:
        st = self.residual_totals[sid]
        last = self.residual_last[sid]
        values: dict[str, object] = {
            'windows': self.residual_windows[sid],
            'rows': st.rows,
            'rejected': int(st.rejected.sum()),
            'not_measured': st.not_measured,
        }
        for j, f in enumerate(st.fields):
            values[f'{f}_count'] = int(st.count[j])
            values[f'{f}_rms'] = float(st.rms[j])
            values[f'{f}_mean'] = float(st.mean[j])
            values[f'{f}_rejected'] = int(st.rejected[j])
        values['last_window_end'] = self._stamp(last.t1)
        lr = last.stats.rms
        for j, f in enumerate(last.stats.fields):
            values[f'last_{f}_rms'] = float(lr[j])
        high = [f for f, r in zip(st.fields, st.rms, strict=True) if r > _RMS_WARN]
        text = ', '.join(f'{f} {r:.2f}' for f, r in zip(st.fields, st.rms, strict=True))
        return diagnostic_status(
            f'results: residuals {sid}',
            DiagnosticStatus.WARN if high else DiagnosticStatus.OK,
            f'{st.rows} rows, {int(st.rejected.sum())} values rejected; whitened RMS {text}'
            + (f'; RMS above {_RMS_WARN:g} for {", ".join(high)}' if high else ''),
            values,
            hardware_id=sid,
        )


def main(args: list[str] | None = None) -> None:
    run_node(ResultsNode, args)


if __name__ == '__main__':
    main()
