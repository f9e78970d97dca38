"""``triangulation``: lines of sight of the stations intersected into position fixes.

Subscribes to ``stations/<id>/measurements`` and ``stations/<id>/state`` of the stations
in its ``stations`` parameter (or of every station that appears), aligns the streams on
common epochs, and publishes one ``geometry_msgs/PoseWithCovarianceStamped`` per target
and epoch on ``triangulation/fixes`` (and on ``triangulation/target_<id>/fixes``), plus
``/diagnostics``: fixes made, rejections by reason, processing time.

The epochs its ``lag`` still holds are fixed when the data stop for ``flush_after`` wall
seconds, or at once on the ``~/flush`` service (``std_srvs/Trigger``: the end of a pass or
of a replay, without waiting).

Example::

    ros2 run orbit_tracking triangulation --ros-args -p stations:="['sat06', 'sat09']"
"""

from __future__ import annotations

import math
import time
from collections import Counter

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.publisher import Publisher
from std_srvs.srv import Trigger

from orbit_tracking.core.triangulation.alignment import AlignConfig
from orbit_tracking.core.triangulation.intersection import REASONS, Gates
from orbit_tracking.core.triangulation.pipeline import TimedFix, TriangulationPipeline
from orbit_tracking.ros import qos
from orbit_tracking.ros.conversions import (
    MeasurementBatch,
    StationStateSample,
    TimeBase,
    diagnostic_array,
    diagnostic_status,
    fix_to_msg,
)
from orbit_tracking.ros.parameters import declare, diagnostics_timer
from orbit_tracking.ros.runner import run_node
from orbit_tracking.ros.station_inputs import StationInputs

__all__ = ['TriangulationNode', 'main']


