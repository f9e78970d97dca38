"""``orbit-tracking triangulate``: the triangulation node's pipeline fed from a bag in
log-time order, ``fixes.csv`` and a fixes bag, with the fixes' errors against truth."""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from orbit_tracking.core.metrics import NeesSummary, hermite_states, nees, nees_summary
from orbit_tracking.core.triangulation.alignment import AlignConfig
from orbit_tracking.core.triangulation.intersection import Gates
from orbit_tracking.core.triangulation.pipeline import (
    TimedFix,
    TriangulationPipeline,
    write_fixes_csv,
)
from orbit_tracking.ros import qos
from orbit_tracking.ros.bag import BagWriter
from orbit_tracking.ros.conversions import TimeBase, fix_to_msg
from orbit_tracking.tools.bag_inputs import BagContext, bag_inputs, feed_pipeline, truth_states

__all__ = ['TriangulationReport', 'triangulate_bag']


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
        out += self.context.state_lines()
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


def _independent_stride(period: float, intervals: Iterable[float]) -> int:
    """Fixes this many epochs apart share no measurement sample: twice the longest
    sampling interval of the stations' series (``intervals``), in epochs of ``period``.

    An interval that is not known (``inf``: a series with fewer than three samples, or
    ``nan``) says nothing about sharing and is left out; without a known period or any
    known interval every fix counts (1).
    """
    known = [dt for dt in intervals if math.isfinite(dt) and dt > 0.0]
    if not known or not (math.isfinite(period) and period > 0.0):
        return 1
    return max(1, math.ceil(2.0 * max(known) / period - 1e-9))


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
    truth: list[Any] = []
    fixes: list[TimedFix] = []
    for item in bag_inputs(bag, ctx, counts, progress, 'triangulate'):
        if item.kind == 'truth':
            truth.append(item.data)
        else:
            fixes.extend(feed_pipeline(pipe, item))
    fixes.extend(pipe.flush())
    counts.update(pipe.counts)
    ctx.truth.update(truth_states(truth))
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
    stride = _independent_stride(
        pipe.aligner.period(), (s.median_dt() for s in pipe.aligner.series.values())
    )
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
        'stations_without_state': dict(ctx.stations_without_state),
        'evaluation': report.evaluation,
        'nees': {
            tid: {'mean': s.mean, 'n': s.n, 'lo': s.lo, 'hi': s.hi, 'consistent': s.consistent}
            for tid, s in report.nees.items()
        },
    }
    (out / 'summary.yaml').write_text(yaml.safe_dump(summary, sort_keys=False))
    files.append(out / 'summary.yaml')
    return report
