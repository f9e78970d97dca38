"""An output folder of ``orbit-tracking estimate`` or ``orbit-tracking demo`` and what the
report knows besides it, put on one time axis for the sections to draw from.

:func:`read_output_folder` reads the folder's files into an :class:`OutputFolder` (only
``trajectory.csv`` is required); truth and measurements, which the folder alone cannot
give, come in a :class:`RunContext` (:func:`context_from_scenario` simulates a scenario
again; :mod:`~orbit_tracking.tools.report.inputs` reads them from a bag). ``_Page``
combines the two on the time axis of the report. No matplotlib, no ROS import.
"""

from __future__ import annotations

import csv
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.data.tables import TargetStates
from orbit_tracking.core.estimation.bias_files import BIASES_BY_WINDOW_CSV_COLUMNS, read_biases_csv
from orbit_tracking.core.estimation.windows import output_times, read_trajectory_csv
from orbit_tracking.core.sim.scenario import Scenario, truth_biases
from orbit_tracking.core.sim.simulator import simulate
from orbit_tracking.core.time import parse_stamp

__all__ = ['OutputFolder', 'RunContext', 'context_from_scenario', 'read_output_folder']

FloatArray = NDArray[np.float64]
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
