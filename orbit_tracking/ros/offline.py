"""Offline processing of recorded bags (no running nodes): the same pipelines as the
nodes, fed from a rosbag2 in log-time order."""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from tqdm import tqdm

from orbit_tracking.core.alignment import AlignConfig
from orbit_tracking.core.errors import MeasurementError
from orbit_tracking.core.fixes import TimedFix, TriangulationPipeline, write_fixes_csv
from orbit_tracking.core.metrics import NeesSummary, hermite_states, nees, nees_summary
from orbit_tracking.core.simulation import TargetStates
from orbit_tracking.core.triangulation import Gates
from orbit_tracking.ros import qos
from orbit_tracking.ros.bag import BagWriter, bag_custom_data, read_bag
from orbit_tracking.ros.conversions import (
    TimeBase,
    cloud_to_measurements,
    fix_to_msg,
    odometry_to_station_state,
    odometry_to_target_state,
    stamp_ns,
)

__all__ = ['BagContext', 'TriangulationReport', 'triangulate_bag']


@dataclass
class BagContext:
    """What a bag says about itself: time base, world frame, gaps, and the truth if any."""

    timebase: TimeBase | None = None
    world_frame: str = ''
    scenario: str = ''
    gaps: list[tuple[float, float]] = field(default_factory=list)
    truth: dict[int, TargetStates] = field(default_factory=dict)

    @classmethod
    def from_custom_data(cls, path: str | Path) -> BagContext:
        data = bag_custom_data(path)
        ctx = cls()
        if 'orbit_tracking.epoch' in data:
            ctx.timebase = TimeBase.from_seconds(float(data['orbit_tracking.epoch']))
        ctx.world_frame = data.get('orbit_tracking.world_frame', '')
        ctx.scenario = data.get('orbit_tracking.scenario', '')
        ctx.gaps = [tuple(g) for g in yaml.safe_load(data.get('orbit_tracking.gaps', '[]')) or []]
        return ctx

    def tb(self, ns: int) -> TimeBase:
        if self.timebase is None:
            self.timebase = TimeBase.whole_second_of(ns)
        return self.timebase

    def in_gap(self, t: np.ndarray) -> np.ndarray:
        out = np.zeros(np.shape(t), dtype=bool)
        for a, b in self.gaps:
            out |= (t >= a) & (t <= b)
        return out


@dataclass
class TriangulationReport:
    """Outcome of :func:`triangulate_bag`."""

    fixes: list[TimedFix]
    counts: Counter[str]
    context: BagContext
    files: list[Path]
    evaluation: dict[int, dict[str, float]] = field(default_factory=dict)
    nees: dict[int, NeesSummary] = field(default_factory=dict)

    def lines(self) -> list[str]:
        """Human-readable summary."""
        c = self.counts
        targets = sorted({f.target_id for f in self.fixes})
        out = [
            f'{c.get("fixes", 0)} fixes for target(s) {targets}; '
            + ', '.join(f'{k} {v}' for k, v in sorted(c.items()) if k != 'fixes')
        ]
        where = ' outside gaps' if self.context.gaps else ''
        for tid, ev in self.evaluation.items():
            out.append(
                f'target {tid} vs truth{where} ({int(ev["n"])} fixes): '
                f'RMS 3-D error {ev["rms"]:.3f} m (x {ev["rms_x"]:.3f}, y {ev["rms_y"]:.3f}, '
                f'z {ev["rms_z"]:.3f}), max {ev["max"]:.3f} m, '
                f'median 1-sigma (sqrt trace P) {ev["median_sigma"]:.3f} m'
            )
            out.append(
                f'target {tid}: {self.nees[tid]} '
                f'(one fix in {int(ev["stride"])}, so that no two share a sample)'
            )
        return out


def _independent_stride(period: float, max_dt: float) -> int:
    """Fixes this many epochs apart share no measurement sample."""
    return max(1, math.ceil(2.0 * max_dt / period - 1e-9))


