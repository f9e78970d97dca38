"""Starting parameters of the rocket model (seed 003).

* **From position fixes** (:func:`start_from_fixes`): a weighted polynomial in time
  through the fixes gives the state at the epoch; the thrust acceleration it implies
  (its second derivative minus gravity) gives the rocket-equation pair: ``1 / a(t) =
  (tau - (t - t0)) / c`` is a straight line in ``t``, fitted by least squares.
* **Rough fixes from the rows themselves** (:func:`rough_fixes`), when no fixes came
  with the data: a pulse radar's range along its line of sight, or the midpoint of the
  common perpendicular of two stations' lines of sight at nearly the same epoch.
* **From one station's lines of sight alone** (:func:`start_from_lines`): a search over
  range hypotheses (an admissible region): the vehicle lies on the first and on the last
  line of sight at altitudes between ``min_altitude`` and ``max_altitude``; for each pair
  of ranges on a grid the flight through both points (state at the epoch from the chord,
  thrust from the defaults) is scored by its misfit of every line of sight, and the best
  few are refined by Levenberg-Marquardt (:func:`~.fit.fit_dynamics`); the lowest cost wins.
"""

from __future__ import annotations

import math
from itertools import product

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from orbit_tracking.core import frames
from orbit_tracking.core.data.observations import FixSeries, StationObservations
from orbit_tracking.core.dynamics.rocket import RocketModel
from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.core.models.dynamics import gravity
from orbit_tracking.core.models.measurements import los_unit_vectors, predict, residual

__all__ = ['DEFAULT_EXHAUST_SPEED', 'rough_fixes', 'start_candidates', 'start_from_fixes']

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


def _band(
    origin: FloatArray, unit: FloatArray, lo: float, hi: float
) -> tuple[float, float] | None:
    """The stretch of ranges ``rho >= 0`` on the ray ``origin + rho unit`` between the radii
    ``lo`` and ``hi``, nearest the origin (None if the ray misses the shell)."""
    b = float(origin @ unit)
    c0 = float(origin @ origin)

    def roots(radius: float) -> tuple[float, float] | None:
        disc = b * b - (c0 - radius * radius)
        if disc < 0.0:
            return None
        q = math.sqrt(disc)
        return -b - q, -b + q

    outer = roots(hi)
    if outer is None:
        return None
    inner = roots(lo)
    a = max(outer[0], 0.0)
    e = inner[0] if inner is not None and inner[0] > a else outer[1]
    return (a, e) if e > a else None


def _angles(
    st: StationObservations, rows: NDArray[np.intp]
) -> tuple[tuple[str, ...], FloatArray, FloatArray]:
    tab = st.table
    fields = tuple(f for f in tab.fields if f in ('azimuth', 'elevation', 'los_alpha', 'los_beta'))
    cols = np.array([tab.fields.index(f) for f in fields], dtype=np.intp)
    return fields, tab.values[np.ix_(rows, cols)], tab.sigmas[np.ix_(rows, cols)]


def start_candidates(
    st: StationObservations,
    target_id: int,
    model: RocketModel,
    min_altitude: float = 0.0,
    max_altitude: float = 1.5e6,
    n_range: int = 12,
    keep: int = 4,
) -> list[FloatArray]:
    """Rocket parameters to start from when one station's angles are all there is.

    Range hypotheses: at the first, middle and last epochs the vehicle lies on the line of
    sight at a range where its altitude is within ``[min_altitude, max_altitude]`` (the
    ray's first crossing of that shell: the admissible region). Every triple of ranges on
    an ``n_range`` grid defines a parabola in time; each is scored by its misfit of the
    station's angles (at most 200 epochs), the ``keep`` best are refined over their three
    ranges by least squares, and each becomes rocket parameters through
    :func:`start_from_fixes` (degree 2). Best first.

    Raises
    ------
    OrbitTrackingError
        Too few rows, or no line of sight crosses the altitude band.
    """
    tab = st.table
    rows = np.flatnonzero(tab.target_id == target_id)
    if rows.size < 10:
        raise OrbitTrackingError(
            f'target {target_id}: {rows.size} rows of {tab.station_id} are too few to start from'
        )
    fields, vals, sig = _angles(st, rows)
    if len(fields) != 2:
        raise OrbitTrackingError(f'{tab.station_id} measures no pair of angles')
    kind = 'los' if 'los_alpha' in fields else 'angles'
    t = tab.time[rows]
    pose = st.pose.take(rows)
    units = los_unit_vectors(kind, vals, fields, pose.rotation)
    if kind == 'los':  # the line, not the ray: point it toward the Earth's centre
        flip = np.einsum('mi,mi->m', units, pose.position) > 0.0
        units[flip] *= -1.0
    pick = np.unique(np.linspace(0, rows.size - 1, 3).round().astype(int))
    if pick.size < 3:
        raise OrbitTrackingError(f'target {target_id}: too few epochs to start from')
    r_lo, r_hi = frames.WGS84_B + min_altitude, frames.WGS84_A + max_altitude
    grids = []
    for i in pick:
        band = _band(pose.position[i], units[i], r_lo, r_hi)
        if band is None:
            raise OrbitTrackingError(
                f'target {target_id}: the line of sight of {tab.station_id} at {t[i]:.3f} s '
                f'misses the altitude band [{min_altitude:.0f}, {max_altitude:.0f}] m'
            )
        grids.append(np.linspace(band[0], band[1], n_range))
    lo_b = np.array([g[0] for g in grids])
    hi_b = np.array([g[-1] for g in grids])
    score_rows = np.unique(np.linspace(0, rows.size - 1, min(rows.size, 200)).round().astype(int))
    ts = t[pick]
    span = float(t[-1] - t[0]) or 1.0

    def curve(rho: FloatArray) -> FloatArray:
        pts = pose.position[pick] + rho[:, None] * units[pick]
        coef = np.polyfit((ts - t[0]) / span, pts, 2)  # (3, 3): parabola per axis
        s = (t[score_rows] - t[0]) / span
        return np.stack([np.polyval(coef[:, k], s) for k in range(3)], axis=1)

    def misfit(rho: FloatArray) -> FloatArray:
        p = curve(rho)
        x = np.hstack([p, np.zeros_like(p)])
        h, _ = predict(fields, x, pose.take(score_rows))
        r = residual(fields, vals[score_rows], h) / sig[score_rows]
        return np.nan_to_num(r, nan=0.0, posinf=1e9, neginf=-1e9).ravel()

    scored = []
    for triple in product(*grids):
        rr = misfit(np.asarray(triple))
        scored.append((float(rr @ rr), np.asarray(triple)))
    scored.sort(key=lambda c: c[0])
    out: list[tuple[float, FloatArray]] = []
    for _, rho in scored[:keep]:
        sol = least_squares(misfit, rho, x_scale=1e3, max_nfev=200, bounds=(lo_b, hi_b))
        p = curve(sol.x)
        fx = FixSeries(
            target_id,
            t[score_rows],
            p,
            np.tile(np.eye(3), (score_rows.size, 1, 1)),
        )
        try:
            out.append((float(sol.cost), start_from_fixes(fx, model, degree=2)))
        except OrbitTrackingError:
            continue
    if not out:
        raise OrbitTrackingError(f'target {target_id}: no range hypothesis gave a start')
    return [th for _, th in sorted(out, key=lambda c: c[0])]


def _units(st: StationObservations, rows: NDArray[np.intp]) -> FloatArray | None:
    fields, vals, _ = _angles(st, rows)
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
