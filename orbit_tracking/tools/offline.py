"""Offline processing of recorded bags (no running nodes): the same pipelines as the
nodes, fed from a rosbag2 in log-time order: :func:`triangulate_bag` (the triangulation
node) and :func:`estimate_bag` (the estimator node's windows, stitched)."""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from tqdm import tqdm

from orbit_tracking.core.data.buffer import ObservationBuffer
from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.data.tables import TargetStates
from orbit_tracking.core.errors import ConfigError, MeasurementError, OrbitTrackingError
from orbit_tracking.core.estimation.bias_files import (
    BiasDeclaration,
    load_bias_declaration,
    station_fields,
    write_biases_by_window_csv,
    write_biases_csv,
)
from orbit_tracking.core.estimation.estimator import (
    BiasEstimate,
    Estimate,
    EstimationError,
    EstimatorConfig,
)
from orbit_tracking.core.estimation.knots import KnotConfig
from orbit_tracking.core.estimation.windows import (
    Span,
    WindowConfig,
    output_times,
    solve_windows,
    stitch,
    write_trajectory_csv,
)
from orbit_tracking.core.metrics import NeesSummary, hermite_states, nees, nees_summary
from orbit_tracking.core.models.systematic import ESTIMABLE_BIASES
from orbit_tracking.core.sim.scenario import load_scenario, truth_biases
from orbit_tracking.core.time import parse_stamp
from orbit_tracking.core.triangulation.alignment import AlignConfig
from orbit_tracking.core.triangulation.intersection import Gates
from orbit_tracking.core.triangulation.pipeline import (
    TimedFix,
    TriangulationPipeline,
    fix_series,
    write_fixes_csv,
)
from orbit_tracking.ros import qos
from orbit_tracking.ros.bag import BagWriter, bag_custom_data, read_bag
from orbit_tracking.ros.conversions import (
    TimeBase,
    biases_to_diagnostics,
    cloud_to_measurements,
    cloud_to_window_states,
    diagnostics_to_biases,
    fix_to_msg,
    msg_to_fix,
    odometry_to_station_state,
    odometry_to_target_state,
    stamp_ns,
    target_state_to_odometry,
    window_states_to_cloud,
)

__all__ = [
    'BagContext',
    'EstimationReport',
    'RecordingReport',
    'TriangulationReport',
    'bag_message_counts',
    'estimate_bag',
    'estimator_configs',
    'read_for_estimation',
    'triangulate_bag',
    'write_recorded_outputs',
]


@dataclass
class BagContext:
    """What a bag says about itself: time base, world frame, gaps, and the truth if any
    (target states; the simulated station biases per (station, bias name), None when the
    bag does not say)."""

    timebase: TimeBase | None = None
    world_frame: str = ''
    scenario: str = ''
    gaps: list[tuple[float, float]] = field(default_factory=list)
    truth: dict[int, TargetStates] = field(default_factory=dict)
    truth_biases: dict[tuple[str, str], float] | None = None
    truth_biases_source: str = ''

    @classmethod
    def from_custom_data(cls, path: str | Path) -> BagContext:
        data = bag_custom_data(path)
        ctx = cls()
        if 'orbit_tracking.epoch' in data:
            ctx.timebase = TimeBase.from_seconds(float(data['orbit_tracking.epoch']))
        ctx.world_frame = data.get('orbit_tracking.world_frame', '')
        ctx.scenario = data.get('orbit_tracking.scenario', '')
        ctx.gaps = [tuple(g) for g in yaml.safe_load(data.get('orbit_tracking.gaps', '[]')) or []]
        if 'orbit_tracking.biases' in data:
            biases = yaml.safe_load(data['orbit_tracking.biases']) or {}
            ctx.truth_biases = {
                (str(sid), str(name)): float(v)
                for sid, values in biases.items()
                for name, v in values.items()
            }
            ctx.truth_biases_source = 'bag metadata (orbit_tracking.biases)'
        return ctx

    def scenario_truth_biases(self) -> None:
        """For a simulated bag written before its metadata kept the biases (it has truth
        and names a scenario of the package): take them from that scenario file."""
        if self.truth_biases is not None or not self.truth or not self.scenario:
            return
        try:
            sc = load_scenario(self.scenario)
        except (FileNotFoundError, ConfigError):
            return
        self.truth_biases = truth_biases(sc)
        self.truth_biases_source = f'scenario file {sc.source}'

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


_TARGET_TOPICS = frozenset({'telemetry/state', 'triangulation/fixes', 'truth/state'})


@dataclass(frozen=True)
class _Input:
    """One decoded input message of a bag."""

    kind: str  # measurements | station_state | telemetry | fix | truth
    data: Any


