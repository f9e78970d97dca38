"""``orbit-tracking report DIR``: report.html of an estimate output folder, built here from
the contract's files (written with the package's own writers) around the 30 s cut of seed
000 scenario 1, with and without truth, and refused for a folder without trajectory.csv."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_windows import write_short_scenario

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.estimation.bias_files import write_biases_by_window_csv, write_biases_csv
from orbit_tracking.core.estimation.results import BiasEstimate
from orbit_tracking.core.estimation.windows import write_trajectory_csv
from orbit_tracking.core.metrics import hermite_states
from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.core.sim.simulator import simulate
from orbit_tracking.tools.cli import main as cli_main
from orbit_tracking.tools.report import HTML_FIGURES, report_context
from orbit_tracking.tools.report.figures import _post_fit

EPOCH_NS = 1_700_000_000 * 1_000_000_000
SIGMA = np.array([0.5, 0.5, 0.5, 0.02, 0.02, 0.02])


def _truth_track(truth, t):
    """Truth states (m, 6) at ``t``, independently of the report's interpolation."""
    vel = np.stack([np.interp(t, truth.time, truth.velocity[:, c]) for c in range(3)], axis=1)
    return np.hstack([hermite_states(truth.time, truth.position, truth.velocity, t), vel])


@pytest.fixture(scope='module')
def run(tmp_path_factory):
    """A simulated bag and an output folder as ``estimate --biases`` writes it: the truth
    plus 0.3 m along x as the 'estimate', two windows, biases of two stations."""
    root = tmp_path_factory.mktemp('report')
    scenario = write_short_scenario(root)
    sc = load_scenario(scenario)
    bag = root / 'bag'
    assert cli_main(['simulate', '--scenario', str(scenario), '--out', str(bag), '--quiet']) == 0
    est = root / 'est'
    est.mkdir()
    t = np.round(np.arange(0.0, 30.0 + 1e-9, 0.1), 9)
    x = _truth_track(simulate(sc).truth[0], t) + np.array([0.3, 0, 0, 0, 0, 0])
    cov = np.broadcast_to(np.diag(SIGMA**2), (t.size, 6, 6))
    write_trajectory_csv(est / 'trajectory.csv', t, x, cov, EPOCH_NS)
    windows = [(0.0, 20.0), (14.0, 30.0)]
    biases = [
        [
            BiasEstimate('cw01', 'range', 0.4 * k, 0.2, 0.0, 10.0, 'estimated'),
            BiasEstimate('opt01', 'azimuth', 2e-6 * k, 1e-6, 0.0, 1e-4, 'estimated'),
        ]
        for k in (1, 2)
    ]
    write_biases_csv(est / 'biases.csv', biases[-1])
    write_biases_by_window_csv(
        est / 'biases_by_window.csv',
        [(a, b, bs) for (a, b), bs in zip(windows, biases, strict=True)],
        EPOCH_NS,
    )
    summary = {
        'bag': str(bag),
        'scenario': sc.name,
        'rough_trajectory': 'telemetry',
        'config': {'window_length': 20.0, 'window_overlap': 6.0, 'output_step': 0.1},
        'counts': {},
        'totals': {'windows': 2, 'succeeded': 2, 'failed': 0, 'output_states': int(t.size)},
        'windows': [
            {
                'start': a,
                'end': b,
                'success': True,
                'iterations': 5,
                'chi2_dof': 1.01,
                'used': {'cw01': 400},
                'rejected': {},
                'segments': {0: [[12.0, 18.0]]},
            }
            for a, b in windows
        ],
        'evaluation': {0: {'outside_gaps': {'n': 240.0, 'rms_position_m': 0.3}}},
    }
    (est / 'summary.yaml').write_text(yaml.safe_dump(summary, sort_keys=False))
    return scenario, bag, est


def _page(folder: Path) -> tuple[str, list[str]]:
    text = (folder / 'report.html').read_text()
    images = re.findall(r'<img src="([^"]+)"', text)
    for name in images:
        png = folder / name
        assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n', f'{name} is not a PNG'
    return text, images


