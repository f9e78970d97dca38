"""Reference frames: WGS-84 geodetic and ECEF, station ENU, launch frame, satellite
observation frame, platform attitude and quaternions.

Conventions (see ``docs/CONVENTIONS.md``):

* Rotation matrices returned here take vectors *from* the named local frame *into* the
  world frame: their columns are the local axes expressed in world coordinates.
  ``world_vector = R @ local_vector``.
* Quaternions are ``(x, y, z, w)`` (scalar last), the order of
  ``geometry_msgs/Quaternion``.
* Angles are radians unless a name ends in ``_deg``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

__all__ = [
    'EARTH_ROTATION_RATE',
    'WGS84_A',
    'WGS84_B',
    'WGS84_E2',
    'WGS84_F',
    'WGS84_GM',
    'WGS84_J2',
    'ecef_to_geodetic',
    'enu_rotation',
    'geodetic_to_ecef',
    'launch_rotation',
    'matrix_to_quaternion',
    'meridian_radii',
    'observation_rotation',
    'platform_rotation',
    'quaternion_to_matrix',
    'states_to_local',
]

FloatArray = NDArray[np.float64]

WGS84_A = 6378137.0
"""WGS-84 semi-major axis [m]."""
WGS84_F = 1.0 / 298.257223563
"""WGS-84 flattening [1]."""
WGS84_B = WGS84_A * (1.0 - WGS84_F)
"""WGS-84 semi-minor axis [m]."""
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
"""First eccentricity squared [1]."""
WGS84_GM = 3.986004418e14
"""WGS-84 Earth gravitational parameter [m^3/s^2]."""
WGS84_J2 = 1.08262668e-3
"""Second zonal harmonic (EGM96/EGM2008 value) [1]."""
EARTH_ROTATION_RATE = 7.292115e-5
"""WGS-84 Earth rotation rate [rad/s]."""

_EP2 = WGS84_E2 / (1.0 - WGS84_E2)  # second eccentricity squared


def _as_float(a: ArrayLike) -> FloatArray:
    return np.asarray(a, dtype=np.float64)


def geodetic_to_ecef(lat: ArrayLike, lon: ArrayLike, h: ArrayLike) -> FloatArray:
    """WGS-84 geodetic coordinates to ECEF.

    Parameters
    ----------
    lat, lon : array_like, shape (...)
        Geodetic latitude and longitude [rad].
    h : array_like, shape (...)
        Height above the ellipsoid [m].

    Returns
    -------
    ndarray, shape (..., 3)
        ECEF position [m].
    """
    lat, lon, h = np.broadcast_arrays(_as_float(lat), _as_float(lon), _as_float(h))
    s, c = np.sin(lat), np.cos(lat)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * s * s)
    return np.stack(
        [(n + h) * c * np.cos(lon), (n + h) * c * np.sin(lon), (n * (1.0 - WGS84_E2) + h) * s],
        axis=-1,
    )


def ecef_to_geodetic(xyz: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """ECEF position to WGS-84 geodetic latitude, longitude [rad] and height [m].

    Bowring's iteration on the parametric latitude; four iterations bring any point
    from the Earth's centre region out to geostationary distance to well below 1e-9 m.

    Parameters
    ----------
    xyz : array_like, shape (..., 3)
        ECEF position [m].
    """
    xyz = _as_float(xyz)
    if xyz.shape[-1] != 3:
        raise ValueError(f'ECEF positions must have shape (..., 3); got {xyz.shape}')
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    p = np.hypot(x, y)
    lon = np.arctan2(y, x)
    beta = np.arctan2(z, (1.0 - WGS84_F) * p)
    lat = beta
    for _ in range(4):
        sb, cb = np.sin(beta), np.cos(beta)
        lat = np.arctan2(z + _EP2 * WGS84_B * sb**3, p - WGS84_E2 * WGS84_A * cb**3)
        beta = np.arctan2((1.0 - WGS84_F) * np.sin(lat), np.cos(lat))
    s, c = np.sin(lat), np.cos(lat)
    h = p * c + z * s - WGS84_A * np.sqrt(1.0 - WGS84_E2 * s * s)
    return lat, lon, h


def meridian_radii(lat: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Meridian radius of curvature M and prime-vertical radius N [m] at ``lat`` [rad]."""
    s = np.sin(_as_float(lat))
    w2 = 1.0 - WGS84_E2 * s * s
    n = WGS84_A / np.sqrt(w2)
    m = WGS84_A * (1.0 - WGS84_E2) / w2**1.5
    return m, n


