"""Scenario files: loading, inheritance, validation, and the truth models they describe.

A scenario is a YAML file (``config/scenarios/<name>.yaml``). A file may name a
``base`` scenario and override parts of it: top-level keys replace the base's, except
``stations`` whose entries are deep-merged with the base entry of the same ``id`` (new
ids are appended; an entry ``{id: X, remove: true}`` drops station X).
The schema a file is validated against is
:data:`~orbit_tracking.core.sim.scenario_schema.SCENARIO_SCHEMA`; see ``docs/SCENARIOS.md``
for every key.
"""

from __future__ import annotations

import math
import os
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from orbit_tracking.core import frames
from orbit_tracking.core.errors import ConfigError
from orbit_tracking.core.models import dynamics
from orbit_tracking.core.models.measurements import KIND_FIELDS, KIND_OPTIONAL_FIELDS
from orbit_tracking.core.models.systematic import CLOCK
from orbit_tracking.core.sim.scenario_schema import SCENARIO_SCHEMA as _SCENARIO
from orbit_tracking.core.sim.telemetry import MODEL_PARAMETERS, parameters_of

__all__ = [
    'Scenario',
    'StationConfig',
    'TelemetryConfig',
    'build_platform_tracks',
    'build_targets',
    'find_scenario',
    'list_scenarios',
    'load_scenario',
    'orbit_state_from_elements',
    'scenario_dirs',
    'scenario_from_dict',
    'station_rng',
    'truth_biases',
]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class StationConfig:
    """One station of a scenario (validated)."""

    id: str
    kind: str
    fields: tuple[str, ...]
    platform: Mapping[str, Any]
    rate_hz: float
    first_epoch: float
    sigma: Mapping[str, float]
    bias: Mapping[str, float]
    clock_bias_s: float
    elevation_mask_deg: float | None
    max_range_m: float | None
    earth_occlusion: bool
    dropouts: tuple[Mapping[str, Any], ...]
    loss_probability: float
    targets: tuple[int, ...]
    gross_errors: Mapping[str, float] = field(
        default_factory=lambda: {'count': 0, 'min_sigma': 20.0, 'max_sigma': 1000.0}
    )
    """``count`` values of the station (over all its rows and fields) off by a factor of
    ``min_sigma``..``max_sigma`` (log-uniform, random sign) of their sigma."""

    @property
    def moving(self) -> bool:
        """Whether the station's state changes over time (satellite or ship)."""
        return str(self.platform['type']) != 'fixed'

    @property
    def sigmas(self) -> FloatArray:
        """Standard deviations in the order of :attr:`fields`."""
        return np.array([self.sigma[f] for f in self.fields])


@dataclass(frozen=True)
class TelemetryConfig:
    """On-board telemetry or airborne GPS (validated)."""

    kind: str
    rate_hz: float
    first_epoch: float
    targets: tuple[int, ...]
    position_sigma_m: float
    velocity_sigma_m_s: float
    position_drift_m: float
    velocity_drift_m_s: float
    outages: tuple[Mapping[str, Any], ...]
    error_model: str = 'drift'
    """One of :data:`~orbit_tracking.core.sim.telemetry.ERROR_MODELS`."""
    error_parameters: Mapping[str, float] = field(default_factory=dict)
    """Parameters of the error models (every key of
    :data:`~orbit_tracking.core.sim.telemetry.MODEL_PARAMETERS`, defaults filled in)."""