def triangulate_bag(
    bag: str | Path,
    out: str | Path,
    align: AlignConfig | None = None,
    gates: Gates | None = None,
    target_id: int | None = None,
    progress: bool = True,
) -> TriangulationReport:
    """Triangulate every epoch of a bag; write ``fixes.csv`` (and a bag with
    ``triangulation/fixes``) to ``out``; evaluate against ``truth/state`` when present.

    ``fixes.csv`` holds the fixes of ``target_id`` (default: every target if there is one,
    else the lowest id); with several targets each also gets ``fixes_target_<id>.csv``.
    """
    ctx = BagContext.from_custom_data(bag)
    pipe = TriangulationPipeline(align, gates)
    counts: Counter[str] = Counter()
    truth_rows: dict[int, list[tuple[float, np.ndarray, np.ndarray]]] = {}
    fixes: list[TimedFix] = []
    for m in tqdm(read_bag(bag), unit='msg', disable=not progress, desc='triangulate'):
        topic = m.topic.lstrip('/')
        if topic.endswith('/measurements') and topic.startswith('stations/'):
            tb = ctx.tb(stamp_ns(m.msg.header.stamp))
            try:
                b = cloud_to_measurements(m.msg, tb)
            except MeasurementError:
                counts['invalid_messages'] += 1
                continue
            counts['rejected_points'] += b.rejected
            pipe.add_measurements(b.station_id, b.fields, b.time, b.target_id, b.values, b.sigmas)
            fixes.extend(pipe.process())
        elif topic.endswith('/state') and topic.startswith('stations/'):
            tb = ctx.tb(stamp_ns(m.msg.header.stamp))
            try:
                s = odometry_to_station_state(m.msg, tb)
            except ValueError:
                counts['invalid_state'] += 1
                continue
            ctx.world_frame = ctx.world_frame or m.msg.header.frame_id
            pipe.add_pose(s.station_id, s.time, s.position, s.velocity, s.rotation, s.moving)
        elif topic == 'truth/state':
            st = odometry_to_target_state(m.msg, ctx.tb(stamp_ns(m.msg.header.stamp)))
            truth_rows.setdefault(st.target_id, []).append((st.time, st.position, st.velocity))
    fixes.extend(pipe.flush())
    counts.update(pipe.counts)
    counts['rejected_points'] = counts.get('rejected_points', 0)
    if not counts['rejected_points']:
        del counts['rejected_points']
    for tid, rows in truth_rows.items():
        rows.sort(key=lambda r: r[0])
        t = np.array([r[0] for r in rows])
        z = np.zeros((t.size, 3))
        ctx.truth[tid] = TargetStates(
            tid, t, np.array([r[1] for r in rows]), np.array([r[2] for r in rows]), z, z
        )
    tb = ctx.timebase or TimeBase(0)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    targets = sorted({f.target_id for f in fixes})
    main_target = target_id if target_id is not None else (targets[0] if targets else 0)
    files = []
    selected = [
        f for f in fixes if f.target_id == main_target or (target_id is None and len(targets) == 1)
    ]
    write_fixes_csv(out / 'fixes.csv', selected, tb.ref_ns)
    files.append(out / 'fixes.csv')
    if len(targets) > 1:
        for tid in targets:
            write_fixes_csv(
                out / f'fixes_target_{tid}.csv',
                [f for f in fixes if f.target_id == tid],
                tb.ref_ns,
            )
            files.append(out / f'fixes_target_{tid}.csv')
    bag_out = out / 'bag'
    if bag_out.exists():
        import shutil

        shutil.rmtree(bag_out)
    with BagWriter(bag_out) as w:
        for f in fixes:
            msg = fix_to_msg(
                ctx.world_frame or 'earth', f.time, f.fix.position, f.fix.covariance, tb
            )
            w.write(
                'triangulation/fixes'
                if f.target_id == main_target
                else f'triangulation/target_{f.target_id}/fixes',
                msg,
                tb.to_ns(f.time),
                qos.STATE_STREAM,
            )
    files.append(bag_out)
    report = TriangulationReport(fixes, counts, ctx, files)
    period = pipe.aligner.period()
    max_dt = max((s.median_dt() for s in pipe.aligner.series.values()), default=period)
    stride = _independent_stride(period, max_dt) if math.isfinite(period) else 1
    for tid in targets:
        if tid not in ctx.truth:
            continue
        tf = [f for f in fixes if f.target_id == tid]
        t = np.array([f.time for f in tf])
        tr = ctx.truth[tid]
        x_true = hermite_states(tr.time, tr.position, tr.velocity, t)
        keep = ~ctx.in_gap(t) & np.all(np.isfinite(x_true), axis=1)
        pos = np.array([f.fix.position for f in tf])
        cov = np.array([f.fix.covariance for f in tf])
        err = (pos - x_true)[keep]
        if err.size == 0:
            continue
        n3 = nees(err, cov[keep])
        norms = np.linalg.norm(err, axis=1)
        report.evaluation[tid] = {
            'n': float(err.shape[0]),
            'rms': float(np.sqrt(np.mean(norms**2))),
            'rms_x': float(np.sqrt(np.mean(err[:, 0] ** 2))),
            'rms_y': float(np.sqrt(np.mean(err[:, 1] ** 2))),
            'rms_z': float(np.sqrt(np.mean(err[:, 2] ** 2))),
            'max': float(norms.max()),
            'median_sigma': float(np.median(np.sqrt(np.trace(cov[keep], axis1=1, axis2=2)))),
            'stride': float(stride),
        }
        report.nees[tid] = nees_summary(n3[::stride])
    summary = {
        'bag': str(bag),
        'scenario': ctx.scenario,
        'counts': dict(counts),
        'evaluation': report.evaluation,
        'nees': {
            tid: {'mean': s.mean, 'n': s.n, 'lo': s.lo, 'hi': s.hi, 'consistent': s.consistent}
            for tid, s in report.nees.items()
        },
    }
    (out / 'summary.yaml').write_text(yaml.safe_dump(summary, sort_keys=False))
    files.append(out / 'summary.yaml')
    return report
