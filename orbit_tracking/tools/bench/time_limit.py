"""A time limit on a call in the main thread, for the benchmarks: a method that runs
past it is recorded as failing on that draw instead of holding the whole run."""

from __future__ import annotations

import signal
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ['MethodTimeout', 'time_limit_of']


class MethodTimeout(RuntimeError):
    """A method ran past its time limit."""


@contextmanager
def time_limit_of(seconds: float | None) -> Iterator[None]:
    """Raise :class:`MethodTimeout` in the main thread after ``seconds`` (no-op elsewhere,
    or when a C call does not return to Python in time)."""
    if not seconds:
        yield
        return

    def on_alarm(_sig: int, _frame: object) -> None:
        raise MethodTimeout(f'ran longer than {seconds:g} s')

    try:
        old = signal.signal(signal.SIGALRM, on_alarm)
    except ValueError:  # not the main thread
        yield
        return
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, old)
