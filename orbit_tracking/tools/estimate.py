"""``orbit-tracking estimate``: the estimator node's windows solved on a bag, stitched
into one trajectory, with the output files (``trajectory.csv``, ``biases.csv``,
``biases_by_window.csv``, ``summary.yaml``) and the errors against truth."""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import yaml
from tqdm import tqdm

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.core.estimation.bias_files import (
    BiasDeclaration,
    load_bias_declaration,
    station_fields,
    write_biases_by_window_csv,
    write_biases_csv,
)
from orbit_tracking.core.estimation.config import EstimationError, EstimatorConfig
from orbit_tracking.core.estimation.results import BiasEstimate, Estimate
from orbit_tracking.core.estimation.windows import (
    Span,
    WindowConfig,
    output_times,
    solve_windows,
    stitch,
    write_trajectory_csv,
)
from orbit_tracking.core.models.systematic import BiasParameter
from orbit_tracking.core.triangulation.intersection import Gates
from orbit_tracking.core.triangulation.pipeline import TimedFix, TriangulationPipeline, fix_series
from orbit_tracking.ros import qos
from orbit_tracking.ros.bag import BagWriter
from orbit_tracking.ros.conversions import (
    TimeBase,
    biases_to_diagnostics,
    target_state_to_odometry,
    window_states_to_cloud,
)
from orbit_tracking.tools.bag_inputs import (
    BagContext,
    bag_inputs,
    feed_pipeline,
    read_for_estimation,
)
from orbit_tracking.tools.evaluation import (
    bias_lines,
    bias_summary,
    evaluate_tracks,
    evaluation_lines,
    final_biases,
)

__all__ = [
    'EstimationReport',
    'estimate_bag',
    'median_miss_sigma',
    'resolve_declaration',
    'triangulated_fixes',
    'trajectory_messages',
    'write_output_bag',
]


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
            f'{n_all} windows: {n_ok} succeeded, {n_all - n_ok} failed (not published); '
            f'{its} Gauss-Newton iterations; '
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
        for e in self.estimates:
            if not e.success:
                out.append(f'window [{e.t0:.3f}, {e.t1:.3f}] s failed: {e.message}')
        out += self.context.state_lines()
        out += evaluation_lines(self.evaluation)
        out += self.bias_notes
        out += bias_lines(self.biases, self.bias_evaluation)
        return out


MISS_WARNING_SIGMA = 3.0
"""Median miss of the lines of sight [their sigma] beyond which, with no bias declared,
the tools say systematic errors are likely."""


def median_miss_sigma(fixes: list[TimedFix]) -> float:
    """Median over the fixes of ``sqrt(chi2 / dof)``: how many sigma the lines of sight
    miss each other by (nan without a fix with degrees of freedom)."""
    chi = [f.fix.chi2 / f.fix.dof for f in fixes if f.fix.dof > 0]
    return math.sqrt(float(np.median(chi))) if chi else math.nan


def resolve_declaration(
    decl: BiasDeclaration | None, obs: Observations
) -> tuple[tuple[BiasParameter, ...], list[str]]:
    """The biases a declaration gives for the stations and fields of ``obs``, and the notes
    on what it could not apply (a station without measurements, a field it does not
    measure)."""
    if decl is None or decl.empty:
        return (), []
    fields = station_fields(obs)
    declared, notes = decl.resolve(fields)
    notes += [
        f'bias declaration names station {sid}, which has no measurements in the bag'
        for sid in decl.stations
        if sid not in fields
    ]
    return tuple(declared), notes


Track = tuple[np.ndarray, np.ndarray, np.ndarray]


def trajectory_messages(
    tracks: Mapping[int, Track], main: int, frame: str, tb: TimeBase
) -> list[tuple[int, str, object]]:
    """``trajectory/states`` (the ``main`` target, ``child_frame_id`` ``target``) and
    ``trajectory/target_<id>/states`` Odometry messages of stitched tracks
    ``{id: (times, x (m, 6), cov (m, 6, 6))}``, as ``(stamp ns, topic, message)``."""
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
    return msgs


def write_output_bag(bag_out: Path, msgs: list[tuple[int, str, object]]) -> Path:
    """Write the messages (any order) into a new bag at ``bag_out`` (replacing one)."""
    if bag_out.exists():
        import shutil

        shutil.rmtree(bag_out)
    msgs.sort(key=lambda r: r[0])
    with BagWriter(bag_out) as w:
        for t_ns, topic, msg in msgs:
            w.write(
                topic, msg, t_ns, qos.LATCHED if topic == 'trajectory/biases' else qos.STATE_STREAM
            )
    return bag_out


