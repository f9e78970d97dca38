"""Measurement models h(x) of the tracking sensors, with analytic Jacobians.

Each model maps the target state ``x = (p, v)`` in the world frame, seen from a
station whose pose is given by a :class:`StationPose`, to one measured quantity:

===============  ==========================================================  =======
field            model (``d = p - p_s``, ``(e, n, u) = (x_s, y_s, z_s) = R^T d``)  unit
===============  ==========================================================  =======
``range``        ``|d|``                                                     m
``range_rate``   ``d . (v - v_s) / |d|``                                     m/s
``azimuth``      ``atan2(e, n)`` in [0, 2 pi), from the frame's y toward x   rad
``elevation``    ``atan2(u, sqrt(e^2 + n^2))``                               rad
``los_alpha``    ``y_s / x_s`` (seed 003 observation frame)                  1
``los_beta``     ``z_s / x_s``                                               1
===============  ==========================================================  =======

For a fixed ground station ``R`` is the ENU rotation so that azimuth runs from north
toward east (surveying convention, *not* REP 103's counter-clockwise yaw); for a ship
it is the unstabilised deck attitude; for an observing satellite the radial/east/north
observation frame. Light time and refraction are not modelled.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbit_tracking.core.errors import MeasurementError

__all__ = [
    'ANGLE_FIELDS',
    'FIELDS',
    'KIND_FIELDS',
    'KIND_OPTIONAL_FIELDS',
    'StationPose',
    'los_unit_vectors',
    'predict',
    'residual',
    'sigma_field',
    'wrap_azimuth',
]

FloatArray = NDArray[np.float64]

FIELDS: tuple[str, ...] = (
    'range',
    'range_rate',
    'azimuth',
    'elevation',
    'los_alpha',
    'los_beta',
)
"""Every value field a station may measure, in the contract's order."""

ANGLE_FIELDS = frozenset({'azimuth'})
"""Fields that wrap at 2 pi: residuals are taken modulo 2 pi into (-pi, pi]."""

KIND_FIELDS: dict[str, tuple[str, ...]] = {
    'cw_radar': ('range', 'range_rate'),
    'pulse_radar': ('range', 'azimuth', 'elevation'),
    'optical': ('azimuth', 'elevation'),
    'satellite': ('los_alpha', 'los_beta'),
}
"""The fields each sensor kind measures (contract table)."""

KIND_OPTIONAL_FIELDS: dict[str, tuple[str, ...]] = {
    'cw_radar': (),
    'pulse_radar': ('range_rate',),
    'optical': (),
    'satellite': (),
}
"""Fields a kind may add to its own."""


def wrap_azimuth(angle: ArrayLike) -> FloatArray:
    """Angles [rad] wrapped into [0, 2 pi), the contract's azimuth range.

    ``np.mod`` alone returns 2 pi itself for a tiny negative angle (the sum rounds up).
    """
    a = np.mod(np.asarray(angle, dtype=np.float64), 2.0 * np.pi)
    return np.where(a >= 2.0 * np.pi, 0.0, a)


def sigma_field(field: str) -> str:
    """Name of the standard-deviation field of a value field (``range`` -> ``sigma_range``)."""
    return f'sigma_{field}'


@dataclass(frozen=True)
class StationPose:
    """Station origin, velocity and attitude at m epochs (world frame).

    Attributes
    ----------
    position : ndarray, shape (m, 3)
        Station origin [m].
    velocity : ndarray, shape (m, 3)
        Station velocity [m/s].
    rotation : ndarray, shape (m, 3, 3)
        Rotation taking station-frame vectors into the world frame.
    """

    position: FloatArray
    velocity: FloatArray
    rotation: FloatArray

    def __post_init__(self) -> None:
        m = self.position.shape[0]
        if self.position.shape != (m, 3) or self.velocity.shape != (m, 3):
            raise ValueError(
                f'station position/velocity must be (m, 3); got {self.position.shape}, '
                f'{self.velocity.shape}'
            )
        if self.rotation.shape != (m, 3, 3):
            raise ValueError(f'station rotation must be ({m}, 3, 3); got {self.rotation.shape}')

    @classmethod
    def fixed(cls, position: ArrayLike, rotation: ArrayLike, m: int) -> StationPose:
        """The same pose repeated at m epochs (a station fixed in the world frame)."""
        p = np.asarray(position, dtype=np.float64).reshape(3)
        r = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
        return cls(np.tile(p, (m, 1)), np.zeros((m, 3)), np.tile(r, (m, 1, 1)))

    def __len__(self) -> int:
        return int(self.position.shape[0])

    def take(self, index: ArrayLike) -> StationPose:
        """Subset of epochs."""
        i = np.asarray(index)
        return StationPose(self.position[i], self.velocity[i], self.rotation[i])


def _local(target: FloatArray, pose: StationPose) -> tuple[FloatArray, FloatArray]:
    d = target[:, :3] - pose.position
    local = np.einsum('mji,mj->mi', pose.rotation, d)  # R^T d
    return d, local


def _to_world(pose: StationPose, grad_local: FloatArray) -> FloatArray:
    """Gradient w.r.t. local coordinates (m, 3) -> w.r.t. world position (m, 3)."""
    return np.einsum('mij,mj->mi', pose.rotation, grad_local)


