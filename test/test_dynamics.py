"""Unit tests of orbit_tracking.core.models.dynamics: closed-form orbits and rocket equation,
conservation laws, finite-difference derivatives and the seed 000/003/004 truth models."""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np
import pytest
from scipy.optimize import brentq

from orbit_tracking.core import frames
from orbit_tracking.core.models import dynamics
from orbit_tracking.core.sim.scenario import build_targets, load_scenario

GM_SEED003 = 3.986005e14
SAT09_R0 = np.array([2043922.166765, 8186504.631471, 4343461.714791])
SAT09_V0 = np.array([-5379.544693, -407.095342, 3516.052656])
SAT06_R0 = np.array([-1732113.220573, 9092044.771852, 1732113.220573])
SAT06_V0 = np.array([-4453.807606, -1566.513180, 4453.807606])


# --------------------------------------------------------------------------- references


def _kepler_reference(r0: np.ndarray, v0: np.ndarray, gm: float, t: np.ndarray) -> np.ndarray:
    """Two-body states at times t (from t = 0) by solving Kepler's equation (elliptic orbit)."""
    r0n = np.linalg.norm(r0)
    h = np.cross(r0, v0)
    e_vec = np.cross(v0, h) / gm - r0 / r0n
    e = np.linalg.norm(e_vec)
    a = 1.0 / (2.0 / r0n - v0 @ v0 / gm)
    p_hat = e_vec / e
    q_hat = np.cross(h / np.linalg.norm(h), p_hat)
    e0 = np.arctan2((r0 @ v0) / np.sqrt(gm * a), 1.0 - r0n / a)  # (e sin E, e cos E)
    mean0 = e0 - e * np.sin(e0)
    mean = mean0 + np.sqrt(gm / a**3) * np.asarray(t, dtype=float)
    ecc_anom = mean.copy()
    for _ in range(50):
        step = (ecc_anom - e * np.sin(ecc_anom) - mean) / (1.0 - e * np.cos(ecc_anom))
        ecc_anom -= step
        if np.max(np.abs(step)) < 1e-15:
            break
    c, s = np.cos(ecc_anom), np.sin(ecc_anom)
    b_fac = np.sqrt(1.0 - e * e)
    pos = a * ((c - e)[:, None] * p_hat + (b_fac * s)[:, None] * q_hat)
    r = a * (1.0 - e * c)
    vel = (np.sqrt(gm * a) / r)[:, None] * (-s[:, None] * p_hat + (b_fac * c)[:, None] * q_hat)
    return np.hstack([pos, vel])


def _two_body(r: np.ndarray, gm: float) -> np.ndarray:
    return -gm * r / np.linalg.norm(r, axis=-1, keepdims=True) ** 3


def _central_difference(
    f: Callable[[np.ndarray], np.ndarray], t: np.ndarray, h: float
) -> np.ndarray:
    return (f(t + h) - f(t - h)) / (2.0 * h)


# --------------------------------------------------------------------------- gravity


def test_j2_gravity_is_the_gradient_of_the_j2_geopotential() -> None:
    gm, j2, re = frames.WGS84_GM, frames.WGS84_J2, frames.WGS84_A

    def potential(r: np.ndarray) -> float:
        rn = np.linalg.norm(r)
        s = r[2] / rn
        return gm / rn * (1.0 - j2 * (re / rn) ** 2 * 0.5 * (3.0 * s * s - 1.0))

    rng = np.random.default_rng(3)
    for _ in range(10):
        r = rng.normal(size=3)
        r *= rng.uniform(6.4e6, 4.0e7) / np.linalg.norm(r)
        step = 1.0
        grad = np.array(
            [(potential(r + step * e) - potential(r - step * e)) / (2 * step) for e in np.eye(3)]
        )
        acc = dynamics.gravity(r, gm, j2)
        np.testing.assert_allclose(acc, grad, rtol=1e-6, atol=1e-9 * float(np.linalg.norm(acc)))
        # the J2 term is a small correction of the point mass
        np.testing.assert_allclose(acc, _two_body(r, gm), rtol=5e-3)


