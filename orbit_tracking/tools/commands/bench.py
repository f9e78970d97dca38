"""``orbit-tracking bench``: the benchmark suites (triangulation, estimator, biases, seed 003, the
live nodes over DDS and fault injection over DDS), printed as tables and optionally written
into docs/BENCHMARKS.md."""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from orbit_tracking.tools.bench.faults import FaultResult

__all__ = ['add_bench']


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
    if args.suite in ('seed003', 'all'):
        from orbit_tracking.tools.bench.seed003 import (
            SEED003_SCENARIOS,
            bench_seed003,
            seed003_tables,
        )
        from orbit_tracking.tools.bench.seed003_family import bench_seed003_family, family_table

        t0 = time.monotonic()
        plots = Path(args.docs).parent / 'bench' if args.write_docs else args.plots
        srows = bench_seed003(
            args.scenarios or SEED003_SCENARIOS, args.seeds, not args.quiet, print, plots
        )
        text = seed003_tables(srows, args.seeds) + footer(t0)
        if plots:
            text += f' Error plots (seed 0): `{plots}/<scenario>_<biases>_<rocket|adjoint>.png`.'
        t1 = time.monotonic()
        family = bench_seed003_family(args.draws, not args.quiet)
        text += (
            '\n\n'
            + family_table(family)
            + f'\n\nMeasured by `orbit-tracking bench --suite seed003 --draws {args.draws}` '
            f'in {time.monotonic() - t1:.0f} s.'
        )
        print(text)
        if args.write_docs:
            write_docs(args.docs, 'seed003', text)
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
    if args.suite == 'speed':  # wall time against the KF+RTS baseline; not part of 'all'
        from orbit_tracking.tools.bench.speed import SPEED_SCENARIO, bench_speed, speed_table

        t0 = time.monotonic()
        scenario = args.scenarios[0] if args.scenarios else SPEED_SCENARIO
        text = speed_table(bench_speed(scenario, args.repeats, not args.quiet)) + (
            f'\n\nMeasured by `orbit-tracking bench --suite speed --repeats {args.repeats}` on '
            f'{platform.machine()} ({platform.python_implementation()} '
            f'{platform.python_version()}, {os.cpu_count()} cores) in '
            f'{time.monotonic() - t0:.0f} s.'
        )
        print(text)
        if args.write_docs:
            write_docs(args.docs, 'speed', text)
            print(f'updated {args.docs}')
    if args.suite == 'robustness':  # randomised draws against their own CRB; not part of 'all'
        from orbit_tracking.tools.bench.robustness import robustness_tables, run_robustness

        text = robustness_tables(
            run_robustness(
                args.draws, args.kind, args.seed, args.jobs, None if args.quiet else print
            )
        )
        print(text)
        if args.write_docs:
            write_docs(args.docs, 'robustness', text)
            print(f'updated {args.docs}')
    if args.suite == 'faults':  # bad messages into the live nodes over DDS; not part of 'all'
        from orbit_tracking.tools.bench.faults import (
            EXTRA_ROWS,
            faults_table,
            run_faults,
            select_faults,
        )

        if not args.faults:  # the whole catalogue: a restart row per processing node too
            for node in ('estimator', 'results', 'triangulation'):
                EXTRA_ROWS.append(
                    lambda node=node: _restart_row(node, None if args.quiet else print)
                )

        suite = run_faults(
            select_faults(args.faults),
            log_dir=args.logs,
            lanes=args.lanes,
            progress=None if args.quiet else print,
        )
        command = 'orbit-tracking bench --suite faults' + (
            f' --faults {" ".join(args.faults)}' if args.faults else ''
        )
        text = faults_table(suite, command)
        print(text)
        if args.write_docs:
            write_docs(args.docs, 'faults', text)
            print(f'updated {args.docs}')
    return 0


