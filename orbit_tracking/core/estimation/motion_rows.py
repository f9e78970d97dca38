"""Rows that constrain a trajectory's motion rather than measure it, for
:class:`~orbit_tracking.core.estimation.problem.Problem`: the thrust-along-velocity
constraint of seed 003 (:func:`thrust_normal`) and the white-jerk prior (issue 14,
:func:`jerk_rows`; its density is estimated in :mod:`.priors`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.estimation.bspline import SplineTrajectory

__all__ = ['JERK_EVENT_MARGIN', 'JerkRows', 'jerk_rows', 'thrust_normal']

FloatArray = NDArray[np.float64]


def thrust_normal(
    p: FloatArray, v: FloatArray, a: FloatArray, gm: float, jacobian: bool
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """``c = (I - u u^T)(a - g(p))`` with ``u = v/|v|`` and ``g = -gm p/|p|^3``: the
    non-gravitational acceleration normal to the velocity, (m, 3); and its derivatives
    by p, v and a, (m, 3, 3) each (zeros when ``jacobian`` is False)."""
    rn = np.linalg.norm(p, axis=1)
    g = -gm * p / rn[:, None] ** 3
    f = a - g
    vn = np.linalg.norm(v, axis=1)
    u = v / vn[:, None]
    eye = np.eye(3)
    proj = eye - np.einsum('mi,mj->mij', u, u)
    c = np.einsum('mij,mj->mi', proj, f)
    m = p.shape[0]
    if not jacobian:
        z = np.zeros((m, 3, 3))
        return c, z, z, z
    dg = -gm * (
        eye / rn[:, None, None] ** 3 - 3.0 * np.einsum('mi,mj->mij', p, p) / rn[:, None, None] ** 5
    )
    jp = -np.einsum('mij,mjk->mik', proj, dg)
    fm = np.einsum('mj,mjk->mk', f, proj)  # f^T (I - u u^T)
    fu = np.einsum('mi,mi->m', f, u)
    jv = -(np.einsum('mi,mk->mik', u, fm) + fu[:, None, None] * proj) / vn[:, None, None]
    return c, jp, jv, proj


JERK_EVENT_MARGIN = 2.0
"""Seconds on each side of an event (a knot repeated on every axis: the acceleration jumps
there) left out of the white-jerk prior: thrust builds up and tails off around it with a
jerk far beyond the window's average."""


@dataclass(frozen=True)
class JerkRows:
    """The white-jerk prior's rows of one trajectory: ``rows`` (m, n_coef) with
    ``sum |rows c|^2`` the integral of the squared jerk, ``block`` (m,) the block of the
    window each row belongs to (:func:`jerk_rows`), ``rank`` the rank of the whole penalty
    (its degrees of freedom) and ``n_blocks`` the number of blocks."""

    rows: FloatArray
    block: NDArray[np.int_]
    rank: int
    n_blocks: int


def jerk_rows(
    traj: SplineTrajectory, t0: float, t1: float, step: float, block: float = 0.0
) -> JerkRows:
    """The rows of the white-jerk prior of ``traj`` over [t0, t1] (midpoint rule at
    ``step``), leaving out :data:`JERK_EVENT_MARGIN` around its events.

    ``block`` 0: the square root of the penalty's nonzero eigen-part, so that as
    pseudo-measurements the rows count as many degrees of freedom as the penalty has rank.
    ``block`` > 0: the same per block ``k``, ``[t0 + k block, t0 + (k + 1) block)`` (the
    rows of one block touch only the coefficients under it; a block inside the event
    margins has none), so that each block's share of the prior can be weighted on its own;
    the rows of all blocks together give the same penalty."""
    n = max(int(math.ceil((t1 - t0) / step)), 1)
    h = (t1 - t0) / n
    tg = t0 + h * (np.arange(n) + 0.5)
    repeated = []
    for ax in traj.axes:
        k, counts = np.unique(ax.interior, return_counts=True)
        repeated.append(set(k[counts > 1].tolist()))
    events = np.array(sorted(set.intersection(*repeated)), dtype=float)
    if events.size:
        tg = tg[np.min(np.abs(tg[:, None] - events[None, :]), axis=1) > JERK_EVENT_MARGIN]
    if not tg.size:
        return JerkRows(np.zeros((0, traj.n_coef)), np.zeros(0, dtype=int), 0, 1)
    d3 = traj.world_design(tg, 3).tocsr()
    pen = h * (d3.T @ d3).toarray()
    rows, rank = _sqrt_rows(pen)
    if block <= 0.0:
        return JerkRows(rows, np.zeros(rows.shape[0], dtype=int), rank, 1)
    scale = float(np.max(np.abs(pen)))
    kb = np.floor((tg - t0) / block).astype(int)
    parts, ids = [], []
    for b in np.unique(kb):
        sub = d3[(3 * np.flatnonzero(kb == b)[:, None] + np.arange(3)).ravel()]
        cols = np.unique(sub.indices)
        local = sub[:, cols].toarray()
        r_b, _ = _sqrt_rows(h * local.T @ local, scale)
        full = np.zeros((r_b.shape[0], traj.n_coef))
        full[:, cols] = r_b
        parts.append(full)
        ids.append(np.full(r_b.shape[0], b, dtype=int))
    n_blocks = max(int(math.ceil((t1 - t0) / block)), int(kb.max()) + 1)
    return JerkRows(np.vstack(parts), np.concatenate(ids), rank, n_blocks)


def _sqrt_rows(pen: FloatArray, scale: float | None = None) -> tuple[FloatArray, int]:
    """Rows ``R`` with ``R^T R = pen`` over ``pen``'s eigen-directions above ``1e-10`` of
    ``scale`` (default: its largest eigenvalue), and their number."""
    w, v = np.linalg.eigh(0.5 * (pen + pen.T))
    top = float(w.max()) if scale is None else scale
    keep = w > 1e-10 * max(top, 1e-300)
    return np.asarray(np.sqrt(w[keep])[:, None] * v[:, keep].T), int(keep.sum())
