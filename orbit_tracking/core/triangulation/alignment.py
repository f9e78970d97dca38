"""Alignment of unsynchronised station streams onto common epochs for triangulation.

Each angle-measuring station keeps a time series of samples per target. At a common
epoch ``t_k = k * period`` the line of sight of a station is interpolated linearly
between its two bracketing samples (as unit vectors in the world frame, so azimuth
wrap-around and the rotation of a moving station's frame need no special care), and
its origin is the station pose interpolated at ``t_k``. Linear interpolation of white
noise with weights ``(1 − f, f)`` scales the angle variance by ``(1 − f)² + f²``, which
the line's covariance carries.

The seed-003 low-pass filter ``a'(i) = (1 − ε)/2 (a(i−1) + a(i+1)) + ε a(i)`` can be
applied to each angle series before alignment (``smoothing_eps``). With ε = 0.95 it
scales the noise standard deviation by ``sqrt(ε² + (1 − ε)²/2) ≈ 0.951`` only, while it
correlates neighbouring samples and adds a bias ``(1 − ε)/2 · ä Δt²`` on curving
angles; it is therefore off by default.

Used unchanged by the live ``triangulation`` node (``process(latest − lag)`` as data
arrive) and by the offline ``orbit-tracking triangulate`` (``flush``).
"""

from __future__ import annotations

import math
from bisect import bisect_left
from collections import Counter, defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.data.poses import PoseTrack
from orbit_tracking.core.triangulation.intersection import LineOfSight, angle_jacobian_local

__all__ = ['AlignConfig', 'Aligner', 'EpochLines', 'low_pass']

FloatArray = NDArray[np.float64]

_ANGLE_PAIRS = (('azimuth', 'elevation', 'angles'), ('los_alpha', 'los_beta', 'los'))


@dataclass(frozen=True)
class AlignConfig:
    """Alignment settings.

    Attributes
    ----------
    period : float
        Spacing of the common epochs [s]; 0 picks the smallest median sampling interval
        among the angle stations.
    max_gap_factor : float
        Two samples bracket an epoch only if they are at most this many of the station's
        sampling intervals apart.
    lag : float
        Live use: an epoch is processed once data up to ``epoch + lag`` have arrived [s].
    smoothing_eps : float or None
        Seed 003's low-pass weight ε (e.g. 0.95); None disables it.
    stale_after : float
        Live use: a stream silent for this long (data time, s) no longer holds epochs back.
    max_time_jump : float
        A sample this far [s] ahead of all data so far is taken for a corrupt stamp.
    """

    period: float = 0.0
    max_gap_factor: float = 2.5
    lag: float = 1.0
    smoothing_eps: float | None = None
    stale_after: float = 5.0
    max_time_jump: float = 600.0

    def __post_init__(self) -> None:
        if self.period < 0.0:
            raise ValueError(f'period must be >= 0; got {self.period}')
        if self.max_gap_factor < 1.0:
            raise ValueError(f'max_gap_factor must be >= 1; got {self.max_gap_factor}')
        if self.lag < 0.0:
            raise ValueError(f'lag must be >= 0; got {self.lag}')
        if self.max_time_jump <= 0.0:
            raise ValueError(f'max_time_jump must be > 0; got {self.max_time_jump}')
        if self.stale_after <= 0.0:
            raise ValueError(f'stale_after must be > 0; got {self.stale_after}')
        if self.smoothing_eps is not None and not 0.0 < self.smoothing_eps <= 1.0:
            raise ValueError(f'smoothing_eps must be in (0, 1]; got {self.smoothing_eps}')


def low_pass(values: FloatArray, eps: float, wrap: bool = False) -> tuple[FloatArray, FloatArray]:
    """Seed 003's three-point low-pass filter (its eqs. 5-5, 5-6).

    Returns the filtered series and the factor by which each sample's noise standard
    deviation is scaled (1 at the two ends, which are left unfiltered).
    """
    v = np.asarray(values, dtype=np.float64)
    if wrap:
        v = np.unwrap(v)
    out = v.copy()
    scale = np.ones_like(v)
    if v.size >= 3:
        out[1:-1] = 0.5 * (1.0 - eps) * (v[:-2] + v[2:]) + eps * v[1:-1]
        scale[1:-1] = math.sqrt(eps * eps + 0.5 * (1.0 - eps) ** 2)
    if wrap:
        out = np.mod(out, 2.0 * np.pi)
    return out, scale


