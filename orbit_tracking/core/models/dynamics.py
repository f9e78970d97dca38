"""Truth dynamics: orbits, boosting vehicles, powered ascent with staging, aircraft and
ship tracks, integrated with ``scipy.integrate.solve_ivp`` and evaluated anywhere in
their span through dense output.

Every trajectory exposes the same small interface (:class:`Trajectory`):
``state(t) -> (m, 6)`` position and velocity in the world frame, ``acceleration(t)``,
and the span ``[t_start, t_end]`` in scenario seconds.

The module is a little over the project's ~600-line guide: it holds every truth model the
simulator flies, side by side on one integrator (:func:`_integrate`) so that they are
written and checked alike; splitting it would scatter that one piece of machinery.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.integrate import OdeSolution, solve_ivp

from orbit_tracking.core import frames

__all__ = [
    'AircraftTrack',
    'BoostVehicle',
    'GeodeticTrack',
    'KeplerOrbit',
    'PoweredAscent',
    'Stage',
    'TrackSegment',
    'Trajectory',
    'gravity',
]

FloatArray = NDArray[np.float64]
Rhs = Callable[[float, FloatArray], FloatArray]

G0 = 9.80665
"""Standard gravity [m/s^2] (load factors, specific impulse)."""

_RTOL = 1e-12
_ATOL_POS = 1e-7
_ATOL_VEL = 1e-10


class Trajectory(Protocol):
    """What the simulator needs from a moving body."""

    t_start: float
    t_end: float

    def state(self, t: ArrayLike) -> FloatArray:
        """Position and velocity, shape (m, 6), world frame [m, m/s]."""
        ...

    def acceleration(self, t: ArrayLike) -> FloatArray:
        """Acceleration, shape (m, 3), world frame [m/s^2]."""
        ...


def gravity(
    r: FloatArray, gm: float, j2: float = 0.0, radius: float = frames.WGS84_A
) -> FloatArray:
    """Point-mass gravity plus the J2 zonal term.

    Parameters
    ----------
    r : ndarray, shape (..., 3)
        Position in an Earth-centred frame whose z axis is the Earth's spin axis [m].
    gm : float
        Gravitational parameter [m^3/s^2].
    j2 : float
        Second zonal harmonic; 0 gives two-body gravity.
    radius : float
        Reference radius of ``j2`` [m].

    Returns
    -------
    ndarray, shape (..., 3)
        Acceleration [m/s^2].
    """
    rn = np.linalg.norm(r, axis=-1, keepdims=True)
    acc = -gm * r / rn**3
    if j2 != 0.0:
        z2 = (r[..., 2:3] / rn) ** 2
        k = -1.5 * j2 * gm * radius**2 / rn**5
        factor = np.concatenate([1.0 - 5.0 * z2, 1.0 - 5.0 * z2, 3.0 - 5.0 * z2], axis=-1)
        acc = acc + k * r * factor
    return acc


@dataclass
class _Piece:
    """One dense-output solution valid on [lo, hi] with the right-hand side it solved."""

    lo: float
    hi: float
    solution: OdeSolution
    rhs: Rhs


@dataclass
class _PiecewiseSolution:
    """Dense solutions of one ODE on adjacent intervals split at discontinuities."""

    pieces: list[_Piece] = field(default_factory=list)

    @property
    def t_start(self) -> float:
        return min(p.lo for p in self.pieces)

    @property
    def t_end(self) -> float:
        return max(p.hi for p in self.pieces)

    def _index(self, t: FloatArray) -> NDArray[np.intp]:
        bounds = np.array([p.lo for p in self.pieces] + [self.pieces[-1].hi])
        tol = 1e-9 * max(1.0, abs(bounds[-1]))
        if np.any(t < bounds[0] - tol) or np.any(t > bounds[-1] + tol):
            raise ValueError(
                f'time outside the trajectory span [{bounds[0]}, {bounds[-1]}]: '
                f'{t[(t < bounds[0] - tol) | (t > bounds[-1] + tol)][:3]}'
            )
        idx = np.searchsorted(bounds, t, side='right') - 1
        return np.clip(idx, 0, len(self.pieces) - 1)

    def y(self, t: ArrayLike) -> FloatArray:
        tt = np.atleast_1d(np.asarray(t, dtype=np.float64))
        idx = self._index(tt)
        n = self.pieces[0].solution(self.pieces[0].lo).shape[0]
        out = np.empty((tt.size, n))
        for k in np.unique(idx):
            sel = idx == k
            out[sel] = self.pieces[k].solution(tt[sel]).T
        return out

    def ydot(self, t: ArrayLike) -> FloatArray:
        tt = np.atleast_1d(np.asarray(t, dtype=np.float64))
        idx = self._index(tt)
        y = self.y(tt)
        out = np.empty_like(y)
        for i, (ti, k) in enumerate(zip(tt, idx, strict=True)):
            out[i] = self.pieces[k].rhs(float(ti), y[i])
        return out


def _integrate(
    rhs_for: Callable[[float], Rhs],
    t0: float,
    y0: FloatArray,
    t_start: float,
    t_end: float,
    breakpoints: Sequence[float] = (),
    atol: FloatArray | float = 1e-9,
) -> _PiecewiseSolution:
    """Integrate ``y' = rhs(t, y)`` from ``t0`` forward to ``t_end`` and back to
    ``t_start``, restarting at every breakpoint so discontinuities never fall inside a
    step. ``rhs_for(t_mid)`` returns the right-hand side valid on the interval that
    contains ``t_mid``.
    """
    if not t_start <= t0 <= t_end:
        raise ValueError(f'initial time {t0} must lie in the span [{t_start}, {t_end}]')
    inner = sorted({b for b in breakpoints if t_start < b < t_end} | {t0})
    grid = [t_start, *inner, t_end]
    grid = sorted(set(grid))
    i0 = grid.index(t0)
    result = _PiecewiseSolution()
    # forward from t0
    y = np.array(y0, dtype=np.float64)
    fwd: list[_Piece] = []
    for a, b in zip(grid[i0:-1], grid[i0 + 1 :], strict=True):
        rhs = rhs_for(0.5 * (a + b))
        sol = solve_ivp(rhs, (a, b), y, method='DOP853', rtol=_RTOL, atol=atol, dense_output=True)
        if not sol.success:
            raise RuntimeError(f'integration failed on [{a}, {b}]: {sol.message}')
        fwd.append(_Piece(a, b, sol.sol, rhs))
        y = sol.y[:, -1]
    # backward from t0
    y = np.array(y0, dtype=np.float64)
    bwd: list[_Piece] = []
    for b, a in zip(grid[i0:0:-1], grid[i0 - 1 :: -1], strict=False):
        rhs = rhs_for(0.5 * (a + b))
        sol = solve_ivp(rhs, (b, a), y, method='DOP853', rtol=_RTOL, atol=atol, dense_output=True)
        if not sol.success:
            raise RuntimeError(f'integration failed on [{a}, {b}]: {sol.message}')
        bwd.append(_Piece(a, b, sol.sol, rhs))
        y = sol.y[:, -1]
    result.pieces = bwd[::-1] + fwd
    if not result.pieces:
        raise ValueError(f'empty span [{t_start}, {t_end}]')
    return result


_POS_VEL_ATOL = np.array([_ATOL_POS] * 3 + [_ATOL_VEL] * 3)


class _PosVelTrajectory:
    """A trajectory whose ODE state is directly (position, velocity)."""

    def __init__(self, solution: _PiecewiseSolution) -> None:
        self._solution = solution
        self.t_start = solution.t_start
        self.t_end = solution.t_end

    def state(self, t: ArrayLike) -> FloatArray:
        return self._solution.y(t)

    def acceleration(self, t: ArrayLike) -> FloatArray:
        return self._solution.ydot(t)[:, 3:]


class KeplerOrbit(_PosVelTrajectory):
    """Two-body orbit (optionally with J2) in an inertial Earth-centred frame.

    ``r'' = -GM r / |r|^3`` (seed 003, eq. 5-1), plus J2 if ``j2`` is non-zero.

    Parameters
    ----------
    position, velocity : array_like, shape (3,)
        State at ``t0`` [m, m/s].
    t0 : float
        Epoch of the state [s].
    t_start, t_end : float
        Span to integrate [s]; must contain ``t0``.
    gm : float
        Gravitational parameter [m^3/s^2].
    j2 : float
        Zonal harmonic (0 for two-body).
    """

    def __init__(
        self,
        position: ArrayLike,
        velocity: ArrayLike,
        t0: float,
        t_start: float,
        t_end: float,
        gm: float = frames.WGS84_GM,
        j2: float = 0.0,
    ) -> None:
        self.gm = gm
        self.j2 = j2

        def rhs(_t: float, y: FloatArray) -> FloatArray:
            return np.concatenate([y[3:], gravity(y[:3], gm, j2)])

        y0 = np.concatenate([np.asarray(position, float), np.asarray(velocity, float)])
        super().__init__(_integrate(lambda _t: rhs, t0, y0, t_start, t_end, atol=_POS_VEL_ATOL))


class BoostVehicle(_PosVelTrajectory):
    """Seed 003's boosting vehicle: gravity plus thrust along the velocity.

    ``r'' = -GM r/|r|^3 + v_e / (tau0 - t) * v/|v|``: the rocket equation's thrust
    acceleration ``v_e * mdot / m`` with ``m(t)/mdot = tau0 - t``.

    Parameters
    ----------
    position, velocity : array_like, shape (3,)
        State at ``t0`` (inertial frame) [m, m/s].
    t0, t_start, t_end : float
        Epoch of the state and span [s].
    exhaust_speed : float
        Effective exhaust speed v_e [m/s].
    tau0 : float
        Scenario time at which the mass would reach zero [s]; must exceed ``t_end`` (or
        the staging time when there is a second stage).
    gm, j2 : float
        Gravity model.
    second_stage : (time, exhaust_speed, tau0), optional
        A staging at scenario time ``time`` [s] after which the thrust is ``exhaust_speed
        / (tau0 - t)`` (``tau0`` [s] past ``t_end``): the second stage of the staged
        rocket model, simulated independently of it.
    """

    def __init__(
        self,
        position: ArrayLike,
        velocity: ArrayLike,
        t0: float,
        t_start: float,
        t_end: float,
        exhaust_speed: float,
        tau0: float,
        gm: float = frames.WGS84_GM,
        j2: float = 0.0,
        second_stage: tuple[float, float, float] | None = None,
    ) -> None:
        t_s, c2, tau2 = second_stage if second_stage is not None else (math.inf, 0.0, math.inf)
        if tau0 <= min(t_end, t_s):
            raise ValueError(
                f'tau0 ({tau0} s) must exceed the end of the span ({t_end} s) or the staging'
            )
        if second_stage is not None and not (tau2 > t_end and c2 > 0.0):
            raise ValueError(
                f'the second stage needs exhaust speed > 0 and tau0 ({tau2} s) past the end '
                f'of the span ({t_end} s)'
            )
        self.exhaust_speed = exhaust_speed
        self.tau0 = tau0
        self.second_stage = second_stage

        def stage(c: float, tau: float) -> Rhs:
            def rhs(t: float, y: FloatArray) -> FloatArray:
                v = y[3:]
                thrust = c / (tau - t) * v / np.linalg.norm(v)
                return np.concatenate([v, gravity(y[:3], gm, j2) + thrust])

            return rhs

        first, second = stage(exhaust_speed, tau0), stage(c2, tau2)
        y0 = np.concatenate([np.asarray(position, float), np.asarray(velocity, float)])
        super().__init__(
            _integrate(
                lambda t_mid: first if t_mid < t_s else second,
                t0,
                y0,
                t_start,
                t_end,
                breakpoints=[t_s] if math.isfinite(t_s) else [],
                atol=_POS_VEL_ATOL,
            )
        )

    def thrust_acceleration(self, t: ArrayLike) -> FloatArray:
        """Magnitude of the thrust acceleration [m/s^2], shape (m,)."""
        tt = np.atleast_1d(np.asarray(t, float))
        if self.second_stage is None:
            return self.exhaust_speed / (self.tau0 - tt)
        t_s, c2, tau2 = self.second_stage
        late = tt >= t_s
        out = np.empty_like(tt)
        out[~late] = self.exhaust_speed / (self.tau0 - tt[~late])
        out[late] = c2 / (tau2 - tt[late])
        return out


@dataclass(frozen=True)
class Stage:
    """One rocket stage.

    Attributes
    ----------
    mass_kg : float
        Mass of the whole stack at this stage's ignition [kg].
    propellant_kg : float
        Propellant this stage burns [kg].
    mass_flow_kg_s : float
        Propellant mass flow [kg/s]; burn time = propellant / flow.
    exhaust_speed_m_s : float
        Effective exhaust speed [m/s]; thrust = flow * exhaust speed.
    coast_before_s : float
        Unpowered coast between the previous stage's burnout and this ignition [s].
    """

    mass_kg: float
    propellant_kg: float
    mass_flow_kg_s: float
    exhaust_speed_m_s: float
    coast_before_s: float = 0.0

    @property
    def burn_time_s(self) -> float:
        return self.propellant_kg / self.mass_flow_kg_s

    @property
    def thrust_n(self) -> float:
        return self.mass_flow_kg_s * self.exhaust_speed_m_s


class PoweredAscent(_PosVelTrajectory):
    """Multi-stage powered ascent from a launch site, integrated in ECEF (seed 000).

    Equations of motion in the rotating Earth-fixed frame::

        r'' = g_J2(r) - 2 w x v - w x (w x r) + (T/m) u(t) - (rho |v| cd_a / 2m) v

    with ``u(t)`` the thrust direction of the pitch program, fixed in the launch frame
    (``(cos phi, sin phi, 0)``: ``phi`` above the horizontal, in the launch-azimuth
    plane), an exponential atmosphere for drag, and the stack's mass decreasing at each
    stage's flow. At each burnout the spent stage is dropped (the next stage's
    ``mass_kg`` is the stack after separation) and the vehicle coasts for
    ``coast_before_s`` before the next ignition, so the acceleration jumps there.

    Parameters
    ----------
    latitude, longitude, height : float
        Launch point (geodetic) [rad, rad, m].
    azimuth : float
        Launch azimuth [rad] from north toward east.
    liftoff_time : float
        Scenario time of lift-off [s]; the trajectory starts there (at rest on the pad).
    t_end : float
        End of the integration [s].
    stages : sequence of Stage
    pitch_program : array_like, shape (k, 2)
        ``(time since lift-off [s], pitch above horizontal [rad])`` nodes, linearly
        interpolated and held constant beyond the last node.
    cd_area_m2 : float
        Drag coefficient times reference area [m^2]; 0 disables drag.
    """

    def __init__(
        self,
        latitude: float,
        longitude: float,
        height: float,
        azimuth: float,
        liftoff_time: float,
        t_end: float,
        stages: Sequence[Stage],
        pitch_program: ArrayLike,
        cd_area_m2: float = 0.0,
    ) -> None:
        if not stages:
            raise ValueError('a powered ascent needs at least one stage')
        prog = np.asarray(pitch_program, dtype=np.float64)
        if prog.ndim != 2 or prog.shape[1] != 2 or prog.shape[0] < 1:
            raise ValueError(f'pitch program must have shape (k, 2); got {prog.shape}')
        if np.any(np.diff(prog[:, 0]) <= 0):
            raise ValueError('pitch program times must increase strictly')
        self.launch_rotation = frames.launch_rotation(latitude, longitude, azimuth)
        self.launch_origin = frames.geodetic_to_ecef(latitude, longitude, height)
        self.liftoff_time = liftoff_time
        self.stages = tuple(stages)
        omega = np.array([0.0, 0.0, frames.EARTH_ROTATION_RATE])
        s_mat = self.launch_rotation

        # Phase table: (start, end, stage index or -1 for coast, stack mass at start)
        phases: list[tuple[float, float, int, float]] = []
        t = liftoff_time
        for k, st in enumerate(self.stages):
            if st.coast_before_s > 0.0:
                phases.append((t, t + st.coast_before_s, -1, st.mass_kg))
                t += st.coast_before_s
            phases.append((t, t + st.burn_time_s, k, st.mass_kg))
            t += st.burn_time_s
        phases.append((t, np.inf, -1, self.stages[-1].mass_kg - self.stages[-1].propellant_kg))
        self.phases = tuple(phases)
        self.separation_times = tuple(p[1] for p in phases if p[2] >= 0)

        def make_rhs(t_mid: float) -> Rhs:
            start, _, k, m0 = next(p for p in phases if p[0] <= t_mid < p[1])
            if k >= 0:
                flow = self.stages[k].mass_flow_kg_s
                thrust = self.stages[k].thrust_n
            else:
                flow = thrust = 0.0

            def rhs(tt: float, y: FloatArray) -> FloatArray:
                r, v = y[:3], y[3:]
                acc = gravity(r, frames.WGS84_GM, frames.WGS84_J2)
                acc = acc - 2.0 * np.cross(omega, v) - np.cross(omega, np.cross(omega, r))
                mass = m0 - flow * (tt - start)
                if thrust > 0.0:
                    phi = np.interp(tt - liftoff_time, prog[:, 0], prog[:, 1])
                    acc = acc + thrust / mass * (s_mat @ np.array([np.cos(phi), np.sin(phi), 0.0]))
                if cd_area_m2 > 0.0:
                    _, _, h = frames.ecef_to_geodetic(r)
                    rho = 1.225 * np.exp(-max(float(h), 0.0) / 8500.0)
                    acc = acc - 0.5 * rho * np.linalg.norm(v) * cd_area_m2 / mass * v
                return np.concatenate([v, acc])

            return rhs

        breaks = [p[0] for p in phases] + list(liftoff_time + prog[:, 0])
        y0 = np.concatenate([self.launch_origin, np.zeros(3)])
        sol = _integrate(make_rhs, liftoff_time, y0, liftoff_time, t_end, breaks, _POS_VEL_ATOL)
        super().__init__(sol)

    def to_launch_frame(self, state: ArrayLike) -> FloatArray:
        """ECEF states (m, 6) to launch-frame states (m, 6)."""
        s = np.atleast_2d(np.asarray(state, dtype=np.float64))
        pos = (s[:, :3] - self.launch_origin) @ self.launch_rotation
        vel = s[:, 3:] @ self.launch_rotation
        return np.hstack([pos, vel])


@dataclass(frozen=True)
class TrackSegment:
    """One leg of a geodetic kinematic track (aircraft pattern or ship course).

    Attributes
    ----------
    duration_s : float
        Length of the leg [s].
    lateral_accel_m_s2 : float
        Horizontal acceleration normal to the velocity [m/s^2]; positive turns right
        (clockwise seen from above). A level turn at load factor n has
        ``g0 * sqrt(n^2 - 1)``.
    speed_rate_m_s2 : float
        Rate of change of airspeed [m/s^2].
    path_angle_rate_rad_s : float
        Rate of change of the flight-path angle [rad/s].
    """

    duration_s: float
    lateral_accel_m_s2: float = 0.0
    speed_rate_m_s2: float = 0.0
    path_angle_rate_rad_s: float = 0.0


class GeodeticTrack:
    """A body moving over the WGS-84 ellipsoid by prescribed speed, heading and path
    angle rates, output in ECEF.

    The ODE state is ``(lat, lon, h, V, psi, gamma)`` with
    ``lat' = v_n/(M+h)``, ``lon' = v_e/((N+h) cos lat)``, ``h' = v_u`` and
    ``v_enu = V (cos g sin psi, cos g cos psi, sin g)``, so the ECEF velocity is exactly
    the derivative of the ECEF position. Controls change linearly over
    ``transition_s`` at each leg boundary so that the acceleration stays continuous
    (roll-in of a turn).

    Parameters
    ----------
    latitude, longitude, height : float
        Start point [rad, rad, m].
    speed : float
        Initial speed [m/s] (> 0).
    heading : float
        Initial course from north toward east [rad].
    t_start : float
        Scenario time of the start point [s].
    segments : sequence of TrackSegment
        Consecutive legs from ``t_start``; the track ends after the last.
    transition_s : float
        Duration of the linear change of controls at each leg boundary [s].
    path_angle : float
        Initial flight-path angle [rad].
    """

    def __init__(
        self,
        latitude: float,
        longitude: float,
        height: float,
        speed: float,
        heading: float,
        t_start: float,
        segments: Sequence[TrackSegment],
        transition_s: float = 2.0,
        path_angle: float = 0.0,
    ) -> None:
        if speed <= 0.0:
            raise ValueError(f'track speed must be positive; got {speed}')
        if not segments:
            raise ValueError('a track needs at least one segment')
        bounds = t_start + np.concatenate([[0.0], np.cumsum([s.duration_s for s in segments])])
        controls = np.array(
            [[s.lateral_accel_m_s2, s.speed_rate_m_s2, s.path_angle_rate_rad_s] for s in segments]
        )
        self.segments = tuple(segments)
        self.t_start = float(bounds[0])
        self.t_end = float(bounds[-1])
        tr = float(transition_s)
        # control nodes: at each boundary k>0 ramp from controls[k-1] to controls[k]
        node_t = [bounds[0]]
        node_u = [controls[0]]
        for k in range(1, len(segments)):
            ramp = min(tr, 0.5 * segments[k].duration_s, 0.5 * segments[k - 1].duration_s)
            node_t += [bounds[k] - 0.5 * ramp, bounds[k] + 0.5 * ramp]
            node_u += [controls[k - 1], controls[k]]
        node_t.append(bounds[-1])
        node_u.append(controls[-1])
        self._node_t = np.array(node_t)
        self._node_u = np.array(node_u)

        def rhs(t: float, y: FloatArray) -> FloatArray:
            lat, _lon, h, v, psi, gam = y
            u = self.controls(t)
            m, n = frames.meridian_radii(lat)
            ve = v * np.cos(gam) * np.sin(psi)
            vn = v * np.cos(gam) * np.cos(psi)
            vu = v * np.sin(gam)
            return np.array(
                [
                    vn / (m + h),
                    ve / ((n + h) * np.cos(lat)),
                    vu,
                    u[1],
                    u[0] / (v * np.cos(gam)),
                    u[2],
                ]
            )

        y0 = np.array([latitude, longitude, height, speed, heading, path_angle], dtype=float)
        atol = np.array([1e-14, 1e-14, 1e-7, 1e-10, 1e-12, 1e-12])
        self._solution = _integrate(
            lambda _t: rhs, self.t_start, y0, self.t_start, self.t_end, list(self._node_t), atol
        )

    def controls(self, t: float) -> FloatArray:
        """(lateral accel, speed rate, path-angle rate) at scenario time ``t``."""
        return np.array([np.interp(t, self._node_t, self._node_u[:, j]) for j in range(3)])

    def geodetic_state(self, t: ArrayLike) -> FloatArray:
        """ODE state ``(lat, lon, h, V, psi, gamma)``, shape (m, 6)."""
        return self._solution.y(t)

    def course(self, t: ArrayLike) -> FloatArray:
        """Course over ground from north toward east [rad], shape (m,)."""
        return self.geodetic_state(t)[:, 4]

    def state(self, t: ArrayLike) -> FloatArray:
        g = self.geodetic_state(t)
        lat, lon, h, v, psi, gam = g.T
        pos = frames.geodetic_to_ecef(lat, lon, h)
        v_enu = np.stack(
            [v * np.cos(gam) * np.sin(psi), v * np.cos(gam) * np.cos(psi), v * np.sin(gam)],
            axis=-1,
        )
        vel = np.einsum('mij,mj->mi', frames.enu_rotation(lat, lon), v_enu)
        return np.hstack([pos, vel])

    def acceleration(self, t: ArrayLike, dt: float = 1e-3) -> FloatArray:
        """ECEF acceleration by a central difference of the dense velocity [m/s^2]."""
        tt = np.atleast_1d(np.asarray(t, dtype=np.float64))
        lo = np.maximum(tt - dt, self.t_start)
        hi = np.minimum(tt + dt, self.t_end)
        return (self.state(hi)[:, 3:] - self.state(lo)[:, 3:]) / (hi - lo)[:, None]


AircraftTrack = GeodeticTrack
"""Alias: an aircraft test pattern is a geodetic track with turns of 2-3 g (seed 004)."""
