"""Randomised scenario families (orbit_tracking.core.sim.families): a draw is a validated
scenario, determined by its seed, and holds what it claims (stations, incomplete segments
with only the named stations measuring, staging events where the truth's acceleration
jumps, telemetry model, GPS outages over the aircraft's turns)."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from orbit_tracking.core.sim.families import KINDS, Draw, draw, draw_scenario
from orbit_tracking.core.sim.scenario import Scenario
from orbit_tracking.core.sim.simulator import SimulationResult, World, simulate
from orbit_tracking.core.sim.telemetry import ERROR_MODELS


@cache
def _draw(kind: str, seed: int) -> Draw:
    return draw(kind, seed)


@cache
def _sim(kind: str, seed: int) -> tuple[World, SimulationResult]:
    sc = _draw(kind, seed).scenario
    world = World(sc)
    return world, simulate(sc, world)


@pytest.mark.parametrize('kind', KINDS)
def test_a_draw_is_determined_by_its_seed(kind: str):
    a, b = draw(kind, 3), draw(kind, 3)
    assert a.scenario == b.scenario and a.summary == b.summary
    _, ra = _sim(kind, 3)
    rb = simulate(b.scenario)
    for sid, table in ra.measurements.items():
        np.testing.assert_array_equal(table.values, rb.measurements[sid].values)


@pytest.mark.parametrize('kind', KINDS)
def test_different_seeds_draw_different_scenarios(kind: str):
    assert len({draw(kind, s).summary for s in range(6)}) == 6


def test_unknown_family_and_bad_seed_are_refused():
    with pytest.raises(ValueError, match='family'):
        draw('balloon', 0)
    with pytest.raises(ValueError, match='seed'):
        draw('ascent', -1)


@pytest.mark.parametrize('seed', range(12))
def test_ascent_draws_stay_in_their_documented_ranges(seed: int):
    d = _draw('ascent', seed)
    sc = d.scenario
    assert isinstance(sc, Scenario) and sc.name == f'ascent_{seed:05d}'
    assert 60.0 <= sc.t_end - sc.t_start <= 120.0
    assert 3 <= len(sc.stations) <= 12
    assert {s.kind for s in sc.stations} <= {'cw_radar', 'pulse_radar', 'optical'}
    assert 2 <= len(d.events) <= 4  # one or two staging events, each burnout (+ ignition)
    assert len(d.segments) <= 2 and sc.gaps == d.segments
    for st in sc.stations:
        assert st.gross_errors['count'] <= 5
        assert st.elevation_mask_deg is not None and 0.0 <= st.elevation_mask_deg <= 5.0
        assert st.rate_hz in (5.0, 10.0, 20.0, 25.0, 50.0)
    if sc.telemetry is None:
        assert d.telemetry_model is None
        assert sum(s.kind != 'cw_radar' for s in sc.stations) >= 2
    else:
        assert sc.telemetry.error_model == d.telemetry_model
        assert d.telemetry_model in ERROR_MODELS and d.telemetry_model != 'none'
    assert f'{len(sc.stations)} stations' in d.summary


@pytest.mark.parametrize('seed', [0, 4, 5])
def test_only_the_claimed_stations_measure_in_an_incomplete_segment(seed: int):
    d = _draw('ascent', seed)
    assert d.segments, 'these seeds draw incomplete segments'
    _, result = _sim('ascent', seed)
    for (a, b), who in zip(d.segments, d.segment_stations, strict=True):
        assert 1 <= len(who) <= 2
        inside = {
            sid
            for sid, tab in result.measurements.items()
            if np.any((tab.time > a + 1e-6) & (tab.time < b - 1e-6))
        }
        assert inside <= set(who), (a, b, inside, who)


@pytest.mark.parametrize('seed', [0, 1])
def test_staging_events_are_where_the_truth_acceleration_jumps(seed: int):
    d = _draw('ascent', seed)
    world, _ = _sim('ascent', seed)
    traj = world.targets[0]
    eps = 1e-4
    for e in d.events:
        jump = traj.acceleration(np.array([e + eps]))[0] - traj.acceleration(np.array([e - eps]))
        assert np.linalg.norm(jump) > 1.0, e
    # and nowhere else on a grid that avoids them
    t = np.arange(1.0, d.scenario.t_end - 1.0, 0.5)
    t = t[np.min(np.abs(t[:, None] - np.asarray(d.events)[None, :]), axis=1) > 0.1]
    da = np.linalg.norm(traj.acceleration(t + eps) - traj.acceleration(t - eps), axis=1)
    assert da.max() < 0.01


@pytest.mark.parametrize('seed', range(8))
def test_aircraft_draws_have_gps_with_outages_over_turns(seed: int):
    d = _draw('aircraft', seed)
    sc = d.scenario
    assert 120.0 <= sc.t_end - sc.t_start <= 300.0
    assert sc.telemetry is not None and sc.telemetry.kind == 'gps'
    assert any(s.kind == 'pulse_radar' for s in sc.stations)
    assert all(s.platform['type'] == 'ship' for s in sc.stations)
    turns = []
    t = 0.0
    for leg in sc.targets[0]['legs']:
        if leg['turn'] != 'none':
            assert 2.0 <= leg['load_factor'] <= 3.0
            turns.append((t, t + leg['duration_s']))
        t += leg['duration_s']
    assert sc.gaps == d.segments
    for a, b in d.segments:
        assert any(a <= tb and b >= ta for ta, tb in turns), (a, b, turns)


def test_draw_scenario_is_the_scenario_of_the_draw():
    assert draw_scenario('aircraft', 2) == _draw('aircraft', 2).scenario