def _bag_inputs(
    bag: str | Path, ctx: BagContext, counts: Counter[str], progress: bool, desc: str
) -> Iterator[_Input]:
    """Decode the input topics of a bag in log order, as the nodes receive them.

    Undecodable messages and messages whose station id differs from their topic's are
    counted in ``counts`` (``invalid_messages``, ``invalid_state``, ``station_mismatch``,
    ``invalid_fix``) and skipped; ``rejected_points`` counts bad points inside good
    messages. The first station state sets ``ctx.world_frame``.
    """
    for m in tqdm(read_bag(bag), unit='msg', disable=not progress, desc=desc):
        topic = m.topic.lstrip('/')
        parts = topic.split('/')
        station = len(parts) == 3 and parts[0] == 'stations'
        if not station and topic not in _TARGET_TOPICS:
            continue  # e.g. /clock, /diagnostics, outputs: not inputs, no time base from them
        tb = ctx.tb(stamp_ns(m.msg.header.stamp))
        if len(parts) == 3 and parts[0] == 'stations' and parts[2] == 'measurements':
            try:
                b = cloud_to_measurements(m.msg, tb)
            except MeasurementError:
                counts['invalid_messages'] += 1
                continue
            if b.rejected:
                counts['rejected_points'] += b.rejected
            if b.station_id != parts[1]:
                counts['station_mismatch'] += 1
                continue
            yield _Input('measurements', b)
        elif len(parts) == 3 and parts[0] == 'stations' and parts[2] == 'state':
            try:
                st = odometry_to_station_state(m.msg, tb)
            except ValueError:
                counts['invalid_state'] += 1
                continue
            if st.station_id != parts[1]:
                counts['station_mismatch'] += 1
                continue
            ctx.world_frame = ctx.world_frame or m.msg.header.frame_id
            yield _Input('station_state', st)
        elif topic == 'telemetry/state':
            yield _Input('telemetry', odometry_to_target_state(m.msg, tb))
        elif topic == 'triangulation/fixes':
            try:
                yield _Input('fix', msg_to_fix(m.msg, tb))
            except ValueError:
                counts['invalid_fix'] += 1
        elif topic == 'truth/state':
            yield _Input('truth', odometry_to_target_state(m.msg, tb))


def _truth_states(samples: list[Any]) -> dict[int, TargetStates]:
    """Truth samples (TargetStateSample) gathered per target, in time order."""
    rows: dict[int, list[Any]] = {}
    for s in samples:
        rows.setdefault(s.target_id, []).append(s)
    out = {}
    for tid, ss in rows.items():
        ss.sort(key=lambda s: s.time)
        t = np.array([s.time for s in ss])
        z = np.zeros((t.size, 3))
        out[tid] = TargetStates(
            tid, t, np.array([s.position for s in ss]), np.array([s.velocity for s in ss]), z, z
        )
    return out


def _feed_pipeline(pipe: TriangulationPipeline, item: _Input) -> list[TimedFix]:
    """Give one decoded input to a triangulation pipeline; the fixes it makes ready."""
    if item.kind == 'measurements':
        b = item.data
        pipe.add_measurements(b.station_id, b.fields, b.time, b.target_id, b.values, b.sigmas)
        return pipe.process()
    if item.kind == 'station_state':
        s = item.data
        pipe.add_pose(s.station_id, s.time, s.position, s.velocity, s.rotation, s.moving)
    return []


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
    for item in _bag_inputs(bag, ctx, counts, progress, 'triangulate'):
        if item.kind == 'truth':
            truth.append(item.data)
        else:
            fixes.extend(_feed_pipeline(pipe, item))
    fixes.extend(pipe.flush())
    counts.update(pipe.counts)
    ctx.truth.update(_truth_states(truth))
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


# ---------------------------------------------------------------------------------------
# sliding-window estimation


@dataclass
class EstimationReport:
    """Outcome of :func:`estimate_bag`.

    ``times``, ``state`` (m, 6) and ``covariance`` (m, 6, 6) are the stitched trajectory
    of ``target_id`` (the lowest target id solved). ``biases`` are the final station biases
    (each from the last window with rows of its station), ``bias_notes`` what the
    declaration could not apply, ``bias_evaluation`` their errors against the bag's truth.
    """

    estimates: list[Estimate]
    failures: list[tuple[Span, str]]
    target_id: int
    times: np.ndarray
    state: np.ndarray
    covariance: np.ndarray
    counts: Counter[str]
    context: BagContext
    rough: str
    files: list[Path]
    evaluation: dict[int, dict[str, dict[str, float]]] = field(default_factory=dict)
    biases: tuple[BiasEstimate, ...] = ()
    bias_notes: list[str] = field(default_factory=list)
    bias_evaluation: dict[tuple[str, str], dict[str, float]] = field(default_factory=dict)

    def lines(self) -> list[str]:
        """Human-readable summary."""
        n_ok = sum(e.success for e in self.estimates)
        n_all = len(self.estimates) + len(self.failures)
        its = sum(e.iterations for e in self.estimates)
        used = sum(
            v for e in self.estimates for k, v in e.used.items() if not k.startswith('telemetry')
        )
        rej = sum(sum(e.rejected.values()) for e in self.estimates)
        chi2 = [e.chi2_dof for e in self.estimates]
        out = [
            f'{n_all} windows: {n_ok} converged, {len(self.estimates) - n_ok} solved with a '
            f'warning, {len(self.failures)} failed; {its} Gauss-Newton iterations; '
            f'chi2/dof {min(chi2, default=math.nan):.3f}-{max(chi2, default=math.nan):.3f}; '
            f'{used} measured values used, {rej} rejected; rough trajectory: {self.rough}',
            f'{self.times.size} output states of target {self.target_id}'
            + (
                f' from {self.times[0]:.3f} s to {self.times[-1]:.3f} s' if self.times.size else ''
            ),
        ]
        if self.counts:
            out.append('input: ' + ', '.join(f'{k} {v}' for k, v in sorted(self.counts.items())))
        for span, why in self.failures:
            out.append(f'window [{span[0]:.3f}, {span[1]:.3f}] s failed: {why}')
        out += _evaluation_lines(self.evaluation)
        out += self.bias_notes
        out += _bias_lines(self.biases, self.bias_evaluation)
        return out