def test_gravity_without_j2_is_the_point_mass_field_on_a_batch() -> None:
    r = np.array([[7.0e6, 0.0, 0.0], [0.0, -8.0e6, 3.0e6]])
    np.testing.assert_allclose(
        dynamics.gravity(r, GM_SEED003), _two_body(r, GM_SEED003), rtol=1e-15
    )


# --------------------------------------------------------------------------- Kepler orbit


@pytest.fixture(scope='module')
def sat09_two_periods() -> dynamics.KeplerOrbit:
    return dynamics.KeplerOrbit(SAT09_R0, SAT09_V0, 0.0, 0.0, 18200.0, gm=GM_SEED003)


def test_satellite_09_at_50_s_is_at_the_seed_position(
    sat09_two_periods: dynamics.KeplerOrbit,
) -> None:
    pos = sat09_two_periods.state(50.0)[0, :3]
    assert np.linalg.norm(pos - [1.773806e6, 8.161384e6, 4.516700e6]) < 1.0


def test_satellite_09_period_from_successive_perigee_passages_is_9028_s(
    sat09_two_periods: dynamics.KeplerOrbit,
) -> None:
    def radial_velocity(t: float) -> float:
        x = sat09_two_periods.state(t)[0]
        return float(x[:3] @ x[3:])

    grid = np.arange(0.0, 18200.0, 20.0)
    rv = np.array([radial_velocity(t) for t in grid])
    # perigee: r.v changes sign from - to +
    ups = np.flatnonzero((rv[:-1] < 0.0) & (rv[1:] >= 0.0))
    assert len(ups) == 2
    perigees = [brentq(radial_velocity, grid[i], grid[i + 1], xtol=1e-9) for i in ups]
    period = perigees[1] - perigees[0]
    assert abs(period - 9028.0) <= 1.0
    # and it is the period of the orbit's energy: a = -GM / (2 E)
    energy = 0.5 * SAT09_V0 @ SAT09_V0 - GM_SEED003 / np.linalg.norm(SAT09_R0)
    a = -GM_SEED003 / (2.0 * energy)
    assert a == pytest.approx(9371004.0, abs=1.0)
    period_energy = 2.0 * np.pi * np.sqrt(a**3 / GM_SEED003)
    assert period == pytest.approx(period_energy, abs=1e-3)
    back = sat09_two_periods.state(period_energy)[0, :3]
    assert np.linalg.norm(back - SAT09_R0) < 1e-2


def test_two_body_energy_and_angular_momentum_are_conserved_over_a_period(
    sat09_two_periods: dynamics.KeplerOrbit,
) -> None:
    x = sat09_two_periods.state(np.linspace(0.0, 9030.0, 3001))
    energy = 0.5 * np.sum(x[:, 3:] ** 2, axis=1) - GM_SEED003 / np.linalg.norm(x[:, :3], axis=1)
    h = np.cross(x[:, :3], x[:, 3:])
    assert np.max(np.abs(energy / energy[0] - 1.0)) < 1e-9
    assert np.max(np.linalg.norm(h - h[0], axis=1)) / np.linalg.norm(h[0]) < 1e-9


@pytest.mark.parametrize(('r0', 'v0'), [(SAT09_R0, SAT09_V0), (SAT06_R0, SAT06_V0)])
def test_kepler_orbit_matches_the_solution_of_keplers_equation(
    r0: np.ndarray, v0: np.ndarray
) -> None:
    # forward and backward of the state epoch t0 = 1000 s
    t0 = 1000.0
    orbit = dynamics.KeplerOrbit(r0, v0, t0, 0.0, 10000.0, gm=GM_SEED003)
    t = np.linspace(0.0, 10000.0, 401)
    ref = _kepler_reference(r0, v0, GM_SEED003, t - t0)
    x = orbit.state(t)
    assert np.max(np.linalg.norm(x[:, :3] - ref[:, :3], axis=1)) < 1e-3
    assert np.max(np.linalg.norm(x[:, 3:] - ref[:, 3:], axis=1)) < 1e-6
    acc_ref = _two_body(ref[:, :3], GM_SEED003)
    np.testing.assert_allclose(orbit.acceleration(t), acc_ref, rtol=0.0, atol=1e-9 * 5.0)


