"""Scenario simulator: station measurements, station states, telemetry and truth.

Everything is computed up front as arrays (a few seconds at most for the reference
scenarios); the nodes and the bag writer then stream them in time order.
Randomness enters only through :func:`~orbit_tracking.core.sim.scenario.station_rng`, so a
scenario file and its seed fully determine the output.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core import frames
from orbit_tracking.core.data.tables import MeasurementTable, StationStates, TargetStates
from orbit_tracking.core.models.measurements import StationPose, predict, wrap_azimuth
from orbit_tracking.core.models.systematic import BiasModel
from orbit_tracking.core.sim.scenario import (
    Scenario,
    StationConfig,
    TelemetryConfig,
    build_orbit,
    build_platform_tracks,
    build_targets,
    station_rng,
)
from orbit_tracking.core.sim.telemetry import simulate_model

__all__ = [
    'SimulationResult',
    'World',
    'epoch_grid',
    'simulate',
    'simulate_station',
    'simulate_station_with_gross_errors',
    'simulate_telemetry',
    'simulate_truth',
]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SimulationResult:
    """Everything a scenario run produces, keyed by station id / target id."""

    scenario: Scenario
    measurements: Mapping[str, MeasurementTable]
    station_states: Mapping[str, StationStates]
    truth: Mapping[int, TargetStates]
    telemetry: Mapping[int, TargetStates] = field(default_factory=dict)
    gross_errors: Mapping[str, NDArray[np.bool_]] = field(default_factory=dict)
    """Per station, which values (n, k) of its table carry a simulated gross error
    (``gross_errors`` of the station's config)."""


def epoch_grid(first: float, rate_hz: float, t_start: float, t_end: float) -> FloatArray:
    """Epochs ``first + k / rate`` (k = 0, 1, ...) that fall within [t_start, t_end]."""
    dt = 1.0 / rate_hz
    k0 = max(0, int(np.ceil((t_start - first) / dt - 1e-9)))
    k1 = int(np.floor((t_end - first) / dt + 1e-9))
    return np.asarray(first + np.arange(k0, k1 + 1) * dt, dtype=np.float64)


class World:
    """Truth of a scenario: target trajectories and station platforms.

    Parameters
    ----------
    scenario : Scenario
    """

    def __init__(self, scenario: Scenario) -> None:
        self.scenario = scenario
        self.targets = build_targets(scenario)
        self.ships = build_platform_tracks(scenario)
        self.orbits = {
            s.id: build_orbit(s.platform, scenario)
            for s in scenario.stations
            if s.platform['type'] == 'orbit'
        }

    def station_states(self, st: StationConfig, t: FloatArray) -> StationStates:
        """Pose of station ``st`` at epochs ``t`` (one row for a fixed station)."""
        p = st.platform
        if p['type'] == 'fixed':
            lat, lon = np.radians(p['latitude_deg']), np.radians(p['longitude_deg'])
            pos = frames.geodetic_to_ecef(lat, lon, p['height_m'])
            rot = frames.enu_rotation(lat, lon)
            return StationStates(
                st.id,
                False,
                np.array([t[0] if len(t) else self.scenario.t_start]),
                pos[None, :],
                np.zeros((1, 3)),
                rot[None, :, :],
                np.zeros((1, 3)),
            )
        if p['type'] == 'orbit':
            x = self.orbits[st.id].state(t)
            rot = frames.observation_rotation(x[:, :3])
            # the observation frame turns with the orbit: w = r x v / |r|^2, in frame axes
            w_world = np.cross(x[:, :3], x[:, 3:]) / np.sum(x[:, :3] ** 2, axis=1)[:, None]
            w_body = np.einsum('mji,mj->mi', rot, w_world)
            return StationStates(st.id, True, t, x[:, :3], x[:, 3:], rot, w_body)
        return self._ship_station(st, t)

    def ship_attitude(self, ship_id: str, t: FloatArray) -> FloatArray:
        """Deck-to-ECEF rotations of a ship, shape (m, 3, 3)."""
        track = self.ships[ship_id]
        cfg = next(s for s in self.scenario.platforms if s['id'] == ship_id)
        att = cfg['attitude']

        def wave(amp_deg: float, period: float, phase: float) -> FloatArray:
            return np.radians(amp_deg) * np.sin(2.0 * np.pi * t / period + phase)

        yaw = track.course(t) + wave(
            att.get('yaw_amplitude_deg', 0.0), att.get('yaw_period_s', 15.0), 0.3
        )
        pitch = wave(att.get('pitch_amplitude_deg', 0.0), att.get('pitch_period_s', 10.0), 1.1)
        roll = wave(att.get('roll_amplitude_deg', 0.0), att.get('roll_period_s', 10.0), 2.0)
        g = track.geodetic_state(t)
        r_enu = frames.enu_rotation(g[:, 0], g[:, 1])
        return np.einsum('mij,mjk->mik', r_enu, frames.platform_rotation(yaw, pitch, roll))

    def _ship_station(self, st: StationConfig, t: FloatArray) -> StationStates:
        ship_id = st.platform['ship']
        track = self.ships[ship_id]
        lever = np.asarray(st.platform['lever_arm_m'], dtype=np.float64)
        dt = 1e-3
        lo = np.maximum(t - dt, track.t_start)
        hi = np.minimum(t + dt, track.t_end)
        rot = self.ship_attitude(ship_id, t)
        rot_lo, rot_hi = self.ship_attitude(ship_id, lo), self.ship_attitude(ship_id, hi)
        x = track.state(t)
        pos = x[:, :3] + rot @ lever
        # velocity of the sensor = ship velocity + d/dt (R lever)
        vel = x[:, 3:] + ((rot_hi - rot_lo) @ lever) / (hi - lo)[:, None]
        # body angular rate from R^T dR/dt (skew-symmetric)
        omega_hat = np.einsum('mji,mjk->mik', rot, (rot_hi - rot_lo)) / (hi - lo)[:, None, None]
        w = np.stack([omega_hat[:, 2, 1], omega_hat[:, 0, 2], omega_hat[:, 1, 0]], axis=1)
        return StationStates(st.id, True, t, pos, vel, rot, w)

    def target_state(self, target_id: int, t: FloatArray) -> FloatArray:
        return self.targets[target_id].state(t)


def _visible(
    st: StationConfig, sc: Scenario, target: FloatArray, pose: StationPose
) -> NDArray[np.bool_]:
    d = target[:, :3] - pose.position
    rng = np.linalg.norm(d, axis=1)
    ok = np.ones(len(d), dtype=bool)
    if st.max_range_m is not None:
        ok &= rng <= st.max_range_m
    if st.elevation_mask_deg is not None and sc.world_frame == 'earth':
        # mask in the local (stabilised) horizon of the station
        lat, lon, _ = frames.ecef_to_geodetic(pose.position)
        up = frames.enu_rotation(lat, lon)[..., 2]
        elev = np.arcsin(np.clip(np.einsum('mi,mi->m', d, up) / rng, -1.0, 1.0))
        ok &= elev >= np.radians(st.elevation_mask_deg)
    if st.earth_occlusion and st.kind == 'satellite':
        # the segment station -> target must not pass inside the Earth's polar radius
        u = d / rng[:, None]
        s = np.clip(-np.einsum('mi,mi->m', pose.position, u), 0.0, rng)
        closest = pose.position + s[:, None] * u
        ok &= np.linalg.norm(closest, axis=1) > frames.WGS84_B
    return ok


def _in_windows(t: FloatArray, windows: Sequence[Mapping[str, float]]) -> NDArray[np.bool_]:
    inside = np.zeros(t.shape, dtype=bool)
    for w in windows:
        inside |= (t >= w['start']) & (t <= w['end'])
    return inside


def simulate_station(world: World, st: StationConfig) -> tuple[MeasurementTable, StationStates]:
    """Measurements and station states of one station over the scenario span."""
    table, states, _ = simulate_station_with_gross_errors(world, st)
    return table, states


def simulate_station_with_gross_errors(
    world: World, st: StationConfig
) -> tuple[MeasurementTable, StationStates, NDArray[np.bool_]]:
    """:func:`simulate_station`, and which values (n, k) of the table carry a gross
    error (``st.gross_errors``; drawn after all other noise of the station, so a station
    without them is simulated exactly as before)."""
    sc = world.scenario
    rng = station_rng(sc, st.id)
    grid = epoch_grid(st.first_epoch, st.rate_hz, sc.t_start, sc.t_end)
    states = world.station_states(st, grid)
    full_dropouts = [w for w in st.dropouts if w['fields'] is None]
    keep_epoch = ~_in_windows(grid, full_dropouts)
    if st.loss_probability > 0.0:
        keep_epoch &= rng.random(grid.size) >= st.loss_probability
    bias = BiasModel(st.bias)
    k = len(st.fields)
    rows_t, rows_id, rows_v = [], [], []
    pose_all = (
        states.pose()
        if states.moving
        else StationPose.fixed(states.position[0], states.rotation[0], grid.size)
    )
    for tid in st.targets:
        # the sensor's clock reads t when the true time is t + clock_bias
        truth = world.target_state(tid, np.clip(grid + st.clock_bias_s, sc.t_start, sc.t_end))
        vis = keep_epoch & _visible(st, sc, truth, pose_all)
        if not np.any(vis):
            continue
        values, _ = predict(st.fields, truth[vis], pose_all.take(np.flatnonzero(vis)))
        rows_t.append(grid[vis])
        rows_id.append(np.full(int(vis.sum()), tid, dtype=np.uint32))
        rows_v.append(values)
    if rows_t:
        time = np.concatenate(rows_t)
        tids = np.concatenate(rows_id)
        true_vals = np.concatenate(rows_v)
        order = np.lexsort((tids, time))
        time, tids, true_vals = time[order], tids[order], true_vals[order]
    else:
        time, tids, true_vals = np.empty(0), np.empty(0, np.uint32), np.empty((0, k))
    sig = np.tile(st.sigmas, (time.size, 1))
    meas = bias.apply(st.fields, true_vals) + rng.standard_normal(true_vals.shape) * sig
    for j, f in enumerate(st.fields):
        if f == 'azimuth':
            meas[:, j] = wrap_azimuth(meas[:, j])
    for w in st.dropouts:
        if w['fields'] is not None:
            inside = _in_windows(time, [w])
            for f in w['fields']:
                meas[inside, st.fields.index(f)] = np.nan
    gross = _gross_errors(st, meas, sig, rng)
    table = MeasurementTable(st.id, st.kind, st.fields, time, tids, meas, sig)
    # a point whose every value is NaN carries nothing: drop it
    keep = ~np.all(np.isnan(table.values), axis=1)
    return table.select(keep), states, gross[keep]


def _gross_errors(
    st: StationConfig, meas: FloatArray, sig: FloatArray, rng: np.random.Generator
) -> NDArray[np.bool_]:
    """Add the station's gross errors to ``meas`` in place; returns where they are."""
    mask = np.zeros(meas.shape, dtype=bool)
    count = int(st.gross_errors.get('count', 0))
    cand = np.flatnonzero(np.isfinite(meas).ravel())
    if count <= 0 or cand.size == 0:
        return mask
    pick = rng.choice(cand, size=min(count, cand.size), replace=False)
    lo, hi = float(st.gross_errors['min_sigma']), float(st.gross_errors['max_sigma'])
    factor = np.exp(rng.uniform(np.log(lo), np.log(hi), pick.size))
    sign = np.where(rng.random(pick.size) < 0.5, -1.0, 1.0)
    flat, sflat = meas.reshape(-1), sig.reshape(-1)
    flat[pick] += sign * factor * sflat[pick]
    mask.reshape(-1)[pick] = True
    for j, f in enumerate(st.fields):
        if f == 'azimuth':
            meas[:, j] = wrap_azimuth(meas[:, j])
    return mask


def simulate_telemetry(world: World, tel: TelemetryConfig) -> dict[int, TargetStates]:
    """On-board telemetry or airborne GPS, with the errors of ``tel.error_model``
    (default ``drift``: slowly drifting errors, below; the others in
    :mod:`~orbit_tracking.core.sim.telemetry`)."""
    sc = world.scenario
    out: dict[int, TargetStates] = {}
    grid = epoch_grid(tel.first_epoch, tel.rate_hz, sc.t_start, sc.t_end)
    grid = grid[~_in_windows(grid, tel.outages)]
    for tid in tel.targets:
        rng = station_rng(sc, f'telemetry_{tid}')
        if tel.error_model != 'drift':
            got = simulate_model(
                tel, grid, sc.t_start, sc.t_end, partial(world.target_state, tid), rng
            )
            ones = np.ones((grid.size, 3))
            out[tid] = TargetStates(
                tid,
                grid,
                got.position,
                got.velocity,
                got.position_sigma * ones,
                got.velocity_sigma * ones,
            )
            continue
        x = world.target_state(tid, grid)
        tau = grid - sc.t_start
        span = max(sc.t_end - sc.t_start, 1.0)
        # drift: e(t) = a + b tau + c tau^2 (+ a slow sinusoid), e'(t) its exact derivative,
        # so the error is smooth and the dynamic features of the truth are kept
        a = rng.standard_normal(3) * tel.position_drift_m
        b = rng.standard_normal(3) * tel.velocity_drift_m_s
        c = rng.standard_normal(3) * tel.velocity_drift_m_s / span
        amp = rng.standard_normal(3) * 0.2 * tel.position_drift_m
        period = span * (1.0 + rng.random(3))
        ph = 2.0 * np.pi * rng.random(3)
        arg = 2.0 * np.pi * tau[:, None] / period + ph
        e_pos = a + b * tau[:, None] + c * tau[:, None] ** 2 + amp * np.sin(arg)
        e_vel = b + 2.0 * c * tau[:, None] + amp * 2.0 * np.pi / period * np.cos(arg)
        pos = x[:, :3] + e_pos + rng.standard_normal((grid.size, 3)) * tel.position_sigma_m
        vel = x[:, 3:] + e_vel + rng.standard_normal((grid.size, 3)) * tel.velocity_sigma_m_s
        # the reported sigma is honest: white noise plus the drift's size
        ps = np.hypot(tel.position_sigma_m, tel.position_drift_m)
        vs = np.hypot(tel.velocity_sigma_m_s, tel.velocity_drift_m_s)
        out[tid] = TargetStates(
            tid, grid, pos, vel, np.full((grid.size, 3), ps), np.full((grid.size, 3), vs)
        )
    return out


def simulate_truth(world: World) -> dict[int, TargetStates]:
    sc = world.scenario
    grid = epoch_grid(sc.t_start, sc.truth_rate_hz, sc.t_start, sc.t_end)
    out = {}
    for tid in sc.target_ids:
        x = world.target_state(tid, grid)
        zeros = np.zeros((grid.size, 3))
        out[tid] = TargetStates(tid, grid, x[:, :3], x[:, 3:], zeros, zeros)
    return out


def simulate(scenario: Scenario, world: World | None = None) -> SimulationResult:
    """Run a scenario: every station's measurements and states, telemetry and truth.

    ``world`` reuses truth already integrated (e.g. Monte-Carlo runs over seeds); it must
    come from a scenario with the same span, targets and platforms. Seed, stations and
    telemetry are always those of ``scenario``.
    """
    if world is None:
        world = World(scenario)
    elif world.scenario is not scenario:
        built = world.scenario
        truth_keys = ('t_start', 't_end', 'gm', 'launch', 'targets', 'platforms')
        if any(getattr(built, k) != getattr(scenario, k) for k in truth_keys):
            raise ValueError(
                f'world was built for scenario {built.name!r}, whose truth '
                f'({", ".join(truth_keys)}) differs from {scenario.name!r}'
            )
        # the simulation functions read seed and span from world.scenario
        world = copy.copy(world)
        world.scenario = scenario
    meas: dict[str, MeasurementTable] = {}
    states: dict[str, StationStates] = {}
    gross: dict[str, NDArray[np.bool_]] = {}
    for st in scenario.stations:
        meas[st.id], states[st.id], gross[st.id] = simulate_station_with_gross_errors(world, st)
    tel = simulate_telemetry(world, scenario.telemetry) if scenario.telemetry else {}
    return SimulationResult(scenario, meas, states, simulate_truth(world), tel, gross)