def _evaluation_lines(evaluation: dict[int, dict[str, dict[str, float]]]) -> list[str]:
    """One line per target and part (outside / inside gaps) of :func:`_evaluate`'s figures."""
    out = []
    for tid, parts in evaluation.items():
        for where, ev in parts.items():
            out.append(
                f'target {tid} vs truth {where.replace("_", " ")} ({int(ev["n"])} states): '
                f'position RMS {ev["rms_position_m"]:.3f} m (mean '
                f'{ev["mean_position_m"]:.3f} m), velocity RMS '
                f'{ev["rms_velocity_m_s"]:.4f} m/s (mean {ev["mean_velocity_m_s"]:.4f} '
                f'm/s), mean NEES {ev["mean_nees_position"]:.2f} (position, 3 dof), '
                f'{ev["mean_nees_state"]:.2f} (state, 6 dof)'
            )
    return out


def _bias_lines(
    biases: Sequence[BiasEstimate], evaluation: dict[tuple[str, str], dict[str, float]]
) -> list[str]:
    """One line per station: its final biases, with truth and z when known."""
    per_station: dict[str, list[str]] = {}
    for b in biases:
        text = f'{b.name} {b.value:.6g} +- {b.sigma:.3g}'
        ev = evaluation.get((b.station, b.name))
        if ev is not None:
            text += f' (truth {ev["truth"]:.6g}, z {ev["z"]:+.2f})'
        if b.status != 'estimated':
            text += f' [{b.status.split(":")[0]}]'
        per_station.setdefault(b.station, []).append(text)
    return [f'biases {sid}: ' + ', '.join(texts) for sid, texts in per_station.items()]


def read_for_estimation(
    bag: str | Path, ctx: BagContext, progress: bool
) -> tuple[ObservationBuffer, Counter[str]]:
    """Measurements, station states, telemetry and fixes of a bag into a buffer (what the
    node receives); the truth goes to ``ctx.truth``."""
    buf = ObservationBuffer()
    counts: Counter[str] = Counter()
    truth: list[Any] = []
    for item in _bag_inputs(bag, ctx, counts, progress, 'read bag'):
        d = item.data
        if item.kind == 'measurements':
            buf.add_measurements(d.station_id, d.fields, d.time, d.target_id, d.values, d.sigmas)
        elif item.kind == 'station_state':
            buf.add_pose(d.station_id, d.time, d.position, d.velocity, d.rotation, d.moving)
        elif item.kind == 'telemetry':
            try:
                buf.add_telemetry(
                    d.target_id,
                    d.time,
                    d.position,
                    d.velocity,
                    np.sqrt(np.clip(np.diag(d.position_cov), 0.0, None)),
                    np.sqrt(np.clip(np.diag(d.velocity_cov), 0.0, None)),
                )
            except ValueError:
                counts['invalid_telemetry'] += 1
        elif item.kind == 'fix':
            try:
                buf.add_fix(0, *d)
            except ValueError:
                counts['invalid_fix'] += 1
        elif item.kind == 'truth':
            truth.append(d)
    ctx.truth.update(_truth_states(truth))
    return buf, +counts


def _triangulated_fixes(
    bag: str | Path, ctx: BagContext, progress: bool, gates: Gates | None = None
) -> list[TimedFix]:
    """Fixes of the bag's lines of sight (the rough trajectory when the bag has neither
    telemetry nor fixes)."""
    pipe = TriangulationPipeline(gates=gates)
    ignored: Counter[str] = Counter()  # already counted by the first pass
    fixes: list[TimedFix] = []
    for item in _bag_inputs(bag, ctx, ignored, progress, 'triangulate'):
        fixes.extend(_feed_pipeline(pipe, item))  # epochs fixed as the data pass them
    return fixes + pipe.flush()


def _truth_velocity(tr: TargetStates, t: np.ndarray) -> np.ndarray:
    from scipy.interpolate import CubicSpline

    v = CubicSpline(tr.time, tr.velocity, axis=0, extrapolate=False)(t)
    return np.asarray(v, dtype=np.float64)


