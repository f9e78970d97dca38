"""Incomplete-measurement segments (seed 000): spans where the measurements that exist
cannot fix the target's position and velocity epoch by epoch.

A bag carries no note of where its gaps are, so they are found from the data. Around
each time bin the measurement rows of every station are linearised at the rough
trajectory under a constant-velocity motion model (six unknowns, the position and
``velocity x bin width`` in metres). A bin is incomplete when fewer than six rows exist,
when that 6x6 information matrix is singular, or when its worst-determined direction
has a standard deviation more than ``factor`` times the median of all bins (e.g. two
CW radars give range and range-rate only along two directions; one theodolite leaves
the range free).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.models.measurements import predict

__all__ = ['CoverageConfig', 'find_incomplete_segments', 'merge_segments', 'unsampled_spans']

FloatArray = NDArray[np.float64]
Segment = tuple[float, float]


@dataclass(frozen=True)
class CoverageConfig:
    """bin [s]; factor: worst sigma vs the median that marks a bin incomplete;
    min_length [s]: shorter incomplete runs are ignored."""

    bin: float = 1.0
    factor: float = 10.0
    min_length: float = 1.0

    def __post_init__(self) -> None:
        if self.bin <= 0.0 or self.factor <= 1.0 or self.min_length < 0.0:
            raise ValueError(f'coverage needs bin > 0, factor > 1, min_length >= 0; got {self}')


def merge_segments(segments: Sequence[Segment], join: float = 0.0) -> list[Segment]:
    """Union of intervals; intervals closer than ``join`` are merged."""
    out: list[list[float]] = []
    for a, b in sorted((float(a), float(b)) for a, b in segments if b > a):
        if out and a <= out[-1][1] + join:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return [(a, b) for a, b in out]


def unsampled_spans(
    times: FloatArray, t0: float, t1: float, hole: float, reach: float
) -> list[Segment]:
    """Spans of [t0, t1] where a rough trajectory sampled at ``times`` cannot show an
    event: its holes longer than ``hole`` seconds (a telemetry outage; before its first
    sample and after its last too), widened on each side by the event detector's ``reach``
    and clipped to the window. Empty with fewer than two samples in the window (the
    rough trajectory is then something else, whose events are found on it)."""
    t = np.sort(np.asarray(times, dtype=np.float64))
    t = t[(t >= t0) & (t <= t1)]
    if t.size < 2:
        return []
    lo = np.concatenate([[t0], t])
    hi = np.concatenate([t, [t1]])
    wide = hi - lo > hole
    return merge_segments(
        [(max(t0, a - reach), min(t1, b + reach)) for a, b in zip(lo[wide], hi[wide], strict=True)]
    )


def find_incomplete_segments(
    obs: Observations,
    target_id: int,
    state_at: Callable[[FloatArray], FloatArray],
    t0: float,
    t1: float,
    cfg: CoverageConfig | None = None,
) -> list[Segment]:
    """Incomplete segments of ``target_id`` within [t0, t1].

    Parameters
    ----------
    state_at : callable
        ``state_at(t) -> (m, 6)`` world-frame states used for the linearisation (the
        rough trajectory).
    """
    cfg = cfg or CoverageConfig()
    if not t1 > t0:
        return []
    # bins on multiples of the bin width, the window's partial end bins merged into their
    # neighbours: moving a window edge by a microsecond moves no segment
    b0 = math.floor(t0 / cfg.bin + 0.5) + 1
    b1 = math.ceil(t1 / cfg.bin - 0.5) - 1
    edges = np.concatenate([[t0], np.arange(b0, b1 + 1, dtype=np.float64) * cfg.bin, [t1]])
    nb = edges.size - 1
    info = np.zeros((nb, 6, 6))
    rows = np.zeros(nb, dtype=int)
    mid = 0.5 * (edges[:-1] + edges[1:])
    centre = np.asarray(state_at(mid), dtype=np.float64)
    for s in obs.stations:
        tab = s.table
        sel = (tab.target_id == target_id) & (tab.time >= t0) & (tab.time <= t1)
        if not np.any(sel):
            continue
        t = tab.time[sel]
        b = np.clip(np.searchsorted(edges, t, side='right') - 1, 0, nb - 1)
        tau = (t - mid[b]) / cfg.bin
        # linearised on the bin's own constant-velocity motion through its centre state:
        # a rough trajectory held constant past its samples (fixes that stop where the
        # segment starts) put every row of a bin at one position moving at speed, and two
        # CW radars' blind direction (the whole path turned about their baseline changes
        # no range and no range rate) came out determined to 65 m: no outlier against the
        # median of a window whose bins were mostly in the segment
        x = centre[b].copy()
        x[:, :3] += (t - mid[b])[:, None] * x[:, 3:]
        _, jac = predict(tab.fields, x, s.pose.take(np.flatnonzero(sel)), jacobian=True)
        assert jac is not None
        valid = np.isfinite(tab.values[sel])
        w = np.where(valid, 1.0 / tab.sigmas[sel], 0.0)
        hp = jac[:, :, :3] * w[:, :, None]
        hv = jac[:, :, 3:] * w[:, :, None] / cfg.bin
        h = np.concatenate([hp, hp * tau[:, None, None] + hv], axis=2)  # (m, k, 6)
        outer = np.einsum('mki,mkj->mij', h, h)
        np.add.at(info, b, outer)
        np.add.at(rows, b, valid.sum(axis=1))
    worst = np.full(nb, np.inf)
    for i in range(nb):
        if rows[i] < 6 or not np.all(np.isfinite(info[i])):
            continue
        ev = np.linalg.eigvalsh(info[i])
        if ev[0] > 1e-12 * max(ev[-1], 1e-300):
            worst[i] = 1.0 / np.sqrt(ev[0])
    finite = worst[np.isfinite(worst)]
    if finite.size == 0:
        return [(t0, t1)]
    bad = ~(worst <= cfg.factor * float(np.median(finite)))
    segs = [(float(edges[i]), float(edges[i + 1])) for i in np.flatnonzero(bad)]
    merged = merge_segments(segs, join=cfg.bin * 0.5)
    return [(a, b) for a, b in merged if b - a >= cfg.min_length]
