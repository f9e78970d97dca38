"""Randomised scenario families: data shaped differently from the reference scenarios.

:func:`draw_scenario` ``(kind, seed)`` draws one scenario of a family and returns it as a
normal validated :class:`~orbit_tracking.core.sim.scenario.Scenario` (built as the mapping a
YAML file would hold and passed through
:func:`~orbit_tracking.core.sim.scenario.scenario_from_dict`); :func:`draw` also returns what
was drawn (:class:`Draw`). Everything comes from ``numpy.random.default_rng([seed,
crc32(kind)])``, so a kind and a seed fully determine the scenario, and the scenario's own
noise seed is ``seed``.

Families (every random choice and its range: docs/SCENARIOS.md, "Randomised families"):

* ``ascent`` (seed 000's kind): a two- or three-stage ascent from a random launch site and
  azimuth, one or two staging events with random coasts inside a 60-120 s span, 3-12
  stations (CW radars, pulse radars, theodolites) 10-150 km from the ground track, each
  with its own noise, rate, mask, gross errors and dropouts; 0-2 incomplete segments (only
  1-2 stations measure) over an event, across a window edge, at the very start or
  anywhere; telemetry (85 %) with a random error model (:mod:`.telemetry`) and outages.
* ``aircraft`` (seed 004's kind): an aircraft flying straight legs, 2-3 g turns and climbs
  over 120-300 s, tracked from one or two rolling ships (pulse radar, EO theodolite,
  INS attitude), airborne GPS with a random error model and outages over the turns (the
  evaluation's gaps).

A draw that comes out implausible (a vehicle that does not climb, stations that would not
see it) is drawn again from the same generator, so it is still determined by the seed.

The module is longer than the project's ~600-line guide on purpose: it holds every random
choice of both families and its range, in the order docs/SCENARIOS.md lists them; split,
the ranges of one draw would sit in several files.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core import frames
from orbit_tracking.core.models import dynamics
from orbit_tracking.core.sim.scenario import (
    Scenario,
    build_platform_tracks,
    build_targets,
    scenario_from_dict,
)

__all__ = ['KINDS', 'Draw', 'acceleration_jumps', 'draw', 'draw_scenario', 'jerk_jumps']

FloatArray = NDArray[np.float64]

KINDS: tuple[str, ...] = ('ascent', 'aircraft')
"""The families :func:`draw_scenario` knows."""

TELEMETRY_MODELS: tuple[str, ...] = (
    'drift',
    'white',
    'random_walk',
    'gauss_markov',
    'bias_drift',
    'separate_velocity',
    'time_skew',
    'jumps',
    'quantised',
)
"""Error models the families draw telemetry with. ``none`` (exact telemetry) is not
drawn: its bound is zero, so no ratio to it would mean anything."""

_G0 = dynamics.G0
_MAX_TRIES = 40
_WINDOW_EDGES = (40.0, 60.0, 80.0, 100.0, 120.0)
"""Starts and ends of the default 60 s windows overlapping by 20 s, from the first data."""


@dataclass(frozen=True)
class Draw:
    """One drawn scenario and what was drawn.

    Attributes
    ----------
    kind : str
    seed : int
    scenario : Scenario
    events : tuple of float
        Times [s] inside the span where the true acceleration jumps (burnouts, ignitions).
    kinks : tuple of float
        Times [s] inside the span where the true jerk jumps (:func:`jerk_jumps`).
    segments : tuple of (float, float)
        The evaluation's gaps: incomplete segments (ascent) or GPS outages (aircraft).
    segment_stations : tuple of tuple of str
        Stations that still measure in each incomplete segment (ascent; empty for aircraft).
    telemetry_model : str or None
        Error model of the telemetry; None without telemetry.
    summary : str
        One line: what was drawn (also the scenario's description).
    """

    kind: str
    seed: int
    scenario: Scenario
    events: tuple[float, ...]
    kinks: tuple[float, ...]
    segments: tuple[tuple[float, float], ...]
    segment_stations: tuple[tuple[str, ...], ...]
    telemetry_model: str | None
    summary: str


def draw_scenario(kind: str, seed: int) -> Scenario:
    """A validated scenario of family ``kind`` (one of :data:`KINDS`) for ``seed`` (>= 0)."""
    return draw(kind, seed).scenario


def draw(
    kind: str, seed: int, span_s: float | None = None, telemetry_model: str | None = None
) -> Draw:
    """One scenario of family ``kind`` and what was drawn (:class:`Draw`).

    ``span_s`` replaces the drawn span length (short draws for tests; everything else is
    drawn for that span, so the draw differs from the family's own for ``seed``).
    ``telemetry_model`` (one of :data:`TELEMETRY_MODELS`) forces telemetry with that error
    model (its parameters still drawn): a test per error class.
    """
    if kind not in KINDS:
        raise ValueError(f'unknown scenario family {kind!r}; known: {KINDS}')
    if int(seed) != seed or seed < 0:
        raise ValueError(f'seed must be an integer >= 0; got {seed!r}')
    if span_s is not None and not 20.0 <= span_s <= 600.0:
        raise ValueError(f'span_s must lie in [20, 600] s; got {span_s}')
    if telemetry_model is not None and telemetry_model not in TELEMETRY_MODELS:
        raise ValueError(
            f'unknown telemetry_model {telemetry_model!r}; known: {TELEMETRY_MODELS}'
        )
    rng = np.random.default_rng([int(seed), zlib.crc32(kind.encode())])
    if kind == 'ascent':
        return _ascent(rng, int(seed), span_s, telemetry_model)
    return _aircraft(rng, int(seed), span_s, telemetry_model)


def jerk_jumps(scenario: Scenario) -> tuple[float, ...]:
    """Times [s] inside the span where the truth's jerk jumps (its acceleration has a
    kink): a powered ascent's pitch-program nodes (the thrust direction is interpolated
    linearly) and the ends of an aircraft's control ramps between legs of different
    controls (:class:`~orbit_tracking.core.models.dynamics.GeodeticTrack`)."""
    out: set[float] = set()
    for t in scenario.targets:
        if t['model'] == 'powered_ascent':
            prog = np.asarray(t['pitch_program_deg'], dtype=float)
            slope = np.diff(prog[:, 1]) / np.diff(prog[:, 0])
            slope = np.concatenate([slope, [0.0]])
            for k in range(1, prog.shape[0]):
                if slope[k] != slope[k - 1]:
                    out.add(float(t['liftoff_time'] + prog[k, 0]))
        elif t['model'] == 'aircraft':
            legs = t['legs']
            start = scenario.t_start if t['start_time'] is None else t['start_time']
            bounds = start + np.concatenate([[0.0], np.cumsum([g['duration_s'] for g in legs])])

            def controls(g: Any) -> tuple[float, float, float]:
                n = g['load_factor']
                sign = {'none': 0.0, 'right': 1.0, 'left': -1.0}[g['turn']]
                lat = sign * _G0 * np.sqrt(max(n * n - 1.0, 0.0))
                return (lat, g['speed_rate_m_s2'], g['path_angle_rate_deg_s'])

            for k in range(1, len(legs)):
                if controls(legs[k]) == controls(legs[k - 1]):
                    continue
                ramp = min(
                    t['transition_s'], 0.5 * legs[k]['duration_s'], 0.5 * legs[k - 1]['duration_s']
                )
                out |= {float(bounds[k] - 0.5 * ramp), float(bounds[k] + 0.5 * ramp)}
    return tuple(sorted(e for e in out if scenario.t_start < e < scenario.t_end))


def acceleration_jumps(scenario: Scenario) -> tuple[float, ...]:
    """Times [s] inside the span where a powered ascent's acceleration jumps: every
    burnout and every ignition after a coast (the phase boundaries after lift-off)."""
    out: set[float] = set()
    for t in scenario.targets:
        if t['model'] != 'powered_ascent':
            continue
        time = float(t['liftoff_time'])
        for st in t['stages']:
            if st['coast_before_s'] > 0.0 and time > float(t['liftoff_time']):
                time += st['coast_before_s']
                out.add(time)
            elif st['coast_before_s'] > 0.0:
                time += st['coast_before_s']
            time += st['propellant_kg'] / st['mass_flow_kg_s']
            out.add(time)
    return tuple(sorted(e for e in out if scenario.t_start < e < scenario.t_end))


# -- helpers ------------------------------------------------------------------------------


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _r(x: float, nd: int = 3) -> float:
    """Rounded so the scenario reads well; every value is still drawn."""
    return float(round(float(x), nd))


def _station_sigma(rng: np.random.Generator, kind: str, ship: bool) -> dict[str, float]:
    if kind == 'cw_radar':
        return {
            'range': _r(_log_uniform(rng, 0.3, 3.0), 4),
            'range_rate': _r(_log_uniform(rng, 0.01, 0.1), 5),
        }
    if kind == 'optical':
        lo, hi = (2.5e-5, 1e-4) if ship else (1e-5, 1e-4)
        s = float(f'{_log_uniform(rng, lo, hi):.4g}')
        return {'azimuth': s, 'elevation': s}
    rng_lo, rng_hi = (2.0, 10.0) if ship else (1.0, 10.0)
    ang_lo, ang_hi = (1e-4, 6e-4) if ship else (5e-5, 5e-4)
    a = float(f'{_log_uniform(rng, ang_lo, ang_hi):.4g}')
    return {'range': _r(_log_uniform(rng, rng_lo, rng_hi), 3), 'azimuth': a, 'elevation': a}


def _dropouts(rng: np.random.Generator, span: float) -> list[dict[str, float]]:
    """Random station dropouts: with probability 0.3, one or two of 1-10 s."""
    if rng.random() >= 0.3:
        return []
    out = []
    for _ in range(int(rng.integers(1, 3))):
        length = rng.uniform(1.0, 10.0)
        start = rng.uniform(0.0, max(span - length, 0.1))
        out.append({'start': _r(start), 'end': _r(start + length)})
    return out


def _gross(rng: np.random.Generator) -> dict[str, float]:
    return {'count': int(rng.integers(0, 6)), 'min_sigma': 20.0, 'max_sigma': 1000.0}


def _telemetry_errors(rng: np.random.Generator, model: str, span: float) -> dict[str, float]:
    """Parameters of an error model for a span of ``span`` seconds."""
    u = rng.uniform
    if model == 'drift':
        # drift publishes hypot(white, position_drift_m), leaving out the slope terms (kept
        # so the reference scenarios do not change); with velocity_drift_m_s at most
        # 0.6 position_drift_m / span that sigma is within 10 % of the honest one
        pd = u(5, 40)
        return {
            'position_drift_m': _r(pd),
            'velocity_drift_m_s': _r(u(0.2, 1.0) * min(0.2, 0.6 * pd / span), 4),
        }
    if model == 'random_walk':
        return {'position_walk_m_sqrt_s': _r(_log_uniform(rng, 0.1, 2.0), 4)}
    if model == 'gauss_markov':
        return {
            'position_markov_m': _r(u(1, 20)),
            'position_markov_tau_s': _r(u(10, 200), 1),
            'velocity_markov_m_s': _r(u(0.01, 0.2), 4),
            'velocity_markov_tau_s': _r(u(5, 100), 1),
        }
    if model == 'bias_drift':
        return {
            'position_bias_m': _r(u(1, 30)),
            'position_drift_rate_m_s': _r(u(0.01, 0.3), 4),
            'velocity_bias_m_s': _r(u(0.005, 0.1), 4),
        }
    if model == 'separate_velocity':
        return {
            'position_drift_m': _r(u(5, 40)),
            'velocity_drift_m_s': _r(u(0.02, 0.2), 4),
            'velocity_markov_m_s': _r(u(0.01, 0.2), 4),
            'velocity_markov_tau_s': _r(u(5, 100), 1),
        }
    if model == 'time_skew':
        return {
            'position_delay_s': _r(u(0.02, 0.1), 4),
            'velocity_delay_s': _r(u(-0.05, 0.05), 4),
        }
    if model == 'jumps':
        return {'jump_rate_hz': _r(u(0.01, 0.05), 4), 'jump_sigma_m': _r(u(2, 20))}
    if model == 'quantised':
        return {
            'position_quantum_m': float(rng.choice([0.5, 1.0, 2.0])),
            'velocity_quantum_m_s': float(rng.choice([0.05, 0.1])),
        }
    return {}


def _elevations(site: FloatArray, target: FloatArray) -> FloatArray:
    lat, lon, _ = frames.ecef_to_geodetic(site)
    up = frames.enu_rotation(lat, lon)[:, 2]
    d = target - site
    return np.asarray(np.degrees(np.arcsin(d @ up / np.linalg.norm(d, axis=1))))


def _describe_telemetry(tel: dict[str, Any] | None) -> str:
    if tel is None:
        return 'no telemetry'
    extra = ', '.join(
        f'{k} {v:g}'
        for k, v in tel.items()
        if k not in ('kind', 'rate_hz', 'first_epoch', 'outages', 'error_model')
    )
    outages = ', '.join(f'{o["start"]:g}-{o["end"]:g}' for o in tel['outages']) or 'none'
    return (
        f'telemetry {tel["kind"]} {tel["rate_hz"]:g} Hz, {tel["error_model"]} ({extra}), '
        f'outages {outages}'
    )


# -- ascent --------------------------------------------------------------------------------


def _ascent_vehicle(
    rng: np.random.Generator, span: float, n_events: int
) -> tuple[dict[str, Any], list[float]]:
    """Stages and pitch program with ``n_events`` staging events inside [0, span]."""
    pre = rng.uniform(20.0, 70.0)  # lift-off this long before the span starts
    if n_events == 1:
        sep = [rng.uniform(0.15, 0.55) * span]
    else:
        e1 = rng.uniform(0.1, 0.4) * span
        sep = [e1, e1 + rng.uniform(15.0, max(16.0, 0.5 * span))]
    coasts = [0.0 if rng.random() < 0.2 else rng.uniform(0.3, 4.0) for _ in sep]
    m1 = rng.uniform(80e3, 160e3)
    ve1 = rng.uniform(2400.0, 2900.0)
    burn1 = pre + sep[0]
    tw1 = rng.uniform(1.25, min(1.8, 0.8 * ve1 / (_G0 * burn1)))
    flow1 = tw1 * m1 * _G0 / ve1
    stages = [
        {
            'mass_kg': _r(m1, 1),
            'propellant_kg': _r(flow1 * burn1, 1),
            'mass_flow_kg_s': _r(flow1, 3),
            'exhaust_speed_m_s': _r(ve1, 1),
        }
    ]
    dry = m1 - stages[0]['propellant_kg']
    for k in range(len(sep)):
        mk = dry * rng.uniform(0.55, 0.8)
        ve = rng.uniform(2900.0, 3400.0)
        tw = rng.uniform(0.9, 1.6)
        ignition = sep[k] + coasts[k]
        burn = (sep[k + 1] - ignition) if k + 1 < len(sep) else (span - ignition + 20.0)
        flow = min(tw * mk * _G0 / ve, 0.85 * mk / burn)
        stages.append(
            {
                'mass_kg': _r(mk, 1),
                'propellant_kg': _r(flow * burn, 1),
                'mass_flow_kg_s': _r(flow, 3),
                'exhaust_speed_m_s': _r(ve, 1),
                'coast_before_s': _r(coasts[k], 3),
            }
        )
        dry = mk - stages[-1]['propellant_kg']
    pitch = [
        [0.0, 90.0],
        [_r(rng.uniform(5.0, 12.0), 2), 90.0],
        [_r(rng.uniform(50.0, 70.0), 2), _r(rng.uniform(45.0, 60.0), 2)],
        [_r(rng.uniform(150.0, 200.0), 2), _r(rng.uniform(15.0, 35.0), 2)],
    ]
    target = {
        'id': 0,
        'model': 'powered_ascent',
        'liftoff_time': _r(-pre, 3),
        'stages': stages,
        'pitch_program_deg': pitch,
        'cd_area_m2': _r(rng.uniform(1.0, 5.0), 2),
    }
    return target, sep


def _ascent_truth(data: dict[str, Any]) -> tuple[dynamics.PoweredAscent, FloatArray, FloatArray]:
    """The ascent's truth and its states (m, 6) on a 1 s grid over the span."""
    la = data['launch']
    t = data['targets'][0]
    veh = dynamics.PoweredAscent(
        np.radians(la['latitude_deg']),
        np.radians(la['longitude_deg']),
        la['height_m'],
        np.radians(la['azimuth_deg']),
        liftoff_time=t['liftoff_time'],
        t_end=data['span'][1],
        stages=[dynamics.Stage(**st) for st in t['stages']],
        pitch_program=np.column_stack(
            [
                [p[0] for p in t['pitch_program_deg']],
                np.radians([p[1] for p in t['pitch_program_deg']]),
            ]
        ),
        cd_area_m2=t['cd_area_m2'],
    )
    grid = np.linspace(data['span'][0], data['span'][1], int(data['span'][1]) + 1)
    return veh, grid, veh.state(grid)


