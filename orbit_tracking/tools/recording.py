"""The output files of a live pass, written from its recording: the results node's
final states, the estimator's window diagnostics and biases, in the same files as
``orbit-tracking estimate`` writes (used by ``orbit-tracking demo``)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.core.estimation.bias_files import write_biases_by_window_csv, write_biases_csv
from orbit_tracking.core.estimation.results import BiasEstimate
from orbit_tracking.core.estimation.windows import write_trajectory_csv
from orbit_tracking.core.time import parse_stamp
from orbit_tracking.ros.bag import read_bag
from orbit_tracking.ros.conversions import (
    TimeBase,
    cloud_to_window_states,
    diagnostics_to_biases,
    odometry_to_target_state,
    stamp_ns,
)
from orbit_tracking.tools.bag_inputs import BagContext, bag_message_counts, truth_states
from orbit_tracking.tools.evaluation import (
    bias_lines,
    bias_summary,
    evaluate_target,
    evaluation_lines,
    final_biases,
)

__all__ = ['RecordingReport', 'write_recorded_outputs']


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
        chi2 = [float(w['chi2_dof']) for w in solved if 'chi2_dof' in w]
        out = [
            f'{len(self.windows)} windows of the estimator node: {len(solved)} succeeded, '
            f'{len(self.windows) - len(solved)} failed (not published)'
            + (f'; chi2/dof {min(chi2):.3f}-{max(chi2):.3f}' if chi2 else ''),
            f'{self.times.size} final states of target {self.target_id} from the results node'
            + (f' from {self.times[0]:.3f} s to {self.times[-1]:.3f} s' if self.times.size else '')
            + (f' ({self.duplicates} published twice, kept once)' if self.duplicates else ''),
        ]
        for w in self.windows:
            if not w['success']:
                out.append(f'window [{w["start"]:.3f}, {w["end"]:.3f}] s failed: {w["error"]}')
        out += evaluation_lines(self.evaluation)
        out += bias_lines(self.biases, self.bias_evaluation)
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
    row: dict[str, Any] = {'message': message}
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
    ctx.truth.update(truth_states(truth))
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
    final = final_biases(by_window)
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
            ev = evaluate_target(ctx, tid, tt, x, cov)
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
            'succeeded': len(solved),
            'failed': len(windows) - len(solved),
            'output_states': int(t_main.size),
            'states_published_twice': duplicates,
        },
        'windows': windows,
        'evaluation': report.evaluation,
    }
    if final:
        summary['biases'] = bias_summary(ctx, final, [], report.bias_evaluation)
    summary.update(extra or {})
    (out / 'summary.yaml').write_text(yaml.safe_dump(summary, sort_keys=False))
    files.append(out / 'summary.yaml')
    return report
