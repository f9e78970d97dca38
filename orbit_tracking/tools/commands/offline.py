"""The offline commands of ``orbit-tracking``: ``triangulate`` and ``estimate`` (a bag
through the nodes' pipelines, no DDS) and ``report`` (report.html of an output folder)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.tools.commands.common import add_force, input_bag, prepare_output_folder

__all__ = ['add_triangulate', 'add_estimate', 'add_report']


def _cmd_triangulate(args: argparse.Namespace) -> int:
    bag = input_bag(args.bag)  # checked before the numerical modules load: a quick error
    from orbit_tracking.core.triangulation.alignment import AlignConfig
    from orbit_tracking.core.triangulation.intersection import Gates
    from orbit_tracking.tools.triangulate import triangulate_bag

    align = AlignConfig(
        period=args.period,
        max_gap_factor=args.max_gap_factor,
        smoothing_eps=args.smoothing_eps if args.smoothing_eps > 0 else None,
    )
    gates = Gates(args.min_angle, args.max_gdop, args.miss_probability)
    out = prepare_output_folder(args.out, args.force, [bag])
    t0 = time.monotonic()
    report = triangulate_bag(bag, out, align, gates, args.target_id, not args.quiet)
    for line in report.lines():
        print(line)
    print(f'wrote {", ".join(str(f) for f in report.files)} ({time.monotonic() - t0:.1f} s)')
    return 0


def _cmd_estimate(args: argparse.Namespace) -> int:
    bag = input_bag(args.bag)  # checked before the numerical modules load: a quick error
    from orbit_tracking.core.estimation.bias_files import load_bias_declaration
    from orbit_tracking.tools.estimate import estimate_bag
    from orbit_tracking.tools.estimator_parameters import (
        NODE_ONLY_PARAMETERS,
        estimator_configs,
        read_parameters_file,
    )

    try:
        params = read_parameters_file(args.params_file) if args.params_file else {}
        given = {
            'window_length': args.window_length,
            'window_overlap': args.overlap,
            'output_step': args.output_step,
            'knot_method': args.knot_method,
            'use_telemetry': False if args.no_telemetry else None,
            'bias_file': args.biases,
        }
        params.update({k: v for k, v in given.items() if v is not None})
        est, win, bias_file = estimator_configs(params)
    except ValueError as exc:
        print(f'orbit-tracking estimate: error: {exc}', file=sys.stderr)
        return 2
    unused = sorted(NODE_ONLY_PARAMETERS & set(params) - {'bias_file'})
    if unused and not args.quiet:
        print(f'estimate: parameters of the live node only, not used offline: {", ".join(unused)}')
    # read the declaration and the times before anything is deleted: a one-line error
    biases = load_bias_declaration(bias_file)
    times = None
    if args.report_times:
        from orbit_tracking.tools.estimate_dynamics import parse_report_times

        try:
            times = parse_report_times(args.report_times)
        except ValueError as exc:
            print(f'orbit-tracking estimate: error: {exc}', file=sys.stderr)
            return 2
    out = prepare_output_folder(args.out, args.force, [bag])
    t0 = time.monotonic()
    if args.model != 'spline':
        from orbit_tracking.tools.estimate_dynamics import estimate_dynamics_bag

        stages = {'1': 1, '2': 2, 'auto': 0}[args.stages]
        dyn = estimate_dynamics_bag(
            bag,
            out,
            biases,
            times,
            args.model,
            win.output_step,
            not args.quiet,
            args.j2,
            stages,
        )
        for line in dyn.lines():
            print(line)
        print(f'wrote {", ".join(str(f) for f in dyn.files)} ({time.monotonic() - t0:.1f} s)')
        return 0 if dyn.fit.success else 1
    if times is not None:
        print(
            'orbit-tracking estimate: error: --report-times needs a dynamics model '
            '(--model rocket or adjoint)',
            file=sys.stderr,
        )
        return 2
    report = estimate_bag(bag, out, est, win, not args.quiet, biases)
    for line in report.lines():
        print(line)
    print(f'wrote {", ".join(str(f) for f in report.files)} ({time.monotonic() - t0:.1f} s)')
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    if args.bag is not None:
        input_bag(args.bag)  # before the plotting modules load: a quick error
    from orbit_tracking.tools.report import (
        build_html_report,
        output_world_frame,
        read_output_folder,
        report_context,
    )

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


def add_triangulate(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the ``triangulate`` subcommand to ``sub``."""
    s = sub.add_parser('triangulate', help='intersect the lines of sight of a bag into fixes.csv')
    s.add_argument(
        'bag',
        help='rosbag2 folder with stations/<id>/measurements and state (or its only .mcap/.db3 '
        'file)',
    )
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
    add_force(s)
    s.add_argument('--quiet', action='store_true', help='no progress bar')
    s.set_defaults(func=_cmd_triangulate)


