"""Bias declarations (core/bias_files.py): the YAML format, its errors, the auto declaration,
resolving a declaration against the stations seen, and the bias CSV files."""

from __future__ import annotations

import csv
import dataclasses
import math
import re
from pathlib import Path

import pytest
import yaml

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.errors import ConfigError
from orbit_tracking.core.estimation.bias_files import (
    BIASES_BY_WINDOW_CSV_COLUMNS,
    BIASES_CSV_COLUMNS,
    DEFAULT_PRIOR_SIGMA,
    BiasDeclaration,
    auto_biases,
    load_bias_declaration,
    parse_bias_declaration,
    read_biases_csv,
    station_fields,
    write_biases_by_window_csv,
    write_biases_csv,
)
from orbit_tracking.core.estimation.results import BiasEstimate
from orbit_tracking.core.models.measurements import KIND_FIELDS
from orbit_tracking.core.models.systematic import BiasParameter
from orbit_tracking.core.sim.scenario import load_scenario, truth_biases
from orbit_tracking.core.sim.simulator import simulate

ROOT = Path(__file__).resolve().parents[1]
EPOCH_NS = 1_700_000_000 * 1_000_000_000

EXAMPLE = """\
biases:
  - {station: cw01, name: range, prior: 0.0, sigma: 10.0}
  - {station: sat06, name: los_theta, sigma: 1.0e-3, bounds: [-0.01, 0.01]}
  - {station: opt01, name: azimuth, prior: 1.2e-5, estimate: false}   # known calibration
"""


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / 'biases.yaml'
    path.write_text(text)
    return path


def test_a_declaration_file_gives_one_bias_parameter_per_entry(tmp_path):
    decl = load_bias_declaration(_write(tmp_path, EXAMPLE))
    assert decl.source == str(tmp_path / 'biases.yaml') and not decl.auto
    assert decl.entries == (
        BiasParameter('cw01', 'range', 0.0, 10.0),
        BiasParameter('sat06', 'los_theta', 0.0, 1e-3, bounds=(-0.01, 0.01)),
        # no sigma: the name's weak prior
        BiasParameter('opt01', 'azimuth', 1.2e-5, DEFAULT_PRIOR_SIGMA['azimuth'], False),
    )
    assert decl.stations == ('cw01', 'opt01', 'sat06')


def test_open_bounds_yaml_exponents_and_default_sigma_overrides_are_read(tmp_path):
    text = """\
default_sigma: {range: 5.0}
biases:
  - {station: cw01, name: range, bounds: [null, 20.0]}
  - {station: cw02, name: range, bounds: [-.inf, .inf], sigma: 2e-1}
  - {station: cw03, name: clock, prior: 1e-3}
"""
    a, b, c = load_bias_declaration(_write(tmp_path, text)).entries
    assert a.bounds == (-math.inf, 20.0) and a.sigma == 5.0
    assert b.bounds == (-math.inf, math.inf) and b.sigma == 0.2  # '2e-1' is a str in YAML 1.1
    assert c.prior == 1e-3 and c.sigma == DEFAULT_PRIOR_SIGMA['clock']


@pytest.mark.parametrize(
    ('entry', 'where', 'match'),
    [
        ('{station: cw01, name: range, sigmaa: 1.0}', 'biases[1].sigmaa', "did you mean 'sigma'"),
        ('{station: cw01, name: rnage}', 'biases[1].name', "did you mean 'range'"),
        ('{station: cw01, name: range_bias}', 'biases[1].name', 'unknown bias name'),
        ('{name: range}', 'biases[1].station', 'missing required key'),
        ('{station: cw01}', 'biases[1].name', 'missing required key'),
        ('{station: cw01, name: range, sigma: 0.0}', 'biases[1].sigma', 'expected a number > 0'),
        ('{station: cw01, name: range, sigma: -1.0}', 'biases[1].sigma', '> 0'),
        (
            '{station: cw01, name: range, prior: 5.0, bounds: [-1, 1]}',
            'biases[1].prior',
            'outside',
        ),
        ('{station: cw01, name: range, bounds: [1, -1]}', 'biases[1].bounds', 'lower < upper'),
        ('{station: cw01, name: range, bounds: [1]}', 'biases[1].bounds', '[lower, upper]'),
        ('{station: cw01, name: range, estimate: no_way}', 'biases[1].estimate', 'true or false'),
        ('{station: cw09, name: azimuth}', 'biases[1]', 'already declared by biases[0]'),
        ('[cw01, range]', 'biases[1]', 'a mapping'),
    ],
)
def test_bad_entries_are_refused_naming_the_file_and_the_entry(tmp_path, entry, where, match):
    path = _write(tmp_path, f'biases:\n  - {{station: cw09, name: azimuth}}\n  - {entry}\n')
    with pytest.raises(ConfigError, match=re.escape(match)) as info:
        load_bias_declaration(path)
    assert info.value.key == where
    assert str(path) in str(info.value)


