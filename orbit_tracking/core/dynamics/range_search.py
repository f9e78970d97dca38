"""The rocket model's start from one station's angles alone (seed 003's single satellite,
issue 15): a range-hypothesis search flown with the dynamics.

Angles alone fix neither the range nor the range rate, and a kinematic curve fits them
about as well at any range (a parabola through three ranges misses a two-minute burn by
kilometres, hundreds of sigma, and its best ranges were far from the true ones on most
one-satellite draws of the randomised family): only the dynamics make the range
observable, so the hypotheses are flown with them.

* At the first epoch the vehicle lies on the line of sight at a range where its altitude
  is within ``[min_altitude, max_altitude]`` (the ray's first crossing of that shell: the
  admissible region); the line of sight's rate there (a cubic through the first fifth of
  the span) gives the velocity across it for each range.
* Hypotheses (range, range rate, thrust level): ``n_range`` ranges over that stretch,
  range rates within ``+-MAX_START_SPEED``, starting thrusts of 5, 15 and 40 m/s^2 (the
  default exhaust speed, burning past the span); those faster than
  :data:`MAX_START_SPEED` are not flights.
* All are flown at once by a fixed-step integrator (:func:`_fly`) and scored by their
  misfit of the angles over the first third of the span, where a slightly wrong range rate
  or thrust has not yet run away; the best :data:`REFINED_HYPOTHESES` are refined together
  by Levenberg-Marquardt over two thirds and then all of the span.
* The best few that differ (by more than a grid step in some parameter) are the starts;
  :func:`~.solve.fit_rocket` scouts them with the full model and fits the best to the end.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core import frames
from orbit_tracking.core.data.observations import StationObservations
from orbit_tracking.core.dynamics.rocket import RocketModel
from orbit_tracking.core.dynamics.start import DEFAULT_EXHAUST_SPEED, angle_fields
from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.core.models.dynamics import gravity
from orbit_tracking.core.models.measurements import los_unit_vectors, predict, residual

__all__ = ['MAX_START_SPEED', 'REFINED_HYPOTHESES', 'start_candidates']

FloatArray = NDArray[np.float64]

MAX_START_SPEED = 9e3
"""Range hypotheses whose flight would be faster than this [m/s] are not flights."""

REFINED_HYPOTHESES = 48
"""Best range hypotheses of the grid refined by Levenberg-Marquardt."""

THRUST_LEVELS = (5.0, 15.0, 40.0)
"""Starting thrust accelerations [m/s^2] of the hypotheses."""

LM_STEPS = 6
"""Levenberg-Marquardt steps of the refinement on each stretch of the data."""


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


def _line_of_sight_rate(t: FloatArray, units: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The unit line of sight at ``t[0]`` and its rate [1/s] from a cubic through the
    first fifth of the span (at least eight epochs)."""
    span = float(t[-1] - t[0])
    n = max(8, int(np.searchsorted(t, t[0] + 0.2 * span)))
    tt = t[:n] - t[0]
    coef = [np.polyfit(tt, units[:n, k], min(3, n - 2)) for k in range(3)]
    u0 = np.array([np.polyval(c, 0.0) for c in coef])
    du = np.array([np.polyval(np.polyder(c), 0.0) for c in coef])
    u0 = u0 / np.linalg.norm(u0)
    return u0, du - (du @ u0) * u0


