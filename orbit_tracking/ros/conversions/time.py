"""Stamps <-> float seconds: :class:`TimeBase`, :func:`stamp_ns` and
:func:`checked_stamp_ns` (the nodes' check of every incoming stamp).

The core computes in float seconds relative to a :class:`TimeBase` (an integer number of
nanoseconds, by default the scenario epoch), so that float64 keeps sub-nanosecond
resolution across a long pass.
"""

from __future__ import annotations

from dataclasses import dataclass

from builtin_interfaces.msg import Time

__all__ = ['TimeBase', 'checked_stamp_ns', 'stamp_ns']


@dataclass(frozen=True)
class TimeBase:
    """Maps ``builtin_interfaces/Time`` stamps to float seconds and back.

    Parameters
    ----------
    ref_ns : int
        Stamp (integer nanoseconds) of float time 0.
    """

    ref_ns: int

    @classmethod
    def from_seconds(cls, epoch_s: float) -> TimeBase:
        return cls(int(round(epoch_s * 1e9)))

    @classmethod
    def whole_second_of(cls, stamp_ns_: int) -> TimeBase:
        """A time base at the whole second of a stamp (what nodes use when no reference
        is configured: the first stamp they receive)."""
        return cls((stamp_ns_ // 1_000_000_000) * 1_000_000_000)

    def to_seconds(self, stamp: Time) -> float:
        return ((int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)) - self.ref_ns) * 1e-9

    def to_ns(self, t: float) -> int:
        return self.ref_ns + int(round(t * 1e9))

    def to_stamp(self, t: float) -> Time:
        ns = self.to_ns(t)
        return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def stamp_ns(stamp: Time) -> int:
    """Integer nanoseconds of a stamp."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def checked_stamp_ns(stamp: Time) -> int:
    """Integer nanoseconds of an incoming stamp, after checking it is a valid
    ``builtin_interfaces/Time``.

    Raises
    ------
    ValueError
        ``nanosec`` is not below 1e9 (it would read as a jump of up to 4.29 s) or ``sec``
        is negative (before 1970: no tracking data carries such a stamp).
    """
    sec, nsec = int(stamp.sec), int(stamp.nanosec)
    if not 0 <= nsec < 1_000_000_000:
        raise ValueError(f'stamp nanosec must lie in [0, 1e9); got {nsec}')
    if sec < 0:
        raise ValueError(f'stamp sec must be >= 0 (not before 1970); got {sec}')
    return sec * 1_000_000_000 + nsec