def _evaluate(
    ctx: BagContext, tid: int, t: np.ndarray, x: np.ndarray, cov: np.ndarray
) -> dict[str, dict[str, float]]:
    """Errors of a stitched trajectory against the bag's truth, outside and inside gaps."""
    tr = ctx.truth[tid]
    ep = x[:, :3] - hermite_states(tr.time, tr.position, tr.velocity, t)
    ev = x[:, 3:] - _truth_velocity(tr, t)
    ok = np.all(np.isfinite(ep), axis=1) & np.all(np.isfinite(ev), axis=1)
    gap = ctx.in_gap(t)
    out: dict[str, dict[str, float]] = {}
    for where, sel in (('outside_gaps', ok & ~gap), ('inside_gaps', ok & gap)):
        if not np.any(sel):
            continue
        npos = np.linalg.norm(ep[sel], axis=1)
        nvel = np.linalg.norm(ev[sel], axis=1)
        e6 = np.hstack([ep[sel], ev[sel]])
        out[where] = {
            'n': float(sel.sum()),
            'rms_position_m': float(np.sqrt(np.mean(npos**2))),
            'mean_position_m': float(np.mean(npos)),
            'max_position_m': float(np.max(npos)),
            'rms_velocity_m_s': float(np.sqrt(np.mean(nvel**2))),
            'mean_velocity_m_s': float(np.mean(nvel)),
            'mean_nees_position': float(np.mean(nees(ep[sel], cov[sel][:, :3, :3]))),
            'mean_nees_state': float(np.mean(nees(e6, cov[sel]))),
        }
    return out


def _window_summary(e: Estimate) -> dict[str, object]:
    return {
        'start': float(e.t0),
        'end': float(e.t1),
        'success': bool(e.success),
        'message': e.message,
        'iterations': int(e.iterations),
        'halvings': int(e.halvings),
        'chi2_dof': float(e.chi2_dof),
        'parameters': int(e.n_parameters),
        'condition': float(e.condition),
        'knot_time_s': float(e.knot_time),
        'solve_time_s': float(e.solve_time),
        'used': {str(k): int(v) for k, v in sorted(e.used.items())},
        'rejected': {f'{s}/{why}': int(n) for (s, why), n in sorted(e.rejected.items())},
        'segments': {
            int(tid): [[float(a), float(b)] for a, b in sol.segments]
            for tid, sol in sorted(e.targets.items())
        },
    }


_KNOT_PARAMETERS = (
    'degree',
    'base_spacing',
    'gap_spacing',
    'delta_position',
    'delta_velocity',
    'solver',
    'sparse',
)


def estimator_configs(
    parameters: Mapping[str, Any],
) -> tuple[EstimatorConfig, WindowConfig, str]:
    """The settings of :func:`estimate_bag` that match an estimator node started with
    ``parameters`` (its parameter names; missing ones keep the defaults, which are the
    node's): ``(estimator config, window config, bias_file)``."""
    p = parameters
    knots = KnotConfig(**{k: p[k] for k in _KNOT_PARAMETERS if k in p})
    est = EstimatorConfig(
        knots=knots,
        **{k: p[k] for k in ('knot_method', 'use_telemetry', 'gate_sigma') if k in p},
    )
    names = {'window_length': 'length', 'window_overlap': 'overlap'}
    win = WindowConfig(
        **{
            names.get(k, k): float(p[k])
            for k in ('window_length', 'window_overlap', 'latency', 'output_step')
            if k in p
        }
    )
    return est, win, str(p.get('bias_file') or '')


