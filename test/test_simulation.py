"""Statistical and structural tests of the scenario simulator on the core arrays:
normalised residuals against the truth, epochs, dropouts, gaps, masks and seeding."""

from __future__ import annotations

import dataclasses
from functools import cache
from pathlib import Path

import numpy as np
import pytest
import yaml

from orbit_tracking.core import frames
from orbit_tracking.core.data.tables import StationStates
from orbit_tracking.core.models.measurements import StationPose, predict, residual
from orbit_tracking.core.models.systematic import BiasModel
from orbit_tracking.core.sim.scenario import Scenario, load_scenario
from orbit_tracking.core.sim.simulator import SimulationResult, World, simulate

# Noise statistics pool runs of the scenario over consecutive seeds (its own first) until
# every station and field has N_MIN points: the sample std of n standard normals spreads by
# 1/sqrt(2n), so a 5 % bound is then a 4-sigma bound and the test does not hinge on one draw.
N_MIN = 3200


@cache
def _world(name: str) -> tuple[Scenario, World]:
    sc = load_scenario(name)
    return sc, World(sc)


@cache
def _result(name: str, seed_offset: int = 0) -> SimulationResult:
    sc, world = _world(name)
    if seed_offset:
        sc = dataclasses.replace(sc, random_seed=sc.random_seed + seed_offset)
    return simulate(sc, world)


def _run(name: str) -> tuple[Scenario, World, SimulationResult]:
    sc, world = _world(name)
    return sc, world, _result(name)


def _poses_at(states: StationStates, time: np.ndarray) -> StationPose:
    """Station poses at measurement epochs, taken from the published station states."""
    if not states.moving:
        return StationPose.fixed(states.position[0], states.rotation[0], len(time))
    idx = np.clip(np.searchsorted(states.time, time), 0, len(states) - 1)
    np.testing.assert_allclose(states.time[idx], time, rtol=0.0, atol=1e-9)
    return StationPose(states.position[idx], states.velocity[idx], states.rotation[idx])


def _truth_at(
    world: World, target_id: np.ndarray, time: np.ndarray, clock_bias: float
) -> np.ndarray:
    out = np.empty((len(time), 6))
    for tid in np.unique(target_id):
        sel = target_id == tid
        out[sel] = world.target_state(int(tid), time[sel] + clock_bias)
    return out


def _predictions(result: SimulationResult, world: World, station_id: str) -> np.ndarray:
    """h(truth) at the measurement epochs from the station poses the result publishes."""
    st = result.scenario.station(station_id)
    table = result.measurements[station_id]
    assert table.fields == st.fields
    np.testing.assert_array_equal(table.sigmas, np.tile(st.sigmas, (len(table), 1)))
    truth = _truth_at(world, table.target_id, table.time, st.clock_bias_s)
    predicted, _ = predict(
        st.fields, truth, _poses_at(result.station_states[station_id], table.time)
    )
    return predicted


def _normalised_residuals(
    result: SimulationResult, world: World, station_id: str, bias: str = 'keep'
) -> np.ndarray:
    """(measured - h(truth)) / sigma; ``bias`` 'remove' applies BiasModel.remove to the
    measurements, 'apply' applies the bias model to the predictions."""
    st = result.scenario.station(station_id)
    table = result.measurements[station_id]
    predicted = _predictions(result, world, station_id)
    measured = table.values
    if bias == 'remove':
        measured = BiasModel(st.bias).remove(st.fields, measured)
    elif bias == 'apply':
        predicted = BiasModel(st.bias).apply(st.fields, predicted)
    return residual(st.fields, measured, predicted) / table.sigmas


def _pooled_residuals(name: str, station_id: str, bias: str = 'keep') -> np.ndarray:
    _, world = _world(name)
    runs: list[np.ndarray] = []
    for k in range(50):
        runs.append(_normalised_residuals(_result(name, k), world, station_id, bias))
        z = np.concatenate(runs)
        if np.min(np.sum(np.isfinite(z), axis=0)) >= N_MIN:
            return z
    raise AssertionError(f'{name} {station_id}: fewer than {N_MIN} points in 50 runs')


def _assert_standard_normal(label: str, fields: tuple[str, ...], z: np.ndarray) -> None:
    for j, f in enumerate(fields):
        col = z[:, j][np.isfinite(z[:, j])]
        n = col.size
        assert n >= N_MIN, f'{label} {f}: only {n} points'
        assert abs(col.mean()) <= 4.0 / np.sqrt(n), f'{label} {f}: mean {col.mean():.4f}'
        assert abs(col.std(ddof=1) - 1.0) <= 0.05, f'{label} {f}: std {col.std(ddof=1):.4f}'


def _station_cases(names: list[str]) -> list[tuple[str, str]]:
    return [(n, st.id) for n in names for st in load_scenario(n).stations]


# --------------------------------------------------------------------------- noise statistics


