"""``orbit-tracking``: the command-line front end: offline tools, the recorder and player,
the main job and the benchmarks.

Subcommands::

    orbit-tracking scenarios                          list the scenario files
    orbit-tracking simulate --scenario NAME --out DIR write a scenario to a rosbag2
    orbit-tracking record --out DIR [--scenario NAME] record the contract topics from DDS
    orbit-tracking replay BAG [--rate R] [--loop] [--clock]
                                                      publish a bag's messages over DDS
                                                      (alias: play)
    orbit-tracking triangulate BAG --out DIR          fixes.csv from a bag's lines of sight
    orbit-tracking estimate BAG --out DIR             trajectory.csv from a bag, estimated in
                                                      the estimator node's sliding windows
    orbit-tracking demo [--scenario NAME] [--out DIR] the main job: the nodes over DDS
                                                      (scenario_sim, triangulation, estimator,
                                                      results) and a recorder, the output
                                                      files of the recording, an offline
                                                      cross-check, report.html
    orbit-tracking report DIR                         report.html (with PNG figures) of an
                                                      estimate or demo output folder
    orbit-tracking bench [--suite S] [--seeds N] [--write-docs]
                                                      accuracy vs truth and CRB, wall time

Run ``orbit-tracking <command> --help`` for the options of each.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from orbit_tracking.core.errors import OrbitTrackingError

if TYPE_CHECKING:
    from orbit_tracking.core.sim.scenario import Scenario
    from orbit_tracking.tools.recording import RecordingReport

__all__ = ['main']


def _cmd_scenarios(_args: argparse.Namespace) -> int:
    from orbit_tracking.core.sim.scenario import list_scenarios, load_scenario

    for name in list_scenarios():
        sc = load_scenario(name)
        print(f'{name:24s} {sc.description}')
    return 0


def _cmd_simulate(args: argparse.Namespace) -> int:
    from orbit_tracking.core.sim.scenario import load_scenario
    from orbit_tracking.tools.simulate import simulate_to_bag

    sc = load_scenario(args.scenario)
    t0 = time.monotonic()
    n = simulate_to_bag(
        sc, args.out, args.storage, args.batch_period, not args.no_truth, not args.quiet
    )
    print(
        f'wrote {n} messages of scenario {sc.name} to {args.out} ({time.monotonic() - t0:.1f} s)'
    )
    return 0


def _cmd_record(args: argparse.Namespace) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException

    from orbit_tracking.ros.recorder import DEFAULT_TOPICS, RecorderNode
    from orbit_tracking.ros.runner import context_goes_down

    labels: dict[str, str] = {}
    if args.scenario:
        from orbit_tracking.core.sim.scenario import load_scenario
        from orbit_tracking.tools.simulate import scenario_custom_data

        labels = scenario_custom_data(load_scenario(args.scenario))
    rclpy.init()
    try:
        node = RecorderNode(args.out, args.topics or DEFAULT_TOPICS, args.storage, labels)
    except BaseException:
        # e.g. --out exists: leave rclpy as we found it, so main() can report and return
        rclpy.try_shutdown()
        raise
    start = time.monotonic()
    try:
        while rclpy.ok():
            rclpy.spin_once(node, timeout_sec=0.1)
            now = time.monotonic()
            if args.duration and now - start >= args.duration:
                break
            if (
                args.idle
                and node.first_message is not None
                and now - node.last_message >= args.idle
            ):
                break
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        if not context_goes_down():  # see run_node: Ctrl-C inside a message conversion
            raise
    finally:
        node.close()
        total = sum(node.counts.values())
        node.destroy_node()
        rclpy.try_shutdown()
    print(f'recorded {total} messages on {len(node.counts)} topics to {args.out}')
    for topic, n in sorted(node.counts.items()):
        print(f'  {topic}: {n}')
    return 0


def _cmd_play(args: argparse.Namespace) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rosbags.rosbag2 import ReaderError

    from orbit_tracking.ros.player import BagPlayerNode

    rclpy.init()
    node = None
    try:
        node = BagPlayerNode(
            args.bag,
            args.rate,
            args.topics,
            args.wait_for_subscribers,
            args.wait_timeout,
            loop=args.loop,
            clock=args.clock,
        )
        rclpy.spin_until_future_complete(node, node.done)  # with --loop: until Ctrl-C
        end = time.monotonic() + args.linger  # let reliable readers catch up before leaving
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, ReaderError) as exc:
        print(f'orbit-tracking {args.command}: error: {exc}', file=sys.stderr)
        return 2
    finally:
        if node is not None:
            loops = f' ({node.loops} loop(s) restarted)' if node.loops else ''
            print(f'played {node.count} messages from {args.bag}{loops}', flush=True)
            node.close()
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def _cmd_triangulate(args: argparse.Namespace) -> int:
    from orbit_tracking.core.triangulation.alignment import AlignConfig
    from orbit_tracking.core.triangulation.intersection import Gates
    from orbit_tracking.tools.triangulate import triangulate_bag

    align = AlignConfig(
        period=args.period,
        max_gap_factor=args.max_gap_factor,
        smoothing_eps=args.smoothing_eps if args.smoothing_eps > 0 else None,
    )
    gates = Gates(args.min_angle, args.max_gdop, args.miss_probability)
    t0 = time.monotonic()
    report = triangulate_bag(args.bag, args.out, align, gates, args.target_id, not args.quiet)
    for line in report.lines():
        print(line)
    print(f'wrote {", ".join(str(f) for f in report.files)} ({time.monotonic() - t0:.1f} s)')
    return 0


def _cmd_estimate(args: argparse.Namespace) -> int:
    import shutil

    from orbit_tracking.core.estimation.bias_files import load_bias_declaration
    from orbit_tracking.core.estimation.config import EstimatorConfig
    from orbit_tracking.core.estimation.windows import WindowConfig
    from orbit_tracking.tools.estimate import estimate_bag

    try:
        win = WindowConfig(args.window_length, args.overlap, output_step=args.output_step)
    except ValueError as exc:
        print(f'orbit-tracking estimate: error: {exc}', file=sys.stderr)
        return 2
    est = EstimatorConfig(knot_method=args.knot_method, use_telemetry=not args.no_telemetry)
    # read the declaration before anything is deleted: a bad file is a one-line error
    biases = load_bias_declaration(args.biases)
    if not Path(args.bag).is_dir():
        raise FileNotFoundError(f'no bag folder {args.bag}')
    out = Path(args.out)
    if out.exists() and any(out.iterdir()):
        if not args.force:
            raise FileExistsError(
                f'{out} exists; pass --force to replace it or choose another --out'
            )
        shutil.rmtree(out)
    t0 = time.monotonic()
    report = estimate_bag(args.bag, out, est, win, not args.quiet, biases)
    for line in report.lines():
        print(line)
    print(f'wrote {", ".join(str(f) for f in report.files)} ({time.monotonic() - t0:.1f} s)')
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    import shutil

    import yaml

    from orbit_tracking.core.sim.scenario import load_scenario
    from orbit_tracking.tools.live import NODES, SIMULATOR, run_live
    from orbit_tracking.tools.recording import write_recorded_outputs
    from orbit_tracking.tools.report import build_html_report, read_output_folder
    from orbit_tracking.tools.report_inputs import report_context

    if not args.rate_factor > 0.0:
        print(
            f'orbit-tracking demo: error: --rate-factor must be > 0; got {args.rate_factor}',
            file=sys.stderr,
        )
        return 2
    sc = load_scenario(args.scenario)
    out = Path(args.out or Path('runs') / sc.name)
    if out.exists():
        if not args.force:
            raise FileExistsError(
                f'{out} exists; pass --force to replace it or choose another --out'
            )
        shutil.rmtree(out)
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
    from orbit_tracking.tools.estimate import estimate_bag, estimator_configs
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


def _cmd_report(args: argparse.Namespace) -> int:
    from orbit_tracking.tools.report import build_html_report, read_output_folder
    from orbit_tracking.tools.report_inputs import output_world_frame, report_context

    run = Path(args.run)
    if not run.is_dir():
        raise FileNotFoundError(f'no folder {run}')
    est = next((d for d in (run, run / 'estimate') if (d / 'trajectory.csv').is_file()), None)
    if est is None:
        raise FileNotFoundError(
            f'{run} has no trajectory.csv (write one with orbit-tracking estimate BAG --out '
            f'{run}, or orbit-tracking demo --out {run})'
        )
    try:
        folder = read_output_folder(est)
    except ValueError as exc:
        raise OrbitTrackingError(str(exc)) from exc
    ctx, notes = report_context(est, folder.summary, args.bag, args.scenario)
    for line in notes:
        print(line)
    path = build_html_report(folder, args.out, ctx, notes, output_world_frame(est))
    print(f'wrote {path}')
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    import platform

    from orbit_tracking.tools.bench.triangulation import (
        TRIANGULATION_SCENARIOS,
        bench_triangulation,
        markdown_table,
        write_docs,
    )

    def footer(t0: float) -> str:
        return (
            f'\n\nMeasured by `orbit-tracking bench --suite {args.suite} --seeds {args.seeds}` '
            f'on {platform.machine()} ({platform.python_implementation()} '
            f'{platform.python_version()}, {os.cpu_count()} cores) in '
            f'{time.monotonic() - t0:.0f} s.'
        )

    if args.suite in ('triangulation', 'all'):
        t0 = time.monotonic()
        rows = bench_triangulation(
            args.scenarios or TRIANGULATION_SCENARIOS, args.seeds, not args.quiet
        )
        text = markdown_table(rows, args.seeds) + footer(t0)
        print(text)
        if args.write_docs:
            write_docs(args.docs, 'triangulation', text)
            print(f'updated {args.docs}')
    if args.suite in ('estimator', 'all'):
        from orbit_tracking.tools.bench.estimator import (
            ESTIMATOR_SCENARIOS,
            bench_estimator,
            estimator_tables,
        )

        t0 = time.monotonic()
        plots = Path(args.docs).parent / 'bench' if args.write_docs else args.plots
        erows = bench_estimator(
            args.scenarios or ESTIMATOR_SCENARIOS, args.seeds, not args.quiet, plots
        )
        text = estimator_tables(erows, args.seeds) + footer(t0)
        if plots:
            text += f' Error plots (seed 0): `{plots}/<scenario>_<method>.png`.'
        print(text)
        if args.write_docs:
            write_docs(args.docs, 'estimator', text)
            print(f'updated {args.docs}')
    if args.suite in ('biases', 'all'):
        from orbit_tracking.tools.bench.biases import BIAS_SCENARIOS, bench_biases, bias_tables

        t0 = time.monotonic()
        brows = bench_biases(args.scenarios or BIAS_SCENARIOS, args.seeds, not args.quiet)
        text = bias_tables(brows, args.seeds) + footer(t0)
        print(text)
        if args.write_docs:
            write_docs(args.docs, 'biases', text)
            print(f'updated {args.docs}')
    if args.suite == 'dds':  # live nodes over DDS; not part of 'all'
        from orbit_tracking.tools.bench.dds import (
            DDS_RATES,
            DDS_SCENARIO,
            DDS_WINDOWS,
            bench_dds,
            dds_table,
        )

        t0 = time.monotonic()
        scenario = args.scenarios[0] if args.scenarios else DDS_SCENARIO
        rates = args.rates or DDS_RATES
        drows = bench_dds(scenario, rates, args.span, progress=not args.quiet)
        command = (
            f'orbit-tracking bench --suite dds --rates {" ".join(f"{r:g}" for r in rates)} '
            f'--span {args.span:g}'
        )
        text = dds_table(drows, scenario, args.span, DDS_WINDOWS, time.monotonic() - t0, command)
        print(text)
        if args.write_docs:
            write_docs(args.docs, 'dds', text)
            print(f'updated {args.docs}')
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='orbit-tracking',
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest='command', required=True)

    s = sub.add_parser('scenarios', help='list the scenario files and their descriptions')
    s.set_defaults(func=_cmd_scenarios)

    s = sub.add_parser('simulate', help='simulate a scenario into a rosbag2 (no DDS)')
    s.add_argument('--scenario', required=True, help='scenario name or YAML path')
    s.add_argument('--out', required=True, help='bag folder to create')
    s.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap')
    s.add_argument(
        '--batch-period',
        type=float,
        default=0.0,
        help='scenario seconds of epochs per measurement message (0: one per epoch)',
    )
    s.add_argument('--no-truth', action='store_true', help='leave truth/state out of the bag')
    s.add_argument('--quiet', action='store_true', help='no progress bar')
    s.set_defaults(func=_cmd_simulate)

    s = sub.add_parser('record', help='record the contract topics from DDS into a rosbag2')
    s.add_argument('--out', required=True, help='bag folder to create')
    s.add_argument(
        '--topics', nargs='*', help='topic glob patterns (default: the contract topics)'
    )
    s.add_argument(
        '--duration',
        type=float,
        default=0.0,
        help='stop after this many seconds (0: until Ctrl-C)',
    )
    s.add_argument(
        '--idle',
        type=float,
        default=0.0,
        help='stop after this many seconds without messages, once some arrived',
    )
    s.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap')
    s.add_argument(
        '--scenario',
        default=None,
        help='label the bag with the scenario being streamed (name or YAML path; its epoch, '
        'world frame, gaps and simulated biases, as simulate writes them), so that estimate '
        'and report find its truth',
    )
    s.set_defaults(func=_cmd_record)

    s = sub.add_parser(
        'replay',
        aliases=['play'],
        help='publish the messages of a bag over DDS with their recorded pace (ros2 bag play)',
    )
    s.add_argument('bag', help='rosbag2 folder')
    s.add_argument('--rate', type=float, default=1.0, help='playback speed factor')
    s.add_argument(
        '--loop',
        action='store_true',
        help='start again at the beginning after the last message, until Ctrl-C',
    )
    s.add_argument(
        '--clock',
        action='store_true',
        help='also publish /clock (rosgraph_msgs/Clock) with the message stamps, for nodes '
        'run with use_sim_time:=true',
    )
    s.add_argument('--topics', nargs='*', help='topic glob patterns to play (default all)')
    s.add_argument(
        '--wait-for-subscribers',
        type=int,
        default=0,
        help='wait until every non-latched topic has this many subscribers before playing',
    )
    s.add_argument('--wait-timeout', type=float, default=30.0, help='longest such wait [s]')
    s.add_argument(
        '--linger', type=float, default=1.0, help='seconds to stay after the last message'
    )
    s.set_defaults(func=_cmd_play)

    s = sub.add_parser('triangulate', help='intersect the lines of sight of a bag into fixes.csv')
    s.add_argument('bag', help='rosbag2 folder with stations/<id>/measurements and state')
    s.add_argument('--out', required=True, help='output folder (fixes.csv, bag/, summary.yaml)')
    s.add_argument(
        '--period',
        type=float,
        default=0.0,
        help='fix epoch spacing [s] (0: smallest sampling interval)',
    )
    s.add_argument(
        '--max-gap-factor',
        type=float,
        default=2.5,
        help='largest interpolation gap in sampling intervals',
    )
    s.add_argument(
        '--smoothing-eps',
        type=float,
        default=0.0,
        help='seed 003 low-pass weight (0: off; e.g. 0.95)',
    )
    s.add_argument(
        '--min-angle', type=float, default=1.0, help='smallest widest-intersection angle [deg]'
    )
    s.add_argument(
        '--max-gdop', type=float, default=100.0, help='largest geometric dilution of precision'
    )
    s.add_argument(
        '--miss-probability',
        type=float,
        default=0.9999,
        help='chi-square gate on the miss distance (1: off)',
    )
    s.add_argument(
        '--target-id',
        type=int,
        default=None,
        help='target written to fixes.csv (default: lowest id)',
    )
    s.add_argument('--quiet', action='store_true', help='no progress bar')
    s.set_defaults(func=_cmd_triangulate)

    s = sub.add_parser('estimate', help='estimate the trajectory of a bag in sliding windows')
    s.add_argument('bag', help='rosbag2 folder with stations/<id>/measurements and state')
    s.add_argument(
        '--out', required=True, help='output folder (trajectory.csv, bag/, summary.yaml)'
    )
    s.add_argument('--window-length', type=float, default=60.0, help='window length [s]')
    s.add_argument(
        '--overlap', type=float, default=20.0, help='overlap of consecutive windows [s]'
    )
    s.add_argument(
        '--output-step', type=float, default=0.1, help='spacing of the output states [s]'
    )
    s.add_argument(
        '--no-telemetry',
        action='store_true',
        help='do not fuse telemetry as measurements (it still places the knots)',
    )
    s.add_argument(
        '--knot-method',
        choices=('sparse', 'dynamics', 'uniform', 'dense', 'polynomial'),
        default='sparse',
        help="knot placement: the seed's sparse selection (default) or a baseline",
    )
    s.add_argument(
        '--biases',
        metavar='FILE|auto',
        default='',
        help='estimate station biases: a YAML declaration (config/biases_example.yaml) or '
        '"auto" (every measured field of every station, weak priors); writes biases.csv',
    )
    s.add_argument('--force', action='store_true', help='replace an existing output folder')
    s.add_argument('--quiet', action='store_true', help='no progress bars')
    s.set_defaults(func=_cmd_estimate)

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
    s.add_argument('--force', action='store_true', help='replace an existing run folder')
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

    s = sub.add_parser('bench', help='accuracy against truth and the CRB, and wall time')
    s.add_argument('--scenarios', nargs='*', help='scenario names (default: the reference set)')
    s.add_argument('--seeds', type=int, default=3, help='noise seeds per scenario')
    s.add_argument('--write-docs', action='store_true', help='update docs/BENCHMARKS.md')
    s.add_argument('--docs', default='docs/BENCHMARKS.md', help='file updated by --write-docs')
    s.add_argument('--quiet', action='store_true', help='no progress lines')
    s.add_argument(
        '--suite',
        choices=('triangulation', 'estimator', 'biases', 'all', 'dds'),
        default='all',
        help='which benchmark to run (default: all; dds, the live nodes over DDS, only '
        'when asked)',
    )
    s.add_argument(
        '--rates',
        type=float,
        nargs='+',
        help='dds: offered measurement rates [measurements/s] (default 250 500 1000 2000 4000)',
    )
    s.add_argument(
        '--span', type=float, default=30.0, help='dds: data seconds published at each rate'
    )
    s.add_argument('--plots', type=Path, help='folder for the estimator error plots')
    s.set_defaults(func=_cmd_bench)

    s = sub.add_parser(
        'report',
        help='report.html of an estimate or demo output folder',
    )
    s.add_argument(
        'run',
        help='folder written by estimate or demo (trajectory.csv, summary.yaml, ...), or one '
        'with such a folder as estimate/',
    )
    s.add_argument(
        '--out', default=None, help='folder for report.html and its PNGs (default: the folder)'
    )
    s.add_argument(
        '--bag',
        default=None,
        help='the estimated bag, for residuals and truth (default: the one summary.yaml names)',
    )
    s.add_argument(
        '--scenario',
        default=None,
        help='scenario name or YAML path to simulate again for truth and measurements',
    )
    s.set_defaults(func=_cmd_report)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except (OrbitTrackingError, FileNotFoundError, FileExistsError) as exc:
        print(f'orbit-tracking {args.command}: error: {exc}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
