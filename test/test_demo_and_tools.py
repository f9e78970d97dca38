"""The README's main job (``orbit-tracking demo``), the report, the benchmark command and
the node parameter files."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from orbit_tracking.bench import bench_triangulation, markdown_table, write_docs
from orbit_tracking.cli import main as cli_main
from orbit_tracking.core.alignment import AlignConfig
from orbit_tracking.core.fixes import TriangulationPipeline
from orbit_tracking.core.scenario import load_scenario
from orbit_tracking.core.simulation import simulate

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.dds
def test_demo_runs_the_whole_chain_and_writes_a_report(tmp_path, capsys):
    out = tmp_path / 'run'
    assert cli_main(['demo', '--scenario', 'seed003_q2', '--out', str(out), '--quiet']) == 0
    printed = capsys.readouterr().out
    assert (out / 'bag' / 'metadata.yaml').is_file()
    assert (out / 'triangulation' / 'fixes.csv').is_file()
    assert (out / 'live_bag' / 'metadata.yaml').is_file()
    report = (out / 'report' / 'report.md').read_text()
    for fig in ('geometry.png', 'residuals.png', 'fixes.png'):
        assert (out / 'report' / fig).stat().st_size > 10_000
        assert fig in report
    assert 'mean NEES' in report
    # the live pass over DDS gave exactly the offline fixes
    assert '598 fixes recorded from DDS' in printed
    assert '598 live fixes share an epoch with an offline fix' in printed
    # re-running into the same folder needs --force
    assert cli_main(['demo', '--scenario', 'seed003_q2', '--out', str(out), '--no-live']) == 2
    assert cli_main(['report', str(out)]) == 0


def test_bench_reports_errors_crb_and_times_and_writes_the_docs(tmp_path):
    rows = bench_triangulation(['seed003_q2'], seeds=1, progress=False)
    by = {r.method: r for r in rows}
    assert set(by) == {'weighted', 'weighted+lowpass', 'seed003-midpoint', 'seed003-lowpass'}
    ours = by['weighted']
    assert ours.fixes == 598
    assert 0.85 < ours.efficiency < 1.2  # near the single-epoch Cramér–Rao bound
    assert 2.5 < ours.nees < 3.5
    assert ours.wall_ms_per_fix > 0
    text = markdown_table(rows, 1)
    doc = tmp_path / 'BENCH.md'
    doc.write_text('# Benchmarks\n\nintro\n')
    write_docs(doc, 'triangulation', text)
    write_docs(doc, 'triangulation', text)  # replaced, not appended twice
    body = doc.read_text()
    assert body.count('BEGIN bench:triangulation') == 1
    assert 'intro' in body and '| seed003_q2 | weighted |' in body


def test_fixes_wait_for_the_station_states_that_bracket_them():
    """Live streams: a measurement may arrive before its station's state (other topic)."""
    res = simulate(load_scenario('seed003_q2'))
    pipe = TriangulationPipeline(AlignConfig(lag=0.5))
    fixes = []
    states = {sid: res.station_states[sid] for sid in res.station_states}
    meas = {sid: res.measurements[sid] for sid in res.measurements}
    # measurements run 3 s of data time ahead of the states
    for step in np.arange(50.0, 171.0, 0.2):
        for sid, m in meas.items():
            sel = (m.time >= step) & (m.time < step + 0.2)
            pipe.add_measurements(
                sid, m.fields, m.time[sel], m.target_id[sel], m.values[sel], m.sigmas[sel]
            )
        for sid, st in states.items():
            sel = np.flatnonzero((st.time >= step - 3.0) & (st.time < step - 2.8))
            for i in sel:
                pipe.add_pose(
                    sid, st.time[i], st.position[i], st.velocity[i], st.rotation[i], True
                )
        fixes += pipe.process()
    for sid, st in states.items():
        for i in np.flatnonzero(st.time >= 167.8):
            pipe.add_pose(sid, st.time[i], st.position[i], st.velocity[i], st.rotation[i], True)
    fixes += pipe.flush()
    assert pipe.counts['no_station_state'] == 0
    assert len(fixes) == 598


@pytest.mark.dds
@pytest.mark.parametrize(
    'node,module',
    [
        ('station_sim', 'station_sim'),
        ('scenario_sim', 'scenario_sim'),
        ('triangulation', 'triangulation_node'),
    ],
)
def test_node_parameter_files_are_accepted(start_process, node, module):
    import sys

    proc = start_process(
        [
            sys.executable,
            '-m',
            f'orbit_tracking.ros.{module}',
            '--ros-args',
            '--params-file',
            str(ROOT / 'config' / f'{node}.yaml'),
        ]
    )
    deadline = time.monotonic() + 4.0
    while time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.2)
    assert proc.poll() is None, proc.errors()
    assert 'Traceback' not in proc.errors() and 'FATAL' not in proc.errors()