@pytest.mark.parametrize(
    ('text', 'where', 'match'),
    [
        ('bias: []\n', 'bias', "did you mean 'biases'"),
        ('- {station: cw01, name: range}\n', 'biases', 'biases: list'),
        ('biases: {station: cw01}\n', 'biases', 'a list'),
        ('auto_clock: true\n', 'auto_clock', 'needs auto: true'),
        ('default_sigma: {range: 0}\n', 'default_sigma.range', '> 0'),
        ('biases: [\n', '', 'not valid YAML'),
    ],
)
def test_bad_files_are_refused_with_the_key(tmp_path, text, where, match):
    with pytest.raises(ConfigError, match=match) as info:
        load_bias_declaration(_write(tmp_path, text))
    assert info.value.key == where


def test_empty_auto_and_missing_files():
    assert load_bias_declaration('').empty
    assert parse_bias_declaration(None).empty
    auto = load_bias_declaration('auto')
    assert auto.auto and not auto.auto_clock and not auto.empty and auto.source == 'auto'
    with pytest.raises(FileNotFoundError, match='bias file no/such.yaml'):
        load_bias_declaration('no/such.yaml')
    # a bare file name is found in the package's config/ folder
    assert load_bias_declaration('biases_example.yaml').source.endswith('biases_example.yaml')


def test_the_example_file_declares_the_biases_of_seed000_s1_bias():
    decl = load_bias_declaration(ROOT / 'config' / 'biases_example.yaml')
    sc = load_scenario('seed000_s1_bias')
    biases, notes = decl.resolve({s.id: s.fields for s in sc.stations})
    assert notes == []
    assert set(truth_biases(sc)) <= {(b.station, b.name) for b in biases}
    assert [b for b in biases if not b.estimate] == [
        BiasParameter('opt02', 'azimuth', 0.0, 1e-4, False)
    ]


def test_auto_declares_every_measured_field_with_weak_priors():
    fields = {
        'opt01': KIND_FIELDS['optical'],
        'cw01': KIND_FIELDS['cw_radar'],
        'sat06': KIND_FIELDS['satellite'],
        'ship': ('range', 'azimuth', 'elevation', 'range_rate'),  # order as the messages
    }
    got = auto_biases(fields)
    assert [(b.station, b.name, b.sigma) for b in got] == [
        ('cw01', 'range', 10.0),
        ('cw01', 'range_rate', 0.1),
        ('opt01', 'azimuth', 1e-4),
        ('opt01', 'elevation', 1e-4),
        ('sat06', 'los_alpha', 1e-3),
        ('sat06', 'los_beta', 1e-3),
        ('sat06', 'los_theta', 1e-3),  # seed 003's rotation, for line-of-sight observers
        ('ship', 'range', 10.0),
        ('ship', 'range_rate', 0.1),
        ('ship', 'azimuth', 1e-4),
        ('ship', 'elevation', 1e-4),
    ]
    assert all(b.prior == 0.0 and b.estimate and b.bounds == (-math.inf, math.inf) for b in got)
    with_clock = auto_biases(fields, clock=True, sigma={'clock': 0.005})
    assert [b for b in with_clock if b.name == 'clock'] == [
        BiasParameter(s, 'clock', 0.0, 0.005) for s in ('cw01', 'opt01', 'sat06', 'ship')
    ]


def test_auto_of_a_simulation_follows_the_scenario_stations():
    result = simulate(load_scenario('seed003_q2'))
    fields = station_fields(Observations.from_simulation(result))
    assert fields == {s.id: s.fields for s in result.scenario.stations}
    names = {(b.station, b.name) for b in auto_biases(fields)}
    assert ('sat06', 'los_theta') in names and ('sat09', 'los_theta') in names
    assert not any(n == 'clock' for _, n in names)


