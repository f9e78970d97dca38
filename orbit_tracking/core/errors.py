"""Domain errors of the numerical core."""

from __future__ import annotations

__all__ = [
    'ConfigError',
    'GeometryError',
    'MeasurementError',
    'OrbitTrackingError',
]


class OrbitTrackingError(Exception):
    """Base class of every error raised on purpose by orbit_tracking."""


class ConfigError(OrbitTrackingError, ValueError):
    """A scenario or parameter file is malformed.

    The message names the file, the key (as a dotted path) and what was expected.
    """

    def __init__(self, source: str, key: str, problem: str) -> None:
        self.source = source
        self.key = key
        self.problem = problem
        super().__init__(f'{source}: {key}: {problem}')


class MeasurementError(OrbitTrackingError, ValueError):
    """Measurement data that cannot be used as given (bad field, shape or sigma).

    ``reason`` is a short snake_case key for counting rejections by cause (``layout``,
    ``stamp``, ``time_offset``, ...); ``invalid`` when the raiser gave none.
    """

    def __init__(self, message: str, reason: str = 'invalid') -> None:
        self.reason = reason
        super().__init__(message)


class GeometryError(OrbitTrackingError, ValueError):
    """A geometric construction is degenerate (parallel lines, zero range, ...)."""
