"""A bounded append-only journal on disk: what a processing node killed at any moment finds
again when it starts (the inputs it had accepted and not yet let go, its checkpoints).

File layout
-----------
The file starts with the 4-byte magic ``OTJ`` + version byte; then records, each framed as

    u32 payload length | u32 CRC-32 of the payload | payload

(little endian). The payload is ``f64 time | u8 flags | u8 len(kind) | u16 len(key) |
kind | key | data``: ``time`` is the record's data time [s] (the TimeBase seconds of the
node), ``flags`` bit 0 marks a *sticky* record (below). A process killed mid-write leaves
a torn last record, a disk error a record whose CRC fails: :func:`scan_journal` stops at
the first bad frame and says how many bytes it left out, it never raises on content;
:class:`Journal` cuts such a tail off before it appends again.

Durability
----------
Each record is handed to the kernel with one ``write`` as it is appended (no user-space
buffer), so a killed process (SIGKILL included) loses nothing it appended. ``fsync`` runs
at most every ``fsync_interval`` seconds while records arrive, and at once for a
:meth:`Journal.append` with ``sync=True`` (the node's checkpoints): a power cut loses at
most the records of the last interval.

What is kept
------------
:meth:`Journal.compact` rewrites the file with the records still needed (to a temporary
file, fsynced, then ``os.replace``, so a kill during compaction leaves the old or the new
file, never a mix): a record is needed while its time is not before ``keep_from``; of the
records of one sticky ``(kind, key)`` the newest one before ``keep_from`` is needed too
(the pose a moving station is interpolated from, a fixed station's only pose, the latest
checkpoint). The file stays under ``max_bytes`` (plus one record): when an append would
pass it, the journal compacts, and if the records still needed do not fit in three
quarters of the bound it drops the oldest of them (never the newest of a sticky group) and
counts them (``records_dropped``).

One process at a time: the journal holds an exclusive ``flock`` on ``<file>.lock``
(released by the kernel when the process dies, however it dies), and a second process
opening the same journal gets a :class:`JournalError`.

What goes in the records is the caller's business; the observation buffer's records are in
:mod:`orbit_tracking.core.data.journaled_buffer`.
"""

from __future__ import annotations

import errno
import fcntl
import math
import os
import struct
import time as _time
import zlib
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from orbit_tracking.core.errors import OrbitTrackingError

__all__ = [
    'MAGIC',
    'MAX_RECORD_BYTES',
    'MIN_JOURNAL_BYTES',
    'Journal',
    'JournalError',
    'JournalRecord',
    'JournalScan',
    'encode_record',
    'records_to_keep',
    'scan_journal',
]

MAGIC = b'OTJ\x01'
"""First bytes of a journal file (version 1)."""

MAX_RECORD_BYTES = 64 * 2**20
"""A frame announcing a longer payload is corrupt."""

MIN_JOURNAL_BYTES = 64 * 2**10
"""Smallest ``max_bytes`` a journal accepts."""

_FRAME = struct.Struct('<II')  # payload length, CRC-32
_HEAD = struct.Struct('<dBBH')  # time, flags, len(kind), len(key)
_STICKY = 0x01


class JournalError(OrbitTrackingError, ValueError):
    """A journal cannot be used: a foreign file in its place, or another process holds it."""


@dataclass(frozen=True)
class JournalRecord:
    """One journal entry.

    Attributes
    ----------
    kind, key : str
        What it is (``measurements``, ``pose``, ...) and of what (a station id, ...).
    time : float
        Data time [s]: the record is needed while ``time >= keep_from`` (``-inf`` for a
        record only its stickiness keeps).
    data : bytes
    sticky : bool
        The newest record of its ``(kind, key)`` before ``keep_from`` is kept as well.
    """

    kind: str
    key: str
    time: float
    data: bytes
    sticky: bool = False


def encode_record(rec: JournalRecord) -> bytes:
    """The framed bytes of one record (see the module docstring)."""
    kind, key = rec.kind.encode(), rec.key.encode()
    if not kind or len(kind) > 255 or len(key) > 65535:
        raise ValueError(
            f'record kind must be 1-255 bytes and key at most 65535; got {rec.kind!r}'
        )
    if math.isnan(rec.time):
        raise ValueError(f'record {rec.kind}/{rec.key}: time must not be NaN')
    payload = (
        _HEAD.pack(rec.time, _STICKY if rec.sticky else 0, len(kind), len(key))
        + kind
        + key
        + rec.data
    )
    if len(payload) > MAX_RECORD_BYTES:
        raise ValueError(f'record {rec.kind}/{rec.key} of {len(payload)} bytes is too long')
    return _FRAME.pack(len(payload), zlib.crc32(payload)) + payload


