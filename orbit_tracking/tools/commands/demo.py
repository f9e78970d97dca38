"""``orbit-tracking demo``, the main job: the nodes as separate processes over DDS, the
output files of the recording, an offline cross-check and report.html."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from orbit_tracking.tools.commands.common import add_force, prepare_output_folder

if TYPE_CHECKING:
    from orbit_tracking.core.sim.scenario import Scenario
    from orbit_tracking.tools.recording import RecordingReport

__all__ = ['add_demo']


def _cmd_demo(args: argparse.Namespace) -> int:
    import yaml

    from orbit_tracking.core.sim.scenario import load_scenario
    from orbit_tracking.tools.live import NODES, SIMULATOR, run_live
    from orbit_tracking.tools.recording import write_recorded_outputs
    from orbit_tracking.tools.report import build_html_report, read_output_folder, report_context

    if not args.rate_factor > 0.0:
        print(
            f'orbit-tracking demo: error: --rate-factor must be > 0; got {args.rate_factor}',
            file=sys.stderr,
        )
        return 2
    sc = load_scenario(args.scenario)
    out = prepare_output_folder(args.out or Path('runs') / sc.name, args.force)
    out.mkdir(parents=True)
    t_all = time.monotonic()
    steps = 4 if args.offline_check else 3
    counter = iter(range(1, steps + 1))

    def step(text: str) -> None:
        print(f'[{next(counter)}/{steps}] {text}', flush=True)

    def say(text: str) -> None:
        print(f'   {text}', flush=True)

    chain = ' -> '.join(sorted((n.executable for n in NODES), key=lambda e: e != SIMULATOR))
    step(
        f'live pass over DDS of {sc.name} at {args.rate_factor:g}x real time: {chain}, '
        f'recorded -> {out / "live_bag"}'
    )
    try:
        live = run_live(args.scenario, out, args.rate_factor, progress=None if args.quiet else say)
    except RuntimeError as exc:  # a node died or a wait ran out: its log says why
        print(f'orbit-tracking demo: error: {exc}', file=sys.stderr)
        return 1
    for line in live.lines():
        say(line)
    step(f'output files from the recording -> {out}')
    est_params = live.parameters['estimator']
    config = {
        k: est_params[k]
        for k in ('window_length', 'window_overlap', 'latency', 'output_step', 'knot_method')
        if k in est_params
    }
    config['use_telemetry'] = bool(est_params.get('use_telemetry', True))
    config['biases'] = str(est_params.get('bias_file') or '')
    extra = {
        'live': {
            'rate_factor': args.rate_factor,
            'wall_s': round(live.wall_s, 1),
            'nodes': live.location.describe(),
            'commands': {k: ' '.join(v) for k, v in live.commands.items()},
            'measurement_messages_sent': dict(live.sent),
            'states_published': live.states_published,
            'exit_codes': dict(live.exit_codes),
        }
    }
    rec = write_recorded_outputs(live.bag, out, config, extra)
    for line in rec.lines():
        say(line)
    say(f'wrote {", ".join(str(f) for f in rec.files)}')
    if args.offline_check:
        step(
            f'offline cross-check: the same scenario simulated and estimated -> {out / "offline"}'
        )
        check = _offline_check(sc, out / 'offline', est_params, rec, not args.quiet)
        for line in check.pop('lines'):
            say(line)
        summary_path = out / 'summary.yaml'
        summary = yaml.safe_load(summary_path.read_text())
        summary['live_vs_offline'] = check
        summary_path.write_text(yaml.safe_dump(summary, sort_keys=False))
    step(f'report -> {out / "report.html"}')
    folder = read_output_folder(out)
    ctx, notes = report_context(out, folder.summary)
    for line in notes:
        say(line)
    path = build_html_report(folder, None, ctx, notes)
    print(f'done in {time.monotonic() - t_all:.1f} s; open {path}')
    return 0


def _offline_check(
    sc: Scenario,
    folder: Path,
    est_params: Mapping[str, Any],
    rec: RecordingReport,
    progress: bool,
) -> dict[str, Any]:
    """Simulate the scenario into a bag (what the simulator node streamed), estimate it
    offline with the estimator node's settings, and compare with the live trajectory: the
    same windows over the same data give the same states, unless data were lost or
    reordered on the way."""
    from orbit_tracking.tools.estimate import estimate_bag
    from orbit_tracking.tools.estimator_parameters import estimator_configs
    from orbit_tracking.tools.simulate import simulate_to_bag

    est_cfg, win_cfg, biases = estimator_configs(est_params)
    t0 = time.monotonic()
    n = simulate_to_bag(sc, folder / 'bag', progress=progress)
    off = estimate_bag(folder / 'bag', folder / 'estimate', est_cfg, win_cfg, progress, biases)
    lines = [f'simulated {n} messages -> {folder / "bag"}; estimated -> {folder / "estimate"}']
    lines += [f'offline: {line}' for line in off.lines()]
    # the live states are stamped on the epoch of the scenario, as the offline ones
    live_ns = np.round(rec.times * 1e9).astype(np.int64)
    off_ns = np.round(off.times * 1e9).astype(np.int64)
    common, i, j = np.intersect1d(live_ns, off_ns, return_indices=True)
    out: dict[str, Any] = {
        'offline_folder': str(folder / 'estimate'),
        'live_states': int(live_ns.size),
        'offline_states': int(off_ns.size),
        'common_states': int(common.size),
    }
    if common.size:
        dp = np.linalg.norm(rec.state[i, :3] - off.state[j, :3], axis=1)
        dv = np.linalg.norm(rec.state[i, 3:] - off.state[j, 3:], axis=1)
        sig = np.sqrt(np.trace(off.covariance[j, :3, :3], axis1=1, axis2=2))
        out.update(
            max_position_difference_m=float(dp.max()),
            max_velocity_difference_m_s=float(dv.max()),
            max_position_difference_over_sigma=float(np.max(dp / sig)),
        )
        lines.append(
            f'live vs offline: {common.size} common states (live {live_ns.size}, offline '
            f'{off_ns.size}); largest position difference {dp.max():.3g} m '
            f'({np.max(dp / sig):.3g} of the offline 1-sigma), velocity {dv.max():.3g} m/s'
        )
    else:
        lines.append(
            f'live vs offline: no common output time (live {live_ns.size}, offline '
            f'{off_ns.size} states)'
        )
    lines.append(f'offline cross-check: {time.monotonic() - t0:.1f} s')
    out['lines'] = lines
    return out


def add_demo(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the ``demo`` subcommand to ``sub``."""
    s = sub.add_parser(
        'demo',
        help='the main job: the nodes over DDS, their recorded output files, report.html',
        description='The main job. Starts triangulation, estimator, results and a recorder '
        '(orbit-tracking record) as separate processes talking over DDS, then scenario_sim, '
        "which streams the scenario with truth and telemetry; waits for the estimator's last "
        "window and the results node's last states, stops everything and writes, into the "
        'run folder, the output files of orbit-tracking estimate from the recording '
        '(trajectory.csv of the results node, biases.csv, biases_by_window.csv, summary.yaml '
        'with the errors against truth), an offline cross-check (the scenario simulated into '
        'offline/bag and estimated into offline/estimate with the same settings, compared '
        'with the live trajectory) and report.html with its PNG figures. Node logs go to '
        'logs/, the recording to live_bag/.',
    )
    s.add_argument('--scenario', default='seed000_s1', help='scenario name or YAML path')
    s.add_argument('--out', default=None, help='run folder (default runs/<scenario>)')
    add_force(s)
    s.add_argument(
        '--rate-factor',
        type=float,
        default=5.0,
        help='scenario seconds streamed per wall second (default 5)',
    )
    s.add_argument(
        '--offline-check',
        action=argparse.BooleanOptionalAction,
        default=True,
        help='also simulate and estimate the scenario offline and compare with the live '
        'trajectory (default on)',
    )
    s.add_argument('--quiet', action='store_true', help='no progress lines or bars')
    s.set_defaults(func=_cmd_demo)
