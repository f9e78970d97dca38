"""The Jazzy start-up/shutdown shape shared by every node's ``main``."""

from __future__ import annotations

import faulthandler
import sys
import time
from collections.abc import Callable, Iterable

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.publisher import Publisher

from orbit_tracking.core.errors import OrbitTrackingError

__all__ = ['context_goes_down', 'ready_to_stream', 'run_node']

SHUTDOWN_GRACE_S = 2.0
"""How long a RuntimeError out of ``spin`` waits for a signal-driven shutdown to show."""

CLEANUP_LIMIT_S = 15.0
"""How long the clean-up after ``spin`` (executor, node, context) may take before the
process dumps every thread's stack to stderr and exits with status 1. A clean-up stuck in
rclpy's ``destroy_node`` (seen once in CI, 30 s and more) must not keep a stopped node alive."""


def context_goes_down(grace_s: float = SHUTDOWN_GRACE_S) -> bool:
    """Whether rclpy's context is shut down within ``grace_s`` seconds (a RuntimeError out
    of a spin during Ctrl-C is then part of the shutdown)."""
    deadline = time.monotonic() + grace_s
    while rclpy.ok():
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)
    return True


def run_node(factory: Callable[[], Node], args: list[str] | None = None) -> None:
    """Initialise rclpy, build the node, spin until shutdown (or until the node's ``done``
    future completes when its ``shutdown_when_done`` parameter is true), then clean up.

    A configuration error while building the node is logged as one clear line and the
    process exits with status 2 instead of a traceback.
    """
    rclpy.init(args=args)
    node = None
    executor = None
    code = 0
    try:
        try:
            node = factory()
        except (
            OrbitTrackingError,
            ParameterException,
            ValueError,
            KeyError,
            FileNotFoundError,
        ) as exc:
            rclpy.logging.get_logger('orbit_tracking').fatal(f'cannot start: {exc}')
            code = 2
            return
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        done = getattr(node, 'done', None)
        if done is not None and bool(getattr(node, 'shutdown_when_done', False)):
            executor.spin_until_future_complete(done)
        else:
            executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # On SIGINT, Python raises KeyboardInterrupt at the next bytecode while rclpy shuts
        # the context down from its own signal thread. When the interrupt lands inside
        # rclpy's C++ message conversion it surfaces as "Unable to convert call argument"
        # instead, possibly before that thread has run (seen under CI load). If the context
        # goes down shortly, it was a shutdown, not an error.
        if not context_goes_down(SHUTDOWN_GRACE_S):
            raise
    finally:
        # a C-level timer: it fires even when the clean-up holds the GIL
        faulthandler.dump_traceback_later(CLEANUP_LIMIT_S, exit=True)
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        faulthandler.cancel_dump_traceback_later()
        if code:
            sys.exit(code)


def ready_to_stream(
    elapsed: float,
    start_delay: float,
    wait_for_subscribers: int,
    wait_timeout: float,
    publishers: Iterable[Publisher],
) -> bool:
    """Whether a streaming node (simulator, bag player) may start: ``start_delay`` wall
    seconds have passed since it was created and every one of ``publishers`` has at least
    ``wait_for_subscribers`` readers, or ``wait_timeout`` more seconds have passed."""
    if elapsed < start_delay:
        return False
    if wait_for_subscribers <= 0 or elapsed >= start_delay + wait_timeout:
        return True
    return all(p.get_subscription_count() >= wait_for_subscribers for p in publishers)
