"""The ``security`` command of ``orbit-tracking``: TLS credentials and Fast DDS profiles that
keep strangers off the nodes' topics (:mod:`orbit_tracking.tools.security`,
docs/SECURITY.md).

::

    orbit-tracking security init DIR --participants a,b,c [--base-port P] [--host IP] [--force]
    orbit-tracking security env DIR NAME      the environment of participant NAME (eval-able)
    orbit-tracking security check DIR NAME    probe the running participant NAME's TLS port
"""

from __future__ import annotations

import argparse
import functools
import shlex
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from orbit_tracking.tools.security import SecurityLayout

__all__ = ['add_security']

_Handler = Callable[[argparse.Namespace], int]


def _one_line_errors(handler: _Handler) -> _Handler:
    """A bad argument value (``ValueError``: a participant name, a port, an unknown
    participant) is one line on stderr and exit status 2, like the errors ``main`` catches."""

    @functools.wraps(handler)
    def run(args: argparse.Namespace) -> int:
        try:
            return handler(args)
        except ValueError as exc:
            print(f'orbit-tracking security: error: {exc}', file=sys.stderr)
            return 2

    return run


def _env_lines(layout: SecurityLayout, name: str) -> list[str]:
    from orbit_tracking.tools.security import UNSET_VARIABLES, environment

    lines = [f'export {k}={shlex.quote(v)}' for k, v in environment(layout, name).items()]
    lines += [f'unset {k}' for k in UNSET_VARIABLES]
    return lines


@_one_line_errors
def _cmd_init(args: argparse.Namespace) -> int:
    from orbit_tracking.tools.security import connects_to, init_security, parse_participants

    participants = parse_participants(args.participants, args.base_port, args.host)
    layout = init_security(args.dir, participants, days=args.days, force=args.force)
    d = layout.directory
    print(f'wrote {d}: CA certificate ca.crt, openssl.cnf, and per participant a folder with')
    print('its certificate, its key (mode 0600) and profile.xml; the CA key was not kept')
    width = max(len(p.name) for p in participants)
    for p in participants:
        peers = (
            ', '.join(q.name for q in participants if connects_to(p, q))
            or 'none (the others connect to it)'
        )
        print(f'  {p.name:<{width}}  listens on {p.host}:{p.port}, connects to {peers}')
    first = participants[0].name
    print()
    print('Start each participant in its own process with its own environment, e.g.')
    print(f'  eval "$(orbit-tracking security env {shlex.quote(str(d))} {first})"')
    print(f'  ros2 run orbit_tracking {first}     # or any ROS 2 process')
    print(f'which sets (for {first}):')
    for line in _env_lines(layout, first):
        print(f'  {line}')
    print('ROS_AUTOMATIC_DISCOVERY_RANGE must not be LOCALHOST (scripts/env.sh sets it: set the')
    print('variables after sourcing it): with LOCALHOST, rmw_fastrtps adds UDP and shared')
    print('memory transports that bypass TLS. Every process on the secured topics, ros2 CLI')
    print('tools included, needs a participant of its own.')
    print(f'Check a running participant: orbit-tracking security check {shlex.quote(str(d))} NAME')
    return 0


@_one_line_errors
def _cmd_env(args: argparse.Namespace) -> int:
    from orbit_tracking.tools.security import load_layout

    print('\n'.join(_env_lines(load_layout(args.dir), args.name)))
    return 0


@_one_line_errors
def _cmd_check(args: argparse.Namespace) -> int:
    from orbit_tracking.tools.security import load_layout
    from orbit_tracking.tools.security_check import check_participant

    layout = load_layout(args.dir)
    me = layout.participant(args.name)
    print(f'probing participant {me.name} at {me.host}:{me.port}')
    failed = 0
    for what, expected, probe in check_participant(layout, args.name):
        ok = probe.accepted == expected
        failed += not ok
        verdict = 'accepted' if probe.accepted else 'refused'
        print(f'  {"ok  " if ok else "FAIL"} {what}: {verdict} ({probe.detail})')
    if failed:
        print(
            f'{failed} check(s) failed: {me.name} is not protected as it should be',
            file=sys.stderr,
        )
        return 1
    print(f'{me.name} accepts only TLS peers with a certificate of this CA')
    return 0


def add_security(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``orbit-tracking security {init,env,check}``."""
    from orbit_tracking.tools.security import DEFAULT_BASE_PORT, DEFAULT_HOST

    p = sub.add_parser(
        'security',
        help='TLS credentials and Fast DDS profiles that keep strangers off the topics',
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ssub = p.add_subparsers(dest='security_command', required=True)

    init = ssub.add_parser(
        'init',
        help='a CA, one certificate/key/profile per participant',
        description='Write a private CA certificate, one certificate, key (0600) and Fast DDS '
        'profile per participant (TLS over TCP only: no UDP, no shared memory) and the '
        'OpenSSL settings that make every participant require a client certificate.',
    )
    init.add_argument('dir', help='folder to create (refused if it exists, unless --force)')
    init.add_argument(
        '--participants',
        required=True,
        help='comma-separated NAME[@HOST][:PORT]: one per process (e.g. '
        'estimator,triangulation,results)',
    )
    init.add_argument(
        '--base-port',
        type=int,
        default=DEFAULT_BASE_PORT,
        help='TCP port of the first participant; the next ones count up (default %(default)s)',
    )
    init.add_argument(
        '--host',
        default=DEFAULT_HOST,
        help='IPv4 address participants without @HOST listen on (default %(default)s)',
    )
    init.add_argument(
        '--days', type=int, default=365, help='certificate validity (default %(default)s)'
    )
    init.add_argument('--force', action='store_true', help='replace DIR if it exists')
    init.set_defaults(func=_cmd_init)

    env = ssub.add_parser(
        'env',
        help="print a participant's environment (eval it before starting the process)",
    )
    env.add_argument('dir', help='folder written by `security init`')
    env.add_argument('name', help='participant name')
    env.set_defaults(func=_cmd_env)

    check = ssub.add_parser(
        'check',
        help="probe a running participant's port: own CA accepted, strangers refused",
    )
    check.add_argument('dir', help='folder written by `security init`')
    check.add_argument('name', help='participant name')
    check.set_defaults(func=_cmd_check)
