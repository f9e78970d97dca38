"""The report's figures: one PNG per section, drawn with matplotlib (Agg) from a ``_Page``.

Trajectory and ground track (:func:`plot_html_trajectory`), position and velocity errors
with their ±3σ bands (:func:`plot_html_errors`), post-fit residuals per station and field
(:func:`plot_html_residuals`), station biases with error bars
(:func:`plot_html_biases`, :func:`plot_html_biases_by_window`); the states of a track are
interpolated at measurement and truth times here. No ROS import.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from numpy.typing import NDArray  # noqa: E402
from scipy.interpolate import CubicSpline  # noqa: E402

from orbit_tracking.core import frames  # noqa: E402
from orbit_tracking.core.data.observations import StationObservations  # noqa: E402
from orbit_tracking.core.data.tables import TargetStates  # noqa: E402
from orbit_tracking.core.metrics import hermite_states  # noqa: E402
from orbit_tracking.core.models.measurements import predict, residual  # noqa: E402
from orbit_tracking.core.models.systematic import ESTIMABLE_BIASES  # noqa: E402
from orbit_tracking.tools.report.folder import _Page, _Skip, _Track  # noqa: E402

__all__ = [
    'plot_html_biases',
    'plot_html_biases_by_window',
    'plot_html_errors',
    'plot_html_residuals',
    'plot_html_trajectory',
]

FloatArray = NDArray[np.float64]
_DPI = 110


def _gap_shading(ax: plt.Axes, gaps: Sequence[tuple[float, float]]) -> None:
    for i, (a, b) in enumerate(gaps):
        ax.axvspan(a, b, color='0.9', zorder=0, label='incomplete segment' if i == 0 else None)


def _breaks(t: FloatArray) -> NDArray[np.intp]:
    """Indices where samples stop for a while (more than 5 median steps): a curve drawn
    through NaNs inserted there breaks at the gap instead of bridging it."""
    if t.size <= 2:
        return np.zeros(0, dtype=np.intp)
    dt = np.diff(t)
    return np.flatnonzero(dt > 5.0 * np.median(dt)) + 1


def _band(
    ax: plt.Axes, t: FloatArray, sigma: FloatArray, k: float, label: str | None, **kw: Any
) -> None:
    """The ±k·sigma envelope around zero, broken where the samples stop."""
    b = _breaks(t)
    te, se = np.insert(t, b, np.nan), np.insert(sigma, b, np.nan)
    ax.fill_between(te, -k * se, k * se, alpha=kw.pop('alpha', 0.2), label=label, lw=0, **kw)


_STATE = ('x', 'y', 'z', 'vx', 'vy', 'vz')
_OFFSET_BIASES = frozenset(
    {'range', 'range_rate', 'azimuth', 'elevation', 'los_alpha', 'los_beta'}
)
_BIAS_UNITS: Mapping[str, tuple[float, str]] = {
    'range': (1.0, 'm'),
    'range_rate': (1.0, 'm/s'),
    'azimuth': (1e6, 'µrad'),
    'elevation': (1e6, 'µrad'),
    'los_alpha': (1e6, '1e-6'),
    'los_beta': (1e6, '1e-6'),
    'los_theta': (1e6, 'µrad'),
    'clock': (1e3, 'ms'),
}


def _states_at(t: FloatArray, x: FloatArray, tq: FloatArray) -> FloatArray:
    """States (n, 6) at times ``tq`` from state samples: Hermite positions, cubic-spline
    velocities; NaN outside the samples."""
    t, idx = np.unique(t, return_index=True)
    x = x[idx]
    pos = hermite_states(t, x[:, :3], x[:, 3:], tq)
    vel = np.asarray(CubicSpline(t, x[:, 3:], axis=0, extrapolate=False)(tq), dtype=np.float64)
    return np.hstack([pos, vel])


def _truth_at(tr: TargetStates, tq: FloatArray) -> FloatArray:
    return _states_at(tr.time, np.hstack([tr.position, tr.velocity]), tq)


def _grid(
    n: int, cols: int, size: tuple[float, float], sharex: bool = False
) -> tuple[plt.Figure, list[plt.Axes]]:
    """A figure of ``n`` panels in rows of ``cols`` (``size`` per panel); spare ones off."""
    cols = max(1, min(cols, n))
    rows = -(-n // cols)
    fig, axes = plt.subplots(
        rows, cols, figsize=(size[0] * cols, size[1] * rows + 0.8), squeeze=False, sharex=sharex
    )
    flat = list(axes.ravel())
    for ax in flat[n:]:
        ax.axis('off')
    for ax in flat[max(0, n - cols) : n]:  # the lowest panel of each column
        ax.tick_params(labelbottom=True)
    return fig, flat[:n]


def _save(
    fig: plt.Figure,
    path: Path,
    title: str,
    axes: Sequence[plt.Axes] = (),
    markerscale: float = 1.0,
) -> Path:
    """Grid and legend on ``axes``, the title above (half an inch kept for it), PNG."""
    for ax in axes:
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6, markerscale=markerscale, loc='upper right')
    fig.suptitle(title)
    fig.tight_layout(rect=(0.0, 0.0, 1.0, 1.0 - 0.45 / fig.get_figheight()))
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def _frame_note(frame: str) -> str:
    if frame == 'eci':
        return 'ECI axes taken as ECEF (Earth rotation ignored, as the eci scenarios model it)'
    if frame == 'earth':
        return 'WGS-84 ECEF'
    return 'world frame not recorded: taken as ECEF'


def plot_html_trajectory(page: _Page, path: Path) -> Path:
    """3-D trajectory in local east/north/up, ground track and height (truth dashed)."""
    fig = plt.figure(figsize=(16, 5))
    ax3 = fig.add_subplot(1, 3, 1, projection='3d')
    axg, axh = fig.add_subplot(1, 3, 2), fig.add_subplot(1, 3, 3)
    t0, x0, _ = page.tracks[min(page.tracks)]
    p0 = x0[np.flatnonzero(np.all(np.isfinite(x0[:, :3]), axis=1))[0], :3]
    lat0, lon0, _h = frames.ecef_to_geodetic(p0)
    origin, rot = frames.geodetic_to_ecef(lat0, lon0, 0.0), frames.enu_rotation(lat0, lon0)
    for k, (tid, (t, x, _s)) in enumerate(page.tracks.items()):
        curves = [('estimate', t, x[:, :3], '-')]
        tr = page.truth.get(tid)
        if tr is not None:
            sel = (tr.time >= t[0]) & (tr.time <= t[-1])
            curves.append(('truth', tr.time[sel], tr.position[sel], '--'))
        for what, tt, p, ls in curves:
            style: dict[str, Any] = {'ls': ls, 'color': f'C{k}', 'lw': 2.0 if ls == '-' else 1.0}
            enu = (p - origin) @ rot / 1e3
            lat, lon, h = frames.ecef_to_geodetic(p)
            ax3.plot(enu[:, 0], enu[:, 1], enu[:, 2], label=f'target {tid} {what}', **style)
            axg.plot(np.degrees(np.unwrap(lon)), np.degrees(lat), **style)
            axh.plot(tt, h / 1e3, label=f'target {tid} {what}', **style)
    obs = page.ctx.observations if page.ctx is not None else None
    for s in obs.stations if obs is not None else ():
        pos = s.pose.position[:: max(1, len(s.pose) // 200)]
        lat, lon, _h = frames.ecef_to_geodetic(pos)
        moving = float(np.ptp(pos, axis=0).max()) > 1.0  # a ship or satellite: its track
        axg.plot(np.degrees(lon), np.degrees(lat), '--' if moving else '^', ms=4, color='0.3')
        axg.annotate(s.table.station_id, (np.degrees(lon[-1]), np.degrees(lat[-1])), fontsize=7)
    ax3.set_xlabel('east [km]')
    ax3.set_ylabel('north [km]')
    ax3.set_zlabel('up [km]')
    ax3.set_title(
        f'east/north/up from {np.degrees(lat0):.4f}°, {np.degrees(lon0):.4f}°', fontsize=9
    )
    ax3.legend(fontsize=6)
    axg.set(xlabel='longitude [deg]', ylabel='latitude [deg]')
    axg.set_title('ground track (stations: ▲ fixed, dashed moving)', fontsize=9)
    axh.set(xlabel='time [s]', ylabel='height above WGS-84 [km]')
    _gap_shading(axh, page.gaps)
    title = f'trajectory (world frame: {_frame_note(page.frame)}; WGS-84 geodetic)'
    return _save(fig, path, title, [axg, axh])


def plot_html_errors(page: _Page, path: Path) -> Path:
    """Position and velocity errors against truth with ±3σ bands, or without truth the
    ±1σ envelope alone."""
    fig, axes = _grid(6, 3, (4.8, 2.8), sharex=True)
    any_truth = False
    for k, (tid, (t, x, sig)) in enumerate(page.tracks.items()):
        tr = page.truth.get(tid)
        err = x - _truth_at(tr, t) if tr is not None else None
        any_truth |= err is not None
        for j, ax in enumerate(axes):
            kk = 3.0 if err is not None else 1.0
            _band(ax, t, sig[:, j], kk, f'target {tid} ±{kk:g}σ', color=f'C{k}')
            if err is not None:
                ax.plot(t, err[:, j], color=f'C{k}', lw=0.8, label=f'target {tid} error')
    for j, ax in enumerate(axes):
        _gap_shading(ax, page.gaps)
        unit = 'm' if j < 3 else 'm/s'
        ax.set_ylabel(f'{_STATE[j]} {"error" if any_truth else "1σ"} [{unit}]', fontsize=8)
        if j >= 3:
            ax.set_xlabel('time [s]')
    title = (
        'estimate minus truth, with the ±3σ of trajectory.csv'
        if any_truth
        else 'no truth: the ±1σ envelope of trajectory.csv'
    )
    return _save(fig, path, f'{title}; world frame: {_frame_note(page.frame)}', axes)


def _post_fit(s: StationObservations, tracks: Mapping[int, _Track]) -> FloatArray:
    """Whitened residuals (n, k) of one station's rows against the estimated trajectory:
    ``(measured - predicted) / sigma``; NaN where unmeasured or outside the trajectory."""
    tab = s.table
    r = np.full(tab.values.shape, np.nan)
    for tid, (t, x, _sig) in tracks.items():
        sel = np.flatnonzero((tab.target_id == tid) & (tab.time >= t[0]) & (tab.time <= t[-1]))
        if sel.size:
            pred, _ = predict(tab.fields, _states_at(t, x, tab.time[sel]), s.pose.take(sel))
            r[sel] = residual(tab.fields, tab.values[sel], pred) / tab.sigmas[sel]
    return r


def plot_html_residuals(page: _Page, path: Path) -> Path:
    """Post-fit residuals per station and field, the final offset biases as dashed lines."""
    obs = page.ctx.observations if page.ctx is not None else None
    stations = [s for s in obs.stations if len(s.table)] if obs is not None else []
    if not stations:
        raise _Skip(
            'no residuals: orbit-tracking estimate does not write them, and no bag or '
            'scenario with the measurements was found (pass --bag BAG or --scenario NAME)'
        )
    final = {(b[0], b[1]): b[2] for b in page.out.biases or ()}
    fig, axes = _grid(len(stations), 2, (7.0, 2.4), sharex=True)
    for ax, s in zip(axes, stations, strict=True):
        tab = s.table
        r = _post_fit(s, page.tracks)
        keep = np.flatnonzero(np.any(np.isfinite(r), axis=1))[:: max(1, len(tab) // 1500)]
        for j, f in enumerate(tab.fields):
            line = ax.plot(tab.time[keep], r[keep, j], '.', ms=1.5, label=f)[0]
            b = final.get((tab.station_id, f))
            if b is not None and f in _OFFSET_BIASES:
                level = b / np.nanmedian(tab.sigmas[:, j])
                ax.axhline(level, color=line.get_color(), ls='--', lw=1, label=f'{f} bias / σ')
        lim = np.nanpercentile(np.abs(r[keep]), 99.5) if np.isfinite(r[keep]).any() else 1.0
        ax.set_ylim(-max(4.0, 1.2 * lim), max(4.0, 1.2 * lim))
        _gap_shading(ax, page.gaps)
        ax.set_title(f'{tab.station_id} ({tab.kind})', fontsize=9)
        ax.set_ylabel('residual / σ', fontsize=8)
    for ax in axes[-2:]:
        ax.set_xlabel('time [s]')
    return _save(
        fig,
        path,
        '(measured − predicted from the estimated trajectory) / σ; biases not removed',
        axes,
        markerscale=4.0,
    )


def _bias_axes(names: Sequence[str]) -> tuple[plt.Figure, dict[str, plt.Axes]]:
    """One panel per bias name, in the order of ESTIMABLE_BIASES, titled with its unit."""
    order = sorted(set(names), key=lambda n: (ESTIMABLE_BIASES + (n,)).index(n))
    fig, axes = _grid(len(order), 3, (5.0, 3.2))
    for ax, name in zip(axes, order, strict=True):
        ax.set_title(f'{name} bias [{_BIAS_UNITS.get(name, (1.0, ""))[1]}]', fontsize=9)
        ax.axhline(0.0, color='0.5', lw=0.6)
    return fig, dict(zip(order, axes, strict=True))


def plot_html_biases(page: _Page, path: Path) -> Path:
    """Final bias estimates per station with ±1σ error bars, and the truth when known."""
    rows = page.out.biases or []
    fig, axes = _bias_axes([r[1] for r in rows])
    truth = page.truth_biases
    for name, ax in axes.items():
        sub = [r for r in rows if r[1] == name]
        scale = _BIAS_UNITS.get(name, (1.0, ''))[0]
        x = np.arange(len(sub))
        v = np.array([r[2] for r in sub]) * scale
        ax.errorbar(
            x,
            v,
            yerr=np.array([r[3] for r in sub]) * scale,
            fmt='o',
            capsize=3,
            ms=4,
            label='estimate ±1σ',
        )
        if truth is not None:
            tv = [truth.get((r[0], name), 0.0) * scale for r in sub]
            ax.plot(x, tv, 'x', color='C3', ms=8, mew=2, label='truth')
        ax.set_xticks(x, [r[0] for r in sub], rotation=45, fontsize=7)
        ax.set_xlim(-0.5, len(sub) - 0.5)
    return _save(fig, path, 'station biases (biases.csv)', list(axes.values()))


def plot_html_biases_by_window(page: _Page, path: Path) -> Path:
    """Every window's bias estimates (±1σ) at the window's middle; truth dotted."""
    rows = page.out.biases_by_window or []
    fig, axes = _bias_axes([r['field'] for r in rows])
    truth = page.truth_biases
    for name, ax in axes.items():
        scale = _BIAS_UNITS.get(name, (1.0, ''))[0]
        stations = sorted({r['station'] for r in rows if r['field'] == name})
        spread = 0.3e-9 * float(np.median([r['t1_ns'] - r['t0_ns'] for r in rows]))
        for k, sid in enumerate(stations):
            sub = [r for r in rows if r['field'] == name and r['station'] == sid]
            tm = np.array([(r['t0_ns'] + r['t1_ns']) / 2 - page.ref_ns for r in sub]) * 1e-9
            # stations side by side around the window's middle, so that no bar hides another
            ax.errorbar(
                tm + spread * ((k + 0.5) / len(stations) - 0.5),
                [r['bias'] * scale for r in sub],
                yerr=[r['sigma'] * scale for r in sub],
                fmt='o-',
                ms=3,
                lw=0.8,
                capsize=2,
                color=f'C{k % 10}',
                label=sid,
            )
            if truth is not None:
                ax.axhline(truth.get((sid, name), 0.0) * scale, color=f'C{k % 10}', ls=':')
        ax.set_xlabel('window middle [s]', fontsize=8)
    return _save(
        fig, path, 'bias estimates per window (biases_by_window.csv)', list(axes.values())
    )