def _ascent_plausible(states: FloatArray) -> bool:
    _, _, h = frames.ecef_to_geodetic(states[:, :3])
    speed = np.linalg.norm(states[:, 3:], axis=1)
    return bool(h.min() > 500.0 and np.all(np.diff(h) > 0.0) and speed.min() > 50.0)


def _segments(
    rng: np.random.Generator, span: float, events: Sequence[float]
) -> list[tuple[float, float, str]]:
    """0-2 incomplete segments (10-30 s): over an event, across a window edge, at the very
    start or anywhere; they do not overlap."""
    n = int(rng.choice([0, 1, 2], p=[0.25, 0.5, 0.25]))
    out: list[tuple[float, float, str]] = []
    for _ in range(n):
        for _try in range(20):
            length = rng.uniform(10.0, 30.0)
            where = str(rng.choice(['event', 'window_edge', 'start', 'anywhere']))
            if where == 'event' and events:
                start = float(rng.choice(np.asarray(events))) - rng.uniform(0.2, 0.8) * length
            elif where == 'window_edge' and span > _WINDOW_EDGES[0] + 5.0:
                edges = [e for e in _WINDOW_EDGES if e < span - 5.0]
                start = float(rng.choice(edges)) - rng.uniform(0.2, 0.8) * length
            elif where == 'start':
                start = 0.0
            else:
                where = 'anywhere'
                start = rng.uniform(0.0, span - length)
            a, b = _r(max(start, 0.0)), _r(min(start + length, span))
            if b - a >= 5.0 and all(b < s[0] - 5.0 or a > s[1] + 5.0 for s in out):
                out.append((a, b, where))
                break
    return sorted(out)