@pytest.mark.parametrize(
    ('name', 'station_id'), _station_cases(['seed000_s1', 'seed003_q2', 'seed004_sea'])
)
def test_simulated_measurements_minus_truth_are_white_noise_of_the_stated_sigma(
    name: str, station_id: str
) -> None:
    sc, _ = _world(name)
    assert not sc.station(station_id).bias
    z = _pooled_residuals(name, station_id)
    _assert_standard_normal(f'{name} {station_id}', sc.station(station_id).fields, z)


@pytest.mark.parametrize(('name', 'station_id'), _station_cases(['seed003_q3', 'seed000_s1_bias']))
def test_biased_measurements_are_white_noise_after_removing_the_bias(
    name: str, station_id: str
) -> None:
    sc, world = _world(name)
    st = sc.station(station_id)
    _assert_standard_normal(
        f'{name} {station_id}', st.fields, _pooled_residuals(name, station_id, 'remove')
    )
    # equivalently: measured minus the bias model applied to the predictions
    _assert_standard_normal(
        f'{name} {station_id}', st.fields, _pooled_residuals(name, station_id, 'apply')
    )
    # and the bias is really there: without removing it the offset fields are off
    raw = _normalised_residuals(_result(name), world, station_id)
    for j, f in enumerate(st.fields):
        col = raw[:, j][np.isfinite(raw[:, j])]
        if f in st.bias:
            assert abs(col.mean()) > 10.0 / np.sqrt(col.size), f'{station_id} {f}'


def test_bias_scenarios_bias_the_stations_the_spec_names() -> None:
    q3, _ = _world('seed003_q3')
    assert dict(q3.station('sat06').bias) == {
        'los_alpha': 2.89e-4,
        'los_beta': 3.23e-4,
        'los_theta': -3.46e-4,
    }
    assert dict(q3.station('sat09').bias) == {
        'los_alpha': -3.51e-4,
        'los_beta': 4.70e-4,
        'los_theta': 4.68e-4,
    }
    s1b, _ = _world('seed000_s1_bias')
    assert {s.id for s in s1b.stations if s.bias} == {'cw02', 'cw05', 'cw08', 'opt01', 'opt03'}


# --------------------------------------------------------------------------- epochs and coverage


def test_seed003_q2_satellites_measure_every_0_2_s_from_their_first_epochs() -> None:
    _, _, result = _run('seed003_q2')
    for sid, first in (('sat06', 50.1812), ('sat09', 50.3754)):
        t = result.measurements[sid].time
        assert t[0] == pytest.approx(first, abs=1e-9)
        np.testing.assert_allclose(np.diff(t), 0.2, rtol=0.0, atol=1e-9)
        assert 169.8 < t[-1] <= 170.0
        assert np.all(result.measurements[sid].target_id == 0)


def test_seed003_q2_satellite_states_are_the_seed_orbits_at_the_measurement_epochs() -> None:
    _, _, result = _run('seed003_q2')
    states = result.station_states['sat09']
    assert states.moving
    np.testing.assert_allclose(states.time, result.measurements['sat09'].time, atol=1e-12)
    k = int(np.argmin(np.abs(states.time - 50.3754)))
    # SCENARIOS.md: satellite 09 near (1.7738e6, 8.1614e6, 4.5167e6) m at 50 s; 0.3754 s later
    expected = np.array([1.773806e6, 8.161384e6, 4.516700e6])
    assert np.linalg.norm(states.position[k] - expected - 0.3754 * states.velocity[k]) < 5.0
    np.testing.assert_allclose(
        states.rotation, frames.observation_rotation(states.position), atol=1e-15
    )


@pytest.mark.parametrize('name', ['seed000_s1', 'seed000_s2', 'seed004_sea'])
def test_no_measurement_lies_in_a_dropout_window(name: str) -> None:
    sc, _, result = _run(name)
    windows = 0
    for st in sc.stations:
        table = result.measurements[st.id]
        for w in st.dropouts:
            windows += 1
            inside = (table.time >= w['start']) & (table.time <= w['end'])
            if w['fields'] is None:
                assert not np.any(inside), f'{st.id} measures in {w}'
                # the window is not wider than configured: the sensor measures either side
                dt = 1.0 / st.rate_hz
                near = np.abs(table.time - w['start']) < 2 * dt
                near |= np.abs(table.time - w['end']) < 2 * dt
                assert np.any(near)
            else:
                cols = [st.fields.index(f) for f in w['fields']]
                assert np.all(np.isnan(table.values[np.ix_(inside, cols)]))
    assert windows > 0


@pytest.mark.parametrize(
    ('name', 'in_gap'), [('seed000_s1', {'cw03', 'cw07'}), ('seed000_s2', {'opt02'})]
)
def test_only_the_gap_stations_measure_in_the_incomplete_segment(
    name: str, in_gap: set[str]
) -> None:
    sc, _, result = _run(name)
    assert sc.gaps == ((45.0, 75.0),)
    measuring = set()
    for sid, table in result.measurements.items():
        n = int(np.sum((table.time > 45.0) & (table.time < 75.0)))
        if n:
            measuring.add(sid)
            assert n >= 0.99 * 30.0 * sc.station(sid).rate_hz  # they measure all along the gap
    assert measuring == in_gap
    assert len(result.measurements) == 13


