"""The README's main job (``orbit-tracking demo``), the report, the benchmark command and
the node parameter files."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from orbit_tracking.core.estimation.windows import read_trajectory_csv
from orbit_tracking.core.metrics import hermite_states
from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.core.sim.simulator import simulate
from orbit_tracking.core.triangulation.alignment import AlignConfig
from orbit_tracking.core.triangulation.pipeline import TriangulationPipeline
from orbit_tracking.tools.bench.triangulation import (
    bench_triangulation,
    markdown_table,
    write_docs,
)
from orbit_tracking.tools.cli import main as cli_main
from orbit_tracking.tools.live import NODES

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.dds
def test_demo_runs_the_nodes_over_dds_and_reports_their_trajectory(tmp_path, capsys):
    """The main job on a short scenario (no telemetry: the estimator's rough trajectory is
    the live triangulation): the results node's trajectory, recorded, is judged against
    truth by its own covariance; the report and ``orbit-tracking report`` work on it."""
    out = tmp_path / 'run'
    args = ['demo', '--scenario', 'seed003_q2', '--out', str(out), '--rate-factor', '10']
    assert cli_main([*args, '--quiet']) == 0
    printed = capsys.readouterr().out
    assert (out / 'live_bag' / 'metadata.yaml').is_file()
    summary = yaml.safe_load((out / 'summary.yaml').read_text())
    assert summary['recorded']['trajectory/states'] == summary['live']['states_published']
    assert summary['totals']['succeeded'] >= 2 and summary['totals']['failed'] == 0

    # the live trajectory covers the measurements and holds no hole
    sc = load_scenario('seed003_q2')
    res = simulate(sc)
    tab = read_trajectory_csv(out / 'trajectory.csv')
    t = (tab['stamp_ns'] - round(sc.epoch * 1e9)) * 1e-9
    step = summary['config']['output_step']
    seen = np.concatenate([m.time for m in res.measurements.values()])
    assert t[0] <= seen.min() + step and t[-1] >= seen.max() - step
    assert np.max(np.diff(t)) < 1.5 * step
    # errors against truth, judged by the covariance the results node published
    truth = res.truth[0]
    err = tab['state'][:, :3] - hermite_states(truth.time, truth.position, truth.velocity, t)
    z = err / tab['sigma'][:, :3]
    assert np.all(np.isfinite(z))
    assert np.mean(z**2) < 3.0  # 1 for an honest covariance; seed003_q2 gives about 1.5
    assert np.max(np.abs(z)) < 6.0

    html = (out / 'report.html').read_text()
    for fig in ('trajectory.png', 'state_errors.png', 'residuals.png'):
        assert (out / fig).stat().st_size > 10_000
        assert f'src="{fig}"' in html
    assert 'could not draw' not in html
    assert 'live vs offline:' in printed
    # the report command redraws the demo folder
    (out / 'report.html').unlink()
    assert cli_main(['report', str(out)]) == 0
    assert (out / 'report.html').is_file()
    # re-running into the same folder needs --force
    assert cli_main(args) == 2
    assert 'pass --force' in capsys.readouterr().err


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
    [('station_sim', 'station_sim'), *((n.executable, n.module) for n in NODES)],
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