@dataclass
class _Series:
    """Samples of one station for one target (angles, optional range, sigmas)."""

    kind: str
    t: list[float] = field(default_factory=list)
    a: list[float] = field(default_factory=list)
    b: list[float] = field(default_factory=list)
    r: list[float] = field(default_factory=list)
    sa: list[float] = field(default_factory=list)
    sb: list[float] = field(default_factory=list)
    sr: list[float] = field(default_factory=list)

    def add(self, t: float, a: float, b: float, r: float, sa: float, sb: float, sr: float) -> None:
        if self.t and t <= self.t[-1]:
            if t == self.t[-1]:
                return
            i = bisect_left(self.t, t)
            for lst, v in zip(
                (self.t, self.a, self.b, self.r, self.sa, self.sb, self.sr),
                (t, a, b, r, sa, sb, sr),
                strict=True,
            ):
                lst.insert(i, v)
            return
        for lst, v in zip(
            (self.t, self.a, self.b, self.r, self.sa, self.sb, self.sr),
            (t, a, b, r, sa, sb, sr),
            strict=True,
        ):
            lst.append(v)

    _dt_cache: tuple[int, float] = (0, math.inf)

    def median_dt(self) -> float:
        """Median sampling interval (recomputed as the series doubles in length).

        A series pruned to its last samples (a station that went out of range) keeps the
        interval it had: the epoch grid and the stride of independent fixes depend on it.
        ``inf`` only while it was never known (fewer than three samples so far).
        """
        n, value = self._dt_cache
        if len(self.t) < 3:
            return value
        if len(self.t) >= 2 * n or not math.isfinite(value):
            value = float(np.median(np.diff(self.t[-200:])))
            self._dt_cache = (len(self.t), value)
        return value

    def prune(self, before: float, keep: int = 2) -> int:
        """Drop the samples before ``before`` but the last ``keep`` of them (interpolation
        brackets); returns how many were dropped."""
        k = max(0, bisect_left(self.t, before) - keep)
        if k:
            for lst in (self.t, self.a, self.b, self.r, self.sa, self.sb, self.sr):
                del lst[:k]
        return k


@dataclass(frozen=True)
class EpochLines:
    """Lines of sight of one target at one common epoch, and why others were missing."""

    time: float
    target_id: int
    lines: tuple[LineOfSight, ...]
    skipped: Counter[str]


