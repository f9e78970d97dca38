"""What a pass of the processing nodes published, and what a pass with a node killed and
restarted lost against a clean one (:func:`compare_passes`; the passes are run by
:mod:`~orbit_tracking.tools.bench.restart`).

A killed pass is compared state by state with the clean one: the states it lost, those it
has and the clean one has not, those it published more than once (a restarted results node
resends states its readers had not acknowledged: allowed, with identical values), the
largest position difference (also in units of the killed pass's own sigma), and whether the
results node blended across the restart as it blends any hand-over (its states equal the
stitch of the windows it received).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ['OUTPUT_STEP', 'PassResult', 'compare_passes']

OUTPUT_STEP = 0.1
"""The results node's output step in these passes [s]."""


@dataclass
class PassResult:
    """What one pass published, as received here.

    Attributes
    ----------
    stamps : ndarray, shape (n,)
        ``trajectory/states`` stamps [ns], in arrival order (a repeat stays a repeat).
    state : ndarray, shape (n, 6)
        Position [m] and velocity [m/s].
    sigma : ndarray, shape (n, 6)
        Their published 1-sigma.
    windows : list of WindowStates
        ``estimator/window_states`` in arrival order.
    epoch_ns : int
        Stamp of the nodes' time 0.
    results, estimator : dict
        The last ``results: trajectory`` and ``estimator: windows`` diagnostics values.
    windows_before_kill : int
        Windows received here before the kill.
    kill_data_s, ready_data_s : float
        Newest measurement time [s] received here when the estimator was killed and when
        its new process reported its first measurement message (nan without a kill).
    restart_wall_s : float
        Wall seconds from the kill to then (nan without a kill).
    paused_data_s : float
        Newest measurement time [s] received here when the player was paused to wait for
        the restarted estimator (``max_gap`` of the pass; nan: it did not wait).
    logs : dict
        Each process's output (``estimator`` and, after a kill, ``estimator_2``).
    wall_s : float
    """

    stamps: np.ndarray
    state: np.ndarray
    sigma: np.ndarray
    windows: list[Any]
    epoch_ns: int
    results: dict[str, str] = field(default_factory=dict)
    estimator: dict[str, str] = field(default_factory=dict)
    windows_before_kill: int = 0
    kill_data_s: float = math.nan
    ready_data_s: float = math.nan
    restart_wall_s: float = math.nan
    paused_data_s: float = math.nan
    logs: dict[str, str] = field(default_factory=dict)
    wall_s: float = 0.0

    def times(self) -> np.ndarray:
        """Stamps as seconds after the epoch."""
        return (self.stamps - self.epoch_ns) * 1e-9


def _spans(t: np.ndarray, step: float = OUTPUT_STEP) -> list[list[float]]:
    """Sorted times as ``[first, last]`` runs of consecutive output times."""
    out: list[list[float]] = []
    for v in np.sort(t):
        if out and v - out[-1][1] <= 1.5 * step:
            out[-1][1] = float(v)
        else:
            out.append([float(v), float(v)])
    return [[round(a, 3), round(b, 3)] for a, b in out]


def _stitched(run: PassResult) -> tuple[np.ndarray, np.ndarray]:
    """The states the results node should publish from the windows this pass received:
    the core stitcher fed the same windows (a repeated window dropped, as the node drops
    it), then flushed."""
    from orbit_tracking.core.estimation.stitcher import TrajectoryStitcher, split_window

    st = TrajectoryStitcher()
    final = []
    for w in run.windows:
        if w.t1 > st.last_end + 1e-6:
            final += st.add(split_window(w.t0, w.t1, w.time, w.target_id, w.state, w.covariance))
    final += st.flush()
    keys = [np.round(fs.time * 1e9).astype(np.int64) + run.epoch_ns for fs in final]
    xs = [fs.state for fs in final]
    if not keys:
        return np.zeros(0, np.int64), np.zeros((0, 6))
    return np.concatenate(keys), np.vstack(xs)


def compare_passes(clean: PassResult, killed: PassResult) -> dict[str, Any]:
    """What the killed pass lost against the clean one (see the module docstring)."""
    c_keys, c_idx = np.unique(clean.stamps, return_index=True)
    k_keys, k_idx = np.unique(killed.stamps, return_index=True)
    lost = np.setdiff1d(c_keys, k_keys)
    extra = np.setdiff1d(k_keys, c_keys)
    common, ci, ki = np.intersect1d(c_keys, k_keys, return_indices=True)
    dx = killed.state[k_idx[ki]] - clean.state[c_idx[ci]]
    sig = killed.sigma[k_idx[ki]]
    dpos = np.linalg.norm(dx[:, :3], axis=1) if common.size else np.zeros(0)
    z = np.abs(dx) / sig if common.size else np.zeros((0, 6))
    s_keys, s_state = _stitched(killed)
    s_map = {int(k): i for i, k in enumerate(s_keys)}
    seam = [
        float(np.max(np.abs(killed.state[i] - s_state[s_map[int(k)]])))
        for i, k in enumerate(killed.stamps)
        if int(k) in s_map
    ]
    t_common = (common - clean.epoch_ns) * 1e-9
    worst = int(np.argmax(dpos)) if dpos.size else -1
    # a state sent again by a restarted results node (its first copy was not acknowledged
    # when the old one died) must repeat the first copy's values
    first = dict(zip(k_keys.tolist(), k_idx.tolist(), strict=True))
    differing = sum(
        1
        for i, k in enumerate(killed.stamps.tolist())
        if i != first[k] and not np.array_equal(killed.state[i], killed.state[first[k]])
    )
    return {
        'states_clean': int(c_keys.size),
        'states_published': int(k_keys.size),
        'lost': int(lost.size),
        'lost_spans_s': _spans((lost - clean.epoch_ns) * 1e-9),
        'extra': int(extra.size),
        'published_twice': int(killed.stamps.size - k_keys.size),
        'repeats_differing': differing,
        'max_position_diff_m': float(dpos.max()) if dpos.size else math.nan,
        'max_position_diff_at_s': round(float(t_common[worst]), 3) if worst >= 0 else math.nan,
        'max_velocity_diff_mps': (
            float(np.linalg.norm(dx[:, 3:], axis=1).max()) if common.size else math.nan
        ),
        'max_diff_over_sigma': float(z.max()) if z.size else math.nan,
        'stitch_mismatch_m': float(max(seam)) if seam else math.nan,
        'stitch_unmatched': int(killed.stamps.size - len(seam)),
    }
