"""Unit tests of orbit_tracking.core.models.measurements: conventions on hand-made geometry and
analytic Jacobians against central finite differences."""

from __future__ import annotations

import numpy as np
import pytest

from orbit_tracking.core import frames
from orbit_tracking.core.errors import MeasurementError
from orbit_tracking.core.models.measurements import (
    FIELDS,
    StationPose,
    los_unit_vectors,
    predict,
    residual,
    wrap_azimuth,
)

TWO_PI = 2.0 * np.pi
LAT, LON, HEIGHT = np.radians(40.9), np.radians(100.3), 1000.0
SITE = frames.geodetic_to_ecef(LAT, LON, HEIGHT)
ENU = frames.enu_rotation(LAT, LON)
EAST, NORTH, UP = ENU.T


def _angle_diff(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    return np.arctan2(np.sin(a - b), np.cos(a - b))


def _predict_one(
    fields: list[str],
    target_pos: np.ndarray,
    target_vel: np.ndarray | tuple[float, ...] = (0.0, 0.0, 0.0),
) -> np.ndarray:
    x = np.concatenate([target_pos, target_vel])[None, :]
    values, _ = predict(fields, x, StationPose.fixed(SITE, ENU, 1))
    return values[0]


# --------------------------------------------------------------------------- geometries


def _random_targets(
    rng: np.random.Generator, pose: StationPose, dist: tuple[float, float]
) -> np.ndarray:
    """Target states around the station, away from the singular directions of every field
    (local x axis, vertical) so that all six models are smooth there."""
    m = len(pose)
    local = rng.normal(size=(m, 3))
    local /= np.linalg.norm(local, axis=1, keepdims=True)
    local[:, 0] = np.sign(local[:, 0]) * np.maximum(np.abs(local[:, 0]), 0.3)
    local[:, 2] = np.clip(local[:, 2], -0.7, 0.7)
    local /= np.linalg.norm(local, axis=1, keepdims=True)
    local *= rng.uniform(*dist, size=(m, 1))
    pos = pose.position + np.einsum('mij,mj->mi', pose.rotation, local)
    vel = rng.normal(size=(m, 3)) * 800.0
    return np.hstack([pos, vel])


def _ground_station(rng: np.random.Generator, m: int) -> tuple[StationPose, tuple[float, float]]:
    return StationPose.fixed(SITE, ENU, m), (1.0e4, 1.5e5)


def _ship(rng: np.random.Generator, m: int) -> tuple[StationPose, tuple[float, float]]:
    lat = np.radians(20.5) + rng.normal(size=m) * 1e-3
    lon = np.radians(114.0) + rng.normal(size=m) * 1e-3
    pos = frames.geodetic_to_ecef(lat, lon, rng.normal(size=m) * 2.0 + 18.0)
    attitude = frames.platform_rotation(
        rng.uniform(0.0, TWO_PI, m), rng.uniform(-0.1, 0.1, m), rng.uniform(-0.2, 0.2, m)
    )
    rot = np.einsum('mij,mjk->mik', frames.enu_rotation(lat, lon), attitude)
    vel = rng.normal(size=(m, 3)) * 8.0
    return StationPose(pos, vel, rot), (1.0e3, 1.2e5)


def _satellite(rng: np.random.Generator, m: int) -> tuple[StationPose, tuple[float, float]]:
    pos = rng.normal(size=(m, 3))
    pos *= 9.371e6 / np.linalg.norm(pos, axis=1, keepdims=True)
    vel = np.cross(pos, rng.normal(size=(m, 3)))
    vel *= 6500.0 / np.linalg.norm(vel, axis=1, keepdims=True)
    return StationPose(pos, vel, frames.observation_rotation(pos)), (5.0e5, 5.0e6)


GEOMETRIES = {'ground_station': _ground_station, 'ship': _ship, 'satellite': _satellite}


@pytest.mark.parametrize('geometry', sorted(GEOMETRIES))
def test_every_field_jacobian_matches_central_finite_differences(geometry: str) -> None:
    rng = np.random.default_rng(sorted(GEOMETRIES).index(geometry) + 101)
    pose, dist = GEOMETRIES[geometry](rng, 64)
    x = _random_targets(rng, pose, dist)
    fields = list(FIELDS)
    values, jac = predict(fields, x, pose, jacobian=True)
    assert jac is not None and jac.shape == (64, len(fields), 6)
    np.testing.assert_array_equal(predict(fields, x, pose)[0], values)

    rng_m = np.linalg.norm(x[:, :3] - pose.position, axis=1)
    fd = np.empty_like(jac)
    for k in range(6):
        h = 1e-6 * rng_m if k < 3 else np.full(len(x), 1e-3)
        plus, minus = x.copy(), x.copy()
        plus[:, k] += h
        minus[:, k] -= h
        diff = residual(fields, predict(fields, plus, pose)[0], predict(fields, minus, pose)[0])
        fd[:, :, k] = diff / (2.0 * h[:, None])
    for block in (slice(0, 3), slice(3, 6)):
        err = np.linalg.norm(jac[:, :, block] - fd[:, :, block], axis=-1)
        scale = np.linalg.norm(jac[:, :, block], axis=-1)
        worst = np.max(err / np.maximum(scale, 1e-300), axis=0)
        assert np.all(err <= 1e-6 * scale + 1e-18), dict(zip(fields, worst, strict=True))
    # only range rate depends on the target velocity
    moving = [f == 'range_rate' for f in fields]
    assert np.all(np.abs(jac[:, ~np.array(moving), 3:]) == 0.0)


# --------------------------------------------------------------------------- conventions


@pytest.mark.parametrize(
    ('direction', 'azimuth'),
    [(EAST, np.pi / 2), (NORTH, 0.0), (-NORTH, np.pi), (-EAST, 3 * np.pi / 2)],
    ids=['east', 'north', 'south', 'west'],
)
@pytest.mark.parametrize('distance', [1.0e3, 1.0e4, 1.0e5, 12345.678])
def test_azimuth_of_target_on_the_horizon_is_measured_from_north_toward_east(
    direction: np.ndarray, azimuth: float, distance: float
) -> None:
    az, el, rng = _predict_one(['azimuth', 'elevation', 'range'], SITE + distance * direction)
    assert 0.0 <= az < TWO_PI
    assert abs(_angle_diff(az, azimuth)) < 1e-12
    assert abs(el) < 1e-12
    assert rng == pytest.approx(distance, rel=1e-12)


def test_azimuth_of_target_due_east_on_horizon_is_half_pi() -> None:
    az, el = _predict_one(['azimuth', 'elevation'], SITE + 2.0e4 * EAST)
    assert az == pytest.approx(np.pi / 2, abs=1e-12)
    assert el == pytest.approx(0.0, abs=1e-12)


def test_azimuth_of_target_due_north_is_zero_not_two_pi() -> None:
    # 1e5 m due north made arctan2 return -1.6e-16, which np.mod rounded to 2 pi itself
    targets = SITE + np.array([1.0e3, 1.0e4, 3.0e4, 1.0e5, 12345.678])[:, None] * NORTH
    x = np.hstack([targets, np.zeros((5, 3))])
    az = predict(['azimuth'], x, StationPose.fixed(SITE, ENU, 5))[0][:, 0]
    assert np.all((az >= 0.0) & (az < TWO_PI))
    assert np.all(np.abs(_angle_diff(az, 0.0)) < 1e-12)


def test_elevation_of_target_straight_up_is_half_pi() -> None:
    (el,) = _predict_one(['elevation'], SITE + 5.0e3 * UP)
    assert el == pytest.approx(np.pi / 2, abs=1e-12)
    (el,) = _predict_one(['elevation'], SITE - 5.0e3 * UP)
    assert el == pytest.approx(-np.pi / 2, abs=1e-12)


def test_target_north_east_at_45_degrees_elevation() -> None:
    d = 1.0e4 * (EAST + NORTH + np.sqrt(2.0) * UP) / 2.0
    az, el, rng = _predict_one(['azimuth', 'elevation', 'range'], SITE + d)
    assert az == pytest.approx(np.pi / 4, abs=1e-12)
    assert el == pytest.approx(np.pi / 4, abs=1e-12)
    assert rng == pytest.approx(1.0e4, rel=1e-12)


def test_range_rate_is_the_velocity_along_the_line_of_sight_relative_to_the_station() -> None:
    los = (EAST + 2.0 * UP) / np.sqrt(5.0)
    target = SITE + 3.0e4 * los
    (away,) = _predict_one(['range_rate'], target, 120.0 * los)
    (across,) = _predict_one(['range_rate'], target, 120.0 * NORTH)
    assert away == pytest.approx(120.0, rel=1e-12)
    assert across == pytest.approx(0.0, abs=1e-9)
    # a station moving with the target sees no range rate
    pose = StationPose(SITE[None, :], 120.0 * los[None, :], ENU[None, :, :])
    rr, _ = predict(['range_rate'], np.r_[target, 120.0 * los][None, :], pose)
    assert rr[0, 0] == pytest.approx(0.0, abs=1e-9)


def test_los_alpha_and_beta_are_ratios_in_the_satellite_observation_frame() -> None:
    sat = np.array([2043922.166765, 8186504.631471, 4343461.714791])
    rot = frames.observation_rotation(sat)
    xs, ys, zs = -2.5e6, 4.0e5, -1.5e5
    target = sat + rot @ [xs, ys, zs]
    pose = StationPose(sat[None, :], np.zeros((1, 3)), rot[None, :, :])
    values, _ = predict(['los_alpha', 'los_beta'], np.r_[target, 0, 0, 0][None, :], pose)
    alpha, beta = values[0]
    assert alpha == pytest.approx(ys / xs, rel=1e-12)
    assert beta == pytest.approx(zs / xs, rel=1e-12)


def test_ship_deck_frame_azimuth_is_measured_from_the_bow_toward_starboard() -> None:
    # a level ship heading east: a target due south is 90 deg to starboard
    rot = ENU @ frames.platform_rotation(np.pi / 2, 0.0, 0.0)
    pose = StationPose(SITE[None, :], np.zeros((1, 3)), rot[None, :, :])
    x = np.r_[SITE - 1.0e4 * NORTH, 0, 0, 0][None, :]
    az, el = predict(['azimuth', 'elevation'], x, pose)[0][0]
    assert az == pytest.approx(np.pi / 2, abs=1e-12)
    assert el == pytest.approx(0.0, abs=1e-12)
    # rolled 0.1 rad starboard-down, the same target appears 0.1 rad below the deck plane
    rot = ENU @ frames.platform_rotation(np.pi / 2, 0.0, 0.1)
    pose = StationPose(SITE[None, :], np.zeros((1, 3)), rot[None, :, :])
    az, el = predict(['azimuth', 'elevation'], x, pose)[0][0]
    assert az == pytest.approx(np.pi / 2, abs=1e-12)
    assert el == pytest.approx(0.1, abs=1e-12)


# --------------------------------------------------------------------------- residual


def test_residual_wraps_azimuth_differences_across_zero() -> None:
    fields = ['range', 'azimuth', 'elevation']
    measured = np.array([[100.0, 0.01, 0.3], [100.0, TWO_PI - 0.01, 0.3]])
    predicted = np.array([[90.0, TWO_PI - 0.01, 0.1], [90.0, 0.01, 0.1]])
    np.testing.assert_allclose(
        residual(fields, measured, predicted), [[10.0, 0.02, 0.2], [10.0, -0.02, 0.2]], atol=1e-12
    )


def test_residual_of_random_azimuths_is_the_shortest_signed_angle() -> None:
    rng = np.random.default_rng(5)
    a, b = rng.uniform(0.0, TWO_PI, (2, 1000))
    r = residual(['azimuth'], a[:, None], b[:, None])[:, 0]
    assert np.all((r > -np.pi) & (r <= np.pi))
    np.testing.assert_allclose(r, _angle_diff(a, b), atol=1e-12)
    # non-angle fields are plain differences even when large
    np.testing.assert_allclose(residual(['elevation'], a[:, None], b[:, None])[:, 0], a - b)


def test_wrap_azimuth_maps_into_zero_two_pi() -> None:
    angles = np.array([-1e-17, -1e-300, 0.0, -np.pi / 2, TWO_PI, 7.0, -7.0])
    wrapped = wrap_azimuth(angles)
    assert np.all((wrapped >= 0.0) & (wrapped < TWO_PI))
    np.testing.assert_allclose(np.cos(wrapped), np.cos(angles), atol=1e-15)
    np.testing.assert_allclose(np.sin(wrapped), np.sin(angles), atol=1e-15)


# --------------------------------------------------------------------------- lines of sight


@pytest.mark.parametrize('geometry', ['ground_station', 'ship'])
def test_los_unit_vectors_from_azimuth_elevation_point_at_the_target(geometry: str) -> None:
    rng = np.random.default_rng(17)
    pose, dist = GEOMETRIES[geometry](rng, 50)
    x = _random_targets(rng, pose, dist)
    fields = ['elevation', 'range', 'azimuth']
    values, _ = predict(fields, x, pose)
    u = los_unit_vectors('angles', values, fields, pose.rotation)
    d = x[:, :3] - pose.position
    np.testing.assert_allclose(u, d / np.linalg.norm(d, axis=1, keepdims=True), atol=1e-12)


def test_los_unit_vectors_from_alpha_beta_lie_along_the_target_line() -> None:
    rng = np.random.default_rng(19)
    pose, dist = _satellite(rng, 50)
    x = _random_targets(rng, pose, dist)
    fields = ['los_alpha', 'los_beta']
    values, _ = predict(fields, x, pose)
    u = los_unit_vectors('los', values, fields, pose.rotation)
    d = x[:, :3] - pose.position
    xs = np.einsum('mi,mi->m', d, pose.rotation[:, :, 0])
    assert np.any(xs > 0.0) and np.any(xs < 0.0)
    # the ratios fix the line; its direction is that of +x_s
    expected = np.sign(xs)[:, None] * d / np.linalg.norm(d, axis=1, keepdims=True)
    np.testing.assert_allclose(u, expected, atol=1e-12)


def test_los_unit_vectors_rejects_an_unknown_kind() -> None:
    with pytest.raises(ValueError, match="'angles' or 'los'"):
        los_unit_vectors('radar', np.zeros((1, 2)), ['azimuth', 'elevation'], np.eye(3)[None])


# --------------------------------------------------------------------------- validation


def test_predict_rejects_unknown_fields_and_mismatched_shapes() -> None:
    pose = StationPose.fixed(SITE, ENU, 2)
    x = np.hstack([SITE + 1e4 * np.vstack([EAST, NORTH]), np.zeros((2, 3))])
    with pytest.raises(MeasurementError, match='rnge'):
        predict(['rnge'], x, pose)
    with pytest.raises(ValueError, match=r'shape \(m, 6\)'):
        predict(['range'], x[:, :3], pose)
    with pytest.raises(ValueError, match='2 target states but 3 station poses'):
        predict(['range'], x, StationPose.fixed(SITE, ENU, 3))


def test_station_pose_rejects_inconsistent_shapes() -> None:
    with pytest.raises(ValueError, match='rotation'):
        StationPose(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((3, 3, 3)))
    with pytest.raises(ValueError, match='position/velocity'):
        StationPose(np.zeros((2, 3)), np.zeros((1, 3)), np.zeros((2, 3, 3)))
