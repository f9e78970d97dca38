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
    orbit-tracking security init|env|check DIR ...    TLS credentials and Fast DDS profiles
                                                      that keep strangers off the topics

Run ``orbit-tracking <command> --help`` for the options of each.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.tools.commands import bench, data, demo, offline, security

__all__ = ['build_parser', 'main']


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog='orbit-tracking',
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest='command', required=True)
    for add in (
        data.add_scenarios,
        data.add_simulate,
        data.add_record,
        data.add_replay,
        offline.add_triangulate,
        offline.add_estimate,
        demo.add_demo,
        bench.add_bench,
        offline.add_report,
        security.add_security,
    ):
        add(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run one subcommand; its exit status.

    The errors a command raises on purpose (:class:`OrbitTrackingError`: a bad bag,
    scenario or parameter file, an output folder that exists, ...) and file-system errors
    (``OSError``: a path that cannot be read or written) are printed as one line,
    ``orbit-tracking <command>: error: <what>``, on stderr, with exit status 2.
    """
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except (OrbitTrackingError, OSError) as exc:
        text = ' '.join(str(exc).split()) or type(exc).__name__
        print(f'orbit-tracking {args.command}: error: {text}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