def estimate_bag(
    bag: str | Path,
    out: str | Path,
    est_cfg: EstimatorConfig | None = None,
    win_cfg: WindowConfig | None = None,
    progress: bool = True,
    biases: BiasDeclaration | str | None = None,
) -> EstimationReport:
    """Estimate the trajectory of a bag in the estimator node's sliding windows.

    Reads the measurements, station states, ``telemetry/state``, ``triangulation/fixes``
    and ``truth/state`` of the bag; when it holds neither telemetry nor fixes, its lines of
    sight are triangulated first (the rough trajectory). The windows are those of the node
    (:func:`~orbit_tracking.core.estimation.windows.solve_windows`).

    ``biases`` (a declaration, or a ``bias_file`` value: ``''``, ``'auto'`` or a YAML
    path) is resolved against the stations of the bag and their fields and replaces
    ``est_cfg.biases`` (an empty declaration keeps them). With biases declared, the
    triangulation that makes the rough trajectory runs without its miss-distance gate
    (``Gates(miss_probability=1.0)``): the lines of biased stations do not meet, and gating
    them would throw away exactly the data the biases are estimated from.

    Writes to ``out``:

    * ``trajectory.csv``: the stitched trajectory of the lowest target id (contract
      columns); with several targets also ``trajectory_target_<id>.csv``;
    * ``biases.csv`` (contract columns ``station,field,bias,sigma``; header only without
      biases): each declared bias from the last window with rows of its station;
      ``biases_by_window.csv``: every window's biases with prior and status;
    * ``bag/``: ``trajectory/states`` (Odometry per output time; other targets on
      ``trajectory/target_<id>/states``), ``estimator/window_states`` and, with biases,
      ``trajectory/biases`` (one DiagnosticArray per window, transient local);
    * ``summary.yaml``: windows, iterations, chi2, used/rejected rows, and with truth the
      errors outside and inside the bag's gaps and the mean NEES; with biases the final
      biases (and their errors against the bag's simulated biases, if known).

    Raises
    ------
    EstimationError
        No window could be solved.
    """
    est_cfg = est_cfg or EstimatorConfig()
    win_cfg = win_cfg or WindowConfig()
    decl = load_bias_declaration(biases) if isinstance(biases, str) else biases
    ctx = BagContext.from_custom_data(bag)
    buf, counts = read_for_estimation(bag, ctx, progress)
    obs = buf.observations()
    if buf.withheld:
        counts['no_station_state'] += sum(buf.withheld.values())
    counts.update(buf.counts)
    bias_notes: list[str] = []
    if decl is not None and not decl.empty:
        fields = station_fields(obs)
        declared, bias_notes = decl.resolve(fields)
        bias_notes += [
            f'bias declaration names station {sid}, which has no measurements in the bag'
            for sid in decl.stations
            if sid not in fields
        ]
        est_cfg = replace(est_cfg, biases=declared)
    if obs.telemetry:
        rough = 'telemetry'
    elif obs.fixes:
        rough = 'triangulation/fixes of the bag'
    else:
        # biased lines of sight miss each other: keep them for the biases to explain
        gates = Gates(miss_probability=1.0) if est_cfg.biases else None
        fixes = _triangulated_fixes(bag, ctx, progress, gates)
        obs = Observations(obs.stations, {}, fix_series(fixes))
        rough = f'{len(fixes)} fixes triangulated from the bag' + (
            ' (miss-distance gate off: biases declared)' if gates else ''
        )
    tb = ctx.timebase or TimeBase(0)
    failures: list[tuple[Span, str]] = []
    bar = tqdm(unit='window', disable=not progress, desc='estimate')

    def on_window(i: int, n: int, span: Span, res: Estimate | OrbitTrackingError) -> None:
        bar.total = n
        bar.update(1)
        if not isinstance(res, Estimate):
            failures.append((span, f'{type(res).__name__}: {res}'))

    try:
        estimates = solve_windows(obs, est_cfg, win_cfg, on_window)
    finally:
        bar.close()
    if not estimates:
        why = '; '.join(f'[{a:.3f}, {b:.3f}]: {w}' for (a, b), w in failures) or 'no data'
        raise EstimationError(f'{bag}: no window could be solved ({why})')
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_lo = min(e.t0 for e in estimates)
    t_hi = max(e.t1 for e in estimates)
    grid = output_times(t_lo, t_hi, win_cfg.output_step)
    targets = sorted({tid for e in estimates for tid in e.targets})
    main = targets[0]
    tracks = {tid: stitch(estimates, grid, tid) for tid in targets}
    files = [out / 'trajectory.csv']
    write_trajectory_csv(files[0], *tracks[main], tb.ref_ns)
    if len(targets) > 1:
        for tid in targets:
            files.append(out / f'trajectory_target_{tid}.csv')
            write_trajectory_csv(files[-1], *tracks[tid], tb.ref_ns)
    final = _final_biases([(e.t0, e.t1, e.biases) for e in estimates])
    files.append(out / 'biases.csv')
    write_biases_csv(files[-1], [b for b, _ in final])
    files.append(out / 'biases_by_window.csv')
    write_biases_by_window_csv(files[-1], [(e.t0, e.t1, e.biases) for e in estimates], tb.ref_ns)
    frame = ctx.world_frame or 'earth'
    msgs: list[tuple[int, str, object]] = []
    for tid, (tt, x, cov) in tracks.items():
        topic = 'trajectory/states' if tid == main else f'trajectory/target_{tid}/states'
        for i in range(tt.size):
            msg = target_state_to_odometry(
                tid, frame, tt[i], x[i, :3], x[i, 3:], cov[i, :3, :3], cov[i, 3:, 3:], tb
            )
            if tid == main:
                msg.child_frame_id = 'target'
            msgs.append((tb.to_ns(tt[i]), topic, msg))
    for e in estimates:
        ts, ids, xs, cs = [], [], [], []
        for tid, sol in sorted(e.targets.items()):
            t = output_times(sol.t0, sol.t1, win_cfg.output_step)
            x, c = sol.states(t)
            ts.append(t)
            ids.append(np.full(t.size, tid, dtype=np.uint32))
            xs.append(x)
            cs.append(c)
        msg = window_states_to_cloud(
            frame,
            e.t0,
            np.concatenate(ts),
            np.concatenate(ids),
            np.vstack(xs),
            np.concatenate(cs),
            tb,
            t1=e.t1,
        )
        msgs.append((tb.to_ns(e.t1), 'estimator/window_states', msg))
        if e.biases:
            msgs.append(
                (
                    tb.to_ns(e.t1),
                    'trajectory/biases',
                    biases_to_diagnostics(e.biases, e.t0, e.t1, tb),
                )
            )
    bag_out = out / 'bag'
    if bag_out.exists():
        import shutil

        shutil.rmtree(bag_out)
    msgs.sort(key=lambda r: r[0])
    with BagWriter(bag_out) as w:
        for t_ns, topic, msg in msgs:
            w.write(
                topic, msg, t_ns, qos.LATCHED if topic == 'trajectory/biases' else qos.STATE_STREAM
            )
    files.append(bag_out)
    t_main, x_main, c_main = tracks[main]
    report = EstimationReport(
        estimates,
        failures,
        main,
        t_main,
        x_main,
        c_main,
        counts,
        ctx,
        rough,
        files,
        biases=tuple(b for b, _ in final),
        bias_notes=bias_notes,
    )
    for tid, (tt, x, cov) in tracks.items():
        if tid in ctx.truth and tt.size:
            ev = _evaluate(ctx, tid, tt, x, cov)
            if ev:
                report.evaluation[tid] = ev
    summary = {
        'bag': str(bag),
        'scenario': ctx.scenario,
        'rough_trajectory': rough,
        'config': {
            'window_length': win_cfg.length,
            'window_overlap': win_cfg.overlap,
            'output_step': win_cfg.output_step,
            'knot_method': est_cfg.knot_method,
            'use_telemetry': est_cfg.use_telemetry,
            'biases': '' if decl is None or decl.empty else decl.source or 'declared',
            'bias_parameters': len(est_cfg.biases),
        },
        'counts': {k: int(v) for k, v in sorted(counts.items())},
        'totals': {
            'windows': len(estimates) + len(failures),
            'converged': int(sum(e.success for e in estimates)),
            'failed': len(failures),
            'iterations': int(sum(e.iterations for e in estimates)),
            'output_states': int(t_main.size),
        },
        'windows': sorted(
            [_window_summary(e) for e in estimates]
            + [
                {'start': float(a), 'end': float(b), 'success': False, 'error': why}
                for (a, b), why in failures
            ],
            key=lambda w: float(w['start']),  # type: ignore[arg-type]
        ),
        'evaluation': report.evaluation,
    }
    if est_cfg.biases:
        summary['biases'] = _bias_summary(ctx, final, bias_notes, report.bias_evaluation)
    (out / 'summary.yaml').write_text(yaml.safe_dump(summary, sort_keys=False))
    files.append(out / 'summary.yaml')
    return report


