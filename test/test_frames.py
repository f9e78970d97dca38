"""Unit tests of orbit_tracking.core.frames against closed forms, a published value and
finite differences."""

from __future__ import annotations

import numpy as np
import pytest

from orbit_tracking.core import frames

DEG = np.pi / 180.0
EPS = np.finfo(np.float64).eps


def _dms(d: float, m: float, s: float) -> float:
    return (d + m / 60.0 + s / 3600.0) * DEG


def _assert_rotation(r: np.ndarray, tol: float = 1e-14) -> None:
    """Orthonormal with determinant +1 (batch aware)."""
    eye = np.broadcast_to(np.eye(3), r.shape)
    np.testing.assert_allclose(np.swapaxes(r, -1, -2) @ r, eye, rtol=0.0, atol=tol)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, rtol=0.0, atol=tol)


# --------------------------------------------------------------------------- geodetic/ECEF


def test_geodetic_ecef_round_trip_reproduces_position_over_latitudes_and_heights() -> None:
    lat_deg = np.concatenate(
        [np.linspace(-90.0, 90.0, 37), [-89.999, 89.999, -89.9999999, 89.9999999, 1e-7, -1e-7]]
    )
    lon_deg = np.linspace(-180.0, 180.0, 13)
    heights = np.array([-500.0, 0.0, 1.0, 1.0e3, 1.0e5, 1.0e6, 3.6e7, 4.0e7])
    lat, lon, h = np.meshgrid(lat_deg * DEG, lon_deg * DEG, heights, indexing='ij')
    xyz = frames.geodetic_to_ecef(lat, lon, h)
    back = frames.geodetic_to_ecef(*frames.ecef_to_geodetic(xyz))
    err = np.linalg.norm(back - xyz, axis=-1)
    # 1e-9 m plus the spacing of doubles at |r| (9.3e-10 m at the Earth's surface, 7.5e-9 m
    # at 4.6e7 m): no double-precision round trip can beat its own representation error.
    tol = 1e-9 + 2.0 * EPS * np.linalg.norm(xyz, axis=-1)
    assert np.all(err <= tol), f'worst round-trip error {err.max():.3e} m'
    surface = np.abs(h) <= 1.0e3
    assert err[surface].max() < 3e-9


def test_ecef_to_geodetic_recovers_height_and_latitude_of_grid_points() -> None:
    lat = np.radians(np.array([-89.999, -60.0, -12.5, 0.0, 33.3, 45.0, 80.0, 89.999]))
    lon = np.radians(np.array([-170.0, -45.0, 0.0, 10.0, 100.3, 135.0, 179.0, 60.0]))
    h = np.array([-500.0, 0.0, 73.0, 1.0e4, 4.0e5, 2.0e6, 2.0e7, 4.0e7])
    lat2, lon2, h2 = frames.ecef_to_geodetic(frames.geodetic_to_ecef(lat, lon, h))
    m, n = frames.meridian_radii(lat)
    # errors converted to metres on the surface of constant height
    np.testing.assert_allclose((lat2 - lat) * (m + h), 0.0, atol=1e-8)
    np.testing.assert_allclose((lon2 - lon) * (n + h) * np.cos(lat), 0.0, atol=1e-8)
    np.testing.assert_allclose(h2, h, rtol=0.0, atol=1e-8)


def test_geodetic_to_ecef_matches_epsg_guidance_note_7_2_example() -> None:
    # EPSG Guidance Note 7-2, geographic/geocentric conversions example (WGS 84)
    lat = _dms(53.0, 48.0, 33.820)
    lon = _dms(2.0, 7.0, 46.380)
    xyz = frames.geodetic_to_ecef(lat, lon, 73.0)
    np.testing.assert_allclose(xyz, [3771793.968, 140253.342, 5124304.349], rtol=0.0, atol=1e-3)
    lat2, lon2, h2 = frames.ecef_to_geodetic([3771793.968, 140253.342, 5124304.349])
    np.testing.assert_allclose([lat2, lon2], [lat, lon], rtol=0.0, atol=1e-3 / frames.WGS84_A)
    assert abs(h2 - 73.0) < 1e-3


def test_geodetic_to_ecef_gives_semi_axes_on_equator_and_poles() -> None:
    xyz = frames.geodetic_to_ecef(
        [0.0, 0.0, np.pi / 2, -np.pi / 2], [0.0, np.pi / 2, 0.3, 2.0], 10.0
    )
    a, b = frames.WGS84_A + 10.0, frames.WGS84_B + 10.0
    expected = [[a, 0.0, 0.0], [0.0, a, 0.0], [0.0, 0.0, b], [0.0, 0.0, -b]]
    np.testing.assert_allclose(xyz, expected, rtol=0.0, atol=1e-8)


def test_ecef_to_geodetic_rejects_positions_without_three_components() -> None:
    with pytest.raises(ValueError, match=r'shape \(\.\.\., 3\)'):
        frames.ecef_to_geodetic(np.zeros((4, 2)))


# --------------------------------------------------------------------------- ENU


