"""``orbit-tracking estimate --model rocket|adjoint``: one fit of seed 003's rocket model
(or its adjoint assimilation) over the whole bag
(:func:`~orbit_tracking.core.dynamics.solve.fit_model`), with the files of the
spline estimate (``trajectory.csv``, ``biases.csv``, ``biases_by_window.csv``, ``bag/``,
``summary.yaml``; a fit that is not a success writes ``trajectory_failed.csv`` instead, and
no bag) and the contest's outputs: ``report_times.csv`` (states and thrust at
the requested times, with sigma) and ``residuals.csv`` (every whitened residual).

The summary says what the data can and cannot determine
(:mod:`~orbit_tracking.core.dynamics.observability`), and when no bias is declared but
the lines of sight miss each other by many sigma, that systematic errors are likely and
which command estimates them.
"""

from __future__ import annotations

import csv
import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from orbit_tracking.core import frames
from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.dynamics.adjoint import COVER_LIMIT_S, AdjointFit, AdjointFlight
from orbit_tracking.core.dynamics.fit import DynamicsFit
from orbit_tracking.core.dynamics.observability import (
    ESTIMATED,
    NOT_OBSERVABLE,
    ParameterObservability,
    bias_estimates,
    classify,
    classify_before,
    weakest_direction,
)
from orbit_tracking.core.dynamics.solve import RocketConfig, fit_model, start_points
from orbit_tracking.core.estimation.bias_files import (
    BiasDeclaration,
    load_bias_declaration,
    write_biases_by_window_csv,
    write_biases_csv,
)
from orbit_tracking.core.estimation.results import BiasEstimate
from orbit_tracking.core.estimation.windows import (
    TRAJECTORY_CSV_COLUMNS,
    output_times,
    write_trajectory_csv,
)
from orbit_tracking.core.time import format_stamp
from orbit_tracking.core.triangulation.intersection import Gates
from orbit_tracking.core.triangulation.pipeline import fix_series
from orbit_tracking.ros.conversions import TimeBase
from orbit_tracking.tools.bag_inputs import BagContext, read_for_estimation
from orbit_tracking.tools.estimate import (
    MISS_WARNING_SIGMA,
    median_miss_sigma,
    resolve_declaration,
    trajectory_messages,
    triangulated_fixes,
    write_output_bag,
)
from orbit_tracking.tools.evaluation import bias_lines, evaluate_tracks, evaluation_lines

__all__ = ['DynamicsReport', 'estimate_dynamics_bag', 'parse_report_times']


def parse_report_times(text: str) -> np.ndarray:
    """``'50:170:10'`` (start:stop:step, both ends included) or ``'50,60,75'`` -> times."""
    text = text.strip()
    try:
        if ':' in text:
            a, b, step = (float(x) for x in text.split(':'))
            if not step > 0.0 or b < a:
                raise ValueError
            n = int(math.floor((b - a) / step + 1e-9))
            return a + step * np.arange(n + 1)
        return np.array([float(x) for x in text.split(',') if x.strip()])
    except ValueError:
        raise ValueError(
            f"report times must be 'start:stop:step' (step > 0, stop >= start) or a comma "
            f'list of seconds; got {text!r}'
        ) from None


@dataclass
class DynamicsReport:
    """Outcome of :func:`estimate_dynamics_bag`."""

    fit: DynamicsFit | AdjointFit
    model: str
    observability: list[ParameterObservability]
    weakest: list[str]
    warnings: list[str]
    files: list[Path]
    counts: Counter[str]
    biases: tuple[BiasEstimate, ...]
    evaluation: dict[int, dict[str, dict[str, float]]] = field(default_factory=dict)
    start: str = ''

    def lines(self) -> list[str]:
        f = self.fit
        out = [
            f'{self.model} model: {"success" if f.success else "FAILED"} ({f.message}); '
            f'{f.iterations} iterations; chi2/dof {f.chi2_dof:.3f} ({f.dof} dof); '
            f'{sum(f.used.values())} measured values used, {sum(f.rejected.values())} '
            f'rejected; {f.solve_time:.1f} s; start: {self.start}',
        ]
        for tid, tf in sorted(f.targets.items()):
            a, sa = tf.thrust(np.array([tf.t0, tf.t1]))
            out.append(
                f'target {tid}: {tf.t0:.3f}-{tf.t1:.3f} s; thrust acceleration '
                f'{a[0]:.3f} +- {sa[0]:.2g} m/s^2 at the start, {a[1]:.3f} +- {sa[1]:.2g} '
                f'at the end'
            )
        out += self.warnings
        out += self.weakest
        out += [
            p.sentence() for p in self.observability if '/' in p.name and p.status != ESTIMATED
        ]
        out += evaluation_lines(self.evaluation)
        out += bias_lines(self.biases, {})
        return out


