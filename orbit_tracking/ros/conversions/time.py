"""Stamps <-> float seconds: :class:`TimeBase` and :func:`stamp_ns`.

The core computes in float seconds relative to a :class:`TimeBase` (an integer number of
nanoseconds, by default the scenario epoch), so that float64 keeps sub-nanosecond
resolution across a long pass.
"""

from __future__ import annotations

from dataclasses import dataclass

from builtin_interfaces.msg import Time

__all__ = ['TimeBase', 'stamp_ns']


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