def add_estimate(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the ``estimate`` subcommand to ``sub``."""
    s = sub.add_parser('estimate', help='estimate the trajectory of a bag in sliding windows')
    s.add_argument(
        'bag',
        help='rosbag2 folder with stations/<id>/measurements and state (or its only .mcap/.db3 '
        'file)',
    )
    s.add_argument(
        '--out', required=True, help='output folder (trajectory.csv, bag/, summary.yaml)'
    )
    s.add_argument(
        '--params-file',
        metavar='YAML',
        default='',
        help="the estimator node's ROS 2 parameter file (config/estimator.yaml format): the "
        'offline run takes the settings a node started with it would; the options below '
        'override it',
    )
    s.add_argument(
        '--window-length', type=float, default=None, help='window length [s] (default 60)'
    )
    s.add_argument(
        '--overlap',
        type=float,
        default=None,
        help='overlap of consecutive windows [s] (default 20)',
    )
    s.add_argument(
        '--output-step',
        type=float,
        default=None,
        help='spacing of the output states [s] (default 0.1)',
    )
    s.add_argument(
        '--no-telemetry',
        action='store_true',
        help='do not fuse telemetry as measurements (it still places the knots)',
    )
    s.add_argument(
        '--knot-method',
        choices=('sparse', 'dynamics', 'uniform', 'dense', 'polynomial'),
        default=None,
        help="knot placement: the seed's sparse selection (default) or a baseline",
    )
    s.add_argument(
        '--model',
        choices=('spline', 'rocket', 'adjoint'),
        default='spline',
        help="trajectory model: the seed's B-spline in sliding windows (default); seed "
        "003's rocket-equation flight fitted to the whole bag; or seed 003's adjoint "
        'assimilation of a free thrust profile, started from the rocket fit (both: '
        'Earth-centred frames, telemetry unused, exit code 1 when the fit is not a success)',
    )
    s.add_argument(
        '--stages',
        choices=('1', '2', 'auto'),
        default='1',
        help='with --model rocket or adjoint: burns of the rocket model: one (default), two '
        '(a staging at an unknown time, searched on a 10 s grid), or auto (two when one does '
        'not fit, or when one leaves more than white noise and a staging explains it)',
    )
    s.add_argument(
        '--j2',
        action='store_true',
        help="with --model rocket or adjoint: the Earth's J2 in the gravity (default: point mass)",
    )
    s.add_argument(
        '--report-times',
        metavar='A:B:STEP|T1,T2,...',
        default='',
        help='with --model rocket or adjoint: also write report_times.csv, the states and thrust '
        'acceleration with sigma at these times (both ends included), e.g. 50:170:10',
    )
    s.add_argument(
        '--biases',
        metavar='FILE|auto',
        default=None,
        help='estimate station biases: a YAML declaration (config/biases_example.yaml) or '
        '"auto" (every measured field of every station, weak priors); writes biases.csv',
    )
    add_force(s)
    s.add_argument('--quiet', action='store_true', help='no progress bars')
    s.set_defaults(func=_cmd_estimate)


def add_report(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the ``report`` subcommand to ``sub``."""
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
