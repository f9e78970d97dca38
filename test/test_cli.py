"""``orbit-tracking`` command-line errors: one clear line on stderr and exit status 2."""

from __future__ import annotations

import sys

import pytest

from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.core.sim.simulator import simulate
from orbit_tracking.core.sim.stream import batch_rows
from orbit_tracking.tools.cli import main

TRACEBACK = 'Traceback (most recent call last)'


def test_simulate_into_an_existing_folder_is_a_clean_error(tmp_path, capsys):
    out = tmp_path / 'bag'
    out.mkdir()
    (out / 'keep.txt').write_text('precious')
    assert main(['simulate', '--scenario', 'seed003_q2', '--out', str(out), '--quiet']) == 2
    err = capsys.readouterr().err
    assert err.startswith('orbit-tracking simulate: error: ')
    assert str(out) in err and 'exists' in err
    assert TRACEBACK not in err
    assert sorted(p.name for p in out.iterdir()) == ['keep.txt']  # left untouched


def test_simulate_unknown_scenario_is_a_clean_error(tmp_path, capsys):
    out = tmp_path / 'bag'
    assert main(['simulate', '--scenario', 'no_such_scenario', '--out', str(out), '--quiet']) == 2
    err = capsys.readouterr().err
    assert err.startswith('orbit-tracking simulate: error: ')
    assert 'no_such_scenario' in err and 'seed003_q2' in err  # names the known ones
    assert TRACEBACK not in err
    assert not out.exists()


@pytest.mark.parametrize(
    ('args', 'needle'),
    [
        (['simulate', '--scenario', 'no_such_scenario', '--out', '{tmp}/bag'], 'no_such_scenario'),
        (['simulate', '--scenario', 'seed003_q2', '--out', '{tmp}'], 'exists'),
    ],
    ids=['unknown_scenario', 'existing_folder'],
)
def test_cli_process_exits_with_status_2_without_traceback(tmp_path, start_process, args, needle):
    cmd = [
        sys.executable,
        '-m',
        'orbit_tracking.tools.cli',
        *(a.format(tmp=tmp_path) for a in args),
        '--quiet',
    ]
    proc = start_process(cmd, label='orbit-tracking')
    assert proc.wait(timeout=60) == 2
    stderr = proc.errors()
    assert TRACEBACK not in stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], stderr


def test_simulate_reports_what_it_wrote(tmp_path, capsys):
    out = tmp_path / 'bag'
    args = ['--quiet', '--no-truth', '--batch-period', '1.0']
    assert main(['simulate', '--scenario', 'seed003_q2', '--out', str(out), *args]) == 0
    stdout = capsys.readouterr().out
    # moving satellites: a state per epoch, and a measurement message per second of epochs
    result = simulate(load_scenario('seed003_q2'))
    n = sum(len(s) for s in result.station_states.values())
    n += sum(len(batch_rows(m.time, 1.0)) for m in result.measurements.values())
    assert f'wrote {n} messages of scenario seed003_q2' in stdout
    assert (out / 'metadata.yaml').is_file()


@pytest.mark.dds
def test_record_into_an_existing_folder_is_a_clean_error_and_leaves_rclpy_shut_down(
    tmp_path, capsys
):
    import rclpy

    (tmp_path / 'keep.txt').write_text('precious')  # an empty folder is used as it is
    for _ in range(2):  # a second call in the same process works the same way
        assert main(['record', '--out', str(tmp_path), '--duration', '1']) == 2
        err = capsys.readouterr().err
        assert err.startswith('orbit-tracking record: error: ') and 'exists' in err, err
        assert TRACEBACK not in err
        assert not rclpy.ok()