def test_trajectory_outside_its_span_raises() -> None:
    orbit = dynamics.KeplerOrbit(SAT09_R0, SAT09_V0, 0.0, 0.0, 100.0, gm=GM_SEED003)
    with pytest.raises(ValueError, match='outside the trajectory span'):
        orbit.state([50.0, 101.0])


# --------------------------------------------------------------------------- boosting vehicle


def _boost(**overrides: float) -> dynamics.BoostVehicle:
    """Seed 003's vehicle 0 (SCENARIOS.md): observed 50-170 s."""
    kw = dict(t0=50.0, t_start=50.0, t_end=170.0, exhaust_speed=3700.0, tau0=200.0)
    kw.update(overrides)
    return dynamics.BoostVehicle(
        [-1.112e6, 6.200e6, 1.133e6], [-697.0, 817.0, 940.0], gm=GM_SEED003, **kw
    )


@pytest.fixture(scope='module')
def boost() -> dynamics.BoostVehicle:
    return _boost()


def test_boost_acceleration_is_gravity_plus_rocket_thrust_along_velocity(
    boost: dynamics.BoostVehicle,
) -> None:
    t = np.linspace(50.0, 170.0, 241)
    x = boost.state(t)
    thrust = boost.acceleration(t) - _two_body(x[:, :3], GM_SEED003)
    expected = 3700.0 / (200.0 - t)
    np.testing.assert_allclose(np.linalg.norm(thrust, axis=1), expected, rtol=1e-12)
    np.testing.assert_allclose(boost.thrust_acceleration(t), expected, rtol=1e-15)
    unit_v = x[:, 3:] / np.linalg.norm(x[:, 3:], axis=1, keepdims=True)
    np.testing.assert_allclose(thrust / expected[:, None], unit_v, atol=1e-12)
    # SCENARIOS.md: the thrust acceleration grows from about 25 to about 120 m/s^2
    assert 24.0 < expected[0] < 26.0 and 115.0 < expected[-1] < 125.0


def test_boost_trajectory_solves_its_equations_of_motion(boost: dynamics.BoostVehicle) -> None:
    t = np.linspace(50.01, 169.99, 200)
    h = 1e-3
    vel_fd = _central_difference(lambda s: boost.state(s)[:, :3], t, h)
    acc_fd = _central_difference(lambda s: boost.state(s)[:, 3:], t, h)
    np.testing.assert_allclose(vel_fd, boost.state(t)[:, 3:], rtol=0.0, atol=1e-5)
    np.testing.assert_allclose(acc_fd, boost.acceleration(t), rtol=0.0, atol=1e-4)


def test_boost_without_gravity_follows_the_rocket_equation() -> None:
    v0 = np.array([300.0, -400.0, 1200.0])
    speed0 = np.linalg.norm(v0)
    ve, tau0, t0 = 3000.0, 150.0, 10.0
    vehicle = dynamics.BoostVehicle([7.0e6, 0.0, 0.0], v0, t0, 0.0, 140.0, ve, tau0, gm=0.0)
    t = np.linspace(0.0, 140.0, 57)
    x = vehicle.state(t)
    u0, u1 = tau0 - t0, tau0 - t
    speed = speed0 + ve * np.log(u0 / u1)
    distance = speed0 * (t - t0) + ve * (
        (t - t0) * np.log(u0) - (u0 * np.log(u0) - u0) + (u1 * np.log(u1) - u1)
    )
    np.testing.assert_allclose(np.linalg.norm(x[:, 3:], axis=1), speed, rtol=1e-10)
    expected_pos = np.array([7.0e6, 0.0, 0.0]) + distance[:, None] * v0 / speed0
    np.testing.assert_allclose(x[:, :3], expected_pos, rtol=0.0, atol=1e-4)


def test_boost_whose_mass_runs_out_inside_the_span_is_rejected() -> None:
    with pytest.raises(ValueError, match='tau0'):
        _boost(tau0=170.0)