def enu_rotation(lat: ArrayLike, lon: ArrayLike) -> FloatArray:
    """Rotation taking local ENU (east, north, up) vectors into ECEF.

    Returns
    -------
    ndarray, shape (..., 3, 3)
        Columns are the east, north and up unit vectors in ECEF.
    """
    lat, lon = np.broadcast_arrays(_as_float(lat), _as_float(lon))
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    zero = np.zeros_like(lat)
    east = np.stack([-so, co, zero], axis=-1)
    north = np.stack([-sl * co, -sl * so, cl], axis=-1)
    up = np.stack([cl * co, cl * so, sl], axis=-1)
    return np.stack([east, north, up], axis=-1)


def launch_rotation(lat: float, lon: float, azimuth: float) -> FloatArray:
    """Rotation taking launch-frame vectors into ECEF (seed 000's matrix S).

    The launch frame has ``y`` along the local geodetic up, ``x`` horizontal along the
    launch azimuth (from north toward east) and ``z = x × y``.

    Parameters
    ----------
    lat, lon : float
        Geodetic latitude and longitude of the launch point [rad].
    azimuth : float
        Launch azimuth A0 [rad], measured from north toward east.

    Returns
    -------
    ndarray, shape (3, 3)
    """
    r_enu = enu_rotation(lat, lon)
    east, north, up = r_enu[:, 0], r_enu[:, 1], r_enu[:, 2]
    x = np.sin(azimuth) * east + np.cos(azimuth) * north
    y = up
    z = np.cross(x, y)
    return np.stack([x, y, z], axis=-1)