def _decode_payload(payload: bytes) -> JournalRecord | None:
    if len(payload) < _HEAD.size:
        return None
    t, flags, nk, nkey = _HEAD.unpack_from(payload)
    start = _HEAD.size
    if nk == 0 or start + nk + nkey > len(payload) or math.isnan(t):
        return None
    try:
        kind = payload[start : start + nk].decode()
        key = payload[start + nk : start + nk + nkey].decode()
    except UnicodeDecodeError:
        return None
    return JournalRecord(kind, key, t, payload[start + nk + nkey :], bool(flags & _STICKY))


@dataclass(frozen=True)
class JournalScan:
    """What :func:`scan_journal` read.

    Attributes
    ----------
    records : tuple of JournalRecord
        The good records, in file order.
    offsets : tuple of int
        Where each record's frame starts.
    valid_bytes : int
        End of the last good record (the magic alone: 4; an empty or missing file: 0).
    discarded_bytes : int
        Bytes after it, left out.
    problem : str
        Why the scan stopped early ('' if it read to the end): ``torn file header``,
        ``torn record frame``, ``torn record``, ``bad record length``, ``CRC mismatch``
        or ``bad record``.
    """

    records: tuple[JournalRecord, ...] = ()
    offsets: tuple[int, ...] = ()
    valid_bytes: int = 0
    discarded_bytes: int = 0
    problem: str = ''


def scan_journal(path: str | Path) -> JournalScan:
    """Read a journal up to its first bad frame (a torn tail, a CRC mismatch).

    Raises
    ------
    JournalError
        The file does not start with :data:`MAGIC` (not a journal, or another version).
    """
    p = Path(path)
    if not p.exists():
        return JournalScan()
    data = p.read_bytes()
    if not data:
        return JournalScan()
    if len(data) < len(MAGIC):
        if MAGIC.startswith(data):
            return JournalScan(discarded_bytes=len(data), problem='torn file header')
        raise JournalError(f'{p} is not an orbit_tracking journal (starts with {data!r})')
    if data[: len(MAGIC)] != MAGIC:
        raise JournalError(
            f'{p} is not an orbit_tracking journal of version {MAGIC[-1]} (starts with '
            f'{data[: len(MAGIC)]!r}); move it away or use another directory'
        )
    pos = len(MAGIC)
    records: list[JournalRecord] = []
    offsets: list[int] = []
    problem = ''
    while pos < len(data):
        if len(data) - pos < _FRAME.size:
            problem = 'torn record frame'
            break
        length, crc = _FRAME.unpack_from(data, pos)
        if not _HEAD.size + 1 <= length <= MAX_RECORD_BYTES:
            problem = 'bad record length'
            break
        end = pos + _FRAME.size + length
        if end > len(data):
            problem = 'torn record'
            break
        payload = data[pos + _FRAME.size : end]
        if zlib.crc32(payload) != crc:
            problem = 'CRC mismatch'
            break
        rec = _decode_payload(payload)
        if rec is None:
            problem = 'bad record'
            break
        records.append(rec)
        offsets.append(pos)
        pos = end
    return JournalScan(tuple(records), tuple(offsets), pos, len(data) - pos, problem)


def records_to_keep(
    entries: Sequence[tuple[str, str, float, bool, int]],
    keep_from: float,
    budget: int | None = None,
) -> tuple[list[bool], int]:
    """Which records a compaction keeps (the rule is in the module docstring).

    Parameters
    ----------
    entries : sequence of (kind, key, time, sticky, size in bytes)
        The records in file order.
    keep_from : float
        Data time [s] from which records are needed.
    budget : int, optional
        Bytes the kept records may take; beyond it the oldest (by time, then file order)
        are dropped, except the newest record of each sticky group.

    Returns
    -------
    keep : list of bool
    dropped : int
        Records dropped for the budget (they were still needed).
    """
    keep = [t >= keep_from for _, _, t, _, _ in entries]
    before: dict[tuple[str, str], int] = {}
    newest: dict[tuple[str, str], int] = {}
    for i, (kind, key, t, sticky, _) in enumerate(entries):
        if not sticky:
            continue
        g = (kind, key)
        j = newest.get(g)
        if j is None or t >= entries[j][2]:
            newest[g] = i
        if t < keep_from:
            j = before.get(g)
            if j is None or t >= entries[j][2]:
                before[g] = i
    for i in before.values():
        keep[i] = True
    dropped = 0
    if budget is not None:
        total = sum(e[4] for e, k in zip(entries, keep, strict=True) if k)
        if total > budget:
            protected = set(newest.values())
            order = sorted(
                (i for i, k in enumerate(keep) if k and i not in protected),
                key=lambda i: (entries[i][2], i),
            )
            for i in order:
                if total <= budget:
                    break
                keep[i] = False
                total -= entries[i][4]
                dropped += 1
    return keep, dropped


