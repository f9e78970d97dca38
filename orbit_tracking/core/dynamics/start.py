"""Starting parameters of the rocket model (seed 003).

* **From position fixes** (:func:`start_from_fixes`): a weighted polynomial in time
  through the fixes gives the state at the epoch; the thrust acceleration it implies
  (its second derivative minus gravity) gives the rocket-equation pair: ``1 / a(t) =
  (tau - (t - t0)) / c`` is a straight line in ``t``, fitted by least squares.
* **Rough fixes from the rows themselves** (:func:`rough_fixes`), when no fixes came
  with the data: a pulse radar's range along its line of sight, or the midpoint of the
  common perpendicular of two stations' lines of sight at nearly the same epoch.
* **From one station's lines of sight alone**: :mod:`.range_search`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.data.observations import FixSeries, StationObservations
from orbit_tracking.core.dynamics.rocket import RocketModel
from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.core.models.dynamics import gravity
from orbit_tracking.core.models.measurements import los_unit_vectors

__all__ = ['DEFAULT_EXHAUST_SPEED', 'angle_fields', 'rough_fixes', 'start_from_fixes']

FloatArray = NDArray[np.float64]

DEFAULT_EXHAUST_SPEED = 3000.0
"""Exhaust speed [m/s] assumed where the data say nothing better (a solid motor's)."""


def _thrust_pair(t: FloatArray, accel: FloatArray, epoch: float, t_last: float) -> FloatArray:
    """``(c, tau)`` from thrust-acceleration magnitudes ``accel`` at ``t``."""
    good = accel > 1.0
    if np.count_nonzero(good) >= 3:
        inv = 1.0 / accel[good]
        slope, icpt = np.polyfit(t[good] - epoch, inv, 1)
        if slope < 0.0:
            c = -1.0 / slope
            tau = icpt * c
            if c > 100.0 and tau > t_last - epoch + 5.0:
                return np.array([c, tau])
        mean_a = float(np.median(accel[good]))
    else:
        mean_a = 10.0
    c = DEFAULT_EXHAUST_SPEED
    return np.array([c, max(c / mean_a, t_last - epoch + 30.0)])


def start_from_fixes(fixes: FixSeries, model: RocketModel, degree: int = 4) -> FloatArray:
    """Rocket parameters (8,) at ``model.epoch`` from a target's position fixes.

    Raises
    ------
    OrbitTrackingError
        Fewer fixes than the polynomial needs.
    """
    t = np.asarray(fixes.time, dtype=np.float64)
    if t.size < degree + 2:
        raise OrbitTrackingError(
            f'target {fixes.target_id}: {t.size} fixes are too few to start the rocket model '
            f'(at least {degree + 2})'
        )
    var = np.trace(fixes.covariance, axis1=1, axis2=2) / 3.0
    w = 1.0 / np.sqrt(np.where(np.isfinite(var) & (var > 0), var, np.nanmedian(var)))
    span = float(t[-1] - t[0]) or 1.0
    s = (t - model.epoch) / span
    coef = [np.polyfit(s, fixes.position[:, k], degree, w=w) for k in range(3)]
    pos = np.array([np.polyval(c, 0.0) for c in coef])
    vel = np.array([np.polyval(np.polyder(c), 0.0) for c in coef]) / span
    grid = np.linspace(t[0], t[-1], 21)
    sg = (grid - model.epoch) / span
    r = np.stack([np.polyval(c, sg) for c in coef], axis=1)
    v = np.stack([np.polyval(np.polyder(c), sg) for c in coef], axis=1) / span
    a = np.stack([np.polyval(np.polyder(c, 2), sg) for c in coef], axis=1) / span**2
    thrust = a - gravity(r, model.gm, model.j2, model.radius)
    if model.earth_rate:
        w3 = np.array([0.0, 0.0, model.earth_rate])
        thrust += 2.0 * np.cross(w3, v) + np.cross(w3, np.cross(w3, r))
    along = np.einsum('mi,mi->m', thrust, v / np.linalg.norm(v, axis=1, keepdims=True))
    pair = _thrust_pair(grid, along, model.epoch, float(t[-1]))
    theta = np.concatenate([pos, vel, pair])
    if not np.all(np.isfinite(theta)) or math.isclose(float(np.linalg.norm(vel)), 0.0):
        raise OrbitTrackingError(f'target {fixes.target_id}: the fixes give no usable start')
    return theta


def angle_fields(
    st: StationObservations, rows: NDArray[np.intp]
) -> tuple[tuple[str, ...], FloatArray, FloatArray]:
    """The angle fields a station measures, and their values and sigmas at ``rows``."""
    tab = st.table
    fields = tuple(f for f in tab.fields if f in ('azimuth', 'elevation', 'los_alpha', 'los_beta'))
    cols = np.array([tab.fields.index(f) for f in fields], dtype=np.intp)
    return fields, tab.values[np.ix_(rows, cols)], tab.sigmas[np.ix_(rows, cols)]


def _units(st: StationObservations, rows: NDArray[np.intp]) -> FloatArray | None:
    fields, vals, _ = angle_fields(st, rows)
    if len(fields) != 2:
        return None
    kind = 'los' if 'los_alpha' in fields else 'angles'
    u = los_unit_vectors(kind, vals, fields, st.pose.rotation[rows])
    if kind == 'los':  # the line, not the ray
        pos = st.pose.position[rows]
        u[np.einsum('mi,mi->m', u, pos) > 0.0] *= -1.0
    return u


def rough_fixes(
    stations: tuple[StationObservations, ...],
    target_id: int,
    max_dt: float = 0.5,
    min_angle_deg: float = 2.0,
) -> FixSeries | None:
    """Position fixes good enough to start from, made from the rows: every pulse radar
    row with a range (the point at that range along its line of sight), and for the two
    angle-measuring stations with most rows, the midpoint of the common perpendicular of
    each line of the first with the second's line nearest in time (within ``max_dt`` s,
    lines at least ``min_angle_deg`` apart). Their covariance is a nominal (1 km)^2: they
    only start the fit. None when there are too few."""
    t_all: list[FloatArray] = []
    p_all: list[FloatArray] = []
    lines = []
    for st in stations:
        rows = np.flatnonzero(st.table.target_id == target_id)
        if rows.size == 0:
            continue
        u = _units(st, rows)
        if u is None:
            continue
        fields = st.table.fields
        if 'range' in fields:
            rng = st.table.values[rows, fields.index('range')]
            ok = np.isfinite(rng) & np.all(np.isfinite(u), axis=1)
            t_all.append(st.table.time[rows][ok])
            p_all.append(st.pose.position[rows][ok] + rng[ok, None] * u[ok])
        else:
            lines.append((st.table.time[rows], st.pose.position[rows], u))
    lines.sort(key=lambda ln: -ln[0].size)
    if len(lines) >= 2:
        (ta, oa, ua), (tb, ob, ub) = lines[:2]
        j = np.clip(np.searchsorted(tb, ta), 1, tb.size - 1)
        j = np.where(np.abs(tb[j - 1] - ta) < np.abs(tb[j] - ta), j - 1, j)
        close = np.abs(tb[j] - ta) <= max_dt
        ob, ub = ob[j], ub[j]
        w = oa - ob
        b = np.einsum('mi,mi->m', ua, ub)
        d = np.einsum('mi,mi->m', ua, w)
        e = np.einsum('mi,mi->m', ub, w)
        den = 1.0 - b * b
        good = close & (den > math.sin(math.radians(min_angle_deg)) ** 2)
        with np.errstate(all='ignore'):
            sa = (b * e - d) / den
            sb = (e - b * d) / den
        pts = 0.5 * (oa + sa[:, None] * ua + ob + sb[:, None] * ub)
        good &= np.all(np.isfinite(pts), axis=1)
        t_all.append(0.5 * (ta + tb[j])[good])
        p_all.append(pts[good])
    if not t_all:
        return None
    t = np.concatenate(t_all)
    if t.size < 6:
        return None
    order = np.argsort(t, kind='stable')
    p = np.vstack(p_all)[order]
    return FixSeries(target_id, t[order], p, np.tile(np.eye(3) * 1e6, (t.size, 1, 1)))
