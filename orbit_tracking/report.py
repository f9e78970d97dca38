"""Plots and a Markdown report for engineers who would rather look than read topics.

Pure matplotlib (Agg) on core arrays; no ROS import. :func:`build_report` writes PNG
figures and ``report.md`` into a folder.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from numpy.typing import NDArray  # noqa: E402
from scipy.stats import chi2  # noqa: E402

from orbit_tracking.core import frames  # noqa: E402
from orbit_tracking.core.fixes import TimedFix  # noqa: E402
from orbit_tracking.core.measurements import StationPose, predict, residual  # noqa: E402
from orbit_tracking.core.metrics import nees  # noqa: E402
from orbit_tracking.core.simulation import SimulationResult, World  # noqa: E402

__all__ = ['ReportInputs', 'build_report']

FloatArray = NDArray[np.float64]
_DPI = 110


@dataclass
class ReportInputs:
    """What a report is made of.

    Attributes
    ----------
    result : SimulationResult
        Scenario, measurements, station states and truth.
    fixes : list of TimedFix
        Triangulation fixes (scenario time).
    summary_lines : list of str
        Text lines of the processing steps (printed figures).
    live_lines : list of str
        Outcome of the live DDS pass, if one ran.
    """

    result: SimulationResult
    fixes: list[TimedFix] = field(default_factory=list)
    summary_lines: list[str] = field(default_factory=list)
    live_lines: list[str] = field(default_factory=list)


def _gap_shading(ax: plt.Axes, gaps: Sequence[tuple[float, float]]) -> None:
    for i, (a, b) in enumerate(gaps):
        ax.axvspan(a, b, color='0.9', zorder=0, label='incomplete segment' if i == 0 else None)


def plot_geometry(result: SimulationResult, world: World, path: Path) -> Path:
    """Ground track (earth scenarios, launch-frame or geodetic) or orbital picture (eci)."""
    sc = result.scenario
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    t = np.linspace(sc.t_start, sc.t_end, 400)
    if sc.world_frame == 'earth':
        ax = axes[0]
        for tid, traj in world.targets.items():
            lat, lon, h = frames.ecef_to_geodetic(traj.state(t)[:, :3])
            ax.plot(np.degrees(lon), np.degrees(lat), lw=2, label=f'target {tid}')
            axes[1].plot(t, h / 1e3, label=f'target {tid} height')
        for sid, st in result.station_states.items():
            lat, lon, _ = frames.ecef_to_geodetic(st.position)
            kind = sc.station(sid).kind
            marker = {'cw_radar': '^', 'optical': 'o', 'pulse_radar': 's'}.get(kind, 'x')
            ax.plot(
                np.degrees(lon),
                np.degrees(lat),
                marker,
                ms=5 if st.moving else 7,
                ls='-' if st.moving else '',
            )
            ax.annotate(sid, (np.degrees(lon[-1]), np.degrees(lat[-1])), fontsize=7)
        ax.set_xlabel('longitude [deg]')
        ax.set_ylabel('latitude [deg]')
        ax.set_title('ground track and stations')
        axes[1].set_ylabel('height above WGS-84 [km]')
    else:
        axes[0].remove()
        ax3 = fig.add_subplot(1, 2, 1, projection='3d')
        u, v = np.mgrid[0 : 2 * np.pi : 24j, 0 : np.pi : 12j]
        r = frames.WGS84_A / 1e3
        ax3.plot_wireframe(
            r * np.cos(u) * np.sin(v),
            r * np.sin(u) * np.sin(v),
            r * np.cos(v),
            color='0.8',
            lw=0.4,
        )
        mid = np.array([t[0], t[t.size // 2], t[-1]])
        for tid, traj in world.targets.items():
            x = traj.state(t)
            ax3.plot(x[:, 0] / 1e3, x[:, 1] / 1e3, x[:, 2] / 1e3, lw=2.5, label=f'target {tid}')
            axes[1].plot(t, np.linalg.norm(x[:, 3:], axis=1), label=f'target {tid} speed')
        for sid, st in result.station_states.items():
            p = st.position / 1e3
            line = ax3.plot(p[:, 0], p[:, 1], p[:, 2], '--', label=sid)[0]
            # a few lines of sight, satellite to target, in the satellite's colour
            for tm in mid:
                i = min(int(np.searchsorted(st.time, tm)), len(st) - 1)
                for traj in world.targets.values():
                    q = traj.state(st.time[i])[0, :3] / 1e3
                    seg = np.column_stack([p[i], q])
                    ax3.plot(seg[0], seg[1], seg[2], color=line.get_color(), lw=0.6, alpha=0.6)
        lim = max(float(np.abs(st.position).max()) for st in result.station_states.values()) / 1e3
        for setter in (ax3.set_xlim, ax3.set_ylim, ax3.set_zlim):
            setter(-lim, lim)
        ax3.set_box_aspect((1, 1, 1))
        ax3.set_xlabel('x [km]')
        ax3.set_ylabel('y [km]')
        ax3.set_zlabel('z [km]')
        ax3.set_title('targets, observing satellites and lines of sight (eci)')
        ax3.legend(fontsize=7)
        axes = np.array([ax3, axes[1]])
        axes[1].set_ylabel('speed [m/s]')
    axes[1].set_xlabel('scenario time [s]')
    _gap_shading(axes[1], sc.gaps)
    for a in axes if sc.world_frame == 'earth' else axes[1:]:
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    fig.suptitle(f'{sc.name}: geometry')
    fig.tight_layout()
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def plot_residuals(result: SimulationResult, world: World, path: Path) -> Path:
    """Measurement minus truth, in units of sigma, per station and field (biases shown)."""
    sc = result.scenario
    tables = [m for m in result.measurements.values() if len(m)]
    n = len(tables)
    cols = 2 if n > 1 else 1
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(12, 2.2 * rows + 1), squeeze=False, sharex=True)
    for ax, m in zip(axes.ravel(), tables, strict=False):
        st = result.station_states[m.station_id]
        idx = np.searchsorted(st.time, m.time) if st.moving else np.zeros(len(m), int)
        idx = np.clip(idx, 0, len(st) - 1)
        pose = StationPose(st.position[idx], st.velocity[idx], st.rotation[idx])
        stride = max(1, len(m) // 2000)
        for tid in np.unique(m.target_id):
            sel = np.flatnonzero(m.target_id == tid)[::stride]
            truth = world.targets[int(tid)].state(m.time[sel])
            pred, _ = predict(m.fields, truth, pose.take(sel))
            r = residual(m.fields, m.values[sel], pred) / m.sigmas[sel]
            for j, f in enumerate(m.fields):
                ax.plot(
                    m.time[sel],
                    r[:, j],
                    '.',
                    ms=1.5,
                    label=f'{f} (target {tid})' if len(m.fields) else f,
                )
        _gap_shading(ax, sc.gaps)
        ax.set_ylim(-6, 6)
        ax.set_title(f'{m.station_id} ({m.kind})', fontsize=9)
        ax.set_ylabel('(meas - truth)/sigma', fontsize=8)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, markerscale=4, loc='upper right')
    for ax in axes.ravel()[n:]:
        ax.axis('off')
    for ax in axes[-1]:
        ax.set_xlabel('scenario time [s]')
    fig.suptitle(
        f'{sc.name}: measurement residuals against truth (systematic errors show as offsets)'
    )
    fig.tight_layout()
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def plot_fixes(
    result: SimulationResult, world: World, fixes: list[TimedFix], path: Path
) -> Path | None:
    """Fix errors per axis with their ±3σ envelope, and the NEES with its 95 % band."""
    if not fixes:
        return None
    sc = result.scenario
    targets = sorted({f.target_id for f in fixes})
    fig, axes = plt.subplots(4, 1, figsize=(11, 10), sharex=True)
    for tid in targets:
        tf = [f for f in fixes if f.target_id == tid]
        t = np.array([f.time for f in tf])
        err = np.array([f.fix.position for f in tf]) - world.targets[tid].state(t)[:, :3]
        cov = np.array([f.fix.covariance for f in tf])
        # break the envelope where fixes stop (a gap), instead of bridging it
        breaks = np.flatnonzero(np.diff(t) > 5.0 * np.median(np.diff(t))) + 1 if t.size > 2 else []
        t_env = np.insert(t, breaks, np.nan)
        for k, name in enumerate('xyz'):
            sig = np.insert(np.sqrt(cov[:, k, k]), breaks, np.nan)
            axes[k].plot(t, err[:, k], '.', ms=2, label=f'target {tid} error')
            axes[k].fill_between(
                t_env, -3 * sig, 3 * sig, alpha=0.2, label='±3σ' if tid == targets[0] else None
            )
            axes[k].set_ylabel(f'{name} error [m]')
        axes[3].semilogy(t, nees(err, cov), '.', ms=2, label=f'target {tid} NEES')
    lo, hi = chi2.ppf([0.025, 0.975], 3)
    axes[3].axhline(3.0, color='k', lw=0.8, label='expected 3')
    axes[3].axhspan(lo, hi, color='g', alpha=0.1, label='95 % of χ²(3)')
    axes[3].set_ylabel('NEES')
    axes[3].set_xlabel('scenario time [s]')
    for a in axes:
        _gap_shading(a, sc.gaps)
        a.grid(alpha=0.3)
        a.legend(fontsize=7, loc='upper right', markerscale=3)
    fig.suptitle(f'{sc.name}: triangulation fixes against truth ({sc.world_frame} frame)')
    fig.tight_layout()
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def build_report(inputs: ReportInputs, out: str | Path, world: World | None = None) -> Path:
    """Write the figures and ``report.md`` into ``out``; returns the report's path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    res = inputs.result
    sc = res.scenario
    world = world or World(sc)
    figures = [
        ('Geometry', plot_geometry(res, world, out / 'geometry.png')),
        ('Measurements', plot_residuals(res, world, out / 'residuals.png')),
    ]
    fx = plot_fixes(res, world, inputs.fixes, out / 'fixes.png')
    if fx is not None:
        figures.append(('Triangulation', fx))
    lines = [
        f'# {sc.name}',
        '',
        sc.description,
        '',
        f'World frame `{sc.world_frame}`, span {sc.t_start:g} to {sc.t_end:g} s, '
        f'{len(sc.stations)} station(s), {len(sc.targets)} target(s).',
        '',
        '| station | kind | points | fields | sigma | systematic errors |',
        '|---|---|---|---|---|---|',
    ]
    for st in sc.stations:
        m = res.measurements[st.id]
        sig = ', '.join(f'{f} {st.sigma[f]:.3g}' for f in st.fields)
        bias = ', '.join(f'{k} {v:.3g}' for k, v in st.bias.items()) or 'none'
        lines.append(
            f'| {st.id} | {st.kind} | {len(m)} | {", ".join(st.fields)} | {sig} | {bias} |'
        )
    lines += ['', '## Processing', '', '```', *inputs.summary_lines, '```', '']
    if inputs.live_lines:
        lines += ['## Live run over DDS', '', '```', *inputs.live_lines, '```', '']
    for title, fig in figures:
        lines += [f'## {title}', '', f'![{title}]({fig.name})', '']
    path = out / 'report.md'
    path.write_text('\n'.join(lines) + '\n')
    return path