def test_a_second_stage_switches_the_thrust_and_continues_the_flight(
    boost: dynamics.BoostVehicle,
) -> None:
    """The staging at 110 s: same flight before it, the second stage's thrust after it,
    and the state continuous through it (integrated across, not restarted from zero)."""
    staged = _boost(tau0=150.0, second_stage=(110.0, 2500.0, 260.0))  # type: ignore[arg-type]
    first = _boost(tau0=150.0, t_end=110.0)
    t = np.array([60.0, 109.9, 110.0, 150.0, 170.0])
    np.testing.assert_allclose(staged.state(t[:2]), first.state(t[:2]), rtol=0.0, atol=1e-6)
    expected = [3700 / 90.0, 3700 / 40.1, 2500 / 150.0, 2500 / 110.0, 2500 / 90.0]
    np.testing.assert_allclose(staged.thrust_acceleration(t), expected, rtol=1e-12)
    x = staged.state(np.array([110.0 - 1e-6, 110.0 + 1e-6]))
    np.testing.assert_allclose(x[0], x[1], rtol=0.0, atol=1e-2)
    thrust = staged.acceleration([120.0]) - _two_body(staged.state([120.0])[:, :3], GM_SEED003)
    assert np.linalg.norm(thrust) == pytest.approx(2500.0 / 140.0, rel=1e-9)
    with pytest.raises(ValueError, match='second stage'):
        _boost(tau0=150.0, second_stage=(110.0, 2500.0, 160.0))  # type: ignore[arg-type]


# --------------------------------------------------------------------------- powered ascent


Ascent = tuple[dynamics.PoweredAscent, Mapping[str, float]]


@pytest.fixture(scope='module')
def seed000_ascent() -> Ascent:
    sc = load_scenario('seed000_s1')
    ascent = build_targets(sc)[0]
    assert isinstance(ascent, dynamics.PoweredAscent)
    assert sc.launch is not None
    return ascent, sc.launch


def test_powered_ascent_starts_at_the_launch_point_at_rest(seed000_ascent: Ascent) -> None:
    ascent, launch = seed000_ascent
    pad = frames.geodetic_to_ecef(
        np.radians(launch['latitude_deg']), np.radians(launch['longitude_deg']), launch['height_m']
    )
    x = ascent.state(ascent.liftoff_time)[0]
    np.testing.assert_array_equal(x[:3], pad)
    np.testing.assert_array_equal(x[3:], 0.0)
    np.testing.assert_array_equal(ascent.to_launch_frame(x), np.zeros((1, 6)))


def test_powered_ascent_rises_vertically_first_then_flies_down_the_launch_azimuth(
    seed000_ascent: Ascent,
) -> None:
    ascent, _ = seed000_ascent
    # pitch program: vertical for the first 8 s, then tilting in the launch (x, y) plane
    early = ascent.to_launch_frame(ascent.state(ascent.liftoff_time + 6.0))[0]
    assert early[4] > 20.0
    assert np.hypot(early[3], early[5]) < 1e-3 * early[4]
    late = ascent.to_launch_frame(ascent.state(94.0))[0]
    assert late[0] > 10.0 * abs(late[2]) and late[3] > 10.0 * abs(late[5])


def test_powered_ascent_acceleration_jumps_at_separation_and_ignition_only(
    seed000_ascent: Ascent,
) -> None:
    ascent, _ = seed000_ascent
    stage1, stage2 = ascent.stages
    separation = ascent.liftoff_time + stage1.burn_time_s
    ignition = separation + stage2.coast_before_s
    assert separation == pytest.approx(33.4, abs=1e-9)
    assert ascent.separation_times[0] == pytest.approx(separation, abs=1e-9)

    t = np.linspace(0.0, 94.0, 1881)  # 0.05 s steps over the estimation span
    jumps = np.linalg.norm(np.diff(ascent.acceleration(t), axis=0), axis=1)
    big = np.flatnonzero(jumps > 1.0)
    assert len(big) == 2
    for k, t_jump in zip(big, (separation, ignition), strict=True):
        assert t[k] <= t_jump <= t[k + 1]
    assert np.max(np.delete(jumps, big)) < 0.1

    # the thrust acceleration F / m stops at burnout (drag per unit mass also changes a
    # little as the spent stage drops away) and starts again at ignition (same mass)
    eps = 1e-7
    drop = ascent.acceleration([separation - eps])[0] - ascent.acceleration([separation + eps])[0]
    rise = ascent.acceleration([ignition + eps])[0] - ascent.acceleration([ignition - eps])[0]
    burnout_mass = stage1.mass_kg - stage1.propellant_kg
    assert np.linalg.norm(drop) == pytest.approx(stage1.thrust_n / burnout_mass, rel=0.02)
    assert np.linalg.norm(rise) == pytest.approx(stage2.thrust_n / stage2.mass_kg, rel=1e-6)