class TriangulationNode(StationInputs):
    def __init__(self) -> None:
        super().__init__('triangulation')
        station_filter = self._declare_station_filter()
        period = declare(
            self,
            'period',
            0.0,
            'Spacing of the fix epochs [s]; 0 = smallest sampling interval of the stations.',
            read_only=True,
            min_value=0.0,
            max_value=60.0,
        )
        lag = declare(
            self,
            'lag',
            1.0,
            'Data time [s] to wait past an epoch before fixing it (late samples).',
            read_only=True,
            min_value=0.0,
            max_value=60.0,
        )
        gap = declare(
            self,
            'max_gap_factor',
            2.5,
            'Largest gap between bracketing samples, in sampling intervals.',
            read_only=True,
            min_value=1.0,
            max_value=100.0,
        )
        eps = declare(
            self,
            'smoothing_eps',
            0.0,
            'Seed 003 low-pass weight epsilon (e.g. 0.95) applied to the angles; 0 = off.',
            read_only=True,
            min_value=0.0,
            max_value=1.0,
        )
        gates = Gates(
            min_intersection_angle_deg=declare(
                self,
                'min_intersection_angle_deg',
                1.0,
                'Reject fixes whose widest angle between lines is smaller [deg].',
                read_only=True,
                min_value=0.0,
                max_value=89.0,
            ),
            max_gdop=declare(
                self,
                'max_gdop',
                100.0,
                'Reject fixes with a larger geometric dilution of precision.',
                read_only=True,
                min_value=1.0,
                max_value=1e6,
            ),
            miss_probability=declare(
                self,
                'miss_probability',
                0.9999,
                'Reject fixes whose miss distance (chi-square misfit) exceeds this quantile; '
                '1 = off.',
                read_only=True,
                min_value=0.5,
                max_value=1.0,
            ),
        )
        self.target_id = declare(
            self,
            'target_id',
            -1,
            'Target published on triangulation/fixes; -1 = every target.',
            read_only=True,
            min_value=-1,
            max_value=2**31 - 1,
        )
        self.time_reference = declare(
            self,
            'time_reference',
            0.0,
            'Stamp [s] of internal time 0; 0 = the first stamp received.',
            read_only=True,
            min_value=0.0,
        )
        self.flush_after = declare(
            self,
            'flush_after',
            2.0,
            'Wall seconds without new measurements after which the epochs still held by the '
            'lag are fixed.',
            read_only=True,
            min_value=0.1,
            max_value=3600.0,
        )
        self.state_wait = declare(
            self,
            'state_wait_timeout',
            5.0,
            'Wall seconds to hold fixes while a station has measurements but no state yet.',
            read_only=True,
            min_value=0.0,
            max_value=3600.0,
        )
        self.pipeline = TriangulationPipeline(
            AlignConfig(
                period=period,
                max_gap_factor=gap,
                lag=lag,
                smoothing_eps=eps if eps > 0.0 else None,
            ),
            gates,
        )
        self.fix_pub = self.create_publisher(
            PoseWithCovarianceStamped, 'triangulation/fixes', qos.STATE_STREAM
        )
        self.target_pubs: dict[int, Publisher] = {}
        self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', qos.DIAGNOSTICS)
        self.counts: Counter[str] = Counter()
        self.proc_ms: list[float] = []
        self.fix_age: list[float] = []
        self.first_pending: float | None = None
        self.last_data = time.monotonic()
        self.flushed = True
        self._start_station_inputs(station_filter, self.time_reference)
        diagnostics_timer(self, self._publish_diagnostics)
        self.create_timer(0.2, lambda: self._guarded('flush', self._flush_if_idle))
        self.create_service(Trigger, '~/flush', self._on_flush)
        self.get_logger().info(f'triangulating {self._stations_text()}')

    # -- callbacks -----------------------------------------------------------------
    def _add_pose(self, sid: str, st: StationStateSample) -> None:
        self.pipeline.add_pose(
            st.station_id, st.time, st.position, st.velocity, st.rotation, st.moving
        )
        if st.moving and not self.flushed:  # a late state may complete held epochs
            self._process()

    def _add_measurements(self, sid: str, batch: MeasurementBatch) -> None:
        self.pipeline.add_measurements(
            batch.station_id, batch.fields, batch.time, batch.target_id, batch.values, batch.sigmas
        )
        self.last_data = time.monotonic()
        self.flushed = False
        self._process()

    def _process(self) -> None:
        """Fix the epochs every delivering stream has passed (see StationInputs)."""
        t_start = time.monotonic()
        missing = self.pipeline.stations_without_pose()
        waiting = False
        if missing:
            now = time.monotonic()
            self.first_pending = self.first_pending or now
            waiting = now - self.first_pending < self.state_wait
            if not waiting:
                self.get_logger().warning(
                    f'no state from station(s) {missing} after {self.state_wait:.0f} s; '
                    'fixing without them',
                    throttle_duration_sec=30.0,
                )
        with self._working():
            fixes = self.pipeline.process(wait_for_poses=waiting, delivering=self._delivering())
            if self.timebase is not None:  # always set once a message was decoded
                self._publish(fixes, self.timebase)
        if fixes:
            self.proc_ms.append(1e3 * (time.monotonic() - t_start))
            latest = self.pipeline.aligner.latest
            self.fix_age.extend(latest - f.time for f in fixes)

    def _flush_if_idle(self) -> None:
        """When the data stop (end of a pass, end of a replay), fix the epochs the lag
        still holds instead of waiting for data that will not come."""
        if time.monotonic() - self.last_data >= self.flush_after:
            self._flush(f'data idle for {self.flush_after:g} s')

    def _flush(self, why: str) -> int:
        """Fix the epochs the lag holds (once per stretch of data); how many were fixed."""
        if self.flushed or self.timebase is None:
            return 0
        self.flushed = True
        fixes = self.pipeline.process(until=self.pipeline.aligner.latest)
        self._publish(fixes, self.timebase)
        if fixes:
            self.get_logger().info(f'{why}: fixed {len(fixes)} held epoch(s)')
        return len(fixes)

    def _on_flush(self, _req: Trigger.Request, resp: Trigger.Response) -> Trigger.Response:
        """``~/flush``: the end of the stream now (the fixes are published before the
        answer)."""
        fixed: list[int] = []
        self._guarded('flush', lambda: fixed.append(self._flush('asked (~/flush)')))
        resp.success = bool(fixed)
        resp.message = f'fixed {fixed[0]} held epoch(s)' if fixed else 'the flush failed (logged)'
        return resp

    def _on_time_reset(self) -> str:
        """Time went back (see StationInputs): fix the epochs the lag still holds, then
        start a new pipeline; its counters carry on."""
        held: list[TimedFix] = []
        if self.timebase is not None and not self.flushed:
            held = self.pipeline.process(until=self.pipeline.aligner.latest)
            self._publish(held, self.timebase)
        old = self.pipeline
        self.pipeline = TriangulationPipeline(old.aligner.config, old.gates)
        self.pipeline.counts.update(old.counts)
        self.pipeline.counts.update(old.aligner.counts)
        self.first_pending = None
        self.flushed = True
        return f'{len(held)} held epoch(s) fixed'

    def _publish(self, fixes: list[TimedFix], tb: TimeBase) -> None:
        frame = self.world_frame or 'earth'
        for f in fixes:
            msg = fix_to_msg(frame, f.time, f.fix.position, f.fix.covariance, tb)
            if self.target_id < 0 or f.target_id == self.target_id:
                self.fix_pub.publish(msg)
            pub = self.target_pubs.get(f.target_id)
            if pub is None:
                pub = self.target_pubs[f.target_id] = self.create_publisher(
                    PoseWithCovarianceStamped,
                    f'triangulation/target_{f.target_id}/fixes',
                    qos.STATE_STREAM,
                )
            pub.publish(msg)

    def _reject(self, key: str, text: str, n: int = 1) -> None:
        self.counts[key] += n
        self.get_logger().warning(f'{text} ({self.counts[key]} so far)', throttle_duration_sec=5.0)

    def _publish_diagnostics(self) -> None:
        counts = Counter(self.pipeline.counts)
        counts.update(self.counts)
        rejected = {f'rejected_{r}': counts.get(r, 0) for r in REASONS}
        other = {k: v for k, v in counts.items() if k not in REASONS and k != 'fixes'}
        bad = counts.get('invalid_messages', 0) + counts.get('invalid_state', 0)
        level = DiagnosticStatus.WARN if bad else DiagnosticStatus.OK
        values: dict[str, object] = {
            'fixes': counts.get('fixes', 0),
            **rejected,
            **other,
            'stations': ' '.join(sorted(self.subs)),
            'processing_ms_mean': float(sum(self.proc_ms) / len(self.proc_ms))
            if self.proc_ms
            else math.nan,
            'processing_ms_max': max(self.proc_ms) if self.proc_ms else math.nan,
            'fix_age_s_mean': float(sum(self.fix_age) / len(self.fix_age))
            if self.fix_age
            else math.nan,
        }
        self.proc_ms = self.proc_ms[-1000:]
        self.fix_age = self.fix_age[-1000:]
        status = diagnostic_status(
            'triangulation: fixes',
            level,
            f'{counts.get("fixes", 0)} fixes' + (f', {bad} invalid messages' if bad else ''),
            values,
        )
        self.diag_pub.publish(diagnostic_array(self.get_clock().now().to_msg(), [status]))


def main(args: list[str] | None = None) -> None:
    run_node(TriangulationNode, args)


if __name__ == '__main__':
    main()