def test_report_of_an_estimate_folder_draws_every_section_with_truth_from_its_bag(run, capsys):
    _scenario, _bag, est = run
    assert cli_main(['report', str(est)]) == 0
    assert f'wrote {est / "report.html"}' in capsys.readouterr().out
    text, images = _page(est)
    assert sorted(images) == sorted(HTML_FIGURES.values())
    assert 'class="missing"' not in text, re.findall(r'class="missing">([^<]*)', text)
    # the summary figures, the evaluation and the windows as tables
    for cell in ('totals.windows', 'config.output_step', 'rms_position_m', 'chi2_dof'):
        assert f'<td>{cell}</td>' in text or f'<th>{cell}</th>' in text
    assert '<td>cw01</td><td>range</td><td>0.8</td><td>0.2</td>' in text
    assert 'Truth and measurements: bag' in text
    assert 'World frame: earth.' in text and 'seconds after stamp 1700000000.000000000' in text


def test_report_without_truth_shows_the_envelope_and_says_what_is_missing(run, tmp_path, capsys):
    _scenario, _bag, est = run
    folder = tmp_path / 'copy'
    shutil.copytree(est, folder, ignore=shutil.ignore_patterns('*.png', '*.html'))
    summary = yaml.safe_load((folder / 'summary.yaml').read_text())
    summary['bag'] = str(tmp_path / 'moved_away')
    (folder / 'summary.yaml').write_text(yaml.safe_dump(summary))
    (folder / 'biases_by_window.csv').unlink()
    (folder / 'biases.csv').write_text('station,field,bias,sigma\n')  # no biases declared
    assert cli_main(['report', str(folder), '--out', str(tmp_path / 'page')]) == 0
    printed = capsys.readouterr().out
    assert 'moved_away named in summary.yaml was not found' in printed
    text, images = _page(tmp_path / 'page')
    assert images == [HTML_FIGURES['trajectory'], HTML_FIGURES['errors']]
    assert 'showing the 1σ envelope alone' in text
    assert 'no residuals: orbit-tracking estimate does not write them' in text
    assert 'biases.csv has no rows' in text
    assert '<td>totals.windows</td>' in text  # the summary table is still there


def test_a_scenario_file_gives_truth_and_measurements_on_the_bag_time_base(run):
    scenario, _bag, est = run
    ctx, notes = report_context(est, None, scenario=str(scenario))
    assert notes == [] and 'simulated again' in ctx.source
    assert ctx.ref_ns == EPOCH_NS and ctx.world_frame == 'earth' and ctx.gaps == ((12.0, 18.0),)
    assert list(ctx.truth) == [0] and len(ctx.observations.stations) == 13
    with pytest.raises(FileNotFoundError):
        report_context(est, None, scenario='no_such_scenario')


def test_report_of_a_bare_trajectory_csv_says_what_each_section_lacks(run, tmp_path):
    _scenario, _bag, est = run
    folder = tmp_path / 'bare'
    folder.mkdir()
    shutil.copy(est / 'trajectory.csv', folder)
    (folder / 'summary.yaml').write_text('[not, a, mapping]\n')
    assert cli_main(['report', str(folder)]) == 0
    text, images = _page(folder)
    assert images == [HTML_FIGURES['trajectory'], HTML_FIGURES['errors']]
    assert 'summary.yaml is unreadable: expected a YAML mapping' in text
    assert 'no biases.csv in' in text and 'World frame: not recorded.' in text


def test_report_refuses_a_folder_without_trajectory_csv(tmp_path, capsys):
    (tmp_path / 'summary.yaml').write_text('bag: x\n')
    assert cli_main(['report', str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert 'has no trajectory.csv' in err and 'orbit-tracking estimate' in err
    assert cli_main(['report', str(tmp_path / 'nope')]) == 2
    (tmp_path / 'trajectory.csv').write_text('time,x\n1,2\n')
    assert cli_main(['report', str(tmp_path)]) == 2
    assert 'header must be time,x,y,z' in capsys.readouterr().err


def test_post_fit_residuals_of_the_true_trajectory_are_the_whitened_noise(run):
    scenario, _bag, _est = run
    res = simulate(load_scenario(scenario))
    t = np.round(np.arange(0.0, 30.0 + 1e-9, 0.05), 9)
    track = {0: (t, _truth_track(res.truth[0], t), np.ones((t.size, 6)))}
    for s in Observations.from_simulation(res).stations:
        r = _post_fit(s, track)
        ok = np.isfinite(r)
        assert ok.mean(axis=0).min() > 0.9, s.table.station_id
        rms = np.sqrt(np.mean(np.where(ok, r, 0.0) ** 2, axis=0) / ok.mean(axis=0))
        assert np.all((rms > 0.85) & (rms < 1.15)), (s.table.station_id, rms)