def _fly(model: RocketModel, y0: FloatArray, thrust: FloatArray, times: FloatArray) -> FloatArray:
    """Positions (N, m, 3) of N rocket flights from states ``y0`` (N, 6) at ``model.epoch``
    with thrust pairs ``(c, tau)`` (N, 2), at increasing ``times`` (m,) after the epoch:
    fixed-step RK4 (<= 1 s) for all at once, Hermite between the steps (metres of error,
    enough to rank hypotheses; the fit integrates properly)."""
    t_end = float(times[-1])
    n_step = max(1, math.ceil((t_end - model.epoch) / 1.0))
    h = (t_end - model.epoch) / n_step
    w = np.array([0.0, 0.0, model.earth_rate])
    c, tau = thrust[:, :1], thrust[:, 1:]

    def f(t: float, y: FloatArray) -> FloatArray:
        r, v = y[:, :3], y[:, 3:]
        speed = np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-3)
        a = gravity(r, model.gm, model.j2, model.radius)
        a = a + c / np.maximum(tau - (t - model.epoch), 1.0) * v / speed
        if model.earth_rate:
            a = a - 2.0 * np.cross(w, v) - np.cross(w, np.cross(w, r))
        return np.hstack([v, a])

    ys, fs = [y0], [f(model.epoch, y0)]
    y = y0
    for k in range(n_step):
        t = model.epoch + k * h
        k1 = fs[-1]
        k2 = f(t + 0.5 * h, y + 0.5 * h * k1)
        k3 = f(t + 0.5 * h, y + 0.5 * h * k2)
        k4 = f(t + h, y + h * k3)
        y = y + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        ys.append(y)
        fs.append(f(t + h, y))
    y_all, v_all = np.stack(ys, axis=1), np.stack(fs, axis=1)  # (N, n_step + 1, 6)
    i = np.clip(((times - model.epoch) / h).astype(int), 0, n_step - 1)
    s = ((times - model.epoch) / h - i)[None, :, None]
    p0, p1 = y_all[:, i, :3], y_all[:, i + 1, :3]
    m0, m1 = h * v_all[:, i, :3], h * v_all[:, i + 1, :3]
    return (
        (2 * s**3 - 3 * s**2 + 1) * p0
        + (s**3 - 2 * s**2 + s) * m0
        + (-2 * s**3 + 3 * s**2) * p1
        + (s**3 - s**2) * m1
    )


def _refine(
    whitened: Callable[[FloatArray, int], FloatArray],
    par: FloatArray,
    horizons: list[int],
    scale: FloatArray,
    bounds: tuple[float, float],
) -> tuple[FloatArray, FloatArray]:
    """Levenberg-Marquardt on every hypothesis at once (forward-difference Jacobians of
    the scaled parameters; Marquardt's damping per hypothesis), on ever longer stretches
    of the data; the refined hypotheses and their costs on the last stretch."""
    par = par.copy()
    cost = np.empty(par.shape[0])
    eye = np.eye(par.shape[1])
    for upto in horizons:
        damp = np.full(par.shape[0], 1e-2)
        r = whitened(par, upto)
        cost = np.sum(r**2, axis=1)
        for _ in range(LM_STEPS):
            h = 1e-3 * scale
            rs = whitened(np.concatenate([par + h * e for e in eye]), upto)
            jac = np.moveaxis((rs.reshape(eye.shape[0], *r.shape) - r) / h[:, None, None], 0, -1)
            jn = jac * scale
            nmat = np.einsum('nmi,nmj->nij', jn, jn)
            nmat = nmat + damp[:, None, None] * (
                eye * np.diagonal(nmat, 0, 1, 2)[:, None, :] + 1e-9 * eye
            )
            g = np.einsum('nmi,nm->ni', jn, r)
            trial = par - np.linalg.solve(nmat, g[..., None])[..., 0] * scale
            trial[:, 0] = np.clip(trial[:, 0], *bounds)
            rt = whitened(trial, upto)
            ct = np.sum(rt**2, axis=1)
            better = ct < cost
            par[better], r[better], cost[better] = trial[better], rt[better], ct[better]
            damp = np.where(better, damp / 3.0, damp * 4.0)
    return par, cost