@pytest.mark.parametrize('lat_deg', [-89.999, -47.0, 0.0, 40.9, 89.999])
@pytest.mark.parametrize('lon_deg', [-150.0, 0.0, 100.3])
def test_enu_rotation_is_orthonormal_and_up_is_the_ellipsoid_normal(
    lat_deg: float, lon_deg: float
) -> None:
    lat, lon = lat_deg * DEG, lon_deg * DEG
    r = frames.enu_rotation(lat, lon)
    _assert_rotation(r)
    # outward normal of x^2/a^2 + y^2/a^2 + z^2/b^2 = 1 at the surface point
    x, y, z = frames.geodetic_to_ecef(lat, lon, 0.0)
    normal = np.array([x / frames.WGS84_A**2, y / frames.WGS84_A**2, z / frames.WGS84_B**2])
    np.testing.assert_allclose(r[:, 2], normal / np.linalg.norm(normal), rtol=0.0, atol=1e-12)


def test_enu_axes_are_the_directions_of_increasing_longitude_latitude_and_height() -> None:
    lat, lon, h, step = 40.9 * DEG, 100.3 * DEG, 1000.0, 1e-7
    r = frames.enu_rotation(lat, lon)

    def direction(dlat: float, dlon: float, dh: float) -> np.ndarray:
        hi = frames.geodetic_to_ecef(lat + dlat, lon + dlon, h + dh)
        lo = frames.geodetic_to_ecef(lat - dlat, lon - dlon, h - dh)
        return (hi - lo) / np.linalg.norm(hi - lo)

    np.testing.assert_allclose(r[:, 0], direction(0.0, step, 0.0), atol=1e-8)
    np.testing.assert_allclose(r[:, 1], direction(step, 0.0, 0.0), atol=1e-8)
    np.testing.assert_allclose(r[:, 2], direction(0.0, 0.0, 1.0), atol=1e-8)


def test_meridian_radii_match_finite_differences_of_ecef_position() -> None:
    lat, lon, step = 33.0 * DEG, 20.0 * DEG, 1e-6
    m, n = frames.meridian_radii(lat)
    d_lat = frames.geodetic_to_ecef(lat + step, lon, 0.0) - frames.geodetic_to_ecef(
        lat - step, lon, 0.0
    )
    d_lon = frames.geodetic_to_ecef(lat, lon + step, 0.0) - frames.geodetic_to_ecef(
        lat, lon - step, 0.0
    )
    assert np.linalg.norm(d_lat) / (2 * step) == pytest.approx(m, rel=1e-9)
    assert np.linalg.norm(d_lon) / (2 * step) == pytest.approx(n * np.cos(lat), rel=1e-9)


# --------------------------------------------------------------------------- launch frame


@pytest.mark.parametrize('azimuth_deg', [0.0, 37.0, 90.0, 150.0, 270.0])
def test_launch_frame_y_is_up_and_x_is_horizontal_at_the_launch_azimuth(
    azimuth_deg: float,
) -> None:
    lat, lon, az = 40.9 * DEG, 100.3 * DEG, azimuth_deg * DEG
    s = frames.launch_rotation(lat, lon, az)
    enu = frames.enu_rotation(lat, lon)
    east, north, up = enu.T
    _assert_rotation(s)
    np.testing.assert_allclose(s[:, 1], up, atol=1e-15)
    x = s[:, 0]
    assert abs(x @ up) < 1e-15
    measured_az = np.mod(np.arctan2(x @ east, x @ north), 2 * np.pi)
    assert measured_az == pytest.approx(az, abs=1e-14)
    np.testing.assert_allclose(s[:, 2], np.cross(s[:, 0], s[:, 1]), atol=1e-15)


def test_launch_frame_due_north_has_z_east_and_due_east_has_z_south() -> None:
    lat, lon = -12.0 * DEG, 40.0 * DEG
    east, north, _ = frames.enu_rotation(lat, lon).T
    north_launch = frames.launch_rotation(lat, lon, 0.0)
    np.testing.assert_allclose(north_launch[:, 0], north, atol=1e-15)
    np.testing.assert_allclose(north_launch[:, 2], east, atol=1e-15)
    east_launch = frames.launch_rotation(lat, lon, np.pi / 2)
    np.testing.assert_allclose(east_launch[:, 0], east, atol=1e-15)
    np.testing.assert_allclose(east_launch[:, 2], -north, atol=1e-15)


# --------------------------------------------------------------------------- observation frame


def test_observation_frame_axes_are_radial_east_and_north_as_in_the_contract() -> None:
    rng = np.random.default_rng(20240601)
    p = rng.normal(size=(50, 3)) * 9.0e6
    r = frames.observation_rotation(p)
    _assert_rotation(r)
    rho = np.hypot(p[:, 0], p[:, 1])
    x_exp = p / np.linalg.norm(p, axis=1, keepdims=True)
    y_exp = np.stack([-p[:, 1], p[:, 0], np.zeros(len(p))], axis=1) / rho[:, None]
    np.testing.assert_allclose(r[:, :, 0], x_exp, atol=1e-15)
    np.testing.assert_allclose(r[:, :, 1], y_exp, atol=1e-15)
    np.testing.assert_allclose(r[:, :, 2], np.cross(x_exp, y_exp), atol=1e-15)
    # z points north: its component along the spin axis is cos(declination) > 0
    np.testing.assert_allclose(r[:, 2, 2], rho / np.linalg.norm(p, axis=1), atol=1e-15)


