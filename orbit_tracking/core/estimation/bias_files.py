"""Bias files: the declaration of which station biases to estimate (YAML, read) and the
tables of estimated biases (``biases.csv``, ``biases_by_window.csv``, written).

A declaration file lists :class:`~orbit_tracking.core.models.systematic.BiasParameter` entries::

    biases:
      - {station: cw01, name: range, prior: 0.0, sigma: 10.0}
      - {station: sat06, name: los_theta, sigma: 1.0e-3, bounds: [-0.01, 0.01]}
      - {station: opt01, name: azimuth, prior: 1.2e-5, estimate: false}   # known

Keys of an entry: ``station`` and ``name`` (required; ``name`` one of
:data:`~orbit_tracking.core.models.systematic.ESTIMABLE_BIASES`), ``prior`` (default 0),
``sigma`` (prior standard deviation, > 0; default :data:`DEFAULT_PRIOR_SIGMA` of the
name), ``estimate`` (default true; false holds the bias at ``prior``, a known
calibration) and ``bounds`` (``[lower, upper]``, ``null`` or ``.inf`` for an open side).

Optional top-level keys: ``auto: true`` adds the *auto declaration* (every measured field
of every station that appears, plus ``los_theta`` for a station measuring both line-of-sight
values), ``auto_clock: true`` adds each station's ``clock`` to it, and ``default_sigma``
(a mapping name -> sigma) replaces the default prior sigmas. Explicit entries replace the
auto entry of the same station and name.
"""

from __future__ import annotations

import csv
import difflib
import math
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.errors import ConfigError
from orbit_tracking.core.estimation.results import BiasEstimate
from orbit_tracking.core.models.measurements import FIELDS
from orbit_tracking.core.models.systematic import CLOCK, ESTIMABLE_BIASES, BiasParameter
from orbit_tracking.core.schema import REQUIRED, Bool, Check, Choice, ListOf, Num, Obj, Str
from orbit_tracking.core.sim.scenario import scenario_dirs
from orbit_tracking.core.time import format_stamp

__all__ = [
    'AUTO',
    'BIASES_BY_WINDOW_CSV_COLUMNS',
    'BIASES_CSV_COLUMNS',
    'DEFAULT_PRIOR_SIGMA',
    'BiasDeclaration',
    'auto_biases',
    'load_bias_declaration',
    'parse_bias_declaration',
    'read_biases_csv',
    'station_fields',
    'write_biases_by_window_csv',
    'write_biases_csv',
]

AUTO = 'auto'
"""The ``bias_file`` value that selects the auto declaration."""

DEFAULT_PRIOR_SIGMA: Mapping[str, float] = {
    'range': 10.0,  # m
    'range_rate': 0.1,  # m/s
    'azimuth': 1e-4,  # rad (about 21")
    'elevation': 1e-4,  # rad
    'los_alpha': 1e-3,  # 1
    'los_beta': 1e-3,  # 1
    'los_theta': 1e-3,  # rad
    CLOCK: 1e-2,  # s
}
"""Weak prior sigmas per bias name: loose enough for any plausible calibration error,
tight enough to keep a barely observed bias bounded."""

BIASES_CSV_COLUMNS: tuple[str, ...] = ('station', 'field', 'bias', 'sigma')
"""``biases.csv`` (the contract's columns; ``field`` is the bias name)."""

BIASES_BY_WINDOW_CSV_COLUMNS: tuple[str, ...] = (
    't0',
    't1',
    'station',
    'field',
    'bias',
    'sigma',
    'prior',
    'prior_sigma',
    'status',
)
"""``biases_by_window.csv``: every window's biases (``t0``, ``t1`` as stamps)."""


