"""One background thread for a node's heavy core calls (the estimator's window solves).

While a window is solved, the node's executor goes on taking messages, answering services
and publishing ``/diagnostics``: before, a solve of a few seconds (more under load, twenty
windows after a stall) held the executor, messages queued in the middleware and the node
looked hung to anyone watching its status.

Only the core call runs on the worker. The node's own state is touched by its executor
thread alone: the node gathers a window's inputs, hands the worker a function of them
(:meth:`SolveWorker.submit`), and takes the finished job back on the executor
(:meth:`SolveWorker.take`), woken by a guard condition the worker triggers when the call
returns. One job at a time: a window starts from the previous window's solution.

The thread is a daemon: a node stopped mid-solve exits without waiting for the solve (the
core holds no files or ROS handles, so nothing is left half-written).
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

from rclpy.node import Node

__all__ = ['Job', 'SolveWorker']


@dataclass
class Job:
    """A core call handed to the worker: what the node needs to finish it (``context``),
    the call's future and when it was handed over (``time.monotonic``)."""

    context: Any
    future: Future[Any]
    started: float = field(default_factory=time.monotonic)

    @property
    def running_s(self) -> float:
        return time.monotonic() - self.started


class SolveWorker:
    """A daemon thread running one job at a time; ``on_done`` is called on the node's
    executor when a job has finished (take it with :meth:`take`). ``prepare`` runs on the
    thread first (imports and solver start-up the first job would otherwise pay)."""

    def __init__(
        self,
        node: Node,
        on_done: Callable[[], None],
        prepare: Callable[[], object] | None = None,
    ) -> None:
        self._guard = node.create_guard_condition(on_done)
        self._prepare = prepare
        self._logger = node.get_logger()
        self._tasks: queue.SimpleQueue[tuple[Future[Any], Callable[[], Any]]] = queue.SimpleQueue()
        self.job: Job | None = None
        self._thread = threading.Thread(
            target=self._run, name=f'{node.get_name()}_solve', daemon=True
        )
        self._thread.start()

    @property
    def busy(self) -> bool:
        """Whether a job was handed over and not yet taken back."""
        return self.job is not None

    def submit(self, context: Any, fn: Callable[[], Any], here: bool = False) -> None:
        """Run ``fn()`` on the worker; ``context`` comes back with the job. ``here``: run
        it now on the calling thread instead (the job is done when this returns), so that
        no two threads ever compute at once and the numbers do not depend on timing."""
        if self.job is not None:
            raise RuntimeError('the solve worker runs one job at a time; take the last first')
        future: Future[Any] = Future()
        self.job = Job(context, future)
        if not here:
            self._tasks.put((future, fn))
            return
        future.set_running_or_notify_cancel()
        try:
            future.set_result(fn())
        except Exception as exc:  # handed to the node with the job
            future.set_exception(exc)

    def take(self, block: bool = False) -> Job | None:
        """The finished job, handed back once (its future holds the result or the
        exception); None while it runs (``block``: wait for it) or when there is none."""
        job = self.job
        if job is None:
            return None
        if not job.future.done():
            if not block:
                return None
            job.future.exception()  # waits; the result or exception stays in the future
        self.job = None
        return job

    def _run(self) -> None:
        if self._prepare is not None:  # jobs handed over meanwhile wait in the queue
            try:
                self._prepare()
            except Exception as exc:  # the first job meets the same failure and reports it
                self._logger.warning(f'solve worker: preparing failed ({exc!r})')
        while True:
            future, fn = self._tasks.get()
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(fn())
            except BaseException as exc:  # handed to the node with the job
                future.set_exception(exc)
            try:
                self._guard.trigger()
            except Exception:  # the node (and its guard condition) is gone
                return