def test_observation_frame_of_a_satellite_over_the_equator_at_zero_longitude() -> None:
    r = frames.observation_rotation([7.0e6, 0.0, 0.0])
    np.testing.assert_allclose(r, np.eye(3), atol=1e-15)


def test_observation_frame_on_the_polar_axis_raises() -> None:
    with pytest.raises(ValueError, match='polar axis'):
        frames.observation_rotation([0.0, 0.0, 7.0e6])


# --------------------------------------------------------------------------- quaternions


def test_quaternion_matrix_round_trip_on_random_rotations() -> None:
    rng = np.random.default_rng(7)
    q = rng.normal(size=(200, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    m = frames.quaternion_to_matrix(q)
    _assert_rotation(m, tol=1e-14)
    q2 = frames.matrix_to_quaternion(m)
    assert np.all(q2[:, 3] >= 0.0)
    np.testing.assert_allclose(q2, q * np.sign(q[:, 3:4]), atol=1e-14)
    np.testing.assert_allclose(frames.quaternion_to_matrix(q2), m, atol=1e-14)


def test_quaternion_of_quarter_turn_about_z_is_scalar_last() -> None:
    rot_z90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    s = np.sqrt(0.5)
    np.testing.assert_allclose(frames.matrix_to_quaternion(rot_z90), [0.0, 0.0, s, s], atol=1e-15)
    # a (m, 3, 3) batch keeps its leading shape
    batch = frames.matrix_to_quaternion(np.stack([np.eye(3), rot_z90]))
    np.testing.assert_allclose(batch, [[0, 0, 0, 1], [0, 0, s, s]], atol=1e-15)


@pytest.mark.parametrize('bad', [[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.1], [np.nan, 0, 0, 1]])
def test_quaternion_to_matrix_rejects_non_unit_quaternions(bad: list[float]) -> None:
    with pytest.raises(ValueError, match='unit quaternion'):
        frames.quaternion_to_matrix(bad)


# --------------------------------------------------------------------------- platform attitude

STARBOARD, BOW, DECK_UP = np.eye(3)


def test_level_ship_heading_north_has_identity_attitude() -> None:
    np.testing.assert_allclose(frames.platform_rotation(0.0, 0.0, 0.0), np.eye(3), atol=0.0)


def test_level_ship_heading_east_points_its_bow_east_and_starboard_south() -> None:
    r = frames.platform_rotation(np.pi / 2, 0.0, 0.0)
    np.testing.assert_allclose(r @ BOW, [1.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(r @ STARBOARD, [0.0, -1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(r @ DECK_UP, [0.0, 0.0, 1.0], atol=1e-15)


def test_positive_pitch_raises_the_bow_and_positive_roll_lowers_starboard() -> None:
    pitch = frames.platform_rotation(0.0, 0.1, 0.0)
    np.testing.assert_allclose(pitch @ BOW, [0.0, np.cos(0.1), np.sin(0.1)], atol=1e-15)
    np.testing.assert_allclose(pitch @ STARBOARD, STARBOARD, atol=1e-15)
    roll = frames.platform_rotation(0.0, 0.0, 0.1)
    np.testing.assert_allclose(roll @ STARBOARD, [np.cos(0.1), 0.0, -np.sin(0.1)], atol=1e-15)
    np.testing.assert_allclose(roll @ BOW, BOW, atol=1e-15)


def test_platform_rotation_applies_yaw_then_pitch_then_roll() -> None:
    rng = np.random.default_rng(11)
    yaw = rng.uniform(-np.pi, np.pi, 40)
    pitch = rng.uniform(-0.5, 0.5, 40)
    roll = rng.uniform(-0.5, 0.5, 40)
    r = frames.platform_rotation(yaw, pitch, roll)
    _assert_rotation(r)
    # roll turns about the bow, so the bow depends on heading and pitch only
    bow = np.stack([np.sin(yaw) * np.cos(pitch), np.cos(yaw) * np.cos(pitch), np.sin(pitch)], 1)
    np.testing.assert_allclose(r @ BOW, bow, atol=1e-15)
    # starboard starts horizontal at the heading (pitch turns about it) and is then turned
    # about the bow by the roll: cos(roll) h + sin(roll) (bow x h)
    h = np.stack([np.cos(yaw), -np.sin(yaw), np.zeros(40)], axis=1)
    starboard = np.cos(roll)[:, None] * h + np.sin(roll)[:, None] * np.cross(bow, h)
    np.testing.assert_allclose(r @ STARBOARD, starboard, atol=1e-14)