def start_candidates(
    st: StationObservations,
    target_id: int,
    model: RocketModel,
    min_altitude: float = 0.0,
    max_altitude: float = 1.5e6,
    n_range: int = 24,
    keep: int = 4,
) -> list[FloatArray]:
    """Rocket parameters (at ``model.epoch``) to start from when one station's angles are
    all there is (module docstring), best first.

    Raises
    ------
    OrbitTrackingError
        Too few rows, or the line of sight misses the altitude band.
    """
    tab = st.table
    rows = np.flatnonzero(tab.target_id == target_id)
    if rows.size < 10:
        raise OrbitTrackingError(
            f'target {target_id}: {rows.size} rows of {tab.station_id} are too few to start from'
        )
    fields, vals, sig = angle_fields(st, rows)
    if len(fields) != 2:
        raise OrbitTrackingError(f'{tab.station_id} measures no pair of angles')
    kind = 'los' if 'los_alpha' in fields else 'angles'
    order = np.argsort(tab.time[rows], kind='stable')
    rows, vals, sig = rows[order], vals[order], sig[order]
    t = tab.time[rows]
    pose = st.pose.take(rows)
    units = los_unit_vectors(kind, vals, fields, pose.rotation)
    if kind == 'los':  # the line, not the ray: point it toward the Earth's centre
        flip = np.einsum('mi,mi->m', units, pose.position) > 0.0
        units[flip] *= -1.0
    u0, du0 = _line_of_sight_rate(t, units)
    band = _band(
        pose.position[0], u0, frames.WGS84_B + min_altitude, frames.WGS84_A + max_altitude
    )
    if band is None:
        raise OrbitTrackingError(
            f'target {target_id}: the line of sight of {tab.station_id} at {t[0]:.3f} s '
            f'misses the altitude band [{min_altitude:.0f}, {max_altitude:.0f}] m'
        )
    search = replace(model, epoch=float(t[0]))  # the hypotheses are states at t[0]
    score = np.unique(np.linspace(0, rows.size - 1, min(rows.size, 200)).round().astype(int))
    t_score, z_score, s_score = t[score], vals[score], sig[score]
    pose_score = pose.take(score)
    span = float(t[-1] - t[0])

    def flights(par: FloatArray) -> tuple[FloatArray, FloatArray]:
        """States at ``t[0]`` (N, 6) and thrust pairs (N, 2) of hypotheses ``par`` (N, 3):
        range [m], range rate [m/s] and log of the starting thrust [m/s^2]."""
        r0 = pose.position[0] + par[:, :1] * u0
        v0 = pose.velocity[0] + par[:, 1:2] * u0 + par[:, :1] * du0
        level = np.exp(par[:, 2])
        tau = np.maximum(DEFAULT_EXHAUST_SPEED / level, span + 30.0)
        return np.hstack([r0, v0]), np.stack([level * tau, tau], axis=1)

    def whitened(par: FloatArray, upto: int) -> FloatArray:
        """Whitened angle residuals (N, 2 upto) of the first ``upto`` scored epochs."""
        y0, pair = flights(par)
        out = np.empty((par.shape[0], upto * len(fields)))
        pos = _fly(search, y0, pair, t_score[:upto])
        for a in range(0, par.shape[0], 256):
            b = min(a + 256, par.shape[0])
            x = pos[a:b].reshape(-1, 3)
            pz = pose_score.take(np.tile(np.arange(upto), b - a))
            h, _ = predict(fields, np.hstack([x, np.zeros_like(x)]), pz)
            r = residual(fields, np.tile(z_score[:upto], (b - a, 1)), h)
            r = r / np.tile(s_score[:upto], (b - a, 1))
            out[a:b] = np.nan_to_num(r, nan=1e6, posinf=1e6, neginf=1e6).reshape(b - a, -1)
        return out

    rho = np.linspace(band[0], band[1], n_range)
    rate = np.linspace(-MAX_START_SPEED, MAX_START_SPEED, 2 * n_range + 1)
    grid = np.meshgrid(rho, rate, np.log(THRUST_LEVELS), indexing='ij')
    par = np.stack(grid, -1).reshape(-1, 3)
    par = par[np.linalg.norm(flights(par)[0][:, 3:], axis=1) <= MAX_START_SPEED]
    if not par.size:
        raise OrbitTrackingError(f'target {target_id}: no range hypothesis is a flight')
    horizons = [int(np.searchsorted(t_score, t[0] + f * span)) for f in (1 / 3, 2 / 3)]
    horizons = [max(h, 8) for h in horizons] + [score.size]
    cost = np.sum(whitened(par, horizons[0]) ** 2, axis=1)
    scale = np.array([(band[1] - band[0]) / n_range, rate[1] - rate[0], 0.3])
    par, cost = _refine(
        whitened, par[np.argsort(cost)[:REFINED_HYPOTHESES]], horizons, scale, band
    )
    picked: list[int] = []
    for n in np.argsort(cost):
        if len(picked) < keep and all(np.any(np.abs(par[n] - par[m]) > scale) for m in picked):
            picked.append(int(n))
    y0, pair = flights(par[picked])
    out = []
    for k in range(len(picked)):
        theta = np.concatenate([y0[k], pair[k]])
        if search.epoch != model.epoch:  # carried back to the model's epoch by its flight
            x = search.propagate(theta, [model.epoch], jacobian=False).state[0]
            theta = np.concatenate([x, pair[k, :1], pair[k, 1:] + search.epoch - model.epoch])
        out.append(theta)
    return out
