"""The triangulation pipeline shared by the live node and the offline tool:
alignment of the station streams, one fix per target and epoch, counted rejections,
and the ``fixes.csv`` table."""

from __future__ import annotations

import csv
import math
from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.data.observations import FixSeries
from orbit_tracking.core.time import format_stamp
from orbit_tracking.core.triangulation.alignment import AlignConfig, Aligner
from orbit_tracking.core.triangulation.intersection import Fix, Gates, triangulate

__all__ = [
    'FIXES_CSV_COLUMNS',
    'TimedFix',
    'TriangulationPipeline',
    'fix_series',
    'read_fixes_csv',
    'write_fixes_csv',
]

FloatArray = NDArray[np.float64]

FIXES_CSV_COLUMNS = (
    'time',
    'x',
    'y',
    'z',
    'cxx',
    'cxy',
    'cxz',
    'cyy',
    'cyz',
    'czz',
    'miss_distance',
    'n_lines',
)


@dataclass(frozen=True)
class TimedFix:
    """A fix of one target at one epoch (``time`` in TimeBase seconds)."""

    time: float
    target_id: int
    fix: Fix


class TriangulationPipeline:
    """Buffers measurements and station poses; returns fixes as epochs become ready.

    Parameters
    ----------
    align : AlignConfig
    gates : Gates

    Attributes
    ----------
    counts : Counter
        ``fixes`` made, and every reason an epoch, a line or a sample was not used:
        the gate reasons of :data:`~orbit_tracking.core.triangulation.intersection.REASONS` (per
        epoch and target), ``no_station_state``, ``interpolation_gap`` (per line),
        ``nan_measurement`` (per sample).
    """

    def __init__(self, align: AlignConfig | None = None, gates: Gates | None = None) -> None:
        self.aligner = Aligner(align)
        self.gates = gates or Gates()
        self.counts: Counter[str] = Counter()
        # input goes straight to the aligner
        self.add_pose = self.aligner.add_pose
        self.add_measurements = self.aligner.add_measurements
        self.stations_without_pose = self.aligner.stations_without_pose

    def process(
        self,
        until: float | None = None,
        wait_for_poses: bool = True,
        delivering: Mapping[str, float] | None = None,
    ) -> list[TimedFix]:
        """Fixes of every epoch that is ready (all epochs with ``until=math.inf``); see
        :meth:`Aligner.process`."""
        out = []
        for ep in self.aligner.process(until, wait_for_poses, delivering):
            for why, n in ep.skipped.items():
                self.counts[why] += n
            res = triangulate(ep.lines, self.gates)
            if res.success and res.fix is not None:
                out.append(TimedFix(ep.time, ep.target_id, res.fix))
                self.counts['fixes'] += 1
            else:
                self.counts[res.reason] += 1
        for key, n in self.aligner.counts.items():
            self.counts[key] += n
        self.aligner.counts.clear()
        return out

    def flush(self) -> list[TimedFix]:
        return self.process(math.inf)


def write_fixes_csv(path: str | Path, fixes: Iterable[TimedFix], ref_ns: int = 0) -> int:
    """Write ``fixes.csv`` (columns :data:`FIXES_CSV_COLUMNS`; ``time`` is the stamp
    ``ref_ns + fix time`` in decimal seconds). Returns the row count."""
    n = 0
    with open(path, 'w', newline='') as fh:
        w = csv.writer(fh)
        w.writerow(FIXES_CSV_COLUMNS)
        for tf in fixes:
            c = tf.fix.covariance
            p = tf.fix.position
            w.writerow(
                [
                    format_stamp(ref_ns, tf.time),
                    *(f'{v:.6f}' for v in p),
                    *(f'{v:.9g}' for v in (c[0, 0], c[0, 1], c[0, 2], c[1, 1], c[1, 2], c[2, 2])),
                    f'{tf.fix.miss_distance:.6f}',
                    tf.fix.n_lines,
                ]
            )
            n += 1
    return n


def read_fixes_csv(path: str | Path) -> dict[str, FloatArray]:
    """Columns of a ``fixes.csv`` as arrays, plus ``position`` (n, 3) and ``covariance``
    (n, 3, 3)."""
    with open(path, newline='') as fh:
        rows = list(csv.DictReader(fh))
    cols = {k: np.array([float(r[k]) for r in rows]) for k in FIXES_CSV_COLUMNS}
    cov = np.empty((len(rows), 3, 3))
    idx = {'x': 0, 'y': 1, 'z': 2}
    for a in 'xyz':
        for b in 'xyz':
            key = f'c{min(a, b)}{max(a, b)}'
            cov[:, idx[a], idx[b]] = cols[key]
    cols['position'] = np.column_stack([cols['x'], cols['y'], cols['z']])
    cols['covariance'] = cov
    return cols


def fix_series(fixes: Iterable[TimedFix]) -> dict[int, FixSeries]:
    """Fixes grouped per target as :class:`~orbit_tracking.core.data.observations.FixSeries`
    (the estimator's rough trajectory when there is no telemetry)."""
    groups: dict[int, list[TimedFix]] = {}
    for f in fixes:
        groups.setdefault(f.target_id, []).append(f)
    out = {}
    for tid, fs in groups.items():
        fs.sort(key=lambda f: f.time)
        out[tid] = FixSeries(
            tid,
            np.array([f.time for f in fs]),
            np.array([f.fix.position for f in fs]),
            np.array([f.fix.covariance for f in fs]),
        )
    return out
