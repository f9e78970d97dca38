"""An observation buffer that journals what it accepts, and the replay of such a journal:
what the live estimator needs to start again, after being killed, with the buffer it had.

:class:`JournaledBuffer` is an :class:`~orbit_tracking.core.data.buffer.ObservationBuffer`
that appends every input it accepts (measurement rows, station poses, telemetry, fixes) to a
:class:`~orbit_tracking.core.data.journal.Journal` as it is given; arrays are packed without
pickle (:func:`pack_arrays`). :func:`replay_records` feeds such records into a buffer again.

Recording what the buffer accepted, rather than the raw messages, means the replay needs
none of the node's message checks and time-line logic (which depend on what came before and
when: a stream that went back in time alone, stragglers of an old time line), and gives the
buffer the node had. Times are the node's TimeBase seconds; a ``context`` record (the time
base and world frame) comes before the first record that needs it.
"""

from __future__ import annotations

import json
import math
import struct
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbit_tracking.core.data.buffer import ObservationBuffer
from orbit_tracking.core.data.journal import Journal, JournalRecord

__all__ = [
    'DATA_KINDS',
    'JournaledBuffer',
    'ReplaySummary',
    'pack_arrays',
    'replay_records',
    'unpack_arrays',
]

DATA_KINDS = ('measurements', 'pose', 'telemetry', 'fix')
"""Record kinds of the buffer's inputs."""

_DTYPES = frozenset({'<f8', '<u4', '<i8', '|b1'})  # what pack_arrays writes and reads


# -- array payloads ---------------------------------------------------------------------------


def pack_arrays(meta: Mapping[str, Any], **arrays: ArrayLike) -> bytes:
    """``meta`` (JSON) and named arrays as bytes: a length-prefixed JSON header (meta,
    names, dtypes, shapes), then each array's little-endian bytes. Only float64, uint32,
    int64 and bool arrays; no pickle either way."""
    header: dict[str, Any] = {'meta': dict(meta), 'arrays': []}
    blobs = []
    for name, a in arrays.items():
        arr = np.asarray(a)
        if arr.dtype.kind == 'f':
            arr = arr.astype('<f8', copy=False)
        elif arr.dtype.kind == 'b':
            arr = arr.astype('|b1', copy=False)
        elif arr.dtype == np.uint32:
            arr = arr.astype('<u4', copy=False)
        elif arr.dtype.kind in 'iu':
            arr = arr.astype('<i8', copy=False)
        else:
            raise ValueError(f'array {name!r}: dtype {arr.dtype} cannot be packed')
        header['arrays'].append([name, arr.dtype.str, list(arr.shape)])
        blobs.append(arr.tobytes())
    head = json.dumps(header, separators=(',', ':')).encode()
    return struct.pack('<I', len(head)) + head + b''.join(blobs)


def unpack_arrays(data: bytes) -> tuple[dict[str, Any], dict[str, NDArray[Any]]]:
    """Inverse of :func:`pack_arrays`.

    Raises
    ------
    ValueError
        Malformed data (sizes that do not add up, an unknown dtype).
    """
    if len(data) < 4:
        raise ValueError('packed arrays: no header')
    (n,) = struct.unpack_from('<I', data)
    try:
        header = json.loads(data[4 : 4 + n])
        items = header['arrays']
        meta = dict(header['meta'])
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f'packed arrays: bad header ({exc})') from exc
    pos = 4 + n
    out: dict[str, NDArray[Any]] = {}
    for name, dt, shape in items:
        if dt not in _DTYPES or not all(isinstance(s, int) and s >= 0 for s in shape):
            raise ValueError(f'packed arrays: {name!r} has dtype {dt} and shape {shape}')
        dtype = np.dtype(dt)
        size = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        if pos + size > len(data):
            raise ValueError(f'packed arrays: {name!r} runs past the end')
        out[str(name)] = np.frombuffer(data, dtype, int(np.prod(shape)), pos).reshape(shape)
        pos += size
    if pos != len(data):
        raise ValueError(f'packed arrays: {len(data) - pos} bytes left over')
    return meta, out


