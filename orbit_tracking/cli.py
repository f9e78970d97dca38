"""``orbit-tracking``: the command-line front end for offline work.

Subcommands::

    orbit-tracking scenarios                          list the scenario files
    orbit-tracking simulate --scenario NAME --out DIR write a scenario to a rosbag2
    orbit-tracking record --out DIR                   record the contract topics from DDS
    orbit-tracking triangulate BAG --out DIR          fixes.csv from a bag's lines of sight

Run ``orbit-tracking <command> --help`` for the options of each.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

from orbit_tracking.core.errors import OrbitTrackingError

__all__ = ['main']


def _cmd_scenarios(_args: argparse.Namespace) -> int:
    from orbit_tracking.core.scenario import list_scenarios, load_scenario

    for name in list_scenarios():
        sc = load_scenario(name)
        print(f'{name:24s} {sc.description}')
    return 0


def _cmd_simulate(args: argparse.Namespace) -> int:
    from orbit_tracking.core.scenario import load_scenario
    from orbit_tracking.ros.bagsim import simulate_to_bag

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

    from orbit_tracking.ros.recorder import DEFAULT_TOPICS, RecorderNode

    rclpy.init()
    node = RecorderNode(args.out, args.topics or DEFAULT_TOPICS, args.storage)
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
    except KeyboardInterrupt:
        pass
    finally:
        node.close()
        total = sum(node.counts.values())
        node.destroy_node()
        rclpy.try_shutdown()
    print(f'recorded {total} messages on {len(node.counts)} topics to {args.out}')
    for topic, n in sorted(node.counts.items()):
        print(f'  {topic}: {n}')
    return 0


def _cmd_triangulate(args: argparse.Namespace) -> int:
    from orbit_tracking.core.alignment import AlignConfig
    from orbit_tracking.core.triangulation import Gates
    from orbit_tracking.ros.offline import triangulate_bag

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
    s.set_defaults(func=_cmd_record)

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