def predict(
    fields: Sequence[str],
    target: ArrayLike,
    pose: StationPose,
    jacobian: bool = False,
) -> tuple[FloatArray, FloatArray | None]:
    """Evaluate the measurement models.

    Parameters
    ----------
    fields : sequence of str
        Fields to predict, any of :data:`FIELDS`.
    target : array_like, shape (m, 6)
        Target position and velocity in the world frame [m, m/s].
    pose : StationPose
        Station pose at the same m epochs.
    jacobian : bool
        Also return ``dh/dx``.

    Returns
    -------
    values : ndarray, shape (m, k)
    jac : ndarray, shape (m, k, 6) or None
        Derivatives w.r.t. (position, velocity) of the target.
    """
    x = np.asarray(target, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 6:
        raise ValueError(f'target states must have shape (m, 6); got {x.shape}')
    if x.shape[0] != len(pose):
        raise ValueError(f'{x.shape[0]} target states but {len(pose)} station poses')
    unknown = [f for f in fields if f not in FIELDS]
    if unknown:
        raise MeasurementError(f'unknown measurement field(s) {unknown}; known: {FIELDS}')
    m = x.shape[0]
    d, loc = _local(x, pose)
    rng = np.linalg.norm(d, axis=1)
    values = np.empty((m, len(fields)))
    jac = np.zeros((m, len(fields), 6)) if jacobian else None
    e, n, u = loc[:, 0], loc[:, 1], loc[:, 2]
    for j, f in enumerate(fields):
        if f == 'range':
            values[:, j] = rng
            if jac is not None:
                jac[:, j, :3] = d / rng[:, None]
        elif f == 'range_rate':
            dv = x[:, 3:] - pose.velocity
            rr = np.einsum('mi,mi->m', d, dv) / rng
            values[:, j] = rr
            if jac is not None:
                unit = d / rng[:, None]
                jac[:, j, :3] = (dv - rr[:, None] * unit) / rng[:, None]
                jac[:, j, 3:] = unit
        elif f == 'azimuth':
            values[:, j] = wrap_azimuth(np.arctan2(e, n))
            if jac is not None:
                h2 = e * e + n * n
                g = np.stack([n / h2, -e / h2, np.zeros(m)], axis=1)
                jac[:, j, :3] = _to_world(pose, g)
        elif f == 'elevation':
            hor = np.hypot(e, n)
            values[:, j] = np.arctan2(u, hor)
            if jac is not None:
                r2 = rng * rng
                g = np.stack([-e * u / (hor * r2), -n * u / (hor * r2), hor / r2], axis=1)
                jac[:, j, :3] = _to_world(pose, g)
        elif f == 'los_alpha':
            values[:, j] = n / e
            if jac is not None:
                g = np.stack([-n / e**2, 1.0 / e, np.zeros(m)], axis=1)
                jac[:, j, :3] = _to_world(pose, g)
        else:  # los_beta
            values[:, j] = u / e
            if jac is not None:
                g = np.stack([-u / e**2, np.zeros(m), 1.0 / e], axis=1)
                jac[:, j, :3] = _to_world(pose, g)
    return values, jac


def residual(fields: Sequence[str], measured: ArrayLike, predicted: ArrayLike) -> FloatArray:
    """``measured - predicted`` with angle fields wrapped into (-pi, pi].

    Both arrays have shape (m, k) with columns in the order of ``fields``.
    """
    r = np.asarray(measured, dtype=np.float64) - np.asarray(predicted, dtype=np.float64)
    for j, f in enumerate(fields):
        if f in ANGLE_FIELDS:
            r[..., j] = -np.mod(-r[..., j] + np.pi, 2.0 * np.pi) + np.pi
    return r


def los_unit_vectors(
    kind: str, values: ArrayLike, fields: Sequence[str], rotation: ArrayLike
) -> FloatArray:
    """Line-of-sight unit vectors in the world frame from angle measurements.

    Parameters
    ----------
    kind : {'angles', 'los'}
        ``'angles'`` uses the ``azimuth`` and ``elevation`` columns,
        ``'los'`` the ``los_alpha`` and ``los_beta`` columns.
    values : array_like, shape (m, k)
        Measurements with columns named by ``fields``.
    fields : sequence of str
    rotation : array_like, shape (m, 3, 3)
        Station-to-world rotations at the same epochs.

    Returns
    -------
    ndarray, shape (m, 3)
        Unit vectors. For ``'los'`` the direction sign is that of ``+x_s`` (the line,
        not the ray, is what the measurement fixes).
    """
    v = np.asarray(values, dtype=np.float64)
    rot = np.asarray(rotation, dtype=np.float64)
    idx = {f: i for i, f in enumerate(fields)}
    if kind == 'angles':
        a, el = v[:, idx['azimuth']], v[:, idx['elevation']]
        local = np.stack([np.cos(el) * np.sin(a), np.cos(el) * np.cos(a), np.sin(el)], axis=1)
    elif kind == 'los':
        al, be = v[:, idx['los_alpha']], v[:, idx['los_beta']]
        local = np.stack([np.ones_like(al), al, be], axis=1)
        local /= np.linalg.norm(local, axis=1, keepdims=True)
    else:
        raise ValueError(f"kind must be 'angles' or 'los'; got {kind!r}")
    return np.einsum('mij,mj->mi', rot, local)