# -- the buffer ----------------------------------------------------------------------------

_Context = Callable[[], Mapping[str, Any]]


class JournaledBuffer(ObservationBuffer):
    """An :class:`ObservationBuffer` that appends every input it accepts to ``journal``.

    Records (``kind`` / ``key``): ``measurements`` / station id (time: newest epoch),
    ``pose`` / station id (sticky), ``telemetry`` / target id, ``fix`` / target id, and
    ``context`` (sticky, time -inf): ``context()``'s JSON mapping (the node's time base
    and world frame, what the times mean) whenever it differs from the last one written,
    before the record that needs it. A write that fails (disk full) is counted
    (``journal_write_errors`` in :attr:`counts`, the text in :attr:`journal_error`) and
    the input is kept in the buffer regardless.
    """

    def __init__(self, journal: Journal, context: _Context | None = None) -> None:
        super().__init__()
        self.journal = journal
        self._context = context
        self._written_context: dict[str, Any] | None = None
        self.journal_error = ''

    def add_measurements(
        self,
        station_id: str,
        fields: Sequence[str],
        time: ArrayLike,
        target_id: ArrayLike,
        values: ArrayLike,
        sigmas: ArrayLike,
    ) -> int:
        n = super().add_measurements(station_id, fields, time, target_id, values, sigmas)
        if n:
            t = np.atleast_1d(np.asarray(time, dtype=np.float64))
            tid = np.broadcast_to(np.asarray(target_id, dtype=np.uint32), t.shape)
            data = pack_arrays(
                {'fields': list(fields)},
                time=t,
                target_id=tid,
                values=np.asarray(values, dtype=np.float64),
                sigmas=np.asarray(sigmas, dtype=np.float64),
            )
            self._write(JournalRecord('measurements', station_id, float(t.max()), data))
        return n

    def add_pose(
        self,
        station_id: str,
        t: float,
        position: ArrayLike,
        velocity: ArrayLike,
        rotation: ArrayLike,
        moving: bool,
    ) -> None:
        super().add_pose(station_id, t, position, velocity, rotation, moving)
        data = pack_arrays(
            {'moving': bool(moving)},
            position=np.asarray(position, dtype=np.float64).reshape(3),
            velocity=np.asarray(velocity, dtype=np.float64).reshape(3),
            rotation=np.asarray(rotation, dtype=np.float64).reshape(3, 3),
        )
        self._write(JournalRecord('pose', station_id, float(t), data, sticky=True))

    def add_telemetry(
        self,
        target_id: int,
        t: float,
        position: ArrayLike,
        velocity: ArrayLike,
        position_sigma: ArrayLike,
        velocity_sigma: ArrayLike,
    ) -> None:
        super().add_telemetry(target_id, t, position, velocity, position_sigma, velocity_sigma)
        data = pack_arrays(
            {},
            position=position,
            velocity=velocity,
            position_sigma=position_sigma,
            velocity_sigma=velocity_sigma,
        )
        self._write(JournalRecord('telemetry', str(int(target_id)), float(t), data))

    def add_fix(
        self, target_id: int, t: float, position: ArrayLike, covariance: ArrayLike
    ) -> None:
        super().add_fix(target_id, t, position, covariance)
        data = pack_arrays({}, position=position, covariance=covariance)
        self._write(JournalRecord('fix', str(int(target_id)), float(t), data))

    def sizes(self) -> dict[str, int]:
        out = super().sizes()
        out['journal_bytes'] = self.journal.size
        out['journal_records'] = self.journal.n_records
        return out

    def _write(self, rec: JournalRecord) -> None:
        try:
            if self._context is not None:
                ctx = dict(self._context())
                if ctx != self._written_context:
                    data = json.dumps(ctx, sort_keys=True).encode()
                    self.journal.append(JournalRecord('context', '', -math.inf, data, True))
                    self._written_context = ctx
            self.journal.append(rec)
        except OSError as exc:
            self.counts['journal_write_errors'] += 1
            self.journal_error = f'{type(exc).__name__}: {exc}'