def test_drag_free_ascent_loses_exactly_the_thrust_acceleration_at_burnout() -> None:
    lat, lon, az = np.radians(40.9), np.radians(100.3), np.radians(150.0)
    stages = [
        dynamics.Stage(120000.0, 65380.0, 700.0, 2600.0),
        dynamics.Stage(44000.0, 30000.0, 180.0, 3100.0, coast_before_s=1.5),
    ]
    program = np.array([[0.0, 90.0], [8.0, 90.0], [60.0, 52.0], [160.0, 28.0]])
    program[:, 1] = np.radians(program[:, 1])
    ascent = dynamics.PoweredAscent(lat, lon, 1000.0, az, -60.0, 40.0, stages, program)
    separation = -60.0 + 65380.0 / 700.0
    eps = 1e-7
    drop = ascent.acceleration([separation - eps])[0] - ascent.acceleration([separation + eps])[0]
    # pitch at burnout (93.4 s after lift-off) interpolated by hand: 52 - 24 * 33.4 / 100 deg
    phi = np.radians(52.0 - 24.0 * 33.4 / 100.0)
    direction = frames.launch_rotation(lat, lon, az) @ [np.cos(phi), np.sin(phi), 0.0]
    expected = 700.0 * 2600.0 / (120000.0 - 65380.0) * direction
    np.testing.assert_allclose(drop, expected, rtol=0.0, atol=1e-6)


def test_powered_ascent_velocity_and_acceleration_are_time_derivatives(
    seed000_ascent: Ascent,
) -> None:
    ascent, _ = seed000_ascent
    h = 1e-3
    t = np.linspace(ascent.liftoff_time + 0.5, 93.9, 400)
    # central differences must not straddle the acceleration jumps (separation, ignition)
    near_break = np.min(np.abs(t[:, None] - np.array([33.4, 34.9])[None, :]), axis=1) < 2 * h
    t = t[~near_break]
    vel_fd = _central_difference(lambda s: ascent.state(s)[:, :3], t, h)
    acc_fd = _central_difference(lambda s: ascent.state(s)[:, 3:], t, h)
    np.testing.assert_allclose(vel_fd, ascent.state(t)[:, 3:], rtol=0.0, atol=1e-5)
    np.testing.assert_allclose(acc_fd, ascent.acceleration(t), rtol=0.0, atol=1e-4)


def test_powered_ascent_rejects_a_malformed_pitch_program() -> None:
    stage = dynamics.Stage(1000.0, 500.0, 10.0, 2500.0)
    with pytest.raises(ValueError, match='increase strictly'):
        dynamics.PoweredAscent(0.7, 1.7, 0.0, 0.0, 0.0, 10.0, [stage], [[0, 1.5], [0, 1.4]])
    with pytest.raises(ValueError, match=r'shape \(k, 2\)'):
        dynamics.PoweredAscent(0.7, 1.7, 0.0, 0.0, 0.0, 10.0, [stage], [0.0, 1.5])


# --------------------------------------------------------------------------- geodetic tracks

LOAD_FACTOR = 2.5
TURN_ACCEL = dynamics.G0 * np.sqrt(LOAD_FACTOR**2 - 1.0)