class Aligner:
    """Buffers station poses and angle measurements and yields aligned lines of sight.

    Parameters
    ----------
    config : AlignConfig
    """

    def __init__(self, config: AlignConfig | None = None) -> None:
        self.config = config or AlignConfig()
        self.poses: dict[str, PoseTrack] = defaultdict(PoseTrack)
        self.series: dict[tuple[str, int], _Series] = {}
        self.latest = -math.inf
        self.earliest = math.inf
        self.last_epoch: float | None = None  # time of the last epoch fixed
        self.counts: Counter[str] = Counter()
        self._jumps = 0

    # -- input ---------------------------------------------------------------------
    def add_pose(
        self,
        station_id: str,
        t: float,
        position: FloatArray,
        velocity: FloatArray,
        rotation: FloatArray,
        moving: bool,
    ) -> None:
        if moving and math.isfinite(self.latest) and t > self.latest + self.config.max_time_jump:
            self.counts['time_jump'] += 1
            return
        self.poses[station_id].add(t, position, velocity, rotation, moving)

    def _plausible(self, t: float) -> bool:
        """Guard against a corrupt stamp far ahead of the data so far: it is rejected
        (``time_jump``), unless jumps persist (50 samples in a row: a new pass hours
        later), in which case the buffers restart at the new time."""
        if not math.isfinite(t):
            self.counts['invalid_time'] += 1
            return False
        if math.isfinite(self.latest) and t > self.latest + self.config.max_time_jump:
            self._jumps += 1
            if self._jumps < 50:
                self.counts['time_jump'] += 1
                return False
            self.counts['restarts'] += 1
            self._restart()
        self._jumps = 0
        return True

    def _restart(self) -> None:
        self.series.clear()
        for sid in [s for s, p in self.poses.items() if p.moving]:
            del self.poses[sid]
        self.latest, self.earliest, self.last_epoch, self._jumps = -math.inf, math.inf, None, 0

    def add_measurements(
        self,
        station_id: str,
        fields: Sequence[str],
        times: FloatArray,
        target_ids: NDArray[np.uint32],
        values: FloatArray,
        sigmas: FloatArray,
    ) -> int:
        """Buffer the angle samples of a measurement batch; returns how many were kept.

        Stations without an angle pair (CW radars) are ignored. Samples with a NaN angle
        are counted as ``nan_measurement``.
        """
        idx = {f: i for i, f in enumerate(fields)}
        pair = next(((a, b, k) for a, b, k in _ANGLE_PAIRS if a in idx and b in idx), None)
        if pair is None:
            self.counts['samples_without_angles'] += len(times)
            return 0
        fa, fb, kind = pair
        ir = idx.get('range') if kind == 'angles' else None
        kept = 0
        for j in range(len(times)):
            a, b = values[j, idx[fa]], values[j, idx[fb]]
            if not (np.isfinite(a) and np.isfinite(b)):
                self.counts['nan_measurement'] += 1
                continue
            t = float(times[j])
            if not self._plausible(t):
                continue
            r = values[j, ir] if ir is not None else math.nan
            sr = sigmas[j, ir] if ir is not None else math.nan
            key = (station_id, int(target_ids[j]))
            s = self.series.get(key)
            if s is None:
                s = self.series[key] = _Series(kind)
            s.add(
                t,
                float(a),
                float(b),
                float(r),
                float(sigmas[j, idx[fa]]),
                float(sigmas[j, idx[fb]]),
                float(sr),
            )
            self.latest = max(self.latest, t)
            self.earliest = min(self.earliest, t)
            kept += 1
        return kept

    # -- output --------------------------------------------------------------------
    def period(self) -> float:
        """Epoch spacing: the configured one, else the smallest median sampling interval."""
        if self.config.period > 0.0:
            return self.config.period
        dts = [s.median_dt() for s in self.series.values()]
        return min(dts) if dts else math.inf

    def stations_without_pose(self) -> list[str]:
        """Angle stations that sent measurements but no state yet."""
        with_data = {sid for sid, _ in self.series}
        return sorted(s for s in with_data if not len(self.poses.get(s, ())))

    def horizon(self, delivering: Mapping[str, float] | None = None) -> float:
        """Data time up to which every live stream has delivered.

        The minimum of the latest sample time of each measurement series and of each moving
        station's pose track. Measurements and station states travel on different topics,
        so an epoch is only fixed once the states that bracket it have arrived too.

        A stream that has gone quiet (a station in a dropout) must not hold the others
        back, but a stream that is merely late (its topic queued behind the others while
        the node was busy) must: fixing an epoch before its samples arrive loses them.
        ``delivering`` tells the two apart. It maps each stream the caller is still
        receiving (a station id for its measurements, ``<id>/state`` for its states) to
        the newest stamp received on it; a stream not in it is quiet. Then:

        * a series of a delivering station is skipped only when the station has moved
          ``stale_after`` seconds past it (its target left the field of view);
        * a pose track of a delivering state stream always counts;
        * a quiet stream, or any stream when ``delivering`` is None (no arrival
          information), is skipped once it is ``stale_after`` seconds of data time behind
          the newest sample.
        """
        stale = self.config.stale_after
        series_ends = [(sid, s.t[-1]) for (sid, _), s in self.series.items() if s.t]
        pose_ends = [
            (f'{sid}/state', p.t[-1])
            for sid, p in self.poses.items()
            if p.moving and p.t and any(k[0] == sid for k in self.series)
        ]
        ends = [e for _, e in series_ends + pose_ends]
        if not ends:
            return -math.inf
        newest = max(ends)
        live = dict(delivering or {})
        for sid, end in series_ends:  # a station's newest sample, whichever target
            if sid in live:
                live[sid] = max(live[sid], end)
        kept = []
        for sid, end in series_ends:
            if end >= (live[sid] if sid in live else newest) - stale:
                kept.append(end)
        for stream, end in pose_ends:
            if stream in live or end >= newest - stale:
                kept.append(end)
        return min(kept) if kept else newest

    def process(
        self,
        until: float | None = None,
        wait_for_poses: bool = True,
        delivering: Mapping[str, float] | None = None,
    ) -> list[EpochLines]:
        """Lines at every new common epoch up to ``until``.

        By default up to :meth:`horizon` minus the lag, and nothing at all while a station
        has measurements but no state yet (``wait_for_poses``; pass False once waiting for
        it has timed out: its lines are then skipped and counted). Call with
        ``until=math.inf`` (or :meth:`flush`) at the end of the data.
        """
        period = self.period()
        if not math.isfinite(period) or not self.series:
            return []
        if until is None and wait_for_poses and self.stations_without_pose():
            return []
        limit = (
            self.horizon(delivering) - self.config.lag
            if until is None
            else min(until, self.latest)
        )
        # the first epoch after the last one fixed, on the grid of the current period (it
        # shrinks when a faster station starts): epochs never go back nor skip ahead
        k_lo = (
            math.ceil(self.earliest / period - 1e-9)
            if self.last_epoch is None
            else math.floor(self.last_epoch / period + 1e-9) + 1
        )
        k_hi = math.floor(limit / period + 1e-9)
        if k_hi - k_lo > 1_000_000:
            self.counts['epochs_skipped'] += k_hi - k_lo - 1_000_000
            k_lo = k_hi - 1_000_000
        out = []
        for k in range(k_lo, k_hi + 1):
            out.extend(self._epoch(k * period))
        if k_hi >= k_lo:
            self.last_epoch = k_hi * period
            self._prune(k_hi * period)
        return out

    def flush(self) -> list[EpochLines]:
        return self.process(until=math.inf)

    def _epoch(self, t: float) -> list[EpochLines]:
        by_target: dict[int, list[LineOfSight]] = defaultdict(list)
        skipped: dict[int, Counter[str]] = defaultdict(Counter)
        for (sid, tid), s in self.series.items():
            line, why = self._line_at(sid, s, t)
            if line is not None:
                by_target[tid].append(line)
            elif why:
                skipped[tid][why] += 1
        targets = sorted(set(by_target) | set(skipped))
        return [
            EpochLines(t, tid, tuple(by_target.get(tid, ())), skipped[tid])
            for tid in targets
            if by_target.get(tid) or skipped[tid]
        ]

    def _max_gap(self, s: _Series) -> float:
        return (
            self.config.max_gap_factor * s.median_dt()
            if len(s.t) >= 3
            else self.config.max_gap_factor * self.period()
        )

    def _sample_line(self, sid: str, s: _Series, i: int, max_gap: float) -> LineOfSight | None:
        pose = self.poses.get(sid)
        at = pose.at(s.t[i], max_gap) if pose is not None else None
        if at is None:
            return None
        origin, rot = at
        a, b, sa, sb = s.a[i], s.b[i], s.sa[i], s.sb[i]
        eps = self.config.smoothing_eps
        if eps is not None and 0 < i < len(s.t) - 1 and s.t[i + 1] - s.t[i - 1] <= 2 * max_gap:
            wrap = s.kind == 'angles'
            a3, scale = low_pass(np.array(s.a[i - 1 : i + 2]), eps, wrap=wrap)
            b3, _ = low_pass(np.array(s.b[i - 1 : i + 2]), eps)
            a, b = float(a3[1]), float(b3[1])
            sa, sb = sa * scale[1], sb * scale[1]
        u_loc, j_loc = angle_jacobian_local(s.kind, a, b)
        return LineOfSight(
            sid,
            np.asarray(origin, dtype=np.float64),
            rot @ u_loc,
            rot @ j_loc,
            np.diag([sa * sa, sb * sb]),
            s.r[i],
            s.sr[i] ** 2,
        )

    def _line_at(self, sid: str, s: _Series, t: float) -> tuple[LineOfSight | None, str]:
        if not s.t or t < s.t[0] - 1e-9 or t > s.t[-1] + 1e-9:
            return None, ''
        max_gap = self._max_gap(s)
        i = bisect_left(s.t, t)
        if i < len(s.t) and abs(s.t[i] - t) < 1e-9:
            line = self._sample_line(sid, s, i, max_gap)
            return (line, '') if line is not None else (None, 'no_station_state')
        if i > 0 and abs(s.t[i - 1] - t) < 1e-9:
            line = self._sample_line(sid, s, i - 1, max_gap)
            return (line, '') if line is not None else (None, 'no_station_state')
        t0, t1 = s.t[i - 1], s.t[i]
        if t1 - t0 > max_gap:
            return None, 'interpolation_gap'
        l0, l1 = self._sample_line(sid, s, i - 1, max_gap), self._sample_line(sid, s, i, max_gap)
        pose = self.poses[sid].at(t, max_gap)
        if l0 is None or l1 is None or pose is None:
            return None, 'no_station_state'
        f = (t - t0) / (t1 - t0)
        u = (1.0 - f) * l0.direction + f * l1.direction
        u /= np.linalg.norm(u)
        near = l0 if f < 0.5 else l1
        jac = (np.eye(3) - np.outer(u, u)) @ near.jacobian
        c = (1.0 - f) ** 2 + f * f
        rng = (1.0 - f) * l0.range_m + f * l1.range_m
        var = (
            ((1.0 - f) ** 2 * l0.range_var + f * f * l1.range_var)
            if l0.has_range and l1.has_range
            else math.nan
        )
        return (
            LineOfSight(
                sid,
                np.asarray(pose[0], dtype=np.float64),
                u,
                jac,
                ((1.0 - f) ** 2 * l0.angle_cov + f * f * l1.angle_cov)
                if c > 0
                else near.angle_cov,
                rng,
                var,
            ),
            '',
        )

    def _prune(self, t: float) -> None:
        horizon = 4.0 * self.config.max_gap_factor * max(self.period(), 1e-3)
        for (sid, _), s in self.series.items():
            if len(self.poses.get(sid, ())):
                s.prune(t - horizon)
            else:  # a station that never sent a state: its samples can never be used
                self.counts['samples_without_station_state'] += s.prune(t - horizon, keep=0)
        for p in self.poses.values():
            p.prune(t - horizon)