@dataclass
class ReplaySummary:
    """What :func:`replay_records` did.

    Attributes
    ----------
    counts : Counter
        Records applied, by kind (``measurement_rows`` too); ``failed_<kind>`` for records
        that no longer decode or that the buffer refused.
    context : dict or None
        The last ``context`` record.
    state : dict or None
        The last ``state`` record (JSON; written by the node, not by the buffer).
    poses : dict
        Station id -> its last pose ``(t, position, velocity, rotation, moving)``.
    first_time, last_time : float
        Earliest and newest data time among the records applied (nan if none).
    """

    counts: Counter[str] = field(default_factory=Counter)
    context: dict[str, Any] | None = None
    state: dict[str, Any] | None = None
    poses: dict[str, tuple[float, NDArray[Any], NDArray[Any], NDArray[Any], bool]] = field(
        default_factory=dict
    )
    first_time: float = math.nan
    last_time: float = math.nan

    @property
    def data_records(self) -> int:
        return sum(self.counts[k] for k in DATA_KINDS)


def replay_records(
    buffer: ObservationBuffer, records: Sequence[JournalRecord], shift: float = 0.0
) -> ReplaySummary:
    """Feed journal records into ``buffer`` (the plain :class:`ObservationBuffer` methods,
    so a :class:`JournaledBuffer` does not write them again), times moved by ``shift``
    seconds (another time base); ``context`` and ``state`` records are returned. A record
    that does not decode or that the buffer refuses is counted and skipped."""
    out = ReplaySummary()
    times: list[float] = []
    for rec in records:
        try:
            if rec.kind in ('context', 'state'):
                value = json.loads(rec.data)
                if not isinstance(value, dict):
                    raise ValueError(f'{rec.kind} record is not a mapping')
                if rec.kind == 'context':
                    out.context = value
                else:
                    out.state = value
            elif rec.kind in DATA_KINDS:
                times += _replay_one(buffer, rec, shift, out)
            else:
                out.counts[f'unknown_{rec.kind}'] += 1
                continue
        except (ValueError, KeyError, TypeError):  # MeasurementError is a ValueError
            out.counts[f'failed_{rec.kind}'] += 1
            continue
        out.counts[rec.kind] += 1
    if times:
        out.first_time, out.last_time = min(times), max(times)
    return out


def _replay_one(
    buffer: ObservationBuffer, rec: JournalRecord, shift: float, out: ReplaySummary
) -> list[float]:
    """Apply one data record; returns its data times."""
    meta, a = unpack_arrays(rec.data)
    base = ObservationBuffer
    t = rec.time + shift
    if rec.kind == 'measurements':
        rows = a['time'] + shift
        base.add_measurements(
            buffer, rec.key, meta['fields'], rows, a['target_id'], a['values'], a['sigmas']
        )
        out.counts['measurement_rows'] += int(rows.size)
        return [float(rows.min()), float(rows.max())]
    if rec.kind == 'pose':
        moving = bool(meta['moving'])
        base.add_pose(buffer, rec.key, t, a['position'], a['velocity'], a['rotation'], moving)
        out.poses[rec.key] = (t, a['position'], a['velocity'], a['rotation'], moving)
        return []
    if rec.kind == 'telemetry':
        base.add_telemetry(
            buffer,
            int(rec.key),
            t,
            a['position'],
            a['velocity'],
            a['position_sigma'],
            a['velocity_sigma'],
        )
    else:
        base.add_fix(buffer, int(rec.key), t, a['position'], a['covariance'])
    return [t]