@pytest.fixture(scope='module')
def track() -> dynamics.GeodeticTrack:
    legs = [
        dynamics.TrackSegment(30.0),
        dynamics.TrackSegment(40.0, lateral_accel_m_s2=TURN_ACCEL),  # level right turn
        dynamics.TrackSegment(20.0, speed_rate_m_s2=2.0, path_angle_rate_rad_s=np.radians(1.0)),
        dynamics.TrackSegment(
            30.0, lateral_accel_m_s2=-TURN_ACCEL, path_angle_rate_rad_s=-np.radians(0.5)
        ),
    ]
    return dynamics.GeodeticTrack(
        np.radians(20.35), np.radians(113.4), 5000.0, 230.0, np.radians(75.0), 10.0, legs
    )


def test_geodetic_track_ecef_velocity_is_the_derivative_of_ecef_position(
    track: dynamics.GeodeticTrack,
) -> None:
    t = np.linspace(10.01, 129.99, 500)
    vel_fd = _central_difference(lambda s: track.state(s)[:, :3], t, 1e-3)
    np.testing.assert_allclose(vel_fd, track.state(t)[:, 3:], rtol=0.0, atol=1e-5)


def test_geodetic_track_keeps_its_speed_on_a_level_turn(track: dynamics.GeodeticTrack) -> None:
    t = np.linspace(10.0, 78.9, 301)  # straight leg, roll-in, turn (the climb ramps in at 79 s)
    x = track.state(t)
    np.testing.assert_allclose(np.linalg.norm(x[:, 3:], axis=1), 230.0, rtol=1e-12)
    lat, lon, h = frames.ecef_to_geodetic(x[:, :3])
    np.testing.assert_allclose(h, 5000.0, atol=1e-6)


def test_geodetic_track_turn_has_horizontal_acceleration_of_its_load_factor(
    track: dynamics.GeodeticTrack,
) -> None:
    t = np.linspace(42.0, 68.0, 27)  # steady part of the turn (roll-in ends at 41 s)
    x = track.state(t)
    lat, lon, _ = frames.ecef_to_geodetic(x[:, :3])
    enu = frames.enu_rotation(lat, lon)
    acc = np.einsum('mji,mj->mi', enu, track.acceleration(t))
    vel = np.einsum('mji,mj->mi', enu, x[:, 3:])
    horizontal = np.linalg.norm(acc[:, :2], axis=1)
    np.testing.assert_allclose(horizontal, TURN_ACCEL, rtol=1e-3)
    # positive lateral acceleration turns right (clockwise seen from above)
    assert np.all(vel[:, 0] * acc[:, 1] - vel[:, 1] * acc[:, 0] < 0.0)
    # and the course turns at a / V
    course = track.course(t)
    np.testing.assert_allclose(np.diff(course) / np.diff(t), TURN_ACCEL / 230.0, rtol=1e-9)


def test_scenario_turn_of_load_factor_n_accelerates_at_g0_sqrt_n2_minus_1() -> None:
    sc = load_scenario('seed004_sea')
    aircraft = build_targets(sc)[0]
    # legs: 290 s straight, then a right turn of 2.5 g for 32.2 s
    t = np.linspace(295.0, 317.0, 12)
    x = aircraft.state(t)
    lat, lon, _ = frames.ecef_to_geodetic(x[:, :3])
    acc = np.einsum('mji,mj->mi', frames.enu_rotation(lat, lon), aircraft.acceleration(t))
    np.testing.assert_allclose(
        np.linalg.norm(acc[:, :2], axis=1), 9.80665 * np.sqrt(2.5**2 - 1.0), rtol=1e-3
    )
    np.testing.assert_allclose(np.linalg.norm(x[:, 3:], axis=1), 230.0, rtol=1e-12)


def test_geodetic_track_rejects_a_non_positive_speed_or_no_legs() -> None:
    with pytest.raises(ValueError, match='speed must be positive'):
        dynamics.GeodeticTrack(0.3, 2.0, 0.0, 0.0, 0.0, 0.0, [dynamics.TrackSegment(10.0)])
    with pytest.raises(ValueError, match='at least one segment'):
        dynamics.GeodeticTrack(0.3, 2.0, 0.0, 8.0, 0.0, 0.0, [])
