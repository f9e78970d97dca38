"""The results node's journal: what a killed ``results`` node needs to go on where it was.

When the node dies it holds the tail of the last windows (states the next window will
still blend into), and it has no memory of how far it had published. Without a journal the
restarted node starts its trajectory at the first window it receives: the held span is
lost, and whatever of the earlier windows it sees again is published twice.

With ``journal_dir`` set the node appends every window its time line takes (the message as
serialized on the wire), the list of the last windows taken, and, once every reader has
acknowledged a publication, how far each target's states went out. A node started on the
same journal feeds the windows still there through its time line and stitcher once more
and publishes only states after those marks. A window it never took (in flight when it
died) comes again from the estimator's kept windows; those it took come too and are
skipped. The trajectory so goes on with nothing lost; a state handed to DDS but not yet
acknowledged when the node died is published again, with the same values (a writer's queue
dies with its process, so the alternative is a state that never arrives).

The journal keeps the windows not wholly published and, of the others, the last one: a
restarted node so knows the end of the time line, and a new pass that goes back in time
restarts the trajectory (and drops the marks) as it would have without the restart.
Records carry absolute stamps [s], since the node takes its time base from the first
window it sees, which differs across a restart.

The file is :class:`~orbit_tracking.core.data.journal.Journal`'s (framed, checksummed,
bounded, one process at a time), at the path :func:`~orbit_tracking.ros.journal.
journal_path` gives. As for the estimator the journal is off by default: a node cannot
tell a journal of its own run from one of an earlier run under the same name.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import PointCloud2

from orbit_tracking.core.data.journal import Journal, JournalError, JournalRecord
from orbit_tracking.ros.journal import journal_path
from orbit_tracking.ros.parameters import declare

__all__ = ['ResultsJournal']

_WINDOW = 'window'
_MARK = 'published'
_SEEN = 'seen'
_READERS = 'readers'


class ResultsJournal:
    """Declares ``journal_dir`` and ``journal_max_mb`` on ``node`` (a results node), and
    with a directory set opens the journal and reads what is there (:meth:`windows`,
    :attr:`marks`).

    Raises
    ------
    JournalError
        Another process holds the journal, its file is not a journal, or the directory
        cannot be used.
    """

    def __init__(self, node: Any) -> None:
        directory = declare(
            node,
            'journal_dir',
            '',
            'Directory of the journal that lets a killed results node go on where it was, '
            'nothing lost or published twice ("" = no journal). The file is <journal_dir>/'
            'domain<ROS_DOMAIN_ID>/<namespace>/<node name>.journal; one process at a time.',
            read_only=True,
        )
        max_mb = declare(
            node,
            'journal_max_mb',
            64.0,
            'Bound on the journal file [MiB]; past it the oldest windows still needed are '
            'dropped (counted).',
            read_only=True,
            min_value=0.0625,
            max_value=1e6,
        )
        self.reader_wait = declare(
            node,
            'restart_reader_wait',
            10.0,
            'After a restart on the journal, wall seconds at most that what the node '
            'publishes waits for as many readers of trajectory/states as it had before (a '
            'volatile reader that has not matched the new process yet would miss it).',
            read_only=True,
            min_value=0.0,
            max_value=600.0,
        )
        self.readers = 0
        """Readers of ``trajectory/states`` when the last publication was marked (from
        the journal at start)."""
        self.journal: Journal | None = None
        self.marks: dict[int, int] = {}
        """Per target, the stamp [ns] up to which its states were published."""
        self.seen: list[tuple[int, int]] = []
        """(start, end) stamps [ns] of the last windows the time line took (the newest
        record's), so that a restarted node knows the windows the estimator sends again."""
        self._pending: dict[int, int] = {}
        self.replaying = False
        self.write_errors = 0
        """Appends that failed (disk full, ...): a restart may then lose or repeat states."""
        if not directory:
            return
        path = journal_path(
            directory, node.get_fully_qualified_name(), node.context.get_domain_id()
        )
        try:
            self.journal = Journal(path, int(max_mb * 2**20))
        except OSError as exc:
            raise JournalError(f'journal_dir {directory!r}: cannot use {path}: {exc}') from exc
        for rec in self.journal.recovered.records:
            if rec.kind == _MARK:
                self.marks[int(rec.key)] = int(rec.data)
            elif rec.kind == _SEEN:
                self.seen = [(int(a), int(b)) for a, b in json.loads(rec.data)]
            elif rec.kind == _READERS:
                self.readers = int(rec.data)

    @property
    def enabled(self) -> bool:
        return self.journal is not None

    @property
    def problem(self) -> str:
        """What was wrong with the file's tail when it was opened ('' if nothing)."""
        if self.journal is None or not self.journal.recovered.problem:
            return ''
        scan = self.journal.recovered
        return (
            f'{scan.problem} at byte {scan.valid_bytes}, {scan.discarded_bytes} byte(s) after '
            'it left out (a write cut short)'
        )

    def windows(self) -> Iterator[PointCloud2]:
        """The windows kept, in the order they arrived (:attr:`replaying` meanwhile)."""
        if self.journal is None:
            return
        self.replaying = True
        try:
            for rec in self.journal.recovered.records:
                if rec.kind == _WINDOW:
                    yield deserialize_message(rec.data, PointCloud2)
        finally:
            self.replaying = False

    def received(self, msg: PointCloud2, end_s: float, seen: Sequence[tuple[int, int]]) -> None:
        """A valid window ending at the absolute stamp ``end_s`` [s] arrived; ``seen`` is
        the node's list of windows taken, this one included."""
        if self.journal is None or self.replaying:
            return
        data = serialize_message(msg)
        try:
            self.journal.append(JournalRecord(_WINDOW, '', end_s, data, sticky=True))
            rec = JournalRecord(_SEEN, '', -math.inf, json.dumps(list(seen)).encode(), True)
            self.journal.append(rec)
        except OSError:
            self.write_errors += 1

    def published(
        self, until_ns: dict[int, int], acked: Callable[[], bool], readers: int = 0
    ) -> None:
        """States up to these stamps [ns] per target were handed to DDS, which ``readers``
        read: marked once ``acked()`` says every reader has them (:meth:`commit`)."""
        for tid, ns in until_ns.items():
            self._pending[tid] = max(ns, self._pending.get(tid, -1))
        self.commit(acked, readers)

    def commit(self, acked: Callable[[], bool], readers: int | None = 0) -> None:
        """Mark what :meth:`published` staged if ``acked()`` (call again until it is), and
        let go of the windows wholly published (all but the last). Until then a restart
        publishes those states again: a state may come twice, never not at all (a writer's
        queue dies with its process).

        The count of ``readers`` is recorded whenever it changes, published states or not: a
        process killed before it published anything still had readers, and its successor
        must hold what it publishes until they have matched it again. ``None`` while that
        hold lasts: the readers still to come back are the old process's, not the count of
        the moment."""
        if self.journal is None:
            return
        try:
            if readers is not None and readers != self.readers:
                self.readers = readers
                rec = JournalRecord(_READERS, '', -math.inf, str(readers).encode(), sticky=True)
                self.journal.append(rec, sync=True)
        except OSError:
            self.write_errors += 1
        if not self._pending or not acked():
            return
        pending, self._pending = self._pending, {}
        try:
            for tid, ns in sorted(pending.items()):
                if ns > self.marks.get(tid, -1):
                    self.marks[tid] = ns
                    data = str(ns).encode()
                    rec = JournalRecord(_MARK, str(tid), -math.inf, data, sticky=True)
                    self.journal.append(rec, sync=True)
            keep_from = min(self.marks.values()) * 1e-9 + 1e-6
            if self.journal.releasable_bytes(keep_from) * 2 >= self.journal.size:
                self.journal.compact(keep_from)
        except OSError:
            self.write_errors += 1

    def unpublished(self, tid: int, stamps_ns: Any) -> Any:
        """Mask of the stamps [ns] of target ``tid`` after its mark (all when unmarked)."""
        mark = self.marks.get(tid)
        return stamps_ns > (-1 if mark is None else mark)

    def clear(self) -> None:
        """A new time line (the trajectory restarts): nothing of the old one is needed."""
        self.marks.clear()
        self._pending.clear()
        self.seen.clear()
        if self.journal is not None:
            self.journal.clear()

    def close(self) -> None:
        if self.journal is not None:
            self.journal.close()
