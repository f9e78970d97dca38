"""The data commands of ``orbit-tracking``: ``scenarios`` (list the scenario files),
``simulate`` (a scenario into a rosbag2), ``record`` (DDS topics into a rosbag2) and
``replay`` (alias ``play``: a rosbag2 back onto DDS)."""

from __future__ import annotations

import argparse
import sys
import time

from orbit_tracking.tools.commands.common import add_force, input_bag, prepare_output_folder

__all__ = ['add_scenarios', 'add_simulate', 'add_record', 'add_replay']


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
    out = prepare_output_folder(args.out, args.force)
    t0 = time.monotonic()
    n = simulate_to_bag(
        sc, out, args.storage, args.batch_period, not args.no_truth, not args.quiet
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
    prepare_output_folder(args.out, args.force)
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

    from orbit_tracking.ros.bag import BagError
    from orbit_tracking.ros.player import BagPlayerNode

    bag = input_bag(args.bag, scan=True)  # a bad bag: one line before any node starts
    rclpy.init()
    node = None
    try:
        node = BagPlayerNode(
            bag,
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
    except (ValueError, ReaderError, BagError) as exc:  # e.g. a storage file bad half way
        text = ' '.join(str(exc).split())
        print(f'orbit-tracking {args.command}: error: {text}', file=sys.stderr)
        return 2
    finally:
        if node is not None:
            loops = f' ({node.loops} loop(s) restarted)' if node.loops else ''
            print(f'played {node.count} messages from {bag}{loops}', flush=True)
            node.close()
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def add_scenarios(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the ``scenarios`` subcommand to ``sub``."""
    s = sub.add_parser('scenarios', help='list the scenario files and their descriptions')
    s.set_defaults(func=_cmd_scenarios)


def add_simulate(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the ``simulate`` subcommand to ``sub``."""
    s = sub.add_parser('simulate', help='simulate a scenario into a rosbag2 (no DDS)')
    s.add_argument('--scenario', required=True, help='scenario name or YAML path')
    s.add_argument('--out', required=True, help='bag folder to create')
    add_force(s)
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


def add_record(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the ``record`` subcommand to ``sub``."""
    s = sub.add_parser('record', help='record the contract topics from DDS into a rosbag2')
    s.add_argument('--out', required=True, help='bag folder to create')
    add_force(s)
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


def add_replay(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the ``replay`` subcommand to ``sub``."""
    s = sub.add_parser(
        'replay',
        aliases=['play'],
        help='publish the messages of a bag over DDS with their recorded pace (ros2 bag play)',
    )
    s.add_argument('bag', help='rosbag2 folder (or its only .mcap/.db3 file)')
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
