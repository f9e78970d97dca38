"""The estimator's solve worker (orbit_tracking.ros.solve_worker) on a real rclpy node: the
executor keeps running timers while a job runs, the job comes back on the executor's thread
once, exceptions come back with it, and one job at a time."""

from __future__ import annotations

import threading
import time

import pytest

from orbit_tracking.ros.solve_worker import SolveWorker


def _busy(seconds: float) -> float:
    """Python work that holds the GIL between switches (as the estimator's does)."""
    end = time.monotonic() + seconds
    n = 0.0
    while time.monotonic() < end:
        n += sum(i * i for i in range(200))
    return n


def test_timers_run_while_a_job_runs_and_the_job_comes_back_on_the_executor(
    rclpy_node, spin_until
):
    ticks: list[float] = []
    done_threads: list[int] = []
    rclpy_node.create_timer(0.05, lambda: ticks.append(time.monotonic()))
    worker = SolveWorker(rclpy_node, lambda: done_threads.append(threading.get_ident()))
    assert not worker.busy and worker.take() is None

    worker.submit('window 1', lambda: _busy(1.0) and 'solved')
    assert worker.busy
    with pytest.raises(RuntimeError, match='one job at a time'):
        worker.submit('window 2', lambda: None)
    started = time.monotonic()
    assert worker.take() is None  # still running
    spin_until(rclpy_node, lambda: bool(done_threads), 30, 'the job to finish')
    took = time.monotonic() - started
    during = [t for t in ticks if t <= started + took]
    # 0.05 s timers all along the job's second (a held executor would show none)
    assert took >= 0.9 and len(during) >= 0.5 * took / 0.05, (took, len(during))
    assert done_threads == [threading.get_ident()]  # on_done ran on the executor's thread
    job = worker.take()
    assert job is not None and job.context == 'window 1' and job.future.result() == 'solved'
    assert not worker.busy and worker.take() is None  # handed back once


def test_an_exception_comes_back_with_its_job_and_the_worker_goes_on(rclpy_node):
    worker = SolveWorker(rclpy_node, lambda: None)
    worker.submit('bad', lambda: 1 / 0)
    job = worker.take(block=True)
    assert job is not None and job.context == 'bad'
    assert isinstance(job.future.exception(), ZeroDivisionError)
    worker.submit('good', lambda: 42)
    job = worker.take(block=True)
    assert job is not None and job.future.result() == 42 and job.running_s >= 0.0


def test_a_job_run_here_is_done_on_the_calling_thread(rclpy_node):
    worker = SolveWorker(rclpy_node, lambda: None)
    worker.submit('here', threading.get_ident, here=True)
    job = worker.take()  # done: no wait
    assert job is not None and job.future.result() == threading.get_ident()
    worker.submit('bad', lambda: 1 / 0, here=True)
    assert isinstance(worker.take().future.exception(), ZeroDivisionError)