def _ascent_station(
    rng: np.random.Generator,
    sid: str,
    kind: str,
    launch: dict[str, float],
    states: FloatArray,
    span: float,
) -> dict[str, Any]:
    lat0, lon0 = np.radians(launch['latitude_deg']), np.radians(launch['longitude_deg'])
    origin = frames.geodetic_to_ecef(lat0, lon0, launch['height_m'])
    rot = frames.launch_rotation(lat0, lon0, np.radians(launch['azimuth_deg']))
    downrange_end = float(((states[-1, :3] - origin) @ rot)[0])
    mask = _r(rng.uniform(0.0, 5.0), 2)
    best: tuple[float, dict[str, float]] = (-1.0, {})
    for _ in range(_MAX_TRIES):
        d = rng.uniform(-20e3, downrange_end + 30e3)
        c = rng.choice([-1.0, 1.0]) * rng.uniform(10e3, 150e3)
        p = origin + rot @ np.array([d, 0.0, c])
        lat, lon, _ = frames.ecef_to_geodetic(p)
        height = rng.uniform(0.0, 2000.0)
        site_d = {
            'latitude_deg': _r(float(np.degrees(lat)), 6),
            'longitude_deg': _r(float(np.degrees(lon)), 6),
            'height_m': _r(height, 1),
        }
        site = frames.geodetic_to_ecef(lat, lon, height)
        seen = float(np.mean(_elevations(site, states[:, :3]) >= mask))
        if seen > best[0]:
            best = (seen, site_d)
        if seen >= 0.6:
            break
    rate = float(rng.choice([5.0, 10.0, 20.0, 25.0, 50.0]))
    return {
        'id': sid,
        'kind': kind,
        'platform': {'type': 'fixed', **best[1]},
        'rate_hz': rate,
        'first_epoch': _r(rng.uniform(0.0, 1.0 / rate), 4),
        'sigma': _station_sigma(rng, kind, ship=False),
        'elevation_mask_deg': mask,
        'gross_errors': _gross(rng),
        'dropouts': _dropouts(rng, span),
    }


