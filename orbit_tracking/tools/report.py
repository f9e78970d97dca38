"""Plots and reports for engineers who would rather look than read topics.

Pure matplotlib (Agg) on core arrays; no ROS import. :func:`build_html_report` writes
``report.html`` and its PNG figures for an output folder of ``orbit-tracking estimate`` or
``orbit-tracking demo`` (:func:`read_output_folder`): trajectory and ground track, position
and velocity errors with their ±3σ bands, post-fit residuals per station and field, station
biases with error bars and the summary figures. What the folder alone cannot give (truth,
the measurements) comes in a :class:`RunContext`.
"""

from __future__ import annotations

import csv
import html
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402
from numpy.typing import NDArray  # noqa: E402
from scipy.interpolate import CubicSpline  # noqa: E402

from orbit_tracking.core import frames  # noqa: E402
from orbit_tracking.core.data.observations import Observations, StationObservations  # noqa: E402
from orbit_tracking.core.data.tables import TargetStates  # noqa: E402
from orbit_tracking.core.estimation.bias_files import BIASES_BY_WINDOW_CSV_COLUMNS, read_biases_csv  # noqa: E402
from orbit_tracking.core.estimation.windows import output_times, read_trajectory_csv  # noqa: E402
from orbit_tracking.core.metrics import hermite_states  # noqa: E402
from orbit_tracking.core.models.measurements import predict, residual  # noqa: E402
from orbit_tracking.core.models.systematic import ESTIMABLE_BIASES  # noqa: E402
from orbit_tracking.core.sim.scenario import (
    Scenario,  # noqa: E402
    truth_biases,  # noqa: E402
)
from orbit_tracking.core.sim.simulator import simulate  # noqa: E402
from orbit_tracking.core.time import parse_stamp  # noqa: E402