@dataclass
class _Entry:
    offset: int
    size: int
    kind: str
    key: str
    time: float
    sticky: bool


class Journal:
    """An append-only record file with a size bound (see the module docstring).

    Opening it takes the lock, reads what is there (:attr:`recovered`) and cuts off a bad
    tail; a missing file (and its directory) is created.

    Parameters
    ----------
    path : path-like
        The journal file; ``<path>.lock`` and ``<path>.tmp`` are used next to it.
    max_bytes : int
        Bound on the file size (at least :data:`MIN_JOURNAL_BYTES`).
    fsync_interval : float
        Seconds between fsyncs while records arrive (0: after every record).
    clock : callable
        Monotonic seconds (tests give their own).

    Raises
    ------
    JournalError
        Another process holds the journal, or the file is not a journal.

    Attributes
    ----------
    recovered : JournalScan
        What was in the file when it was opened.
    counts : Counter
        ``records_appended``, ``bytes_appended``, ``compactions``, ``records_compacted``
        (let go as no longer needed), ``records_dropped`` (let go for the size bound while
        still needed), ``fsyncs``, ``tail_bytes_discarded``.
    """

    def __init__(
        self,
        path: str | Path,
        max_bytes: int,
        fsync_interval: float = 1.0,
        clock: Callable[[], float] = _time.monotonic,
    ) -> None:
        if max_bytes < MIN_JOURNAL_BYTES:
            raise ValueError(f'journal max_bytes must be >= {MIN_JOURNAL_BYTES}; got {max_bytes}')
        if not fsync_interval >= 0.0:
            raise ValueError(f'fsync_interval must be >= 0 s; got {fsync_interval}')
        self.path = Path(path)
        self.max_bytes = int(max_bytes)
        self.fsync_interval = float(fsync_interval)
        self._clock = clock
        self.counts: Counter[str] = Counter()
        self.keep_from = -math.inf
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock_fd = self._lock()
        self._fd = -1
        try:
            self.recovered = scan_journal(self.path)
            self._open(self.recovered)
        except BaseException:
            os.close(self._lock_fd)
            raise
        self._dirty = False
        self._last_sync = clock()

    # -- opening ----------------------------------------------------------------------
    def _lock(self) -> int:
        lock = self.path.with_name(self.path.name + '.lock')
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = os.pread(fd, 32, 0).decode(errors='replace').strip()
            os.close(fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EACCES):
                raise JournalError(
                    f'journal {self.path} is in use by another process'
                    + (f' (pid {holder})' if holder else '')
                    + ': give each node instance its own journal_dir or name'
                ) from exc
            raise
        os.ftruncate(fd, 0)
        os.pwrite(fd, f'{os.getpid()}\n'.encode(), 0)
        return fd

    def _open(self, scan: JournalScan) -> None:
        self._entries: list[_Entry] = []
        if scan.valid_bytes < len(MAGIC):  # missing, empty or a torn header: start anew
            self.counts['tail_bytes_discarded'] += scan.discarded_bytes
            self._write_file([])
        else:
            if scan.discarded_bytes:
                os.truncate(self.path, scan.valid_bytes)
                self.counts['tail_bytes_discarded'] += scan.discarded_bytes
            ends = [*scan.offsets[1:], scan.valid_bytes][: len(scan.offsets)]
            for rec, a, b in zip(scan.records, scan.offsets, ends, strict=True):
                self._entries.append(_Entry(a, b - a, rec.kind, rec.key, rec.time, rec.sticky))
            self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND)
            if scan.discarded_bytes:
                os.fsync(self._fd)
        self.size = scan.valid_bytes if scan.valid_bytes >= len(MAGIC) else len(MAGIC)

    def _write_file(self, frames: Sequence[bytes]) -> None:
        """Replace the file atomically with the magic and ``frames``; reopen for appends."""
        tmp = self.path.with_name(self.path.name + '.tmp')
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            _write_all(fd, MAGIC + b''.join(frames))
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, self.path)
        dfd = os.open(self.path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)  # the rename itself
        finally:
            os.close(dfd)
        if self._fd >= 0:
            os.close(self._fd)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND)
        self.size = len(MAGIC) + sum(len(f) for f in frames)

    # -- writing ----------------------------------------------------------------------
    @property
    def n_records(self) -> int:
        return len(self._entries)

    def append(self, rec: JournalRecord, sync: bool = False) -> None:
        """Append one record (compacting first if it would pass ``max_bytes``); fsync now
        with ``sync``, else when ``fsync_interval`` has passed."""
        frame = encode_record(rec)
        if self.size + len(frame) > self.max_bytes:
            self.compact(self.keep_from, room=len(frame))
        offset = self.size
        _write_all(self._fd, frame)
        self.size += len(frame)
        self._entries.append(_Entry(offset, len(frame), rec.kind, rec.key, rec.time, rec.sticky))
        self.counts['records_appended'] += 1
        self.counts['bytes_appended'] += len(frame)
        self._dirty = True
        self.sync(force=sync)

    def releasable_bytes(self, keep_from: float) -> int:
        """Bytes a compaction at ``keep_from`` would let go (no longer needed)."""
        keep, _ = records_to_keep(self._meta(), max(self.keep_from, float(keep_from)))
        return sum(e.size for e, k in zip(self._entries, keep, strict=True) if not k)

    def sync(self, force: bool = False) -> bool:
        """fsync if anything was appended since the last one and ``force`` or the interval
        has passed; returns whether it did."""
        now = self._clock()
        if not self._dirty or not (force or now - self._last_sync >= self.fsync_interval):
            return False
        os.fsync(self._fd)
        self._dirty = False
        self._last_sync = now
        self.counts['fsyncs'] += 1
        return True

    def compact(self, keep_from: float, room: int = 0) -> tuple[int, int]:
        """Rewrite the file with the records needed from ``keep_from`` on (remembered for
        the compactions :meth:`append` does); the size bound applies with ``room`` bytes
        to spare. Returns (records let go as not needed, records dropped for the bound)."""
        self.keep_from = max(self.keep_from, float(keep_from))
        meta = self._meta()
        keep, dropped = records_to_keep(meta, self.keep_from)
        kept = [e for e, k in zip(self._entries, keep, strict=True) if k]
        if len(MAGIC) + sum(e.size for e in kept) + room > self.max_bytes:
            # still needed, but the bound comes first: make room for a while (3/4)
            budget = max(self.max_bytes * 3 // 4 - room - len(MAGIC), 0)
            keep, dropped = records_to_keep(meta, self.keep_from, budget)
            kept = [e for e, k in zip(self._entries, keep, strict=True) if k]
        if len(kept) == len(self._entries):
            return 0, 0
        self._write_file(self._read_frames(kept))
        offset = len(MAGIC)
        for e in kept:
            e.offset = offset
            offset += e.size
        released = len(self._entries) - len(kept) - dropped
        self._entries = kept
        self.counts['compactions'] += 1
        self.counts['records_compacted'] += released
        self.counts['records_dropped'] += dropped
        self._dirty = False
        self._last_sync = self._clock()
        return released, dropped

    def clear(self) -> None:
        """Forget every record (the data they stood for are gone: a new time line)."""
        self._write_file([])
        self._entries = []
        self.keep_from = -math.inf
        self._dirty = False

    def records(self) -> list[JournalRecord]:
        """Every record now in the file (read back from disk)."""
        out = []
        for e, frame in zip(self._entries, self._read_frames(self._entries), strict=True):
            rec = _decode_payload(frame[_FRAME.size :])
            if rec is None:  # the file changed under us
                raise JournalError(f'{self.path}: record at {e.offset} no longer decodes')
            out.append(rec)
        return out

    def close(self) -> None:
        if self._fd >= 0:
            if self._dirty:
                os.fsync(self._fd)
            os.close(self._fd)
            self._fd = -1
        if self._lock_fd >= 0:
            os.close(self._lock_fd)  # releases the flock
            self._lock_fd = -1

    def _meta(self) -> list[tuple[str, str, float, bool, int]]:
        return [(e.kind, e.key, e.time, e.sticky, e.size) for e in self._entries]

    def _read_frames(self, entries: Sequence[_Entry]) -> list[bytes]:
        fd = os.open(self.path, os.O_RDONLY)
        try:
            return [os.pread(fd, e.size, e.offset) for e in entries]
        finally:
            os.close(fd)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]