def _ascent(
    rng: np.random.Generator, seed: int, span_s: float | None, forced: str | None = None
) -> Draw:
    span = _r(rng.uniform(60.0, 120.0), 1)
    span = span if span_s is None else float(span_s)
    launch = {
        'latitude_deg': _r(rng.uniform(-60.0, 60.0), 4),
        'longitude_deg': _r(rng.uniform(-180.0, 180.0), 4),
        'height_m': _r(rng.uniform(0.0, 2000.0), 1),
        'azimuth_deg': _r(rng.uniform(0.0, 360.0), 2),
    }
    data: dict[str, Any] = {
        'name': f'ascent_{seed:05d}',
        'world_frame': 'earth',
        'span': [0.0, span],
        'random_seed': seed,
        'truth_rate_hz': 20.0,
        'launch': launch,
    }
    n_events = int(rng.integers(1, 3))
    for _ in range(_MAX_TRIES):
        target, _sep = _ascent_vehicle(rng, span, n_events)
        data['targets'] = [target]
        _, _grid, states = _ascent_truth(data)
        if _ascent_plausible(states):
            break
    else:
        raise RuntimeError(f'ascent seed {seed}: no plausible vehicle in {_MAX_TRIES} draws')
    has_tel = rng.random() < 0.85 or forced is not None
    n_st = int(rng.integers(3, 13))
    kinds = list(rng.choice(['cw_radar', 'optical', 'pulse_radar'], n_st, p=[0.45, 0.35, 0.2]))
    if not has_tel:  # the rough trajectory is then triangulated: two stations need angles
        while sum(k != 'cw_radar' for k in kinds) < 2:
            kinds[kinds.index('cw_radar')] = 'optical'
    stations = []
    count = {'cw_radar': 0, 'optical': 0, 'pulse_radar': 0}
    prefix = {'cw_radar': 'cw', 'optical': 'opt', 'pulse_radar': 'pr'}
    for kind in kinds:
        count[kind] += 1
        sid = f'{prefix[kind]}{count[kind]:02d}'
        stations.append(_ascent_station(rng, sid, kind, launch, states, span))
    scratch = scenario_from_dict({**data, 'stations': [{**s} for s in stations]}, 'draw')
    events = acceleration_jumps(scratch)
    segments = _segments(rng, span, events)
    who: list[tuple[str, ...]] = []
    for a, b, _where in segments:
        k = int(rng.integers(1, 3))
        keep = tuple(sorted(str(s) for s in rng.choice([s['id'] for s in stations], k, False)))
        who.append(keep)
        for s in stations:
            if s['id'] not in keep:
                s['dropouts'] = [*s['dropouts'], {'start': a, 'end': b}]
    data['stations'] = stations
    data['evaluation'] = {
        'gaps': [{'start': a, 'end': b} for a, b, _ in segments],
        'output_step_s': 0.1,
    }
    tel = None
    if has_tel:
        rate = float(rng.choice([5.0, 10.0, 20.0]))
        model = str(rng.choice(TELEMETRY_MODELS))
        model = forced or model
        outages = []
        for _ in range(int(rng.integers(0, 3))):
            length = rng.uniform(2.0, 15.0)
            start = rng.uniform(0.0, span - length)
            outages.append({'start': _r(start), 'end': _r(start + length)})
        tel = {
            'kind': 'drift',
            'error_model': model,
            'rate_hz': rate,
            'first_epoch': _r(rng.uniform(0.0, 1.0 / rate), 4),
            'position_sigma_m': _r(_log_uniform(rng, 0.5, 3.0), 3),
            'velocity_sigma_m_s': _r(_log_uniform(rng, 0.01, 0.05), 4),
            **_telemetry_errors(rng, model, span),
            'outages': outages,
        }
        data['telemetry'] = tel
    kinds_txt = ', '.join(f'{v} {k}' for k, v in count.items() if v)
    seg_txt = (
        '; '.join(
            f'{a:g}-{b:g} s ({where}; {" ".join(w)} measure)'
            for (a, b, where), w in zip(segments, who, strict=True)
        )
        or 'none'
    )
    summary = (
        f'ascent seed {seed}: span {span:g} s, launch {launch["latitude_deg"]:.2f}, '
        f'{launch["longitude_deg"]:.2f} az {launch["azimuth_deg"]:.1f}; events '
        f'{", ".join(f"{e:.2f}" for e in events)} s; {n_st} stations ({kinds_txt}); '
        f'incomplete segments {seg_txt}; {_describe_telemetry(tel)}'
    )
    data['description'] = summary
    sc = scenario_from_dict(data, f'family ascent seed {seed}')
    return Draw(
        'ascent',
        seed,
        sc,
        events,
        jerk_jumps(sc),
        tuple((a, b) for a, b, _ in segments),
        tuple(who),
        None if tel is None else str(tel['error_model']),
        summary,
    )


