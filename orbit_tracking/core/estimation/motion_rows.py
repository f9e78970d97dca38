"""Rows that constrain a trajectory's motion rather than measure it, for
:class:`~orbit_tracking.core.estimation.problem.Problem`: the thrust-along-velocity
constraint of seed 003 (:func:`thrust_normal`) and the white-jerk prior (issue 14,
:func:`jerk_rows`; its density is estimated in :mod:`.priors`)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.estimation.bspline import SplineTrajectory

__all__ = ['JERK_EVENT_MARGIN', 'jerk_parts', 'jerk_rows', 'thrust_normal']

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
there, or the jerk at a ramp's end) whose part of the white-jerk prior has a density of its
own: thrust builds up and tails off around a staging, and a turn's control ramp is
entered, with a jerk far beyond the window's average."""


def jerk_rows(
    traj: SplineTrajectory, t0: float, t1: float, step: float, near_events: bool = False
) -> FloatArray:
    """Rows ``M`` (rank of the penalty, n_coef) with ``|M c|^2`` the integral of the squared
    jerk of ``traj`` (midpoint rule at ``step``) over [t0, t1] away from its events, or
    with ``near_events`` over the :data:`JERK_EVENT_MARGIN` around them: the square root
    of the penalty's nonzero eigen-part, so that as pseudo-measurements they count as many
    degrees of freedom as the penalty has rank. The two parts have densities of their own
    (:mod:`.priors`). Left out altogether, the pieces near events were held by nothing but
    the data; at an aircraft's turn ramps they rang by metres with sub-metre sigmas. Both
    parts at once: :func:`jerk_parts`."""
    return jerk_parts(traj, t0, t1, step)[int(near_events)]


def jerk_parts(
    traj: SplineTrajectory, t0: float, t1: float, step: float
) -> tuple[FloatArray, FloatArray]:
    """:func:`jerk_rows` away from the events and near them, the grid and the events
    (knots repeated on every axis) found once."""
    n = max(int(math.ceil((t1 - t0) / step)), 1)
    h = (t1 - t0) / n
    tg = t0 + h * (np.arange(n) + 0.5)
    repeated = []
    for ax in traj.axes:
        k, counts = np.unique(ax.interior, return_counts=True)
        repeated.append(set(k[counts > 1].tolist()))
    events = np.array(sorted(set.intersection(*repeated)), dtype=float)
    near = (
        np.min(np.abs(tg[:, None] - events[None, :]), axis=1) <= JERK_EVENT_MARGIN
        if events.size
        else np.zeros(tg.size, dtype=bool)
    )
    away_rows = _penalty_rows(traj, tg[~near], h)
    near_rows = _penalty_rows(traj, tg[near], h)
    return away_rows, near_rows


def _penalty_rows(traj: SplineTrajectory, tg: FloatArray, h: float) -> FloatArray:
    if not tg.size:
        return np.zeros((0, traj.n_coef))
    d3 = traj.world_design(tg, 3)
    pen = h * (d3.T @ d3).toarray()
    w, v = np.linalg.eigh(0.5 * (pen + pen.T))
    keep = w > 1e-10 * max(float(w.max()), 1e-300)
    return np.asarray(np.sqrt(w[keep])[:, None] * v[:, keep].T)
