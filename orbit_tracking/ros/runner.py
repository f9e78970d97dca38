"""The Jazzy start-up/shutdown shape shared by every node's ``main``.

SIGINT and SIGTERM are served by :class:`StopRequest` on the main thread, not by rclpy's
own handlers: rclpy's shut the context down from its signal thread while the main thread
may be inside an rcl call (publishing, taking a message), and raise KeyboardInterrupt at
whatever bytecode runs next, which can be inside a message's conversion. A node that was
stopped that way once died with SIGSEGV in CI. Here a signal only asks the spin loop to
end; the context is shut down after the loop, on the main thread. Numerical work in the
core (a window solve can take seconds) is interrupted at once, because nothing there
touches ROS or files; anything else finishes its callback first. A second signal
interrupts wherever the node is.
"""

from __future__ import annotations

import faulthandler
import os
import signal
import sys
import time
from collections.abc import Callable, Iterable
from types import FrameType

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.signals import SignalHandlerOptions

from orbit_tracking.core.errors import OrbitTrackingError

__all__ = ['MATCH_SETTLE_S', 'StopRequest', 'StreamGate', 'context_goes_down', 'run_node']

SHUTDOWN_GRACE_S = 2.0
"""How long a RuntimeError out of the spin waits for a shutdown from elsewhere to show."""

CLEANUP_LIMIT_S = 15.0
"""How long the clean-up after ``spin`` (executor, node, context) may take before the
process dumps every thread's stack to stderr and exits with status 1. A clean-up stuck in
rclpy's ``destroy_node`` (seen once in CI, 30 s and more) must not keep a stopped node alive."""


SPIN_PERIOD_S = 0.1
"""Longest wait of one spin step: how soon a stop request that arrived during a wait is seen."""

_PACKAGE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_CORE = os.path.join(_PACKAGE, 'core') + os.sep
_CORE_IO = os.path.join(_CORE, 'data') + os.sep  # journals: their writes are not cut short
_ROS_MARKERS = tuple(
    os.sep + m + os.sep for m in ('rclpy', 'rpyutils', 'msg', 'srv', 'action', 'rosidl_parser')
)


def interruptible(frame: FrameType | None) -> bool:
    """Whether the main thread, stopped at ``frame``, is in the core's numerical work: the
    innermost frame of this package is under ``core/`` (not its file I/O) and no ROS frame
    (rclpy, a message module) lies inside it."""
    while frame is not None:
        path = os.path.abspath(frame.f_code.co_filename)
        if path.startswith(_PACKAGE + os.sep):
            return path.startswith(_CORE) and not path.startswith(_CORE_IO)
        if any(m in path for m in _ROS_MARKERS):
            return False
        frame = frame.f_back
    return False


class StopRequest:
    """SIGINT/SIGTERM turned into a request the spin loop polls (see the module's text).

    ``signum`` is the first signal received (None while there is none). The first signal
    raises KeyboardInterrupt only when it lands in the core's numerical work; a second one
    raises it anywhere.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.signum: int | None = None
        self._previous: dict[int, object] = {}

    def install(self) -> None:
        for s in self.SIGNALS:
            self._previous[s] = signal.signal(s, self._on_signal)

    def restore(self) -> None:
        for s, h in self._previous.items():
            signal.signal(s, h)  # type: ignore[arg-type]
        self._previous.clear()

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        again = self.signum is not None
        if not again:
            self.signum = signum
        if again or interruptible(frame):
            raise KeyboardInterrupt


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
    process exits with status 2 instead of a traceback. SIGINT/SIGTERM end the spin (see
    :class:`StopRequest`); one that arrives while the node is being built ends it right
    after.
    """
    stop = StopRequest()
    stop.install()
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
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
        if done is None or not bool(getattr(node, 'shutdown_when_done', False)):
            done = None
        context = executor.context
        while not stop.requested and context.ok() and not (done is not None and done.done()):
            executor.spin_once(timeout_sec=SPIN_PERIOD_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # When the context is shut down from elsewhere (another thread of the process) while
        # a callback runs, rclpy can fail with "Unable to convert call argument" (rclpy's own
        # signal handling did this under CI load before StopRequest). If the context goes
        # down shortly, it was a shutdown, not an error.
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
        stop.restore()
        if code:
            sys.exit(code)


MATCH_SETTLE_S = 0.5
"""Wall seconds every publisher must have had its readers before a stream starts. A writer
matches a reader before the reader has matched the writer, and a volatile reader drops what
comes before that (seen: the first messages of a 10x simulation lost to a test's reader)."""


class StreamGate:
    """When a streaming node (simulator, bag player) may start: ``start_delay`` wall
    seconds after it was created and once every publisher has had at least
    ``wait_for_subscribers`` readers for :data:`MATCH_SETTLE_S`, or ``wait_timeout`` more
    seconds have passed."""

    def __init__(self, start_delay: float, wait_for_subscribers: int, wait_timeout: float):
        self.start_delay = start_delay
        self.wait_for_subscribers = wait_for_subscribers
        self.wait_timeout = wait_timeout
        self.created = time.monotonic()
        self._matched: float | None = None

    def ready(self, now: float, publishers: Iterable[Publisher]) -> bool:
        elapsed = now - self.created
        if elapsed < self.start_delay:
            return False
        if self.wait_for_subscribers <= 0 or elapsed >= self.start_delay + self.wait_timeout:
            return True
        if not all(p.get_subscription_count() >= self.wait_for_subscribers for p in publishers):
            self._matched = None
            return False
        if self._matched is None:
            self._matched = now
        return now - self._matched >= MATCH_SETTLE_S