# -- aircraft ------------------------------------------------------------------------------


def _aircraft_legs(
    rng: np.random.Generator, span: float, speed: float
) -> tuple[list[dict[str, Any]], list[tuple[float, float]]]:
    """Straight legs (some with a climb or descent) and 2-3 g turns until the span is
    covered; returns the legs and the turns' (start, end) times."""
    legs: list[dict[str, Any]] = []
    turns: list[tuple[float, float]] = []
    t = 0.0
    while t < span + 10.0:
        straight = rng.uniform(15.0, 50.0)
        if rng.random() < 0.3 and straight > 20.0:
            rate = float(rng.choice([-1.0, 1.0])) * _r(rng.uniform(0.5, 1.0), 2)
            hold = straight - 12.0
            legs += [
                {'duration_s': 6.0, 'path_angle_rate_deg_s': rate},
                {'duration_s': _r(hold, 2)},
                {'duration_s': 6.0, 'path_angle_rate_deg_s': -rate},
            ]
        else:
            legs.append({'duration_s': _r(straight, 2)})
        t = sum(leg['duration_s'] for leg in legs)
        if t >= span + 10.0:
            break
        n = rng.uniform(2.0, 3.0)
        turn_rate = _G0 * np.sqrt(n * n - 1.0) / speed
        duration = np.radians(rng.uniform(60.0, 200.0)) / turn_rate
        legs.append(
            {
                'duration_s': _r(duration, 2),
                'load_factor': _r(n, 3),
                'turn': str(rng.choice(['left', 'right'])),
            }
        )
        turns.append((t, t + legs[-1]['duration_s']))
        t += legs[-1]['duration_s']
    return legs, turns