# ---------------------------------------------------------------------------------------
# the outputs of a live run, recorded


def bag_message_counts(bag: str | Path) -> dict[str, int]:
    """Messages per topic (leading ``/`` dropped), from the bag's ``metadata.yaml``."""
    meta = yaml.safe_load((Path(bag) / 'metadata.yaml').read_text())
    info = meta.get('rosbag2_bagfile_information', {})
    out: dict[str, int] = {}
    for t in info.get('topics_with_message_count') or []:
        name = str(t['topic_metadata']['name']).lstrip('/')
        out[name] = out.get(name, 0) + int(t['message_count'])
    return dict(sorted(out.items()))


@dataclass
class RecordingReport:
    """Outcome of :func:`write_recorded_outputs`.

    ``times``, ``state`` (m, 6) and ``covariance`` (m, 6, 6) are the states the results
    node published for ``target_id`` (the lowest id); the covariance holds the position and
    velocity blocks only (``nav_msgs/Odometry`` has no room for their correlation).
    ``windows`` are the estimator's windows as ``summary.yaml`` lists them.
    """

    target_id: int
    times: np.ndarray
    state: np.ndarray
    covariance: np.ndarray
    windows: list[dict[str, Any]]
    context: BagContext
    recorded: dict[str, int]
    files: list[Path]
    duplicates: int = 0
    evaluation: dict[int, dict[str, dict[str, float]]] = field(default_factory=dict)
    biases: tuple[BiasEstimate, ...] = ()
    bias_evaluation: dict[tuple[str, str], dict[str, float]] = field(default_factory=dict)

    def lines(self) -> list[str]:
        """Human-readable summary."""
        solved = [w for w in self.windows if w['success']]
        converged = sum(bool(w.get('converged')) for w in solved)
        chi2 = [float(w['chi2_dof']) for w in solved if 'chi2_dof' in w]
        out = [
            f'{len(self.windows)} windows of the estimator node: {len(solved)} solved '
            f'({converged} converged as its diagnostics tell), {len(self.windows) - len(solved)} '
            'failed' + (f'; chi2/dof {min(chi2):.3f}-{max(chi2):.3f}' if chi2 else ''),
            f'{self.times.size} final states of target {self.target_id} from the results node'
            + (f' from {self.times[0]:.3f} s to {self.times[-1]:.3f} s' if self.times.size else '')
            + (f' ({self.duplicates} published twice, kept once)' if self.duplicates else ''),
        ]
        for w in self.windows:
            if not w['success']:
                out.append(f'window [{w["start"]:.3f}, {w["end"]:.3f}] s failed: {w["error"]}')
        out += _evaluation_lines(self.evaluation)
        out += _bias_lines(self.biases, self.bias_evaluation)
        return out


_RECORDED_OUTPUTS = (
    'trajectory/states',
    'estimator/window_states',
    'trajectory/biases',
    'diagnostics',
    'truth/state',
)
_ESTIMATOR_STATUS = 'estimator: windows'
_WINDOW_REJECT_REASONS = ('residual_gate', 'not_measured')


def _window_row(kv: Mapping[str, str]) -> dict[str, Any]:
    """What the estimator's diagnostics say about its last window, as summary.yaml's
    window entries of ``orbit-tracking estimate`` spell it."""

    def num(key: str, kind: type = float) -> Any:
        try:
            return kind(float(kv[key]))
        except (KeyError, ValueError):
            return None

    message = kv.get('last_window_status', '')
    row: dict[str, Any] = {'message': message, 'converged': message.startswith('converged')}
    for key, name, kind in (
        ('last_iterations', 'iterations', int),
        ('last_halvings', 'halvings', int),
        ('last_chi2_dof', 'chi2_dof', float),
        ('last_parameters', 'parameters', int),
        ('last_condition', 'condition', float),
        ('last_knot_time_s', 'knot_time_s', float),
        ('last_gauss_newton_time_s', 'solve_time_s', float),
        ('last_solve_wall_s', 'solve_wall_s', float),
    ):
        v = num(key, kind)
        if v is not None:
            row[name] = v
    row['used'] = {k[5:]: int(v) for k, v in sorted(kv.items()) if k.startswith('used_')}
    row['rejected'] = {
        f'{k[9 : -len(why) - 1]}/{why}': int(v)
        for k, v in sorted(kv.items())
        for why in _WINDOW_REJECT_REASONS
        if k.startswith('rejected_') and k.endswith('_' + why)
    }
    return row