def _write_report_times(
    path: Path, fit: DynamicsFit | AdjointFit, times: np.ndarray, ref_ns: int
) -> int:
    cols = ['time', 'target_id', *TRAJECTORY_CSV_COLUMNS[1:], 'thrust', 'sigma_thrust']
    n = 0
    with open(path, 'w', newline='') as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for tid, tf in sorted(fit.targets.items()):
            t = times[(times >= tf.t0 - COVER_LIMIT_S) & (times <= tf.t1 + COVER_LIMIT_S)]
            if isinstance(tf, AdjointFlight):  # its thrust spline is where the fit made it
                span = tf.model.control
                t = t[(t >= span.t0 - 1e-9) & (t <= span.t1 + 1e-9)]
            x, cov = tf.states(t)
            if not t.size:
                continue
            a, sa = tf.thrust(t)
            sd = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0))
            for i in range(t.size):
                w.writerow(
                    [
                        format_stamp(ref_ns, float(t[i])),
                        tid,
                        *(f'{v:.6f}' for v in x[i]),
                        *(f'{v:.6g}' for v in sd[i]),
                        f'{a[i]:.6f}',
                        f'{sa[i]:.6g}',
                    ]
                )
                n += 1
    return n


def _write_residuals(
    path: Path, fit: DynamicsFit | AdjointFit, ref_ns: int
) -> dict[str, dict[str, float]]:
    """``residuals.csv`` (time, station, target_id, field, whitened residual; empty where
    not measured or rejected) and the RMS per station and field."""
    rms: dict[str, dict[str, float]] = {}
    with open(path, 'w', newline='') as fh:
        w = csv.writer(fh)
        w.writerow(['time', 'station', 'target_id', 'field', 'residual_sigma'])
        for sid, (t, fields, r, ids) in sorted(fit.residuals.items()):
            order = np.argsort(t, kind='stable')
            for i in order:
                for j, f in enumerate(fields):
                    v = r[i, j]
                    w.writerow(
                        [
                            format_stamp(ref_ns, float(t[i])),
                            sid,
                            int(ids[i]),
                            f,
                            '' if not np.isfinite(v) else f'{v:.4f}',
                        ]
                    )
            rms[sid] = {
                f: float(np.sqrt(np.nanmean(r[:, j] ** 2)))
                if np.any(np.isfinite(r[:, j]))
                else math.nan
                for j, f in enumerate(fields)
            }
    return rms