def _offset(lat_deg: float, lon_deg: float, east_m: float, north_m: float) -> tuple[float, float]:
    """Latitude and longitude [deg] of a point ``east_m``, ``north_m`` from a sea-level one."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    p = frames.geodetic_to_ecef(lat, lon, 0.0) + frames.enu_rotation(lat, lon) @ np.array(
        [east_m, north_m, 0.0]
    )
    la, lo, _ = frames.ecef_to_geodetic(p)
    return float(np.degrees(la)), float(np.degrees(lo))


def _ship(
    rng: np.random.Generator, sid: str, lat: float, lon: float, span: float
) -> dict[str, Any]:
    legs: list[dict[str, Any]] = [{'duration_s': _r(span + 20.0, 2)}]
    if rng.random() < 0.3:  # one slow turn
        first = rng.uniform(0.3, 0.6) * span
        legs = [
            {'duration_s': _r(first, 2)},
            {
                'duration_s': 60.0,
                'load_factor': 1.0005,
                'turn': str(rng.choice(['left', 'right'])),
            },
            {'duration_s': _r(span - first + 20.0, 2)},
        ]
    return {
        'id': sid,
        'start': {'latitude_deg': _r(lat, 6), 'longitude_deg': _r(lon, 6), 'height_m': 0.0},
        'speed_m_s': _r(rng.uniform(4.0, 12.0), 2),
        'heading_deg': _r(rng.uniform(0.0, 360.0), 2),
        'legs': legs,
        'attitude': {
            'roll_amplitude_deg': _r(rng.uniform(2.0, 6.0), 2),
            'roll_period_s': _r(rng.uniform(7.0, 13.0), 2),
            'pitch_amplitude_deg': _r(rng.uniform(0.5, 3.0), 2),
            'pitch_period_s': _r(rng.uniform(5.0, 10.0), 2),
            'yaw_amplitude_deg': _r(rng.uniform(0.2, 1.0), 2),
            'yaw_period_s': _r(rng.uniform(8.0, 16.0), 2),
        },
    }


def _ship_sensors(
    rng: np.random.Generator, ship: str, index: int, need_radar: bool, span: float
) -> list[dict[str, Any]]:
    radar = need_radar or rng.random() < 0.85
    eo = rng.random() < 0.7 or not radar
    out = []
    if radar:
        rate = float(rng.choice([5.0, 10.0, 20.0]))
        out.append(
            {
                'id': f'radar{index}',
                'kind': 'pulse_radar',
                'platform': {
                    'type': 'ship',
                    'ship': ship,
                    'lever_arm_m': [
                        _r(rng.uniform(-20, 20), 2),
                        _r(rng.uniform(-20, 20), 2),
                        _r(rng.uniform(10, 25), 2),
                    ],
                },
                'rate_hz': rate,
                'first_epoch': _r(rng.uniform(0.0, 1.0 / rate), 4),
                'sigma': _station_sigma(rng, 'pulse_radar', ship=True),
                'elevation_mask_deg': _r(rng.uniform(0.0, 2.0), 2),
                'max_range_m': 120000.0,
                'gross_errors': _gross(rng),
                'dropouts': _dropouts(rng, span),
            }
        )
    if eo:
        rate = float(rng.choice([10.0, 25.0, 50.0]))
        out.append(
            {
                'id': f'eo{index}',
                'kind': 'optical',
                'platform': {
                    'type': 'ship',
                    'ship': ship,
                    'lever_arm_m': [
                        _r(rng.uniform(-20, 20), 2),
                        _r(rng.uniform(-20, 20), 2),
                        _r(rng.uniform(10, 25), 2),
                    ],
                },
                'rate_hz': rate,
                'first_epoch': _r(rng.uniform(0.0, 1.0 / rate), 4),
                'sigma': _station_sigma(rng, 'optical', ship=True),
                'elevation_mask_deg': _r(rng.uniform(0.5, 2.0), 2),
                'max_range_m': _r(rng.uniform(20e3, 40e3), 0),
                'gross_errors': _gross(rng),
                'dropouts': _dropouts(rng, span),
            }
        )
    return out


def _radar_coverage(data: dict[str, Any]) -> float:
    """Share of the span (1 s grid) in which some pulse radar sees the aircraft (mask and
    range only; ship motion from its track, attitude and lever arm ignored)."""
    sc = scenario_from_dict(data, 'draw')
    aircraft = build_targets(sc)[0]
    ships = build_platform_tracks(sc)
    grid = np.arange(sc.t_start, sc.t_end, 1.0)
    x = aircraft.state(grid)
    _, _, h = frames.ecef_to_geodetic(x[:, :3])
    if h.min() < 300.0 or h.max() > 15000.0:
        return 0.0
    seen = np.zeros(grid.size, dtype=bool)
    for st in sc.stations:
        if st.kind != 'pulse_radar':
            continue
        site = ships[st.platform['ship']].state(grid)[:, :3]
        d = x[:, :3] - site
        rng_ok = np.linalg.norm(d, axis=1) <= (st.max_range_m or np.inf)
        lat, lon, _ = frames.ecef_to_geodetic(site)
        up = frames.enu_rotation(lat, lon)[..., 2]
        elev = np.degrees(np.arcsin(np.einsum('mi,mi->m', d, up) / np.linalg.norm(d, axis=1)))
        seen |= rng_ok & (elev >= (st.elevation_mask_deg or 0.0))
    return float(np.mean(seen))


def _aircraft(
    rng: np.random.Generator, seed: int, span_s: float | None, forced: str | None = None
) -> Draw:
    span = _r(rng.uniform(120.0, 300.0), 1)
    span = span if span_s is None else float(span_s)
    lat0, lon0 = rng.uniform(-50.0, 50.0), rng.uniform(-180.0, 180.0)
    n_ships = 2 if rng.random() < 0.3 else 1
    for _ in range(_MAX_TRIES):
        ships = [_ship(rng, 'ship1', lat0, lon0, span)]
        if n_ships == 2:
            dist, brg = rng.uniform(10e3, 40e3), rng.uniform(0.0, 2.0 * np.pi)
            la, lo = _offset(lat0, lon0, dist * np.sin(brg), dist * np.cos(brg))
            ships.append(_ship(rng, 'ship2', la, lo, span))
        stations = []
        for k, sh in enumerate(ships):
            stations += _ship_sensors(rng, sh['id'], k + 1, need_radar=k == 0, span=span)
        speed = rng.uniform(150.0, 280.0)
        dist, brg = rng.uniform(15e3, 50e3), rng.uniform(0.0, 360.0)
        la, lo = _offset(
            lat0, lon0, dist * np.sin(np.radians(brg)), dist * np.cos(np.radians(brg))
        )
        legs, turns = _aircraft_legs(rng, span, speed)
        target: dict[str, Any] = {
            'id': 0,
            'model': 'aircraft',
            'start': {
                'latitude_deg': _r(la, 6),
                'longitude_deg': _r(lo, 6),
                'height_m': _r(rng.uniform(2000.0, 8000.0), 1),
            },
            'speed_m_s': _r(speed, 2),
            'heading_deg': _r((brg + 180.0 + rng.uniform(-60.0, 60.0)) % 360.0, 2),
            'transition_s': _r(rng.uniform(1.0, 3.0), 2),
            'legs': legs,
        }
        data: dict[str, Any] = {
            'name': f'aircraft_{seed:05d}',
            'world_frame': 'earth',
            'span': [0.0, span],
            'random_seed': seed,
            'truth_rate_hz': 20.0,
            'platforms': ships,
            'targets': [target],
            'stations': stations,
        }
        if _radar_coverage(data) >= 0.6:
            break
    else:
        raise RuntimeError(
            f'aircraft seed {seed}: no draw seen by the radar in {_MAX_TRIES} tries'
        )
    turns = [(a, b) for a, b in turns if a < span]
    rate = float(rng.choice([1.0, 2.0, 5.0]))
    model = forced or str(rng.choice(TELEMETRY_MODELS))
    outages: list[list[float]] = []
    if turns:
        k = min(len(turns), int(rng.integers(1, 4)))
        for i in sorted(rng.choice(len(turns), k, replace=False)):
            a, b = turns[int(i)]
            lo_t, hi_t = (
                _r(max(a - rng.uniform(0, 10), 0.0)),
                _r(min(b + rng.uniform(0, 10), span)),
            )
            if outages and lo_t <= outages[-1][1]:
                outages[-1][1] = max(outages[-1][1], hi_t)
            elif hi_t > lo_t:
                outages.append([lo_t, hi_t])
    tel = {
        'kind': 'gps',
        'error_model': model,
        'rate_hz': rate,
        'first_epoch': _r(rng.uniform(0.0, 1.0 / rate), 4),
        'position_sigma_m': _r(_log_uniform(rng, 1.0, 5.0), 3),
        'velocity_sigma_m_s': _r(_log_uniform(rng, 0.03, 0.2), 4),
        **_telemetry_errors(rng, model, span),
        'outages': [{'start': a, 'end': b} for a, b in outages],
    }
    data['telemetry'] = tel
    data['evaluation'] = {'gaps': tel['outages'], 'output_step_s': 0.1}
    sensors = ', '.join(f'{s["id"]} on {s["platform"]["ship"]}' for s in stations)
    n_turns = sum(1 for leg in legs if 'turn' in leg)
    summary = (
        f'aircraft seed {seed}: span {span:g} s, {speed:.0f} m/s, {n_turns} turns of '
        f'2-3 g; {n_ships} ship(s), sensors {sensors}; {_describe_telemetry(tel)}'
    )
    data['description'] = summary
    sc = scenario_from_dict(data, f'family aircraft seed {seed}')
    return Draw(
        'aircraft',
        seed,
        sc,
        (),
        jerk_jumps(sc),
        tuple((a, b) for a, b in outages),
        (),
        model,
        summary,
    )
