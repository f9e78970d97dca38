"""Figures of an offline result against the truth a bag carries: position and velocity
errors with their NEES, inside and outside the gaps, and the estimated biases against the
simulated ones; the summary lines the tools print."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from orbit_tracking.core.data.tables import TargetStates
from orbit_tracking.core.estimation.results import BiasEstimate
from orbit_tracking.core.estimation.windows import Span
from orbit_tracking.core.metrics import hermite_states, nees
from orbit_tracking.core.models.systematic import ESTIMABLE_BIASES
from orbit_tracking.tools.bag_inputs import BagContext

__all__ = [
    'bias_lines',
    'bias_summary',
    'evaluate_target',
    'evaluate_tracks',
    'evaluation_lines',
    'final_biases',
]


def evaluation_lines(evaluation: dict[int, dict[str, dict[str, float]]]) -> list[str]:
    """One line per target and part (outside / inside gaps) of :func:`evaluate_target`'s
    figures."""
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


def bias_lines(
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


def _truth_velocity(tr: TargetStates, t: np.ndarray) -> np.ndarray:
    from scipy.interpolate import CubicSpline

    v = CubicSpline(tr.time, tr.velocity, axis=0, extrapolate=False)(t)
    return np.asarray(v, dtype=np.float64)


def evaluate_target(
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


def evaluate_tracks(
    ctx: BagContext, tracks: Mapping[int, tuple[np.ndarray, np.ndarray, np.ndarray]]
) -> dict[int, dict[str, dict[str, float]]]:
    """:func:`evaluate_target` of every track ``{id: (times, x, cov)}`` the bag has truth
    for (the ``evaluation`` of the summaries)."""
    out = {}
    for tid, (tt, x, cov) in tracks.items():
        if tid in ctx.truth and tt.size:
            ev = evaluate_target(ctx, tid, tt, x, cov)
            if ev:
                out[tid] = ev
    return out


def final_biases(
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


def bias_summary(
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