__all__ = [
    'HTML_FIGURES',
    'OutputFolder',
    'RunContext',
    'build_html_report',
    'context_from_scenario',
    'read_output_folder',
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


# ---------------------------------------------------------------------------------------
# orbit-tracking report DIR: report.html of an estimate output folder

HTML_FIGURES: Mapping[str, str] = {
    'trajectory': 'trajectory.png',
    'errors': 'state_errors.png',
    'residuals': 'residuals.png',
    'biases': 'biases.png',
    'biases_by_window': 'biases_by_window.png',
}
"""PNG files :func:`build_html_report` may write next to ``report.html``."""

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
_Track = tuple[FloatArray, FloatArray, FloatArray]  # time (m,), state (m, 6), sigma (m, 6)


@dataclass(frozen=True)
class RunContext:
    """What a report knows besides the output folder: truth and measurements.

    Attributes
    ----------
    ref_ns : int
        Stamp [ns] of time 0 of ``truth``, ``gaps`` and ``observations``.
    source : str
        Where they come from (printed on the page).
    world_frame : str
        ``earth``, ``eci`` or ``''`` when unknown.
    truth : mapping of target id to TargetStates
        Empty when there is no truth.
    truth_biases : mapping of (station, bias name) to float, or None
        Simulated station biases (missing ones are zero); None when unknown.
    gaps : tuple of (start, end)
        Incomplete segments [s].
    observations : Observations or None
        The measurements the estimate was made from, with their station poses.
    """

    ref_ns: int
    source: str = ''
    world_frame: str = ''
    truth: Mapping[int, TargetStates] = field(default_factory=dict)
    truth_biases: Mapping[tuple[str, str], float] | None = None
    gaps: tuple[tuple[float, float], ...] = ()
    observations: Observations | None = None


def context_from_scenario(scenario: Scenario) -> RunContext:
    """Simulate a scenario again (deterministic: the data a bag written from it holds)."""
    res = simulate(scenario)
    return RunContext(
        int(round(scenario.epoch * 1e9)),
        f'scenario {scenario.name} ({scenario.source}), simulated again',
        scenario.world_frame,
        dict(res.truth),
        truth_biases(scenario),
        tuple(scenario.gaps),
        Observations.from_simulation(res),
    )


@dataclass(frozen=True)
class OutputFolder:
    """The files of an ``orbit-tracking estimate`` output folder (docs/CONTRACT.md).

    Attributes
    ----------
    path : Path
    trajectory : dict
        ``trajectory.csv`` as :func:`~orbit_tracking.core.estimation.windows.read_trajectory_csv`
        returns it (the lowest target id).
    per_target : mapping of target id to dict
        ``trajectory_target_<id>.csv`` (several targets only).
    summary : mapping or None
        ``summary.yaml``.
    biases : list of (station, field, bias, sigma), or None
        ``biases.csv``.
    biases_by_window : list of dict, or None
        ``biases_by_window.csv`` rows (``t0_ns``, ``t1_ns``, numbers as floats).
    problems : mapping of file name to str
        Why an optional file is missing or unreadable.
    """

    path: Path
    trajectory: Mapping[str, NDArray[Any]]
    per_target: Mapping[int, Mapping[str, NDArray[Any]]] = field(default_factory=dict)
    summary: Mapping[str, Any] | None = None
    biases: list[tuple[str, str, float, float]] | None = None
    biases_by_window: list[dict[str, Any]] | None = None
    problems: Mapping[str, str] = field(default_factory=dict)


def _read_summary(path: Path) -> Mapping[str, Any]:
    data = yaml.safe_load(path.read_text())
    if not isinstance(data, Mapping):
        raise ValueError(f'expected a YAML mapping, got {type(data).__name__}')
    return data


def _read_biases_by_window(path: Path) -> list[dict[str, Any]]:
    with open(path, newline='') as fh:
        reader = csv.DictReader(fh)
        if tuple(reader.fieldnames or ()) != BIASES_BY_WINDOW_CSV_COLUMNS:
            raise ValueError(
                f'header must be {",".join(BIASES_BY_WINDOW_CSV_COLUMNS)}; got {reader.fieldnames}'
            )
        return [
            {
                't0_ns': parse_stamp(r['t0']),
                't1_ns': parse_stamp(r['t1']),
                'station': r['station'],
                'field': r['field'],
                **{k: float(r[k]) for k in ('bias', 'sigma', 'prior', 'prior_sigma')},
                'status': r['status'],
            }
            for r in reader
        ]


def read_output_folder(folder: str | Path) -> OutputFolder:
    """Read an ``orbit-tracking estimate`` output folder.

    Only ``trajectory.csv`` is required; a missing or unreadable optional file
    (``summary.yaml``, ``biases.csv``, ``biases_by_window.csv``) is recorded in
    ``problems``.

    Raises
    ------
    FileNotFoundError
        No ``trajectory.csv`` in ``folder``.
    ValueError
        ``trajectory.csv`` (or a ``trajectory_target_<id>.csv``) is malformed or empty.
    """
    folder = Path(folder)
    traj = folder / 'trajectory.csv'
    if not traj.is_file():
        raise FileNotFoundError(
            f'{folder} has no trajectory.csv: not an output folder of '
            f'orbit-tracking estimate BAG --out {folder}'
        )
    main = read_trajectory_csv(traj)
    if main['time'].size == 0:
        raise ValueError(f'{traj} has no rows')
    per_target = {}
    for f in sorted(folder.glob('trajectory_target_*.csv')):
        tid = f.stem.rsplit('_', 1)[1]
        if tid.isdigit():
            per_target[int(tid)] = read_trajectory_csv(f)
    problems: dict[str, str] = {}

    def optional(name: str, reader: Callable[[Path], Any]) -> Any:
        path = folder / name
        if not path.is_file():
            problems[name] = f'no {name} in {folder}'
            return None
        try:
            return reader(path)
        except (OSError, ValueError, KeyError, IndexError, yaml.YAMLError, csv.Error) as exc:
            problems[name] = f'{path} is unreadable: {exc}'
            return None

    return OutputFolder(
        folder,
        main,
        per_target,
        optional('summary.yaml', _read_summary),
        optional('biases.csv', read_biases_csv),
        optional('biases_by_window.csv', _read_biases_by_window),
        problems,
    )


def _estimate_ref_ns(out: OutputFolder) -> int:
    """Stamp of the estimate's time 0 (summary.yaml's window times count from it): the
    first trajectory stamp minus the first output time of the solved windows; without a
    usable summary, the whole second of the first stamp (the nodes' default)."""
    first = int(out.trajectory['stamp_ns'][0])
    summary = out.summary or {}
    try:
        spans = [
            (float(w['start']), float(w['end'])) for w in summary['windows'] if 'error' not in w
        ]
        t = output_times(
            min(a for a, _ in spans),
            max(b for _, b in spans),
            float(summary['config']['output_step']),
        )
        return first - int(round(float(t[0]) * 1e9))
    except (KeyError, TypeError, ValueError, IndexError):
        return (first // 1_000_000_000) * 1_000_000_000


class _Skip(Exception):
    """A section that cannot be drawn from what is there; the message says why."""


@dataclass(frozen=True)
class _Page:
    """Everything the sections draw from, on one time axis (seconds after ``ref_ns``)."""

    out: OutputFolder
    ctx: RunContext | None
    ref_ns: int
    shift_s: float  # add to summary.yaml's window times
    tracks: Mapping[int, _Track]
    truth: Mapping[int, TargetStates]
    truth_biases: Mapping[tuple[str, str], float] | None
    gaps: tuple[tuple[float, float], ...]
    frame: str

    @classmethod
    def make(cls, out: OutputFolder, ctx: RunContext | None, frame: str = '') -> _Page:
        est_ref = _estimate_ref_ns(out)
        ref = ctx.ref_ns if ctx is not None else est_ref
        truth = dict(ctx.truth) if ctx is not None else {}
        tabs = dict(out.per_target) or {min(truth, default=0): out.trajectory}
        tracks = {
            tid: ((tab['stamp_ns'] - ref) * 1e-9, tab['state'], tab['sigma'])
            for tid, tab in sorted(tabs.items())
        }
        shift = (est_ref - ref) * 1e-9
        tb = ctx.truth_biases if ctx is not None else None
        final = ((out.summary or {}).get('biases') or {}).get('final') or []
        if tb is None and final and all('truth' in b for b in final):
            tb = {(str(b['station']), str(b['field'])): float(b['truth']) for b in final}
        gaps = tuple(ctx.gaps) if ctx is not None and ctx.gaps else _segments(out, shift)
        frame = (ctx.world_frame if ctx is not None else '') or frame
        return cls(out, ctx, ref, shift, tracks, truth, tb, gaps, frame)


def _segments(out: OutputFolder, shift: float) -> tuple[tuple[float, float], ...]:
    """Incomplete segments the estimator found (summary.yaml), merged."""
    spans: list[list[float]] = []
    for w in (out.summary or {}).get('windows') or []:
        for segs in (w.get('segments') or {}).values():
            spans += [[float(a) + shift, float(b) + shift] for a, b in segs]
    merged: list[list[float]] = []
    for a, b in sorted(spans):
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    return tuple((a, b) for a, b in merged)


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


# -- HTML ------------------------------------------------------------------------------------


def _fmt(v: Any) -> str:
    if isinstance(v, bool) or v is None:
        return str(v)
    if isinstance(v, float):
        return f'{v:.6g}'
    if isinstance(v, Mapping | list | tuple):
        return yaml.safe_dump(v, default_flow_style=True, width=10_000).strip()
    return str(v)


def _table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    head = ''.join(f'<th>{html.escape(h)}</th>' for h in header)
    body = ''.join(
        '<tr>' + ''.join(f'<td>{html.escape(_fmt(c))}</td>' for c in r) + '</tr>' for r in rows
    )
    return f'<table><tr>{head}</tr>{body}</table>'


def _records(records: Sequence[Mapping[str, Any]], first: Sequence[str] = ()) -> str:
    """A table of mappings: the ``first`` keys, then every other key in order of appearance."""
    keys = list(first)
    for r in records:
        keys += [k for k in r if k not in keys]
    return _table(keys, [[r.get(k, '') for k in keys] for r in records])


def _flatten(data: Mapping[str, Any], prefix: str = '') -> list[tuple[str, Any]]:
    out: list[tuple[str, Any]] = []
    for k, v in data.items():
        if isinstance(v, Mapping) and v:
            out += _flatten(v, f'{prefix}{k}.')
        else:
            out.append((f'{prefix}{k}', v))
    return out


def _missing(text: str) -> str:
    return f'<p class="missing">{html.escape(text)}</p>'


def _img(path: Path, caption: str = '') -> str:
    return (
        f'<figure><img src="{html.escape(path.name)}" alt="{html.escape(path.stem)}">'
        f'<figcaption>{html.escape(caption)}</figcaption></figure>'
    )


def _summary_section(page: _Page, out: Path) -> str:
    s = page.out.summary
    if s is None:
        raise _Skip(page.out.problems.get('summary.yaml', 'no summary.yaml'))
    parts = [
        _table(
            ('figure', 'value'),
            _flatten({k: v for k, v in s.items() if k not in ('windows', 'evaluation', 'biases')}),
        )
    ]
    ev = s.get('evaluation') or {}
    rows = [
        {'target': tid, 'where': where.replace('_', ' '), **vals}
        for tid, parts_ in ev.items()
        for where, vals in parts_.items()
    ]
    parts += [
        '<h3>Against truth</h3>',
        _records(rows)
        if rows
        else _missing('no evaluation against truth: the bag had no truth/state'),
    ]
    windows = []
    for w in s.get('windows') or []:
        row = {k: v for k, v in w.items() if not isinstance(v, Mapping | list)}
        row['used'] = sum((w.get('used') or {}).values())
        row['rejected'] = sum((w.get('rejected') or {}).values())
        windows.append(row)
    if windows:
        parts += ['<h3>Windows</h3>', _records(windows, ('start', 'end', 'success'))]
    return '\n'.join(parts)


def _trajectory_section(page: _Page, out: Path) -> str:
    return _img(
        plot_html_trajectory(page, out / HTML_FIGURES['trajectory']),
        'Solid: the estimate (trajectory.csv); dashed: truth. Left: east/north/up from the '
        'ground point below the first state; middle: ground track; right: height.',
    )


def _errors_section(page: _Page, out: Path) -> str:
    text = (
        ''
        if any(t in page.truth for t in page.tracks)
        else _missing('no truth for the estimated targets: showing the 1σ envelope alone')
    )
    return text + _img(
        plot_html_errors(page, out / HTML_FIGURES['errors']),
        'World-frame components; bands from the s* columns of trajectory.csv; grey: '
        'incomplete segments.',
    )


def _residuals_section(page: _Page, out: Path) -> str:
    return _img(
        plot_html_residuals(page, out / HTML_FIGURES['residuals']),
        'Each measurement minus its prediction from the estimated trajectory, in units of its '
        'sigma (at most 1500 rows per station drawn). Dashed: the final estimate of an '
        'offset bias (biases.csv) in units of the median sigma of its field.',
    )


def _biases_section(page: _Page, out: Path) -> str:
    o = page.out
    if o.biases is None:
        raise _Skip(o.problems.get('biases.csv', 'no biases.csv'))
    if not o.biases:
        raise _Skip('biases.csv has no rows: the estimate declared no biases (--biases)')
    parts = [
        _img(
            plot_html_biases(page, out / HTML_FIGURES['biases']),
            'Final estimates ±1σ (biases.csv: each from the last window with rows of its '
            'station); crosses: the simulated truth, when known.',
        )
    ]
    if o.biases_by_window:
        fig = plot_html_biases_by_window(page, out / HTML_FIGURES['biases_by_window'])
        parts.append(_img(fig, "Every window's estimate ±1σ at its middle; dotted: truth."))
    else:
        parts.append(_missing(o.problems.get('biases_by_window.csv', 'no rows per window')))
    summary = (o.summary or {}).get('biases') or {}
    rows = summary.get('final') or [
        dict(zip(('station', 'field', 'bias', 'sigma'), r, strict=True)) for r in o.biases
    ]
    parts.append(_records(rows))
    parts += [_missing(str(n)) for n in summary.get('notes') or []]
    return '\n'.join(parts)


_SECTIONS: tuple[tuple[str, Callable[[_Page, Path], str]], ...] = (
    ('Summary', _summary_section),
    ('Trajectory', _trajectory_section),
    ('Position and velocity errors', _errors_section),
    ('Residuals per station and field', _residuals_section),
    ('Station biases', _biases_section),
)

_CSS = (
    'body{font-family:sans-serif;margin:1em auto;max-width:1500px;padding:0 1em}'
    'table{border-collapse:collapse;font-size:85%;margin:.5em 0}'
    'th,td{border:1px solid #bbb;padding:2px 6px;text-align:left}th{background:#eee}'
    '.missing{color:#a33;font-style:italic}img{max-width:100%}'
)


def build_html_report(
    folder: OutputFolder,
    out: str | Path | None = None,
    context: RunContext | None = None,
    notes: Sequence[str] = (),
    world_frame: str = '',
) -> Path:
    """Write ``report.html`` and its PNG figures (:data:`HTML_FIGURES`) into ``out``.

    Parameters
    ----------
    folder : OutputFolder
        What :func:`read_output_folder` read.
    out : path-like, optional
        Folder to write to (created); default the output folder itself.
    context : RunContext, optional
        Truth and measurements; without it the page shows the 1σ envelope instead of
        errors, and no residuals.
    notes : sequence of str
        Lines printed at the top (e.g. where the context came from).
    world_frame : str
        ``earth`` or ``eci`` when the context does not say (e.g. from the output bag).

    Returns
    -------
    Path
        ``report.html``. Every section that cannot be drawn says why instead; nothing is
        raised for a missing piece.
    """
    out = Path(out) if out is not None else folder.path
    out.mkdir(parents=True, exist_ok=True)
    for name in HTML_FIGURES.values():
        (out / name).unlink(missing_ok=True)  # no stale figure from an earlier report
    page = _Page.make(folder, context, world_frame)
    body = []
    for title, section in _SECTIONS:
        try:
            text = section(page, out)
        except _Skip as exc:
            text = _missing(str(exc))
        except Exception as exc:  # noqa: BLE001 -- a report shows what it can
            plt.close('all')
            text = _missing(f'could not draw this section: {type(exc).__name__}: {exc}')
        body.append(f'<section><h2>{html.escape(title)}</h2>\n{text}\n</section>')
    ref = f'{page.ref_ns // 1_000_000_000}.{page.ref_ns % 1_000_000_000:09d}'
    info = [
        f'Output folder: {folder.path.resolve()}',
        f'Time axis: seconds after stamp {ref} s.',
        f'World frame: {page.frame or "not recorded"}.',
        f'Truth and measurements: {context.source if context else "none"}.',
        *notes,
        *folder.problems.values(),
    ]
    title = f'orbit_tracking report: {folder.path.resolve().name}'
    text = (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f'<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>\n'
        f'<h1>{html.escape(title)}</h1>\n<ul>'
        + ''.join(f'<li>{html.escape(line)}</li>' for line in info)
        + '</ul>\n'
        + '\n'.join(body)
        + '\n</body></html>\n'
    )
    path = out / 'report.html'
    path.write_text(text, encoding='utf-8')
    return path