def write_recorded_outputs(
    bag: str | Path,
    out: str | Path,
    config: Mapping[str, Any] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> RecordingReport:
    """Write the output files of ``orbit-tracking estimate`` from a bag recorded from the
    live nodes: the results node's ``trajectory/states``, the estimator's
    ``estimator/window_states``, ``trajectory/biases`` and ``/diagnostics``, and
    ``truth/state`` when it was published.

    Writes to ``out`` (created):

    * ``trajectory.csv`` (contract columns) of the lowest target id; with several targets
      also ``trajectory_target_<id>.csv``;
    * ``biases.csv`` and ``biases_by_window.csv`` (header only without biases);
    * ``summary.yaml``: the bag, its scenario, ``config`` (the estimator's parameters), the
      messages recorded per topic, the windows (span, states, and what the estimator's
      diagnostics said of each: solver message, iterations, chi2/dof, values used and
      rejected), the errors against truth outside and inside the bag's gaps as
      ``orbit-tracking estimate`` computes them (the 6-dof NEES with the position-velocity
      correlation left out, as Odometry carries it), the biases, then ``extra``.

    Times are on the bag's time base (its ``orbit_tracking.epoch``, else the whole second
    of its first output stamp).

    Raises
    ------
    OrbitTrackingError
        The bag holds no ``trajectory/states``.
    """
    ctx = BagContext.from_custom_data(bag)
    recorded = bag_message_counts(bag)
    states: dict[int, dict[int, tuple[np.ndarray, np.ndarray]]] = {}
    spans: dict[tuple[int, int], tuple[float, float, int]] = {}
    diag_raw: list[tuple[int, float, float, dict[str, str]]] = []
    bias_windows: dict[tuple[int, int], tuple[float, float, tuple[BiasEstimate, ...]]] = {}
    truth: list[Any] = []
    duplicates = 0

    def key(t0: float, t1: float) -> tuple[int, int]:
        return round(t0 * 1e6), round(t1 * 1e6)  # microseconds: '%.9g' diagnostics agree

    for m in read_bag(bag, _RECORDED_OUTPUTS):
        topic = m.topic.lstrip('/')
        if topic == 'diagnostics':
            for st in m.msg.status:
                kv = {v.key: v.value for v in st.values}
                if st.name != _ESTIMATOR_STATUS or not kv.get('last_window_end'):
                    continue
                try:
                    ref = parse_stamp(kv['time_reference_s'])
                    a, b = float(kv['last_window_start']), float(kv['last_window_end'])
                except (KeyError, ValueError):
                    continue
                diag_raw.append((ref, a, b, kv))
            continue
        tb = ctx.tb(stamp_ns(m.msg.header.stamp))
        if topic == 'trajectory/states':
            s = odometry_to_target_state(m.msg, tb)
            cov = np.zeros((6, 6))
            cov[:3, :3], cov[3:, 3:] = s.position_cov, s.velocity_cov
            same_target = states.setdefault(s.target_id, {})
            ns = stamp_ns(m.msg.header.stamp)
            if ns in same_target:
                duplicates += 1
                continue
            same_target[ns] = (np.concatenate([s.position, s.velocity]), cov)
            ctx.world_frame = ctx.world_frame or m.msg.header.frame_id
        elif topic == 'estimator/window_states':
            ws = cloud_to_window_states(m.msg, tb)
            spans[key(ws.t0, ws.t1)] = (ws.t0, ws.t1, int(ws.time.size))
            ctx.world_frame = ctx.world_frame or ws.world_frame
        elif topic == 'trajectory/biases':
            biases = diagnostics_to_biases(m.msg)
            kv = {v.key: v.value for st in m.msg.status for v in st.values}
            if biases and 'window_start' in kv and 'window_end' in kv:
                a = (parse_stamp(kv['window_start']) - tb.ref_ns) * 1e-9
                b = (parse_stamp(kv['window_end']) - tb.ref_ns) * 1e-9
                bias_windows[key(a, b)] = (a, b, biases)
        elif topic == 'truth/state':
            truth.append(odometry_to_target_state(m.msg, tb))
    if not states:
        raise OrbitTrackingError(
            f'{bag} holds no trajectory/states: the results node published nothing '
            "(see its log and the estimator's)"
        )
    ctx.truth.update(_truth_states(truth))
    tb = ctx.timebase or TimeBase(0)
    diag: dict[tuple[int, int], dict[str, str]] = {}
    for ref, a, b, kv in diag_raw:  # on the estimator's time base: moved onto ours
        shift = (ref - tb.ref_ns) * 1e-9
        diag[key(a + shift, b + shift)] = kv
    tracks: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for tid, by_stamp in sorted(states.items()):
        stamps = sorted(by_stamp)
        tracks[tid] = (
            (np.array(stamps, dtype=np.int64) - tb.ref_ns) * 1e-9,
            np.array([by_stamp[n][0] for n in stamps]),
            np.array([by_stamp[n][1] for n in stamps]),
        )
    windows: list[dict[str, Any]] = []
    for k, (a, b, n) in spans.items():
        row = {'start': round(a, 9), 'end': round(b, 9), 'success': True, 'states': n}
        windows.append({**row, **_window_row(diag.get(k, {}))})
    for k, kv in diag.items():
        status = kv.get('last_window_status', '')
        if k not in spans and status.startswith('failed'):
            windows.append(
                {'start': k[0] * 1e-6, 'end': k[1] * 1e-6, 'success': False, 'error': status}
            )
    windows.sort(key=lambda w: (w['start'], w['end']))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    main = min(tracks)
    files = [out / 'trajectory.csv']
    write_trajectory_csv(files[0], *tracks[main], tb.ref_ns)
    if len(tracks) > 1:
        for tid, (tt, x, cov) in tracks.items():
            files.append(out / f'trajectory_target_{tid}.csv')
            write_trajectory_csv(files[-1], tt, x, cov, tb.ref_ns)
    by_window = sorted(bias_windows.values(), key=lambda w: (w[0], w[1]))
    final = _final_biases(by_window)
    files.append(out / 'biases.csv')
    write_biases_csv(files[-1], [b for b, _ in final])
    files.append(out / 'biases_by_window.csv')
    write_biases_by_window_csv(files[-1], by_window, tb.ref_ns)
    t_main, x_main, c_main = tracks[main]
    report = RecordingReport(
        main,
        t_main,
        x_main,
        c_main,
        windows,
        ctx,
        recorded,
        files,
        duplicates,
        biases=tuple(b for b, _ in final),
    )
    for tid, (tt, x, cov) in tracks.items():
        if tid in ctx.truth and tt.size:
            ev = _evaluate(ctx, tid, tt, x, cov)
            if ev:
                report.evaluation[tid] = ev
    solved = [w for w in windows if w['success']]
    summary: dict[str, Any] = {
        'bag': str(bag),
        'scenario': ctx.scenario,
        'source': 'trajectory/states of the results node, recorded over DDS',
        'config': dict(config or {}),
        'recorded': recorded,
        'totals': {
            'windows': len(windows),
            'solved': len(solved),
            'converged': int(sum(bool(w.get('converged')) for w in solved)),
            'failed': len(windows) - len(solved),
            'output_states': int(t_main.size),
            'states_published_twice': duplicates,
        },
        'windows': windows,
        'evaluation': report.evaluation,
    }
    if final:
        summary['biases'] = _bias_summary(ctx, final, [], report.bias_evaluation)
    summary.update(extra or {})
    (out / 'summary.yaml').write_text(yaml.safe_dump(summary, sort_keys=False))
    files.append(out / 'summary.yaml')
    return report


def _final_biases(
    windows: Sequence[tuple[float, float, Sequence[BiasEstimate]]],
) -> list[tuple[BiasEstimate, Span]]:
    """Each (station, bias) from the last window that has it (the final window for a
    station that measures to the end), in the order of the bias names; ``windows`` are
    ``(t0, t1, biases)``."""
    last: dict[tuple[str, str], tuple[BiasEstimate, Span]] = {}
    for t0, t1, biases in sorted(windows, key=lambda w: (w[0], w[1])):
        for b in biases:
            last[(b.station, b.name)] = (b, (t0, t1))
    order = {n: i for i, n in enumerate(ESTIMABLE_BIASES)}
    return [last[k] for k in sorted(last, key=lambda k: (k[0], order[k[1]]))]


def _bias_summary(
    ctx: BagContext,
    final: list[tuple[BiasEstimate, Span]],
    notes: Sequence[str],
    evaluation: dict[tuple[str, str], dict[str, float]],
) -> dict[str, object]:
    """The ``biases`` section of summary.yaml; fills ``evaluation`` (errors against the
    bag's simulated biases, when known)."""
    ctx.scenario_truth_biases()
    rows = []
    for b, (t0, t1) in final:
        row: dict[str, object] = {
            'station': b.station,
            'field': b.name,
            'bias': float(b.value),
            'sigma': float(b.sigma),
            'prior': float(b.prior),
            'prior_sigma': float(b.prior_sigma),
            'status': b.status,
            'window': [float(t0), float(t1)],
        }
        if ctx.truth_biases is not None:
            truth = ctx.truth_biases.get((b.station, b.name), 0.0)
            ev = {
                'truth': truth,
                'error': float(b.value - truth),
                'z': float((b.value - truth) / b.sigma),
            }
            evaluation[(b.station, b.name)] = ev
            row.update(ev)
        rows.append(row)
    out: dict[str, object] = {'final': rows, 'notes': list(notes)}
    if ctx.truth_biases is not None:
        z = [
            abs(evaluation[(b.station, b.name)]['z'])
            for b, _ in final
            if b.status.startswith('estimated')
        ]
        out['truth_source'] = ctx.truth_biases_source
        out['max_abs_z_estimated'] = max(z, default=math.nan)
    return out