def triangulated_fixes(
    bag: str | Path, ctx: BagContext, progress: bool, gates: Gates | None = None
) -> list[TimedFix]:
    """Fixes of the bag's lines of sight (the rough trajectory when the bag has neither
    telemetry nor fixes)."""
    pipe = TriangulationPipeline(gates=gates)
    ignored: Counter[str] = Counter()  # already counted by the first pass
    fixes: list[TimedFix] = []
    for item in bag_inputs(bag, ctx, ignored, progress, 'triangulate'):
        fixes.extend(feed_pipeline(pipe, item))  # epochs fixed as the data pass them
    return fixes + pipe.flush()


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
        # the telemetry velocity error model chosen (derivative / separate) per target
        'telemetry_velocity_error': {
            int(tid): sol.telemetry_velocity
            for tid, sol in sorted(e.targets.items())
            if sol.telemetry_velocity
        },
        # the telemetry's time-tag delays [s] (position, its sigma, velocity, its sigma)
        # where the window estimated them
        'telemetry_delays_s': {
            int(tid): [float(x) for x in sol.telemetry_delays]
            for tid, sol in sorted(e.targets.items())
            if sol.telemetry_delays is not None
        },
        # the prior sigmas of the telemetry error spline [m], its level and its steps
        # (estimated from the data by default)
        'telemetry_error_sigma_m': {
            int(tid): [float(x) for x in sol.telemetry_error_sigma]
            for tid, sol in sorted(e.targets.items())
            if sol.telemetry_error_sigma is not None
        },
        # the density of the white-jerk prior [m^2/s^5] estimated per target, away from
        # its events and within 2 s of them
        'jerk_density': {
            int(tid): float(sol.jerk_density)
            for tid, sol in sorted(e.targets.items())
            if sol.jerk_density is not None
        },
        'jerk_density_near_events': {
            int(tid): float(sol.jerk_density_near_events)
            for tid, sol in sorted(e.targets.items())
            if sol.jerk_density_near_events is not None
        },
        # the events' times [s] and the sigmas [s] before and after them that the
        # covariance carries
        'event_times': {
            int(tid): [[float(x) for x in row] for row in sol.event_times.sigmas]
            for tid, sol in sorted(e.targets.items())
            if sol.event_times is not None
        },
        # where the covariance was made isotropic (beyond the linear range)
        'isotropic_spans': {
            int(tid): [[float(a), float(b)] for a, b in sol.isotropic_spans]
            for tid, sol in sorted(e.targets.items())
            if sol.isotropic_spans
        },
    }


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
    declared, bias_notes = resolve_declaration(decl, obs)
    if declared:
        est_cfg = replace(est_cfg, biases=declared)
    if obs.telemetry:
        rough = 'telemetry'
    elif obs.fixes:
        rough = 'triangulation/fixes of the bag'
    else:
        # biased lines of sight miss each other: keep them for the biases to explain
        gates = Gates(miss_probability=1.0) if est_cfg.biases else None
        fixes = triangulated_fixes(bag, ctx, progress, gates)
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
        why = '; '.join(f'[{a:.3f}, {b:.3f}]: {w}' for (a, b), w in failures)
        if not why and not obs.stations:
            withheld = ', '.join(f'{sid} {n}' for sid, n in sorted(buf.withheld.items()))
            why = 'no measurement has a station state at its epoch' + (
                f' (measurements per station without one: {withheld})' if withheld else ''
            )
        why = '; '.join([why or 'no data', *ctx.state_lines()])
        hint = ''
        if rough.startswith('0 fixes triangulated') and not est_cfg.biases:
            miss = median_miss_sigma(
                triangulated_fixes(bag, ctx, False, Gates(miss_probability=1.0))
            )
            if miss > MISS_WARNING_SIGMA:
                hint = (
                    f'. The lines of sight miss each other by {miss:.1f} sigma (median), so the '
                    f'miss-distance gate refused every fix: the stations have systematic '
                    f'errors; estimate them with orbit-tracking estimate {bag} --biases auto '
                    f'--out DIR (or --model rocket --biases auto for a boosting vehicle)'
                )
        raise EstimationError(f'{bag}: no window could be solved ({why}){hint}')
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
    final = final_biases([(e.t0, e.t1, e.biases) for e in estimates if e.success])
    files.append(out / 'biases.csv')
    write_biases_csv(files[-1], [b for b, _ in final])
    files.append(out / 'biases_by_window.csv')
    write_biases_by_window_csv(files[-1], [(e.t0, e.t1, e.biases) for e in estimates], tb.ref_ns)
    frame = ctx.world_frame or 'earth'
    msgs = trajectory_messages(tracks, main, frame, tb)
    for e in estimates:
        if not e.success:  # withheld, as the node withholds it (its states may not be finite)
            continue
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
    files.append(write_output_bag(out / 'bag', msgs))
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
    report.evaluation.update(evaluate_tracks(ctx, tracks))
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
        'stations_without_state': dict(ctx.stations_without_state),
        'totals': {
            'windows': len(estimates) + len(failures),
            'succeeded': int(sum(e.success for e in estimates)),
            'failed': len(failures) + int(sum(not e.success for e in estimates)),
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
        summary['biases'] = bias_summary(ctx, final, bias_notes, report.bias_evaluation)
    (out / 'summary.yaml').write_text(yaml.safe_dump(summary, sort_keys=False))
    files.append(out / 'summary.yaml')
    return report