def _restart_row(node: str, progress: Callable[[str], None] | None) -> FaultResult:
    """A restart row of the fault table: ``node`` SIGKILLed mid-pass and started again 1 s
    later, with the journals (:func:`~orbit_tracking.tools.bench.restart.
    measure_restart_loss`)."""
    from orbit_tracking.tools.bench.fault_catalogue import FaultClass
    from orbit_tracking.tools.bench.faults import FaultResult
    from orbit_tracking.tools.bench.restart import measure_restart_loss

    # the results node after two windows: it then holds the tail of the second
    r = measure_restart_loss(
        kill_node=node, kill_after_windows=2 if node == 'results' else 1, progress=progress
    )
    fault = FaultClass(
        f'{node}_sigkill_restart',
        'restart',
        f'{node} killed (SIGKILL) mid-pass, started again 1 s later'
        + ('' if node == 'triangulation' else ' with its journal'),
        (),
        (),
        lambda ref: [],
    )
    return FaultResult(
        fault,
        sent=0,
        counted={},
        counted_how='',
        crash='',
        states=int(r['states_published']),
        clean_states=int(r['states_clean']),
        max_dp_m=float(r['max_position_diff_m']),
        run='alone',
        restart_loss=f'{r["lost"]} of {r["states_clean"]} states'
        + (f', {r["published_twice"]} sent again' if r['published_twice'] else ''),
        missing_states=int(r['lost']),
        # a state sent again unacknowledged is allowed, with the same values
        extra_states=int(r['extra']) + int(r['repeats_differing']),
        max_dp_sigma=float(r['max_diff_over_sigma']),
        sigma_tolerance=RESTART_SIGMA_TOLERANCE,
    )


RESTART_SIGMA_TOLERANCE = 5.0
"""The restart row's bound on any state component's difference from the clean pass, in the
killed pass's own published sigma. The killed pass misses the messages sent while no
estimator ran (a gap of a few seconds) and solves its windows anew, so its states there
are worse than the clean pass's, which had everything; measured against the clean pass in
its own sigma the difference is a consistency check of that sigma. An honest sigma puts a
component beyond 5 sigma with a chance of 6e-7, 1e-3 over the 1 800 components of the
30 s pass; a seam or a gap published with too small a sigma shows well beyond it."""


def add_bench(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the ``bench`` subcommand to ``sub``."""
    s = sub.add_parser('bench', help='accuracy against truth and the CRB, and wall time')
    s.add_argument('--scenarios', nargs='*', help='scenario names (default: the reference set)')
    s.add_argument('--seeds', type=int, default=3, help='noise seeds per scenario')
    s.add_argument('--write-docs', action='store_true', help='update docs/BENCHMARKS.md')
    s.add_argument('--docs', default='docs/BENCHMARKS.md', help='file updated by --write-docs')
    s.add_argument('--quiet', action='store_true', help='no progress lines')
    s.add_argument(
        '--suite',
        choices=(
            'triangulation',
            'estimator',
            'biases',
            'seed003',
            'all',
            'dds',
            'faults',
            'robustness',
            'speed',
        ),
        default='all',
        help='which benchmark to run (default: all; dds, the live nodes over DDS, faults, '
        'bad messages thrown at them, robustness and speed only when asked)',
    )
    s.add_argument(
        '--repeats',
        type=int,
        default=3,
        help='speed: timed runs of estimate (the median is reported)',
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
    s.add_argument(
        '--faults',
        nargs='+',
        metavar='NAME',
        help='faults: fault classes or groups to run (default: the whole catalogue)',
    )
    s.add_argument('--lanes', type=int, default=2, help='faults: replays run at a time (1 or 2)')
    s.add_argument('--logs', type=Path, help='faults: keep the node logs of every replay here')
    s.add_argument(
        '--draws',
        type=int,
        default=20,
        help='robustness, seed003: randomised draws in all (seed003: of its own family)',
    )
    s.add_argument(
        '--kind',
        choices=('ascent', 'aircraft', 'all'),
        default='all',
        help='robustness: scenario family (all: half the draws each)',
    )
    s.add_argument('--seed', type=int, default=0, help='robustness: seed of the first draw')
    s.add_argument('--jobs', type=int, default=2, help='robustness: draws run at a time')
    s.set_defaults(func=_cmd_bench)