@dataclass(frozen=True)
class BiasDeclaration:
    """Which biases to estimate: explicit entries, optionally on top of the auto
    declaration (resolved once the stations and their fields are known).

    Attributes
    ----------
    entries : tuple of BiasParameter
        Explicit declarations, unique per (station, name).
    auto : bool
        Also declare every measured field of every station (:func:`auto_biases`).
    auto_clock : bool
        With ``auto``, also each station's time-tag offset ``clock``.
    default_sigma : mapping of str to float
        Prior sigmas of the auto entries.
    source : str
        Where the declaration came from (file name, ``auto`` or ``''``).
    """

    entries: tuple[BiasParameter, ...] = ()
    auto: bool = False
    auto_clock: bool = False
    default_sigma: Mapping[str, float] = field(default_factory=lambda: dict(DEFAULT_PRIOR_SIGMA))
    source: str = ''

    def __post_init__(self) -> None:
        seen: set[tuple[str, str]] = set()
        for bp in self.entries:
            key = (bp.station, bp.name)
            if key in seen:
                raise ValueError(f'bias {bp.station}/{bp.name} declared twice')
            seen.add(key)
        bad = [k for k in self.default_sigma if k not in ESTIMABLE_BIASES]
        if bad:
            raise ValueError(f'default_sigma: unknown bias name(s) {bad}')

    @property
    def empty(self) -> bool:
        """Nothing declared: the estimator estimates no bias."""
        return not self.entries and not self.auto

    @property
    def stations(self) -> tuple[str, ...]:
        """Stations named by the explicit entries."""
        return tuple(sorted({bp.station for bp in self.entries}))

    def resolve(
        self, fields: Mapping[str, Sequence[str]]
    ) -> tuple[tuple[BiasParameter, ...], list[str]]:
        """The bias parameters for stations with these measured fields.

        Parameters
        ----------
        fields : mapping of station id to sequence of str
            The value fields each station measures (:func:`station_fields`).

        Returns
        -------
        biases : tuple of BiasParameter
            The auto entries (if ``auto``) with the explicit ones in place of theirs, plus
            the explicit entries of stations not in ``fields`` (the estimator ignores a
            station without rows in a window).
        notes : list of str
            Explicit entries left out because their station does not measure what they
            bias (e.g. ``range`` of an optical station, ``los_theta`` without both
            line-of-sight values), one sentence each.
        """
        explicit = {(bp.station, bp.name): bp for bp in self.entries}
        out: list[BiasParameter] = []
        if self.auto:
            for bp in auto_biases(fields, self.auto_clock, self.default_sigma):
                out.append(explicit.pop((bp.station, bp.name), bp))
        notes: list[str] = []
        for (sid, name), bp in explicit.items():
            if sid in fields and not _applies(name, fields[sid]):
                have = ', '.join(fields[sid]) or 'nothing'
                notes.append(
                    f'bias {sid}/{name} ignored: station {sid} measures {have}'
                    + (' (los_theta needs los_alpha and los_beta)' if name == 'los_theta' else '')
                )
                continue
            out.append(bp)
        return tuple(out), notes


def _applies(name: str, fields: Sequence[str]) -> bool:
    if name == CLOCK:
        return True
    if name == 'los_theta':
        return 'los_alpha' in fields and 'los_beta' in fields
    return name in fields


def auto_biases(
    fields: Mapping[str, Sequence[str]],
    clock: bool = False,
    sigma: Mapping[str, float] | None = None,
) -> tuple[BiasParameter, ...]:
    """The auto declaration: a bias on every measured field of every station.

    Parameters
    ----------
    fields : mapping of station id to sequence of str
        Value fields each station measures.
    clock : bool
        Also each station's time-tag offset (``clock``, s).
    sigma : mapping of str to float, optional
        Prior sigma per bias name (default :data:`DEFAULT_PRIOR_SIGMA`).

    Returns
    -------
    tuple of BiasParameter
        Per station (sorted by id), its fields in the contract's order, then
        ``los_theta`` if it measures both ``los_alpha`` and ``los_beta`` (seed 003's
        rotation), then ``clock`` if asked; all with prior 0, unbounded.
    """
    sig = {**DEFAULT_PRIOR_SIGMA, **(sigma or {})}
    out: list[BiasParameter] = []
    for sid in sorted(fields):
        have = [f for f in FIELDS if f in fields[sid]]
        names = have + (['los_theta'] if _applies('los_theta', have) else [])
        names += [CLOCK] if clock else []
        out += [BiasParameter(sid, n, 0.0, float(sig[n])) for n in names]
    return tuple(out)


