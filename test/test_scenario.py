"""Unit tests of scenario files: every shipped file loads, ``base`` inheritance, and
ConfigErrors that name the file, the dotted key and what was expected."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from orbit_tracking.core.errors import ConfigError
from orbit_tracking.core.models.measurements import KIND_FIELDS, KIND_OPTIONAL_FIELDS
from orbit_tracking.core.sim.scenario import (
    find_scenario,
    list_scenarios,
    load_scenario,
    orbit_state_from_elements,
)
from orbit_tracking.core.sim.simulator import World

REFERENCE = {
    'seed000_s1',
    'seed000_s2',
    'seed000_s1_bias',
    'seed000_s2_bias',
    'seed003_q2',
    'seed003_q3',
    'seed003_q4',
    'seed003_q4_multi',
    'seed004_sea',
}


def _raw(name: str) -> dict[str, Any]:
    return yaml.safe_load(find_scenario(name).read_text())


def _write(tmp_path: Path, data: dict[str, Any], name: str = 'broken.yaml') -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _config_error(path: Path) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        load_scenario(str(path))
    err = info.value
    assert err.source == str(path)
    assert str(path) in str(err)
    assert err.key in str(err)
    return err


# --------------------------------------------------------------------------- shipped files


def test_every_reference_scenario_of_the_spec_is_shipped() -> None:
    assert REFERENCE <= set(list_scenarios())


@pytest.mark.parametrize('name', list_scenarios())
def test_scenario_file_loads_and_its_truth_covers_the_span(name: str) -> None:
    sc = load_scenario(name)
    assert sc.name == name
    assert sc.t_start < sc.t_end
    assert sc.stations
    for st in sc.stations:
        allowed = KIND_FIELDS[st.kind] + KIND_OPTIONAL_FIELDS[st.kind]
        assert set(KIND_FIELDS[st.kind]) <= set(st.fields) <= set(allowed)
        assert set(st.sigma) == set(st.fields)
        assert np.all(st.sigmas > 0.0)
        assert set(st.targets) <= set(sc.target_ids)
    world = World(sc)
    for tid in sc.target_ids:
        x = world.target_state(tid, np.array([sc.t_start, sc.t_end]))
        assert x.shape == (2, 6) and np.all(np.isfinite(x))


def test_seed000_s2_differs_from_s1_only_where_it_says() -> None:
    s1, s2 = load_scenario('seed000_s1'), load_scenario('seed000_s2')
    changed_top = {'name', 'description', 'source', 'random_seed', 'stations'}
    for f in dataclasses.fields(s1):
        if f.name not in changed_top:
            assert getattr(s1, f.name) == getattr(s2, f.name), f.name
    assert (s1.random_seed, s2.random_seed) == (1, 2)
    assert [s.id for s in s1.stations] == [s.id for s in s2.stations]
    gap = ({'start': 45.0, 'end': 75.0, 'fields': None},)
    overridden = {'cw03': gap, 'cw07': gap, 'opt02': ()}
    for a, b in zip(s1.stations, s2.stations, strict=True):
        if a.id in overridden:
            assert b.dropouts == overridden[a.id]
            assert dataclasses.replace(a, dropouts=b.dropouts) == b
        else:
            assert a == b, a.id


def test_base_override_merges_removes_and_appends_stations(tmp_path: Path) -> None:
    extra = copy.deepcopy(_raw('seed003_q2')['stations'][1])
    extra['id'] = 'sat99'
    data = {
        'base': 'seed003_q2',
        'name': 'derived',
        'stations': [
            {'id': 'sat06', 'remove': True},
            {'id': 'sat09', 'sigma': {'los_beta': 7.0e-6}},
            extra,
        ],
    }
    sc = load_scenario(str(_write(tmp_path, data, 'derived.yaml')))
    base = load_scenario('seed003_q2')
    assert [s.id for s in sc.stations] == ['sat09', 'sat99']
    assert dict(sc.station('sat09').sigma) == {'los_alpha': 5.0e-6, 'los_beta': 7.0e-6}
    assert sc.station('sat09').first_epoch == base.station('sat09').first_epoch
    assert sc.targets == base.targets and sc.gm == base.gm


def test_orbit_elements_give_the_seed003_constellation_orbit() -> None:
    gm = 3.986005e14
    elements = {
        'semi_major_axis_m': 9371004.0,
        'eccentricity': 0.02,
        'inclination_deg': 45.0,
        'raan_deg': 67.5,
        'argument_of_perigee_deg': 90.0,
        'true_anomaly_deg': 0.0,
    }
    x = orbit_state_from_elements(elements, gm)
    r, v = x[:3], x[3:]
    # at perigee: r = a (1 - e), speed from vis-viva, velocity normal to r
    assert np.linalg.norm(r) == pytest.approx(9371004.0 * 0.98, rel=1e-12)
    assert v @ v == pytest.approx(gm * (2 / np.linalg.norm(r) - 1 / 9371004.0), rel=1e-12)
    assert abs(r @ v) < 1e-6 * np.linalg.norm(r) * np.linalg.norm(v)
    h = np.cross(r, v)
    assert np.degrees(np.arccos(h[2] / np.linalg.norm(h))) == pytest.approx(45.0, abs=1e-10)
    node = np.cross([0.0, 0.0, 1.0], h)
    assert np.degrees(np.arctan2(node[1], node[0])) == pytest.approx(67.5, abs=1e-10)
    # argument of perigee 90 deg: the perigee is the orbit's northernmost point
    assert r[2] / np.linalg.norm(r) == pytest.approx(np.sin(np.radians(45.0)), rel=1e-12)


# --------------------------------------------------------------------------- errors


def test_misspelt_sigma_key_names_file_path_and_suggestion(tmp_path: Path) -> None:
    data = _raw('seed000_s1')
    data['stations'][0]['sigma'] = {'rnge': 0.83, 'range_rate': 0.05}
    err = _config_error(_write(tmp_path, data))
    assert err.key == 'stations[0].sigma.rnge'
    assert "did you mean 'range'" in str(err)


def test_misspelt_top_level_key_names_file_and_suggestion(tmp_path: Path) -> None:
    data = _raw('seed003_q2')
    data['statons'] = data.pop('stations')
    err = _config_error(_write(tmp_path, data))
    assert err.key == 'statons'
    assert "did you mean 'stations'" in str(err)


def test_negative_rate_says_a_positive_number_is_expected(tmp_path: Path) -> None:
    data = _raw('seed000_s1')
    data['stations'][4]['rate_hz'] = -20.0
    err = _config_error(_write(tmp_path, data))
    assert err.key == 'stations[4].rate_hz'
    assert 'expected a number > 0' in str(err)
    assert '-20' in str(err)


def test_sigma_for_a_field_the_station_does_not_measure_is_rejected(tmp_path: Path) -> None:
    data = _raw('seed000_s1')
    data['stations'][2]['sigma']['azimuth'] = 1e-5  # cw03 is a CW radar
    err = _config_error(_write(tmp_path, data))
    assert err.key == 'stations[2].sigma'
    assert 'azimuth' in err.problem


def test_missing_sigma_of_a_measured_field_is_rejected(tmp_path: Path) -> None:
    data = _raw('seed000_s1')
    del data['stations'][9]['sigma']['elevation']  # opt01 measures elevation
    err = _config_error(_write(tmp_path, data))
    assert err.key == 'stations[9].sigma'


def test_unknown_target_id_of_a_station_is_rejected(tmp_path: Path) -> None:
    data = _raw('seed003_q2')
    data['stations'][1]['targets'] = [0, 7]
    err = _config_error(_write(tmp_path, data))
    assert err.key == 'stations[1].targets'
    assert 'unknown target id' in err.problem and '7' in err.problem


def test_fixed_station_in_an_eci_world_is_rejected(tmp_path: Path) -> None:
    data = _raw('seed003_q2')
    data['stations'].append(
        {
            'id': 'ground',
            'kind': 'optical',
            'platform': {'type': 'fixed', 'latitude_deg': 10.0, 'longitude_deg': 20.0},
            'rate_hz': 10.0,
            'sigma': {'azimuth': 1e-5, 'elevation': 1e-5},
        }
    )
    err = _config_error(_write(tmp_path, data))
    assert err.key == 'stations[2].platform.type'
    assert 'earth' in err.problem


def test_bias_on_a_field_the_station_does_not_measure_is_rejected(tmp_path: Path) -> None:
    data = _raw('seed000_s1')
    data['stations'][0]['bias'] = {'azimuth': 1e-5}
    err = _config_error(_write(tmp_path, data))
    assert err.key == 'stations[0].bias'


def test_wrong_value_types_name_the_expected_value(tmp_path: Path) -> None:
    data = _raw('seed003_q2')
    data['stations'][0]['kind'] = 'lidar'
    err = _config_error(_write(tmp_path, data))
    assert err.key == 'stations[0].kind'
    assert "one of ['cw_radar'" in err.problem
    data = _raw('seed003_q2')
    data['span'] = [50.0]
    err = _config_error(_write(tmp_path, data))
    assert err.key == 'span' and 'a list of 2 numbers' in err.problem
    data = _raw('seed003_q2')
    data['span'] = [170.0, 50.0]
    err = _config_error(_write(tmp_path, data))
    assert err.key == 'span' and 'start < end' in err.problem


def test_missing_required_key_and_duplicate_ids_are_named(tmp_path: Path) -> None:
    data = _raw('seed003_q2')
    del data['stations'][1]['rate_hz']
    err = _config_error(_write(tmp_path, data))
    assert err.key == 'stations[1].rate_hz' and 'missing required key' in err.problem
    data = _raw('seed003_q2')
    data['stations'][1]['id'] = 'sat06'
    err = _config_error(_write(tmp_path, data))
    assert err.key == 'stations' and 'sat06' in err.problem


def test_boost_that_burns_out_inside_the_span_is_rejected(tmp_path: Path) -> None:
    data = _raw('seed003_q2')
    data['targets'][0]['tau0_s'] = 160.0
    err = _config_error(_write(tmp_path, data))
    assert err.key == 'targets[0].tau0_s'
    # with a second stage the first burn need only last until the staging
    data['targets'][0]['second_stage'] = {'time_s': 120.0, 'exhaust_speed_m_s': 2500.0}
    err = _config_error(_write(tmp_path, data))
    assert err.key == 'targets[0].second_stage.tau0_s' and 'missing' in err.problem
    data['targets'][0]['second_stage']['tau0_s'] = 165.0
    err = _config_error(_write(tmp_path, data))
    assert err.key == 'targets[0].second_stage.tau0_s' and '> 170' in err.problem
    data['targets'][0]['second_stage']['tau0_s'] = 260.0
    scenario = load_scenario(_write(tmp_path, data))
    assert scenario.targets[0]['second_stage']['time_s'] == 120.0


def test_error_in_a_derived_file_names_the_derived_file(tmp_path: Path) -> None:
    data = {'base': 'seed003_q2', 'name': 'derived', 'stations': [{'id': 'sat09', 'rate_hz': 0}]}
    err = _config_error(_write(tmp_path, data, 'derived.yaml'))
    assert err.key.startswith('stations[') and err.key.endswith('].rate_hz')
    assert 'expected a number > 0' in err.problem


def test_circular_base_and_invalid_yaml_are_config_errors(tmp_path: Path) -> None:
    _write(tmp_path, {'base': 'b', 'name': 'a'}, 'a.yaml')
    _write(tmp_path, {'base': 'a', 'name': 'b'}, 'b.yaml')
    err = _config_error(tmp_path / 'a.yaml')
    assert err.key == 'base' and 'circular' in err.problem
    bad = tmp_path / 'bad.yaml'
    bad.write_text('name: [unclosed\n')
    err = _config_error(bad)
    assert 'not valid YAML' in err.problem


def test_unknown_scenario_name_lists_the_known_ones() -> None:
    with pytest.raises(FileNotFoundError, match='seed000_s1'):
        load_scenario('no_such_scenario')