def estimate_dynamics_bag(
    bag: str | Path,
    out: str | Path,
    biases: BiasDeclaration | str | None = None,
    report_times: np.ndarray | None = None,
    model: str = 'rocket',
    output_step: float = 1.0,
    progress: bool = True,
    j2: bool = False,
    stages: int = 1,
) -> DynamicsReport:
    """Fit the rocket model to a bag's station measurements and write the output folder.

    The starts come from the bag's fixes, else from its lines of sight triangulated
    without the miss-distance gate (biased lines miss each other), else (one station) from
    the range-hypothesis search. Telemetry is not used.

    Raises
    ------
    OrbitTrackingError
        No Earth-centred world frame, no measurement, or the fit could not start.
    """
    decl = load_bias_declaration(biases) if isinstance(biases, str) else biases
    ctx = BagContext.from_custom_data(bag)
    cfg = RocketConfig.for_frame(ctx.world_frame, stages=stages, j2=frames.WGS84_J2 if j2 else 0.0)
    buf, counts = read_for_estimation(bag, ctx, progress)
    obs = buf.observations()
    counts.update(buf.counts)
    declared, notes = resolve_declaration(decl, obs)
    warnings = list(notes)
    start = 'the fixes of the bag'
    if not obs.fixes and len(obs.stations) >= 2:
        fixes = triangulated_fixes(bag, ctx, progress, Gates(miss_probability=1.0))
        obs = Observations(obs.stations, {}, fix_series(fixes))
        miss = median_miss_sigma(fixes)
        start = f'{len(fixes)} fixes triangulated from the bag (median miss {miss:.1f} sigma)'
        if not declared and miss > MISS_WARNING_SIGMA:
            warnings.append(
                f'the lines of sight miss each other by {miss:.1f} sigma (median): the stations '
                f'have systematic errors the fit does not model; estimate them with '
                f'orbit-tracking estimate {bag} --model rocket --biases auto --out DIR'
            )
    elif not obs.fixes:
        start = "range-hypothesis search on one station's angles"
        if not declared:
            warnings.append(
                'one station alone cannot tell its systematic errors from the trajectory: '
                'an error of its angles moves the whole flight without changing the '
                'residuals, so the sigma covers the noise only; declare them (--biases auto) '
                'to see the uncertainty they add'
            )
    obs = Observations(obs.stations, {}, obs.fixes)
    points = start_points(obs, config=cfg)
    first = {tid: p[0] for tid, p in points.items()}
    before = classify_before(obs, first, declared) if declared else []
    unseen = [
        p.name
        for p in before
        if '/' in p.name and p.status == NOT_OBSERVABLE and not p.name.split('/')[0].isdigit()
    ]
    if unseen:
        warnings.append(
            'before the solve, at the start: the data cannot determine '
            + ', '.join(unseen)
            + ' (they stay near their priors; their uncertainty is in the sigma)'
        )
    cover = None
    if report_times is not None and report_times.size:
        cover = (float(np.min(report_times)), float(np.max(report_times)))
    fit = fit_model(obs, model, biases=declared, config=cfg, starts=points, cover=cover)
    classes = classify(fit)
    weakest = [weakest_direction(fit, obs, tid) for tid in sorted(fit.targets)]
    bias_rows = bias_estimates(fit, classes)
    tb = ctx.timebase or TimeBase(0)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    tracks = {}
    for tid, tf in sorted(fit.targets.items()):
        t = output_times(tf.t0, tf.t1, output_step)
        tracks[tid] = (t, *tf.states(t))
    main = min(tracks)
    # a failed fit's states are no result: flagged by the file name, never trajectory.csv
    stem = 'trajectory' if fit.success else 'trajectory_failed'
    files = [out / f'{stem}.csv']
    write_trajectory_csv(files[0], *tracks[main], tb.ref_ns)
    if len(tracks) > 1:
        for tid, tr in tracks.items():
            files.append(out / f'{stem}_target_{tid}.csv')
            write_trajectory_csv(files[-1], *tr, tb.ref_ns)
    files.append(out / 'biases.csv')
    write_biases_csv(files[-1], bias_rows)
    files.append(out / 'biases_by_window.csv')
    t_lo = min(tf.t0 for tf in fit.targets.values())
    t_hi = max(tf.t1 for tf in fit.targets.values())
    write_biases_by_window_csv(files[-1], [(t_lo, t_hi, bias_rows)], tb.ref_ns)
    files.append(out / 'residuals.csv')
    rms = _write_residuals(files[-1], fit, tb.ref_ns)
    if report_times is not None and report_times.size:
        files.append(out / 'report_times.csv')
        _write_report_times(files[-1], fit, np.asarray(report_times, float), tb.ref_ns)
    if fit.success:  # a failed fit is not published on the bag's topics
        msgs = trajectory_messages(tracks, main, ctx.world_frame or 'earth', tb)
        files.append(write_output_bag(out / 'bag', msgs))
    report = DynamicsReport(
        fit, model, classes, weakest, warnings, files, counts, tuple(bias_rows), start=start
    )
    report.evaluation.update(evaluate_tracks(ctx, tracks))
    summary = {
        'bag': str(bag),
        'scenario': ctx.scenario,
        'model': model,
        'start': start,
        'config': {
            'output_step': output_step,
            'biases': '' if decl is None or decl.empty else decl.source or 'declared',
            'bias_parameters': len(declared),
            'gm': cfg.gm,
            'j2': cfg.j2,
            'rotating_frame': cfg.rotating,
            'stages': cfg.stages,
        },
        'counts': {k: int(v) for k, v in sorted(counts.items())},
        'totals': {
            'windows': 1,
            'succeeded': int(fit.success),
            'failed': int(not fit.success),
            'iterations': int(fit.iterations),
            'output_states': int(tracks[main][0].size),
        },
        'fit': {
            'success': bool(fit.success),
            'message': fit.message,
            'chi2_dof': float(fit.chi2_dof),
            'dof': int(fit.dof),
            'covariance_scale': float(fit.covariance_scale),
            'solve_time_s': float(fit.solve_time),
            'used': {k: int(v) for k, v in sorted(fit.used.items())},
            'rejected': {f'{s}/{w}': int(n) for (s, w), n in sorted(fit.rejected.items())},
            'residual_rms_sigma': rms,
        },
        'targets': {
            int(tid): {
                'epoch': float(tf.model.epoch),
                'span': [float(tf.t0), float(tf.t1)],
                'parameters': {
                    name: {'value': float(v), 'sigma': float(s)}
                    for name, v, s in zip(
                        tf.model.names, tf.theta, np.sqrt(np.diag(tf.covariance)), strict=True
                    )
                },
            }
            for tid, tf in sorted(fit.targets.items())
        },
        'observability': [
            {
                'parameter': p.name,
                'status': p.status,
                'estimate': p.value,
                'sigma': p.sigma,
                'bound': p.bound,
                'prior_sigma': p.prior_sigma,
            }
            for p in classes
        ],
        'observability_before_solve': [
            {
                'parameter': p.name,
                'status': p.status,
                'bound': p.bound,
                'prior_sigma': p.prior_sigma,
            }
            for p in before
            if not p.name.split('/')[0].isdigit()
        ],
        'weakest_direction': weakest,
        'warnings': warnings,
        'evaluation': report.evaluation,
    }
    (out / 'summary.yaml').write_text(yaml.safe_dump(summary, sort_keys=False))
    files.append(out / 'summary.yaml')
    return report
