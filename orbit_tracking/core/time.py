"""Stamps as text: integer nanoseconds written as decimal seconds and read back exactly.

The output tables (``fixes.csv``, ``trajectory.csv``, ``biases_by_window.csv``) and the
diagnostics carry stamps as ``<seconds>.<nine digits>``; these two functions are the only
place that format is written or parsed, so a stamp survives a round trip to the nanosecond.
"""

from __future__ import annotations

__all__ = ['format_stamp', 'parse_stamp']


def format_stamp(ref_ns: int, t: float) -> str:
    """Stamp ``ref_ns + t`` as decimal seconds with all nine digits exact."""
    ns = ref_ns + int(round(t * 1e9))
    sign = '-' if ns < 0 else ''
    ns = abs(ns)
    return f'{sign}{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}'


def parse_stamp(text: str) -> int:
    """Exact integer nanoseconds of a decimal-seconds stamp (as written by
    :func:`format_stamp`).

    Raises
    ------
    ValueError
        Not a decimal number, or more than nine decimals.
    """
    s = text.strip()
    sign = -1 if s.startswith('-') else 1
    whole, _, frac = s.lstrip('+-').partition('.')
    if len(frac) > 9:
        raise ValueError(f'stamp {text!r} has more than nine decimals')
    if not (whole or frac) or not (whole or '0').isdigit() or not (frac or '0').isdigit():
        raise ValueError(f'stamp {text!r} is not a decimal number of seconds')
    return sign * (int(whole or '0') * 1_000_000_000 + int((frac or '0').ljust(9, '0')))