def station_fields(obs: Observations) -> dict[str, tuple[str, ...]]:
    """The value fields each station of ``obs`` measures (union over its tables)."""
    out: dict[str, list[str]] = {}
    for st in obs.stations:
        have = out.setdefault(st.table.station_id, [])
        have += [f for f in st.table.fields if f not in have]
    return {sid: tuple(f for f in FIELDS if f in have) for sid, have in out.items()}


# ---------------------------------------------------------------------------------------
# reading declarations


@dataclass(frozen=True)
class _Bounds(Check):
    """``[lower, upper]`` with ``null`` or an infinity for an open side."""

    expected = 'a list [lower, upper] of numbers (null or .inf for an open side)'

    def __call__(self, value: Any, path: str, source: str) -> Any:
        if not isinstance(value, list | tuple) or len(value) != 2:
            raise self.fail(value, path, source)
        out = []
        for i, (v, open_side) in enumerate(zip(value, (-math.inf, math.inf), strict=True)):
            if v is None or (isinstance(v, float) and v == open_side):
                out.append(open_side)
            else:
                out.append(Num()(v, f'{path}[{i}]', source))
        if not out[0] < out[1]:
            raise ConfigError(source, path, f'expected lower < upper, got {list(value)}')
        return (out[0], out[1])


class _Any(Check):
    """Anything (the entries of ``biases:`` are checked one by one, with their index)."""

    def __call__(self, value: Any, path: str, source: str) -> Any:
        return value


_ENTRY = Obj(
    {
        'station': (Str(), REQUIRED),
        'name': (Choice(ESTIMABLE_BIASES), REQUIRED),
        'prior': (Num(), 0.0),
        'sigma': (Num(gt=0.0), None),
        'estimate': (Bool(), True),
        'bounds': (_Bounds(), (-math.inf, math.inf)),
    }
)
_FILE = Obj(
    {
        'biases': (ListOf(_Any()), []),
        'auto': (Bool(), False),
        'auto_clock': (Bool(), False),
        'default_sigma': (Obj({n: (Num(gt=0.0), None) for n in ESTIMABLE_BIASES}), {}),
    }
)


def parse_bias_declaration(data: Any, source: str = '<dict>') -> BiasDeclaration:
    """Validate a parsed declaration file (see the module docstring).

    Raises
    ------
    ConfigError
        Naming ``source`` and the entry (``biases[3].sigma``): an unknown key, a missing
        station or name, an unknown bias name, a sigma that is not > 0, bounds that are
        not ordered, a prior outside the bounds, or a (station, name) declared twice.
    """
    if data is None:
        data = {}
    if isinstance(data, list):
        raise ConfigError(
            source, 'biases', 'expected a mapping with a biases: list at the top of the file'
        )
    top = _FILE(data, '', source)
    default_sigma = {
        **DEFAULT_PRIOR_SIGMA,
        **{k: v for k, v in top['default_sigma'].items() if v is not None},
    }
    entries: list[BiasParameter] = []
    first: dict[tuple[str, str], int] = {}
    for i, raw in enumerate(top['biases']):
        path = f'biases[{i}]'
        if isinstance(raw, Mapping) and 'name' in raw and raw['name'] not in ESTIMABLE_BIASES:
            near = difflib.get_close_matches(str(raw['name']), ESTIMABLE_BIASES, n=1)
            raise ConfigError(
                source,
                f'{path}.name',
                f'unknown bias name {raw["name"]!r}'
                + (f' (did you mean {near[0]!r}?)' if near else '')
                + f'; expected one of {list(ESTIMABLE_BIASES)}',
            )
        e = _ENTRY(raw, path, source)
        key = (e['station'], e['name'])
        if key in first:
            raise ConfigError(
                source, path, f'{key[0]}/{key[1]} is already declared by biases[{first[key]}]'
            )
        first[key] = i
        lo, hi = e['bounds']
        if not lo <= e['prior'] <= hi:
            raise ConfigError(
                source, f'{path}.prior', f'prior {e["prior"]:g} outside the bounds [{lo}, {hi}]'
            )
        sigma = e['sigma'] if e['sigma'] is not None else default_sigma[e['name']]
        entries.append(
            BiasParameter(e['station'], e['name'], e['prior'], sigma, e['estimate'], (lo, hi))
        )
    if top['auto_clock'] and not top['auto']:
        raise ConfigError(source, 'auto_clock', 'needs auto: true')
    return BiasDeclaration(tuple(entries), top['auto'], top['auto_clock'], default_sigma, source)