def states_to_local(
    state: ArrayLike, covariance: ArrayLike, origin: ArrayLike, rotation: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """World-frame states and covariances in a local frame fixed in the world frame.

    ``p_L = R^T (p - o)``, ``v_L = R^T v`` and ``P_L = T P T^T`` with
    ``T = diag(R^T, R^T)``, where ``R`` takes local vectors into the world frame (e.g.
    :func:`launch_rotation` for the launch frame, whose velocities are then relative to
    the rotating Earth like the ECEF ones).

    Parameters
    ----------
    state : array_like, shape (m, 6)
        Position [m] and velocity [m/s] in the world frame.
    covariance : array_like, shape (m, 6, 6)
    origin : array_like, shape (3,)
        Local origin in the world frame [m].
    rotation : array_like, shape (3, 3)

    Returns
    -------
    state : ndarray, shape (m, 6)
    covariance : ndarray, shape (m, 6, 6)
    """
    x = np.atleast_2d(_as_float(state))
    c = _as_float(covariance).reshape(-1, 6, 6)
    o = _as_float(origin)
    r = _as_float(rotation)
    if x.shape[1:] != (6,) or c.shape[0] != x.shape[0] or o.shape != (3,) or r.shape != (3, 3):
        raise ValueError(
            f'states_to_local needs state (m, 6), covariance (m, 6, 6), origin (3,) and '
            f'rotation (3, 3); got {x.shape}, {np.shape(covariance)}, {o.shape}, {r.shape}'
        )
    t = np.zeros((6, 6))
    t[:3, :3] = t[3:, 3:] = r.T
    local = np.hstack([(x[:, :3] - o) @ r, x[:, 3:] @ r])
    return local, t @ c @ t.T


def observation_rotation(position: ArrayLike) -> FloatArray:
    """Rotation taking a satellite observation frame into the world frame (seed 003).

    Axes: ``x`` radial outward ``p/|p|``, ``y`` east ``(-y0, x0, 0)/rho``, ``z`` north
    ``= x × y``, for a satellite at ``p = (x0, y0, z0)``.

    Parameters
    ----------
    position : array_like, shape (..., 3)
        Satellite position in the world frame [m]; must not lie on the z axis.

    Returns
    -------
    ndarray, shape (..., 3, 3)
    """
    p = _as_float(position)
    rho = np.hypot(p[..., 0], p[..., 1])
    if np.any(rho <= 0.0):
        raise ValueError('observation frame is undefined for a position on the polar axis')
    x = p / np.linalg.norm(p, axis=-1, keepdims=True)
    y = np.stack([-p[..., 1], p[..., 0], np.zeros_like(rho)], axis=-1) / rho[..., None]
    z = np.cross(x, y)
    return np.stack([x, y, z], axis=-1)


def platform_rotation(yaw: ArrayLike, pitch: ArrayLike, roll: ArrayLike) -> FloatArray:
    """Rotation taking an unstabilised platform (deck) frame into local ENU.

    The deck frame is ``x`` starboard, ``y`` bow, ``z`` deck-up, so that a level ship
    heading north has the identity attitude and azimuth in the deck frame is measured
    from the bow toward starboard. ``yaw`` is the heading (from north toward east),
    ``pitch`` is bow-up positive and ``roll`` is starboard-down positive:
    ``R = Rz(-yaw) Rx(pitch) Ry(roll)``.

    Parameters
    ----------
    yaw, pitch, roll : array_like, shape (...)
        Attitude angles [rad].

    Returns
    -------
    ndarray, shape (..., 3, 3)
    """
    yaw, pitch, roll = np.broadcast_arrays(_as_float(yaw), _as_float(pitch), _as_float(roll))
    one, zero = np.ones_like(yaw), np.zeros_like(yaw)

    def mat(rows: list[list[FloatArray]]) -> FloatArray:
        return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)

    cy, sy = np.cos(-yaw), np.sin(-yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    rz = mat([[cy, -sy, zero], [sy, cy, zero], [zero, zero, one]])
    rx = mat([[one, zero, zero], [zero, cp, -sp], [zero, sp, cp]])
    ry = mat([[cr, zero, sr], [zero, one, zero], [-sr, zero, cr]])
    return rz @ rx @ ry


def matrix_to_quaternion(matrix: ArrayLike) -> FloatArray:
    """Rotation matrix (..., 3, 3) to unit quaternion (..., 4) ordered (x, y, z, w).

    The sign is chosen so that ``w >= 0``.
    """
    m = _as_float(matrix)
    shape = m.shape[:-2]
    q = Rotation.from_matrix(m.reshape(-1, 3, 3)).as_quat()
    q = np.where(q[:, 3:4] < 0.0, -q, q)
    return q.reshape(*shape, 4)


def quaternion_to_matrix(quaternion: ArrayLike) -> FloatArray:
    """Quaternion (..., 4) ordered (x, y, z, w) to rotation matrix (..., 3, 3).

    Raises
    ------
    ValueError
        If a quaternion's norm is not within 1e-3 of one (an uninitialised message).
    """
    q = _as_float(quaternion)
    if q.shape[-1] != 4:
        raise ValueError(f'quaternions must have shape (..., 4); got {q.shape}')
    norm = np.linalg.norm(q, axis=-1)
    if np.any(~np.isfinite(norm)) or np.any(np.abs(norm - 1.0) > 1e-3):
        raise ValueError(f'quaternion is not a unit quaternion (norm {np.ravel(norm)[:3]})')
    shape = q.shape[:-1]
    return Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(*shape, 3, 3)