@pytest.mark.parametrize('name', ['seed000_s1', 'seed004_sea'])
def test_every_ground_measurement_is_above_the_elevation_mask(name: str) -> None:
    sc, world, result = _run(name)
    for st in sc.stations:
        table = result.measurements[st.id]
        assert st.elevation_mask_deg is not None and len(table) > 0
        if name == 'seed000_s1':
            assert st.elevation_mask_deg == 3.0
        pose = _poses_at(result.station_states[st.id], table.time)
        d = _truth_at(world, table.target_id, table.time, st.clock_bias_s)[:, :3] - pose.position
        lat, lon, _ = frames.ecef_to_geodetic(pose.position)
        up = frames.enu_rotation(lat, lon)[..., 2]
        elev = np.arcsin(np.einsum('mi,mi->m', d, up) / np.linalg.norm(d, axis=1))
        assert np.min(elev) >= np.radians(st.elevation_mask_deg)


@pytest.mark.parametrize(
    ('base', 'station_id', 'mask_deg'),
    [('seed000_s1', 'cw05', 20.0), ('seed004_sea', 'radar', 10.0)],
)
def test_elevation_mask_drops_exactly_the_epochs_below_the_local_horizon_mask(
    tmp_path: Path, base: str, station_id: str, mask_deg: float
) -> None:
    path = tmp_path / 'masked.yaml'
    path.write_text(
        yaml.safe_dump(
            {
                'base': base,
                'name': 'masked',
                'stations': [{'id': station_id, 'elevation_mask_deg': mask_deg}],
            }
        )
    )
    sc = load_scenario(str(path))
    world = World(sc)
    st = sc.station(station_id)
    result = simulate(dataclasses.replace(sc, stations=(st,)), world)
    table = result.measurements[station_id]
    # candidate epochs: the station's grid over the span, minus full dropouts
    grid = (
        st.first_epoch + np.arange(int((sc.t_end - st.first_epoch) * st.rate_hz) + 1) / st.rate_hz
    )
    grid = grid[(grid >= sc.t_start) & (grid <= sc.t_end)]
    for w in st.dropouts:
        grid = grid[(grid < w['start']) | (grid > w['end'])]
    states = world.station_states(st, grid)
    pose = _poses_at(states, grid)
    d = world.target_state(0, grid)[:, :3] - pose.position
    if st.max_range_m is not None:
        keep_range = np.linalg.norm(d, axis=1) <= st.max_range_m
        grid, d, pose = grid[keep_range], d[keep_range], pose.take(np.flatnonzero(keep_range))
    lat, lon, _ = frames.ecef_to_geodetic(pose.position)
    up = frames.enu_rotation(lat, lon)[..., 2]
    elev = np.degrees(np.arcsin(np.einsum('mi,mi->m', d, up) / np.linalg.norm(d, axis=1)))
    expected = grid[elev >= mask_deg]
    assert 0 < len(expected) < len(grid)  # the mask bites
    np.testing.assert_allclose(table.time, expected, rtol=0.0, atol=1e-9)


# --------------------------------------------------------------------------- seeding


@pytest.mark.parametrize('name', ['seed000_s1', 'seed003_q3', 'seed004_sea'])
def test_same_seed_reproduces_the_output_and_another_seed_changes_only_the_noise(
    name: str,
) -> None:
    sc, world, first = _run(name)
    again = simulate(load_scenario(name))
    other = simulate(dataclasses.replace(sc, random_seed=sc.random_seed + 1000), world)
    for sid, table in first.measurements.items():
        np.testing.assert_array_equal(again.measurements[sid].time, table.time)
        np.testing.assert_array_equal(again.measurements[sid].values, table.values)
        np.testing.assert_array_equal(again.measurements[sid].target_id, table.target_id)
        np.testing.assert_array_equal(other.measurements[sid].time, table.time)
        z = residual(table.fields, other.measurements[sid].values, table.values) / table.sigmas
        z = z[np.isfinite(z)]
        # the difference of two independent noise draws: std sqrt(2), never identical
        assert np.all(z != 0.0)
        assert np.std(z) == pytest.approx(np.sqrt(2.0), rel=0.1)
    for tid, tel in first.telemetry.items():
        np.testing.assert_array_equal(again.telemetry[tid].position, tel.position)
        assert not np.array_equal(other.telemetry[tid].position, tel.position)
    for tid, truth in first.truth.items():
        np.testing.assert_array_equal(other.truth[tid].position, truth.position)


def test_reusing_a_world_gives_the_same_result_as_a_fresh_simulation() -> None:
    sc, world = _world('seed003_q3')
    other = dataclasses.replace(sc, random_seed=77)
    reused, fresh = simulate(other, world), simulate(other)
    for sid, table in fresh.measurements.items():
        np.testing.assert_array_equal(reused.measurements[sid].values, table.values)
    assert reused.scenario is other


def test_a_world_built_for_another_truth_is_rejected() -> None:
    _, world = _world('seed003_q2')
    sc4, _ = _world('seed003_q4')
    with pytest.raises(ValueError, match='seed003_q2'):
        simulate(sc4, world)