def load_bias_declaration(spec: str | os.PathLike[str]) -> BiasDeclaration:
    """The declaration a ``bias_file`` value names.

    Parameters
    ----------
    spec : str or path
        ``''``: no biases; ``'auto'``: the auto declaration (:func:`auto_biases`, no
        clock); anything else: a YAML file (write ``./auto`` for a file named ``auto``);
        a relative path that does not exist is looked up by its file name in the
        package's ``config/`` folder.

    Raises
    ------
    FileNotFoundError
        No such file.
    ConfigError
        The file is not valid YAML or not a valid declaration (file name and entry).
    """
    text = os.fspath(spec)
    if text == '':
        return BiasDeclaration()
    if text == AUTO:
        return BiasDeclaration(auto=True, source=AUTO)
    path = Path(text).expanduser()
    if not path.is_file() and not path.is_absolute():
        # e.g. biases_example.yaml: the package's config/ (source tree or install share)
        config_dirs = [d.parent for d in scenario_dirs() if d.parent.name == 'config']
        path = next((d / path.name for d in config_dirs if (d / path.name).is_file()), path)
    if not path.is_file():
        raise FileNotFoundError(f'bias file {text} does not exist')
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(str(path), '', f'not valid YAML: {exc}') from None
    return parse_bias_declaration(data, str(path))


# ---------------------------------------------------------------------------------------
# truth and output tables


def write_biases_csv(path: str | Path, biases: Iterable[BiasEstimate]) -> int:
    """Write ``biases.csv`` (columns :data:`BIASES_CSV_COLUMNS`, header only if none).

    Values in the bias's units (m, m/s, rad, 1, s for ``clock``); ``sigma`` is the
    posterior standard deviation (the prior's for a known or unobservable bias).
    Returns the rows written.
    """
    n = 0
    with open(path, 'w', newline='') as fh:
        w = csv.writer(fh)
        w.writerow(BIASES_CSV_COLUMNS)
        for b in biases:
            w.writerow([b.station, b.name, _num(b.value), _num(b.sigma)])
            n += 1
    return n


def write_biases_by_window_csv(
    path: str | Path,
    windows: Iterable[tuple[float, float, Sequence[BiasEstimate]]],
    ref_ns: int = 0,
) -> int:
    """Write ``biases_by_window.csv`` (columns :data:`BIASES_BY_WINDOW_CSV_COLUMNS`).

    ``windows`` yields ``(t0, t1, biases)`` per window, ``t0``/``t1`` in TimeBase seconds,
    written as stamps ``ref_ns + t`` in decimal seconds (nine exact digits). Returns the
    rows written.
    """
    n = 0
    with open(path, 'w', newline='') as fh:
        w = csv.writer(fh)
        w.writerow(BIASES_BY_WINDOW_CSV_COLUMNS)
        for t0, t1, biases in windows:
            for b in biases:
                w.writerow(
                    [
                        format_stamp(ref_ns, t0),
                        format_stamp(ref_ns, t1),
                        b.station,
                        b.name,
                        _num(b.value),
                        _num(b.sigma),
                        _num(b.prior),
                        _num(b.prior_sigma),
                        b.status,
                    ]
                )
                n += 1
    return n


def read_biases_csv(path: str | Path) -> list[tuple[str, str, float, float]]:
    """Rows ``(station, field, bias, sigma)`` of a ``biases.csv``.

    Raises
    ------
    ValueError
        The header is not exactly :data:`BIASES_CSV_COLUMNS`.
    """
    with open(path, newline='') as fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None or tuple(header) != BIASES_CSV_COLUMNS:
            raise ValueError(
                f'{path}: header must be {",".join(BIASES_CSV_COLUMNS)}; got {header}'
            )
        return [(r[0], r[1], float(r[2]), float(r[3])) for r in reader if r]


def _num(v: float) -> str:
    return f'{float(v):.10g}'