@dataclass(frozen=True)
class Scenario:
    """A validated scenario.

    ``targets`` and ``platforms`` keep their validated mappings; :func:`build_targets`
    and :func:`build_platform_tracks` turn them into trajectories.
    """

    name: str
    description: str
    source: str
    world_frame: str
    epoch: float
    t_start: float
    t_end: float
    random_seed: int
    gm: float
    launch: Mapping[str, float] | None
    truth_rate_hz: float
    gaps: tuple[tuple[float, float], ...]
    output_step_s: float
    targets: tuple[Mapping[str, Any], ...]
    platforms: tuple[Mapping[str, Any], ...]
    stations: tuple[StationConfig, ...]
    telemetry: TelemetryConfig | None

    @property
    def target_ids(self) -> tuple[int, ...]:
        return tuple(int(t['id']) for t in self.targets)

    def station(self, station_id: str) -> StationConfig:
        for s in self.stations:
            if s.id == station_id:
                return s
        raise KeyError(f'scenario {self.name} has no station {station_id!r}')

    @property
    def launch_frame(self) -> tuple[FloatArray, FloatArray] | None:
        """``(origin_ecef (3,), rotation (3, 3))`` of the launch frame, if defined."""
        if self.launch is None:
            return None
        lat = np.radians(self.launch['latitude_deg'])
        lon = np.radians(self.launch['longitude_deg'])
        origin = frames.geodetic_to_ecef(lat, lon, self.launch['height_m'])
        rot = frames.launch_rotation(lat, lon, np.radians(self.launch['azimuth_deg']))
        return origin, rot


def scenario_dirs() -> list[Path]:
    """Folders searched for scenario files, in order.

    ``$ORBIT_TRACKING_SCENARIOS`` (``os.pathsep``-separated), the source tree's
    ``config/scenarios`` and the colcon install's ``share/orbit_tracking/config/scenarios``.
    """
    dirs = [Path(p) for p in os.environ.get('ORBIT_TRACKING_SCENARIOS', '').split(os.pathsep) if p]
    pkg = Path(__file__).resolve().parents[2]  # orbit_tracking/core/sim/scenario.py
    dirs.append(pkg.parent / 'config' / 'scenarios')
    # <prefix>/lib/python3.X/site-packages/orbit_tracking -> <prefix>/share/orbit_tracking
    if len(pkg.parents) > 3:
        dirs.append(pkg.parents[3] / 'share' / 'orbit_tracking' / 'config' / 'scenarios')
    return [d for d in dirs if d.is_dir()]


def list_scenarios() -> list[str]:
    """Names of every scenario file found in :func:`scenario_dirs`."""
    names: set[str] = set()
    for d in scenario_dirs():
        names.update(p.stem for p in d.glob('*.yaml'))
    return sorted(names)


def find_scenario(name: str) -> Path:
    """Path of a scenario given its name or a path to a YAML file."""
    p = Path(name)
    if p.suffix in ('.yaml', '.yml') and p.is_file():
        return p
    for d in scenario_dirs():
        cand = d / f'{name}.yaml'
        if cand.is_file():
            return cand
    raise FileNotFoundError(
        f'no scenario {name!r}; known scenarios: {", ".join(list_scenarios()) or "none"} '
        f'(searched {[str(d) for d in scenario_dirs()]})'
    )


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(str(path), '<file>', f'not valid YAML: {exc}') from None
    if not isinstance(data, dict):
        raise ConfigError(str(path), '<file>', f'expected a mapping at top level, got {data!r}')
    return data


def _merge(base: Any, over: Any) -> Any:
    if isinstance(base, dict) and isinstance(over, dict):
        out = dict(base)
        for k, v in over.items():
            out[k] = _merge(base[k], v) if k in base else v
        return out
    return over


