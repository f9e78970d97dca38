"""The estimator node's input journal (``journal_dir``): restart without loss.

With ``journal_dir`` set, the node's observation buffer is a
:class:`~orbit_tracking.core.data.journaled_buffer.JournaledBuffer`: every input the node
accepts (measurement rows, station poses, telemetry, fixes) is appended to
``<journal_dir>/domain<ROS_DOMAIN_ID>/<namespace>/<node name>.journal`` before the callback
that received it returns. A checkpoint timer appends the window scheduler's state (last
window, next start, end of the last residuals) once the window it follows is published
*and acknowledged by every reader* (a window lost with a killed process is solved again),
then compacts the file down to what a later window still needs (the scheduler's
``keep_from``; the newest pose of each station before it).

At start the node replays the journal into its buffer, takes back the time base, world
frame, fixed-station poses and scheduler state, prunes as it had pruned, subscribes at once
to the stations it had (not a discovery period later), and logs what it recovered. A window
solved from the replayed inputs right after the start goes out before discovery has matched
the results node; it reaches it all the same, since ``estimator/window_states`` and
``estimator/window_residuals`` keep their last messages for readers that join
(:func:`~orbit_tracking.ros.qos.window_stream`). A node killed at any
moment therefore publishes, once started again, every window it had not published, from the
inputs it had; only messages sent while no estimator process was running are missing (a gap
in the data, estimated across like any gap), and the first window after the restart starts
from telemetry or fixes rather than from the previous window's solution (an initial guess
only). A window published twice (killed between its publication and the checkpoint) ends at
the same time and is dropped by the results node as a duplicate.

The journal is off by default: a node cannot tell on its own whether a journal it finds
belongs to the run it should resume or to an earlier, unrelated run that happened to use
the same name (a test suite, a second pass of the same bag), and resuming the wrong one
would publish stale windows. Whoever supervises the node (launch file, systemd) knows that,
and names the directory.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
from rclpy.duration import Duration

from orbit_tracking.core.data.buffer import ObservationBuffer
from orbit_tracking.core.data.journal import Journal, JournalError, JournalRecord
from orbit_tracking.core.data.journaled_buffer import (
    JournaledBuffer,
    ReplaySummary,
    replay_records,
)
from orbit_tracking.core.time import format_stamp
from orbit_tracking.ros.conversions import StationStateSample, TimeBase
from orbit_tracking.ros.parameters import declare

__all__ = ['CHECKPOINT_PERIOD', 'EstimatorJournal', 'journal_path']

CHECKPOINT_PERIOD = 0.2
"""Seconds between checkpoint checks (scheduler moved on, window acknowledged, fsync)."""

_NO_ACK = Duration(seconds=0)


def journal_path(directory: str | Path, node_name: str, domain_id: int) -> Path:
    """``<directory>/domain<id>/<namespace>/<name>.journal`` for a fully qualified node name
    (``/ns/estimator``): distinct for every node of a host that shares the directory."""
    parts = [p for p in node_name.split('/') if p]
    if not parts:
        raise ValueError(f'node name {node_name!r} has no name')
    base = Path(directory).expanduser() / f'domain{int(domain_id)}'
    return base.joinpath(*parts[:-1], parts[-1] + '.journal')


class EstimatorJournal:
    """Declares ``journal_dir`` and ``journal_max_mb`` on ``node`` (an
    :class:`~orbit_tracking.ros.estimator_node.EstimatorNode` at the end of its
    ``__init__``), and with a directory set replays what is there and journals from then on.

    Raises
    ------
    JournalError
        Another process holds the journal, or its file is not a journal.
    """

    def __init__(self, node: Any) -> None:
        directory = declare(
            node,
            'journal_dir',
            '',
            'Directory of the input journal that lets a killed node resume where it was '
            '("" = no journal). The file is <journal_dir>/domain<ROS_DOMAIN_ID>/<namespace>/'
            '<node name>.journal; one process at a time may use it.',
            read_only=True,
        )
        max_mb = declare(
            node,
            'journal_max_mb',
            64.0,
            'Bound on the journal file [MiB]; past it the oldest inputs still needed are '
            'dropped (counted and logged).',
            read_only=True,
            min_value=0.0625,
            max_value=1e6,
        )
        self.node = node
        self.journal: Journal | None = None
        self._saved: tuple[Any, ...] | None = None
        self._errors_seen = 0
        self._dropped_seen = 0
        if not directory:
            return
        path = journal_path(
            directory, node.get_fully_qualified_name(), node.context.get_domain_id()
        )
        try:
            self.journal = Journal(path, int(max_mb * 2**20))
        except OSError as exc:  # not writable, not a directory: a configuration error
            raise JournalError(f'journal_dir {directory!r}: cannot use {path}: {exc}') from exc
        self._restore()
        node.create_timer(CHECKPOINT_PERIOD, self._checkpoint)

    @property
    def enabled(self) -> bool:
        return self.journal is not None

    def fresh_buffer(self) -> ObservationBuffer:
        """An empty buffer for a new time line (the node's time reset); the journal starts
        afresh with it (what it held belongs to the old time line)."""
        if self.journal is None:
            return ObservationBuffer()
        self.journal.clear()
        self._saved = None
        return JournaledBuffer(self.journal, self._context)

    # -- start ------------------------------------------------------------------------
    def _context(self) -> dict[str, Any]:
        tb = self.node.timebase
        return {'ref_ns': None if tb is None else tb.ref_ns, 'world_frame': self.node.world_frame}

    def _restore(self) -> None:
        assert self.journal is not None
        node, log = self.node, self.node.get_logger()
        scan = self.journal.recovered
        if scan.problem:
            log.warning(
                f'journal {self.journal.path}: {scan.problem} at byte {scan.valid_bytes}, '
                f'{scan.discarded_bytes} byte(s) after it left out (a write cut short)'
            )
        ctx = next((r for r in reversed(scan.records) if r.kind == 'context'), None)
        shift = 0.0
        if ctx is not None:
            c = json.loads(ctx.data)
            ref = c.get('ref_ns')
            if ref is not None:
                if node.timebase is None:
                    node.timebase = TimeBase(int(ref))
                shift = (int(ref) - node.timebase.ref_ns) * 1e-9
            node.world_frame = str(c.get('world_frame') or '')
        buffer = JournaledBuffer(self.journal, self._context)
        summary = replay_records(buffer, scan.records, shift)
        node.buffer = buffer
        for sid, (t, p, v, r, moving) in summary.poses.items():
            if not moving:  # given back to the node after a time reset, as if received
                node._fixed_states[sid] = StationStateSample(sid, t, p, v, r, np.zeros(3))
        # the stations it had, subscribed at once rather than when discovery finds them:
        # every message missed while the node starts is a gap in the data
        for sid in sorted({r.key for r in scan.records if r.kind == 'measurements'}):
            if sid not in node.subs:
                node._subscribe(sid)
        resumed = self._restore_scheduler(summary, shift)
        node.buffer.prune(node.scheduler.keep_from)
        if summary.data_records:
            node.flushed = False  # the end-of-stream flush covers what was replayed
            node.last_data = time.monotonic()
        s = node.scheduler
        self._saved = (s.last, s.next_t0, node.residuals_after)
        failed = {k: v for k, v in summary.counts.items() if k.startswith(('failed_', 'unknown_'))}
        log.info(
            f'journal {self.journal.path}: {summary.data_records} inputs replayed '
            f'({self._what(summary)})'
            + (f', {sum(failed.values())} unusable {failed}' if failed else '')
            + f'; {resumed}'
        )

    def _restore_scheduler(self, summary: ReplaySummary, shift: float) -> str:
        node = self.node
        st = summary.state
        if not summary.data_records:
            return 'starting afresh'
        if st is None:
            return 'no window solved before: windows start with the data'
        cfg = node.win_cfg
        window = [cfg.length, cfg.overlap, cfg.latency, cfg.output_step]
        if st.get('window') != window:
            node.get_logger().warning(
                f'journal: the windows were {st.get("window")} (length, overlap, latency, '
                f'output step) and are {window} now: they start again with the data'
            )
            return 'windows start with the data'
        s = node.scheduler
        last = st.get('last')
        s.last = None if last is None else (float(last[0]) + shift, float(last[1]) + shift)
        nxt = st.get('next_t0')
        s.next_t0 = None if nxt is None else float(nxt) + shift
        after = st.get('residuals_after')
        node.residuals_after = None if after is None else float(after) + shift
        if s.next_t0 is None:
            return 'no window solved before'
        return (
            f'resuming at window start t={s.next_t0:.3f} s '
            f'(stamp {format_stamp(node.timebase.ref_ns, s.next_t0)})'
        )

    @staticmethod
    def _what(summary: ReplaySummary) -> str:
        c = summary.counts
        text = (
            f'{c["measurement_rows"]} measurement rows in {c["measurements"]} messages, '
            f'{c["pose"]} station poses, {c["telemetry"]} telemetry, {c["fix"]} fixes'
        )
        if math.isfinite(summary.first_time):
            text += f', data {summary.first_time:.3f}-{summary.last_time:.3f} s'
        return text

    # -- checkpoints ------------------------------------------------------------------
    def _checkpoint(self) -> None:
        """After a window: once every reader has acknowledged it, append the scheduler
        state and let go of what no later window needs; else fsync if due."""
        j, node = self.journal, self.node
        if j is None:
            return
        s = node.scheduler
        key = (s.last, s.next_t0, node.residuals_after)
        try:
            if node.worker.busy:  # the scheduler moved on to a window not published yet
                j.sync()
            elif key != self._saved and s.last is not None:
                if not node.window_pub.wait_for_all_acked(_NO_ACK):
                    j.sync()
                    return  # the window may not be out yet: try again next period
                self._save_state()
                self._saved = key
                if j.releasable_bytes(s.keep_from) * 2 >= j.size:
                    j.compact(s.keep_from)
            else:
                j.sync()
        except OSError as exc:
            node.counts['journal_write_errors'] += 1
            node.get_logger().error(
                f'journal {j.path}: {exc}; a restart may lose inputs',
                throttle_duration_sec=10.0,
            )
        dropped = j.counts['records_dropped']
        if dropped > self._dropped_seen:
            node.get_logger().warning(
                f'journal {j.path}: {dropped} inputs still needed dropped so far to stay under '
                f'journal_max_mb ({j.max_bytes / 2**20:g} MiB); a restart now would lose '
                'their span',
                throttle_duration_sec=10.0,
            )
            node.counts['journal_records_dropped'] += dropped - self._dropped_seen
            self._dropped_seen = dropped
        buf = node.buffer
        errors = buf.counts.get('journal_write_errors', 0)
        if errors > self._errors_seen:
            self._errors_seen = errors
            node.get_logger().error(
                f'journal {j.path}: {errors} input(s) not journaled '
                f'({getattr(buf, "journal_error", "")}); a restart may lose them',
                throttle_duration_sec=10.0,
            )

    def _save_state(self) -> None:
        assert self.journal is not None
        node = self.node
        s, cfg = node.scheduler, node.win_cfg
        state = {
            'window': [cfg.length, cfg.overlap, cfg.latency, cfg.output_step],
            'last': None if s.last is None else list(s.last),
            'next_t0': s.next_t0,
            'residuals_after': node.residuals_after,
            'ref_ns': None if node.timebase is None else node.timebase.ref_ns,
        }
        data = json.dumps(state).encode()
        self.journal.append(JournalRecord('state', '', -math.inf, data, sticky=True), sync=True)
