"""What the live estimator has received and not yet let go: measurement rows per station,
station poses, telemetry and fixes, cut into :class:`~orbit_tracking.core.data.observations.
Observations` for a window on demand.

Messages arrive in any order (several publishers, a replay, a station batching epochs), so
rows are kept sorted by their epoch; a row received twice (same epoch, target, values and
sigmas) is kept once. Adding is cheap (the new rows are queued); sorting happens when a
window is cut or the buffer is pruned.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbit_tracking.core.data.observations import (
    FixSeries,
    Observations,
    StationObservations,
    pose_at,
    states_pose,
)
from orbit_tracking.core.data.poses import PoseTrack
from orbit_tracking.core.data.tables import MeasurementTable, StationStates, TargetStates
from orbit_tracking.core.errors import MeasurementError
from orbit_tracking.core.models.measurements import FIELDS, KIND_FIELDS, KIND_OPTIONAL_FIELDS

__all__ = ['ObservationBuffer']

FloatArray = NDArray[np.float64]


def _kind_of(fields: Sequence[str]) -> str:
    """Sensor kind whose fields these are ('' if none matches)."""
    have = set(fields)
    for kind, need in KIND_FIELDS.items():
        if set(need) <= have <= set(need) | set(KIND_OPTIONAL_FIELDS[kind]):
            return kind
    return ''


def _same_rows(a: FloatArray, b: FloatArray) -> NDArray[np.bool_]:
    """Row-wise equality with NaN equal to NaN, for (n, k) arrays."""
    return np.all((a == b) | (np.isnan(a) & np.isnan(b)), axis=1)


@dataclass
class _StationRows:
    """One station's rows: consolidated sorted arrays plus queued chunks."""

    fields: tuple[str, ...] = ()
    time: FloatArray = field(default_factory=lambda: np.zeros(0))
    target_id: NDArray[np.uint32] = field(default_factory=lambda: np.zeros(0, np.uint32))
    values: FloatArray = field(default_factory=lambda: np.zeros((0, 0)))
    sigmas: FloatArray = field(default_factory=lambda: np.zeros((0, 0)))
    queue: list[tuple[tuple[str, ...], FloatArray, NDArray[np.uint32], FloatArray, FloatArray]] = (
        field(default_factory=list)
    )
    earliest: float = math.inf

    def __len__(self) -> int:
        return int(self.time.size) + sum(int(q[1].size) for q in self.queue)

    def _widen(
        self, fields: tuple[str, ...], values: FloatArray, sigmas: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Columns of ``fields`` rearranged into :attr:`fields` (NaN where absent)."""
        n = values.shape[0]
        v = np.full((n, len(self.fields)), np.nan)
        s = np.full((n, len(self.fields)), np.nan)
        for j, f in enumerate(fields):
            k = self.fields.index(f)
            v[:, k], s[:, k] = values[:, j], sigmas[:, j]
        return v, s

    def consolidate(self) -> int:
        """Merge the queue into the sorted arrays; returns the duplicate rows dropped."""
        if not self.queue:
            return 0
        union = set(self.fields)
        for q in self.queue:
            union |= set(q[0])
        fields = tuple(f for f in FIELDS if f in union)
        if fields != self.fields:
            old = self.fields
            self.fields = fields
            self.values, self.sigmas = self._widen(old, self.values, self.sigmas)
        parts = [(self.time, self.target_id, self.values, self.sigmas)]
        for f, t, tid, v, s in self.queue:
            vv, ss = self._widen(f, v, s)
            parts.append((t, tid, vv, ss))
        self.queue = []
        t = np.concatenate([p[0] for p in parts])
        tid = np.concatenate([p[1] for p in parts]).astype(np.uint32)
        v = np.concatenate([p[2] for p in parts])
        s = np.concatenate([p[3] for p in parts])
        # identical rows end up next to each other: sort by time, target, values, sigmas
        keys: list[NDArray[np.generic]] = [s[:, j] for j in range(s.shape[1] - 1, -1, -1)]
        keys += [*(v[:, j] for j in range(v.shape[1] - 1, -1, -1)), tid, t]
        order = np.lexsort(keys)
        t, tid, v, s = t[order], tid[order], v[order], s[order]
        dup = np.zeros(t.size, dtype=bool)
        if t.size > 1:
            dup[1:] = (
                (t[1:] == t[:-1])
                & (tid[1:] == tid[:-1])
                & _same_rows(v[1:], v[:-1])
                & _same_rows(s[1:], s[:-1])
            )
        keep = ~dup
        self.time, self.target_id = t[keep], tid[keep]
        self.values, self.sigmas = v[keep], s[keep]
        return int(dup.sum())

    def drop_before(self, before: float) -> NDArray[np.bool_]:
        """Remove rows older than ``before``; returns the mask of removed rows."""
        gone = self.time < before
        if np.any(gone):
            keep = ~gone
            self.time, self.target_id = self.time[keep], self.target_id[keep]
            self.values, self.sigmas = self.values[keep], self.sigmas[keep]
        self.earliest = float(self.time[0]) if self.time.size else math.inf
        return gone


@dataclass
class _Samples:
    """Time-stamped samples of one target (telemetry or fixes), kept sorted by time."""

    rows: list[tuple[float, tuple[FloatArray, ...]]] = field(default_factory=list)
    sorted_: bool = True

    def add(self, t: float, *arrays: FloatArray) -> None:
        if self.rows and t < self.rows[-1][0]:
            self.sorted_ = False
        self.rows.append((t, arrays))

    def settle(self) -> int:
        """Sort by time and drop repeated epochs; returns how many were dropped."""
        if not self.sorted_:
            self.rows.sort(key=lambda r: r[0])
            self.sorted_ = True
        n = len(self.rows)
        out: list[tuple[float, tuple[FloatArray, ...]]] = []
        for r in self.rows:
            if not (out and r[0] == out[-1][0]):
                out.append(r)
        self.rows = out
        return n - len(out)

    def drop_before(self, before: float) -> int:
        dropped = self.settle()
        self.rows = [r for r in self.rows if r[0] >= before]
        return dropped

    def arrays(self, t0: float, t1: float, n: int) -> tuple[FloatArray, list[FloatArray]]:
        """Times and the ``n`` stacked arrays of the samples in [t0, t1]."""
        rows = [r for r in self.rows if t0 <= r[0] <= t1]
        t = np.array([r[0] for r in rows], dtype=np.float64)
        return t, [np.array([r[1][j] for r in rows], dtype=np.float64) for j in range(n)]


class ObservationBuffer:
    """Measurements, station poses, telemetry and fixes received so far.

    Attributes
    ----------
    counts : Counter
        Rows not kept, by reason: ``duplicate`` (exact repeats), ``too_late`` (older than
        the last prune), ``no_station_state`` (pruned before their station's state ever
        covered them), ``duplicate_telemetry``, ``duplicate_fix``.
    withheld : Counter
        Rows of the last :meth:`observations` call, per station id, that stayed out for
        want of a station pose (kept in the buffer for a later call).
    """

    def __init__(self) -> None:
        self._rows: dict[str, _StationRows] = {}
        self._poses: dict[str, PoseTrack] = {}
        self._telemetry: dict[int, _Samples] = {}
        self._fixes: dict[int, _Samples] = {}
        self._horizon = -math.inf
        self._latest = -math.inf
        self.counts: Counter[str] = Counter()
        self.withheld: Counter[str] = Counter()

    # -- input -----------------------------------------------------------------------
    def add_measurements(
        self,
        station_id: str,
        fields: Sequence[str],
        time: ArrayLike,
        target_id: ArrayLike,
        values: ArrayLike,
        sigmas: ArrayLike,
    ) -> int:
        """Queue measurement rows of one station (as ``cloud_to_measurements`` gives them).

        Parameters
        ----------
        station_id : str
        fields : sequence of str
            Value fields, the column order of ``values`` and ``sigmas``.
        time : array_like, shape (n,)
            Epochs [s].
        target_id : array_like, shape (n,)
        values, sigmas : array_like, shape (n, k)

        Returns
        -------
        int
            Rows queued (rows older than the last prune are counted ``too_late`` instead).

        Raises
        ------
        MeasurementError
            Unknown fields or inconsistent shapes.
        """
        f = tuple(fields)
        bad = [x for x in f if x not in FIELDS]
        if bad or len(set(f)) != len(f):
            raise MeasurementError(f'station {station_id!r}: unknown or repeated fields {f}')
        t = np.atleast_1d(np.asarray(time, dtype=np.float64))
        n = t.size
        v = np.asarray(values, dtype=np.float64)
        s = np.asarray(sigmas, dtype=np.float64)
        tid = np.asarray(target_id, dtype=np.uint32)
        if v.shape != (n, len(f)) or s.shape != v.shape or tid.shape not in ((), (n,)):
            raise MeasurementError(
                f'station {station_id!r}: values {v.shape} and sigmas {s.shape} must be '
                f'({n}, {len(f)}) and target ids {tid.shape} ({n},)'
            )
        tid = np.broadcast_to(tid, (n,)).copy()
        if not np.all(np.isfinite(t)):
            raise MeasurementError(f'station {station_id!r}: non-finite measurement epochs')
        late = t < self._horizon
        if np.any(late):
            self.counts['too_late'] += int(late.sum())
            keep = ~late
            t, tid, v, s = t[keep], tid[keep], v[keep], s[keep]
        if t.size == 0:
            return 0
        rows = self._rows.setdefault(station_id, _StationRows())
        rows.queue.append((f, t, tid, v, s))
        self._latest = max(self._latest, float(t.max()))
        rows.earliest = min(rows.earliest, float(t.min()))
        return int(t.size)

    def add_pose(
        self,
        station_id: str,
        t: float,
        position: ArrayLike,
        velocity: ArrayLike,
        rotation: ArrayLike,
        moving: bool,
    ) -> None:
        """A station pose sample (world frame); a fixed station keeps its latest one."""
        track = self._poses.setdefault(station_id, PoseTrack())
        track.add(
            float(t),
            np.asarray(position, dtype=np.float64).reshape(3),
            np.asarray(velocity, dtype=np.float64).reshape(3),
            np.asarray(rotation, dtype=np.float64).reshape(3, 3),
            bool(moving),
        )

    def add_telemetry(
        self,
        target_id: int,
        t: float,
        position: ArrayLike,
        velocity: ArrayLike,
        position_sigma: ArrayLike,
        velocity_sigma: ArrayLike,
    ) -> None:
        """One telemetry sample: world position [m], velocity [m/s] and their 1-sigma
        per axis (each (3,)).

        Raises
        ------
        ValueError
            Non-finite values or sigmas that are not finite and positive.
        """
        p, v, sp_, sv = (
            np.asarray(a, dtype=np.float64).reshape(3)
            for a in (position, velocity, position_sigma, velocity_sigma)
        )
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(v)) and math.isfinite(t)):
            raise ValueError(f'telemetry of target {target_id} at {t} has non-finite values')
        if not (np.all(np.isfinite(sp_) & (sp_ > 0)) and np.all(np.isfinite(sv) & (sv > 0))):
            raise ValueError(
                f'telemetry of target {target_id} at {t} needs finite positive sigmas; got '
                f'position {sp_}, velocity {sv}'
            )
        if t < self._horizon:
            self.counts['too_late'] += 1
            return
        self._telemetry.setdefault(int(target_id), _Samples()).add(float(t), p, v, sp_, sv)

    def add_fix(
        self, target_id: int, t: float, position: ArrayLike, covariance: ArrayLike
    ) -> None:
        """One position fix (world frame) with its 3x3 covariance.

        Raises
        ------
        ValueError
            Non-finite values or a covariance that is not positive definite.
        """
        p = np.asarray(position, dtype=np.float64).reshape(3)
        c = np.asarray(covariance, dtype=np.float64).reshape(3, 3)
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(c)) and math.isfinite(t)):
            raise ValueError(f'fix of target {target_id} at {t} has non-finite values')
        c = 0.5 * (c + c.T)
        if np.linalg.eigvalsh(c)[0] <= 0.0:
            raise ValueError(f'fix of target {target_id} at {t}: covariance not positive definite')
        if t < self._horizon:
            self.counts['too_late'] += 1
            return
        self._fixes.setdefault(int(target_id), _Samples()).add(float(t), p, c)

    # -- state -----------------------------------------------------------------------
    def latest_time(self) -> float:
        """Newest measurement epoch received (also after it was pruned; nan if none)."""
        return self._latest if math.isfinite(self._latest) else math.nan

    def first_time(self, after: float = -math.inf) -> float:
        """Earliest measurement epoch not before ``after`` (nan if none)."""
        best = math.inf
        for r in self._rows.values():
            if not len(r):
                continue
            if r.earliest >= after:
                best = min(best, r.earliest)
                continue
            self._consolidate(r)
            i = int(np.searchsorted(r.time, after, side='left'))
            if i < r.time.size:
                best = min(best, float(r.time[i]))
        return best if math.isfinite(best) else math.nan

    def stations(self) -> list[str]:
        """Station ids with measurement rows or poses."""
        return sorted(set(self._rows) | set(self._poses))

    def stations_without_pose(self) -> list[str]:
        return sorted(s for s, r in self._rows.items() if len(r) and s not in self._poses)

    def sizes(self) -> dict[str, int]:
        """Rows held: ``measurements``, ``telemetry``, ``fixes``, ``pose_samples``."""
        return {
            'measurements': sum(len(r) for r in self._rows.values()),
            'telemetry': sum(len(s.rows) for s in self._telemetry.values()),
            'fixes': sum(len(s.rows) for s in self._fixes.values()),
            'pose_samples': sum(len(p) for p in self._poses.values()),
        }

    def _count(self, key: str, n: int) -> None:
        if n:
            self.counts[key] += n

    def _consolidate(self, r: _StationRows) -> None:
        dup = r.consolidate()
        if dup:
            self.counts['duplicate'] += dup

    # -- output ----------------------------------------------------------------------
    def _pose_mask(self, sid: str, t: FloatArray) -> NDArray[np.bool_]:
        track = self._poses.get(sid)
        if track is None or not len(track):
            return np.zeros(t.size, dtype=bool)
        if not track.moving:
            return np.ones(t.size, dtype=bool)
        return (t >= track.t[0] - 1e-9) & (t <= track.t[-1] + 1e-9)

    def observations(self, t0: float = -math.inf, t1: float = math.inf) -> Observations:
        """Everything with ``t0 <= t <= t1`` as :class:`Observations`.

        Rows of a station without a pose at their epoch (no state received yet, or a moving
        station whose states do not reach that far) are left out, counted per station in
        :attr:`withheld`, and stay in the buffer.
        """
        self.withheld = Counter()
        stations = []
        for sid in sorted(self._rows):
            r = self._rows[sid]
            self._consolidate(r)
            sel = (r.time >= t0) & (r.time <= t1)
            if not np.any(sel):
                continue
            has = self._pose_mask(sid, r.time)
            missing = int((sel & ~has).sum())
            if missing:
                self.withheld[sid] = missing
            sel &= has
            if not np.any(sel):
                continue
            t = r.time[sel]
            track = self._poses[sid]
            states = StationStates(
                sid,
                track.moving,
                np.asarray(track.t, dtype=np.float64),
                np.array(track.p, dtype=np.float64),
                np.array(track.v, dtype=np.float64),
                np.array(track.r, dtype=np.float64),
                np.zeros((len(track), 3)),
            )
            table = MeasurementTable(
                sid,
                _kind_of(r.fields),
                r.fields,
                t,
                r.target_id[sel],
                r.values[sel],
                r.sigmas[sel],
            )
            stations.append(StationObservations(table, pose_at(states_pose(states), t)))
        telemetry = {}
        for tid, s in sorted(self._telemetry.items()):
            self._count('duplicate_telemetry', s.settle())
            t, (p, v, sp_, sv) = s.arrays(t0, t1, 4)
            if t.size:
                telemetry[tid] = TargetStates(tid, t, p, v, sp_, sv)
        fixes = {}
        for tid, s in sorted(self._fixes.items()):
            self._count('duplicate_fix', s.settle())
            t, (p, c) = s.arrays(t0, t1, 2)
            if t.size:
                fixes[tid] = FixSeries(tid, t, p, c)
        return Observations(tuple(stations), telemetry, fixes)

    def prune(self, before: float) -> None:
        """Forget everything older than ``before`` (rows arriving later that are older
        count as ``too_late``). Rows pruned without ever having had a station pose count
        as ``no_station_state``."""
        self._horizon = max(self._horizon, float(before))
        for sid, r in self._rows.items():
            self._consolidate(r)
            has = self._pose_mask(sid, r.time)
            gone = r.drop_before(before)
            lost = int((gone & ~has).sum())
            if lost:
                self.counts['no_station_state'] += lost
        for s in self._telemetry.values():
            self._count('duplicate_telemetry', s.drop_before(before))
        for s in self._fixes.values():
            self._count('duplicate_fix', s.drop_before(before))
        for track in self._poses.values():
            track.prune(before)