def _resolve(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    if path in seen:
        raise ConfigError(str(path), 'base', 'circular base chain')
    data = _read_yaml(path)
    base_name = data.pop('base', None)
    if base_name is None:
        return data
    if not isinstance(base_name, str):
        raise ConfigError(str(path), 'base', f'expected a scenario name, got {base_name!r}')
    base_path = path.parent / f'{base_name}.yaml'
    if not base_path.is_file():
        base_path = find_scenario(base_name)
    base = _resolve(base_path, (*seen, path))
    stations = data.pop('stations', None)
    merged: dict[str, Any] = {**base, **data}
    if stations is not None:
        if not isinstance(stations, list):
            raise ConfigError(str(path), 'stations', 'expected a list of station overrides')
        out = [dict(s) for s in base.get('stations', [])]
        index = {s.get('id'): i for i, s in enumerate(out)}
        for i, st in enumerate(stations):
            if not isinstance(st, dict) or 'id' not in st:
                raise ConfigError(str(path), f'stations[{i}]', 'expected a mapping with an id')
            if st.get('remove') is True:
                if st['id'] not in index:
                    raise ConfigError(str(path), f'stations[{i}]', 'removes an unknown station')
                out[index[st['id']]] = {}
            elif st['id'] in index:
                out[index[st['id']]] = _merge(out[index[st['id']]], st)
            else:
                out.append(st)
        merged['stations'] = [s for s in out if s]
    return merged


def load_scenario(name_or_path: str | os.PathLike[str]) -> Scenario:
    """Load and validate a scenario by name (see :func:`scenario_dirs`) or path.

    Raises
    ------
    ConfigError
        Naming the file, the key and what was expected.
    FileNotFoundError
        If no such scenario exists.
    """
    path = find_scenario(os.fspath(name_or_path))
    return scenario_from_dict(_resolve(path), str(path))


def scenario_from_dict(data: Mapping[str, Any], source: str = '<dict>') -> Scenario:
    """Validate a scenario mapping (as read from YAML) and build a :class:`Scenario`."""
    d = _SCENARIO(data, '', source)
    t0, t1 = d['span']
    if not t0 < t1:
        raise ConfigError(
            source, 'span', f'expected [start, end] with start < end, got {d["span"]}'
        )
    targets = d['targets']
    target_ids = [t['id'] for t in targets]
    _unique(target_ids, 'targets', source)
    ship_ids = [p['id'] for p in d['platforms']]
    _unique(ship_ids, 'platforms', source)
    _unique([s['id'] for s in d['stations']], 'stations', source)
    for i, t in enumerate(targets):
        key = f'targets[{i}]'
        if t['model'] == 'powered_ascent' and d['launch'] is None:
            raise ConfigError(source, 'launch', 'a powered_ascent target needs the launch site')
        if t['model'] in ('powered_ascent', 'aircraft') and d['world_frame'] != 'earth':
            raise ConfigError(source, f'{key}.model', f'{t["model"]} needs world_frame earth')
        if t['model'] == 'boost':  # the mass must last (until the staging, if any)
            stage2 = t['second_stage'] or {'time_s': t1, 'tau0_s': math.inf}
            for k, end in (('', min(t1, stage2['time_s'])), ('second_stage.', t1)):
                if (t if not k else stage2)['tau0_s'] <= end:
                    raise ConfigError(source, f'{key}.{k}tau0_s', f'expected > {end}')
        if t['model'] == 'orbit':
            _check_orbit_state(t, key, source)
    stations = tuple(
        _station(s, i, d, target_ids, ship_ids, source) for i, s in enumerate(d['stations'])
    )
    tel = d['telemetry']
    telemetry = None
    if tel is not None:
        tel_targets = _target_refs(tel['targets'], target_ids, 'telemetry.targets', source)
        telemetry = TelemetryConfig(
            kind=tel['kind'],
            rate_hz=tel['rate_hz'],
            first_epoch=t0 if tel['first_epoch'] is None else tel['first_epoch'],
            targets=tel_targets,
            position_sigma_m=tel['position_sigma_m'],
            velocity_sigma_m_s=tel['velocity_sigma_m_s'],
            position_drift_m=tel['position_drift_m'],
            velocity_drift_m_s=tel['velocity_drift_m_s'],
            outages=tuple(tel['outages']),
            error_model=tel['error_model'],
            error_parameters=parameters_of(tel),
        )
        _check_error_parameters(data.get('telemetry') or {}, tel['error_model'], source)
    ev = d['evaluation']
    return Scenario(
        name=d['name'],
        description=d['description'],
        source=source,
        world_frame=d['world_frame'],
        epoch=d['epoch'],
        t_start=t0,
        t_end=t1,
        random_seed=d['random_seed'],
        gm=d['gm'],
        launch=d['launch'],
        truth_rate_hz=d['truth_rate_hz'],
        gaps=tuple((g['start'], g['end']) for g in ev.get('gaps', [])),
        output_step_s=ev.get('output_step_s', 1.0),
        targets=tuple(targets),
        platforms=tuple(d['platforms']),
        stations=stations,
        telemetry=telemetry,
    )


def _check_error_parameters(raw: Mapping[str, Any], model: str, source: str) -> None:
    """A parameter of another telemetry error model than the chosen one is an error (it
    would silently do nothing)."""
    own = set(MODEL_PARAMETERS[model])
    for name in sorted({k for ks in MODEL_PARAMETERS.values() for k in ks} - own):
        if name in raw and raw[name]:
            users = [m for m, ks in MODEL_PARAMETERS.items() if name in ks]
            raise ConfigError(
                source,
                f'telemetry.{name}',
                f'a parameter of error model(s) {users}, not of error_model {model!r}',
            )


def _unique(ids: Sequence[Any], key: str, source: str) -> None:
    dup = sorted({str(i) for i in ids if list(ids).count(i) > 1})
    if dup:
        raise ConfigError(source, key, f'duplicate id(s) {dup}')


def _target_refs(
    refs: Sequence[int] | None, target_ids: Sequence[int], key: str, source: str
) -> tuple[int, ...]:
    if refs is None:
        return tuple(target_ids)
    bad = [r for r in refs if r not in target_ids]
    if bad:
        raise ConfigError(source, key, f'unknown target id(s) {bad}; targets are {target_ids}')
    return tuple(refs)


def _check_orbit_state(p: Mapping[str, Any], key: str, source: str) -> None:
    has_state = p['position'] is not None and p['velocity'] is not None
    has_elements = p['elements'] is not None
    if has_state == has_elements:
        raise ConfigError(
            source, key, 'expected either position and velocity, or elements (not both)'
        )


def _station(
    s: Mapping[str, Any],
    i: int,
    d: Mapping[str, Any],
    target_ids: Sequence[int],
    ship_ids: Sequence[str],
    source: str,
) -> StationConfig:
    key = f'stations[{i}]'
    kind = s['kind']
    allowed = KIND_FIELDS[kind] + KIND_OPTIONAL_FIELDS[kind]
    fields = tuple(s['fields']) if s['fields'] is not None else KIND_FIELDS[kind]
    bad = [f for f in fields if f not in allowed]
    if bad:
        raise ConfigError(
            source, f'{key}.fields', f'{kind} cannot measure {bad}; allowed {allowed}'
        )
    sigma = {f: v for f, v in s['sigma'].items() if v is not None}
    if set(sigma) != set(fields):
        raise ConfigError(
            source,
            f'{key}.sigma',
            f'expected one sigma per field {list(fields)}, got {sorted(sigma)}',
        )
    bias = {p: v for p, v in s['bias'].items() if v is not None}
    extra = [p for p in bias if p not in fields and p != 'los_theta']
    if extra or ('los_theta' in bias and kind != 'satellite'):
        raise ConfigError(
            source,
            f'{key}.bias',
            f'bias on parameter(s) the station does not measure: {sorted(bias)}',
        )
    ptype = s['platform']['type']
    if ptype == 'fixed' and d['world_frame'] != 'earth':
        raise ConfigError(source, f'{key}.platform.type', 'fixed stations need world_frame earth')
    if ptype == 'ship':
        if s['platform']['ship'] not in ship_ids:
            raise ConfigError(
                source, f'{key}.platform.ship', f'unknown ship; platforms are {list(ship_ids)}'
            )
    if ptype == 'orbit':
        _check_orbit_state(s['platform'], f'{key}.platform', source)
    if kind == 'satellite' and ptype != 'orbit':
        raise ConfigError(source, f'{key}.platform.type', 'a satellite station needs an orbit')
    for j, w in enumerate(s['dropouts']):
        if w['fields'] is not None and any(f not in fields for f in w['fields']):
            raise ConfigError(
                source, f'{key}.dropouts[{j}].fields', f'expected fields of {list(fields)}'
            )
    gross = s['gross_errors']
    if not gross['min_sigma'] <= gross['max_sigma']:
        raise ConfigError(
            source,
            f'{key}.gross_errors',
            f'expected min_sigma <= max_sigma, got {gross["min_sigma"]} > {gross["max_sigma"]}',
        )
    mask = s['elevation_mask_deg']
    if mask is None and kind != 'satellite':
        mask = 0.0
    return StationConfig(
        id=s['id'],
        kind=kind,
        fields=fields,
        platform=s['platform'],
        rate_hz=s['rate_hz'],
        first_epoch=d['span'][0] if s['first_epoch'] is None else s['first_epoch'],
        sigma=sigma,
        bias=bias,
        clock_bias_s=s['clock_bias_s'],
        elevation_mask_deg=mask,
        max_range_m=s['max_range_m'],
        earth_occlusion=s['earth_occlusion'],
        dropouts=tuple(s['dropouts']),
        loss_probability=s['loss_probability'],
        targets=_target_refs(s['targets'], target_ids, f'{key}.targets', source),
        gross_errors=dict(gross),
    )


def orbit_state_from_elements(elements: Mapping[str, float], gm: float) -> FloatArray:
    """Position and velocity (6,) from classical orbital elements (angles in degrees)."""
    a = elements['semi_major_axis_m']
    e = elements['eccentricity']
    inc = np.radians(elements['inclination_deg'])
    raan = np.radians(elements['raan_deg'])
    argp = np.radians(elements['argument_of_perigee_deg'])
    nu = np.radians(elements['true_anomaly_deg'])
    p = a * (1.0 - e * e)
    r = p / (1.0 + e * np.cos(nu))
    r_pf = r * np.array([np.cos(nu), np.sin(nu), 0.0])
    v_pf = np.sqrt(gm / p) * np.array([-np.sin(nu), e + np.cos(nu), 0.0])

    def rz(x: float) -> FloatArray:
        return np.array([[np.cos(x), -np.sin(x), 0.0], [np.sin(x), np.cos(x), 0.0], [0, 0, 1.0]])

    def rx(x: float) -> FloatArray:
        return np.array([[1.0, 0, 0], [0, np.cos(x), -np.sin(x)], [0, np.sin(x), np.cos(x)]])

    rot = rz(raan) @ rx(inc) @ rz(argp)
    return np.concatenate([rot @ r_pf, rot @ v_pf])


def _orbit(p: Mapping[str, Any], sc: Scenario) -> dynamics.KeplerOrbit:
    if p['elements'] is not None:
        y0 = orbit_state_from_elements(p['elements'], sc.gm)
    else:
        y0 = np.concatenate([p['position'], p['velocity']])
    t0 = float(p['t0'])
    j2 = frames.WGS84_J2 if p['j2'] else 0.0
    return dynamics.KeplerOrbit(
        y0[:3], y0[3:], t0, min(t0, sc.t_start), max(t0, sc.t_end), gm=sc.gm, j2=j2
    )


def _track(p: Mapping[str, Any], sc: Scenario) -> dynamics.GeodeticTrack:
    start = p['start']
    legs = []
    for leg in p['legs']:
        lat_acc = dynamics.G0 * np.sqrt(max(leg['load_factor'] ** 2 - 1.0, 0.0))
        sign = {'none': 0.0, 'right': 1.0, 'left': -1.0}[leg['turn']]
        legs.append(
            dynamics.TrackSegment(
                duration_s=leg['duration_s'],
                lateral_accel_m_s2=sign * lat_acc,
                speed_rate_m_s2=leg['speed_rate_m_s2'],
                path_angle_rate_rad_s=np.radians(leg['path_angle_rate_deg_s']),
            )
        )
    track = dynamics.GeodeticTrack(
        np.radians(start['latitude_deg']),
        np.radians(start['longitude_deg']),
        start['height_m'],
        p['speed_m_s'],
        np.radians(p['heading_deg']),
        sc.t_start if p['start_time'] is None else p['start_time'],
        legs,
        transition_s=p['transition_s'],
    )
    if track.t_start > sc.t_start or track.t_end < sc.t_end:
        raise ConfigError(
            sc.source,
            'legs',
            f'track covers [{track.t_start}, {track.t_end}] s but the span is '
            f'[{sc.t_start}, {sc.t_end}] s; add or lengthen legs',
        )
    return track


def build_targets(sc: Scenario) -> dict[int, dynamics.Trajectory]:
    """Integrate every target's truth trajectory over the scenario span."""
    out: dict[int, dynamics.Trajectory] = {}
    for t in sc.targets:
        model = t['model']
        traj: dynamics.Trajectory
        if model == 'boost':
            t0 = float(t['t0'])
            traj = dynamics.BoostVehicle(
                t['position'],
                t['velocity'],
                t0,
                min(t0, sc.t_start),
                max(t0, sc.t_end),
                exhaust_speed=t['exhaust_speed_m_s'],
                tau0=t['tau0_s'],
                gm=sc.gm,
                j2=frames.WGS84_J2 if t['j2'] else 0.0,
                second_stage=None
                if (s2 := t['second_stage']) is None
                else (s2['time_s'], s2['exhaust_speed_m_s'], s2['tau0_s']),
            )
        elif model == 'orbit':
            traj = _orbit(t, sc)
        elif model == 'powered_ascent':
            assert sc.launch is not None  # checked in scenario_from_dict
            traj = dynamics.PoweredAscent(
                np.radians(sc.launch['latitude_deg']),
                np.radians(sc.launch['longitude_deg']),
                sc.launch['height_m'],
                np.radians(sc.launch['azimuth_deg']),
                liftoff_time=t['liftoff_time'],
                t_end=sc.t_end,
                stages=[dynamics.Stage(**st) for st in t['stages']],
                pitch_program=np.column_stack(
                    [
                        [p[0] for p in t['pitch_program_deg']],
                        np.radians([p[1] for p in t['pitch_program_deg']]),
                    ]
                ),
                cd_area_m2=t['cd_area_m2'],
            )
            if t['liftoff_time'] > sc.t_start:
                raise ConfigError(sc.source, 'liftoff_time', 'expected <= span start')
        else:  # aircraft
            traj = _track(t, sc)
        out[int(t['id'])] = traj
    return out


def build_platform_tracks(sc: Scenario) -> dict[str, dynamics.GeodeticTrack]:
    """Ship tracks by platform id."""
    return {p['id']: _track(p, sc) for p in sc.platforms}


def build_orbit(platform: Mapping[str, Any], sc: Scenario) -> dynamics.KeplerOrbit:
    """The orbit of an observing satellite's platform mapping."""
    return _orbit(platform, sc)


def station_rng(sc: Scenario, name: str) -> np.random.Generator:
    """Independent, reproducible random stream per scenario seed and source name.

    Adding or removing a station does not change the noise of the others.
    """
    return np.random.default_rng([sc.random_seed, zlib.crc32(name.encode())])


def truth_biases(scenario: Scenario) -> dict[tuple[str, str], float]:
    """The systematic errors a scenario simulates, per (station, bias name); the clock
    offset under ``clock``. Biases not listed are zero."""
    out: dict[tuple[str, str], float] = {}
    for st in scenario.stations:
        for name, value in st.bias.items():
            out[(st.id, name)] = float(value)
        if st.clock_bias_s:
            out[(st.id, CLOCK)] = float(st.clock_bias_s)
    return out