def test_explicit_entries_replace_auto_ones_and_misfits_are_left_out_with_a_note(tmp_path):
    text = """\
auto: true
auto_clock: true
biases:
  - {station: cw01, name: range, sigma: 2.0}
  - {station: opt01, name: range}
  - {station: cw01, name: los_theta}
  - {station: cw99, name: range}
"""
    decl = load_bias_declaration(_write(tmp_path, text))
    fields = {'cw01': ('range', 'range_rate'), 'opt01': ('azimuth', 'elevation')}
    biases, notes = decl.resolve(fields)
    assert [(b.station, b.name, b.sigma) for b in biases] == [
        ('cw01', 'range', 2.0),
        ('cw01', 'range_rate', 0.1),
        ('cw01', 'clock', 0.01),
        ('opt01', 'azimuth', 1e-4),
        ('opt01', 'elevation', 1e-4),
        ('opt01', 'clock', 0.01),
        ('cw99', 'range', 10.0),  # not seen (yet): kept, the estimator skips it
    ]
    assert len(notes) == 2
    assert 'opt01/range ignored: station opt01 measures azimuth, elevation' in notes[0]
    assert 'los_theta needs los_alpha and los_beta' in notes[1]
    with pytest.raises(ValueError, match='declared twice'):
        BiasDeclaration((BiasParameter('a', 'range'), BiasParameter('a', 'range')))


def test_truth_biases_of_a_scenario_include_the_clock_offset():
    sc = load_scenario('seed000_s1_bias')
    truth = truth_biases(sc)
    assert truth[('cw02', 'range')] == 3.0 and truth[('opt01', 'elevation')] == -9.70e-6
    assert len(truth) == 7 and not any(n == 'clock' for _, n in truth)
    st = sc.stations[0]
    clocked = dataclasses.replace(sc, stations=(dataclasses.replace(st, clock_bias_s=0.002),))
    assert truth_biases(clocked) == {(st.id, 'clock'): 0.002}


def test_bias_csv_files_have_the_contract_columns(tmp_path):
    biases = (
        BiasEstimate('cw02', 'range', 2.98765432101, 0.12, 0.0, 10.0, 'estimated'),
        BiasEstimate('opt02', 'azimuth', 1e-5, 1e-4, 1e-5, 1e-4, 'known'),
        BiasEstimate('cw03', 'clock', 0.0, 0.01, 0.0, 0.01, 'unobservable (x): held, a, b'),
    )
    path = tmp_path / 'biases.csv'
    assert write_biases_csv(path, biases) == 3
    assert path.read_text().splitlines()[0] == 'station,field,bias,sigma'
    assert BIASES_CSV_COLUMNS == ('station', 'field', 'bias', 'sigma')
    rows = read_biases_csv(path)
    assert rows[0] == ('cw02', 'range', pytest.approx(2.98765432101, rel=1e-9), 0.12)
    assert [r[:2] for r in rows] == [('cw02', 'range'), ('opt02', 'azimuth'), ('cw03', 'clock')]

    path = tmp_path / 'by_window.csv'
    n = write_biases_by_window_csv(path, [(0.0, 20.0, biases), (14.0, 30.5, biases[:1])], EPOCH_NS)
    assert n == 4
    with open(path, newline='') as fh:
        got = list(csv.reader(fh))
    assert tuple(got[0]) == BIASES_BY_WINDOW_CSV_COLUMNS
    assert got[4][:4] == ['1700000014.000000000', '1700000030.500000000', 'cw02', 'range']
    assert got[3][8] == 'unobservable (x): held, a, b'  # quoted, commas and all

    bad = tmp_path / 'bad.csv'
    bad.write_text('station,name,bias,sigma\n')
    with pytest.raises(ValueError, match='header must be station,field,bias,sigma'):
        read_biases_csv(bad)


def test_the_estimator_parameter_file_documents_bias_file():
    params = yaml.safe_load((ROOT / 'config' / 'estimator.yaml').read_text())
    assert params['estimator']['ros__parameters']['bias_file'] == ''
