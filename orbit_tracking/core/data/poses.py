"""Station poses over time: the position, velocity and attitude samples of one station,
interpolated at any epoch (cubic Hermite in position, slerp in attitude).

Shared by the triangulation alignment and the estimator's observation buffer.
"""

from __future__ import annotations

import math
from bisect import bisect_left

import numpy as np
from numpy.typing import NDArray

__all__ = ['PoseTrack']

FloatArray = NDArray[np.float64]


def _rotvec(rot: FloatArray) -> FloatArray:
    """Rotation vector (axis * angle) of a rotation matrix (angle < pi)."""
    c = min(1.0, max(-1.0, 0.5 * (np.trace(rot) - 1.0)))
    angle = math.acos(c)
    w = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    if angle < 1e-12:
        return 0.5 * w
    return w * (angle / (2.0 * math.sin(angle)))


def _expm(v: FloatArray) -> FloatArray:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    angle = float(np.linalg.norm(v))
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    if angle < 1e-12:
        return np.eye(3) + k
    k /= angle
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


class PoseTrack:
    """Poses of one station over time: a single pose for a fixed station, else samples
    interpolated by cubic Hermite (position, with velocity) and slerp (attitude)."""

    def __init__(self) -> None:
        self.t: list[float] = []
        self.p: list[FloatArray] = []
        self.v: list[FloatArray] = []
        self.r: list[FloatArray] = []
        self.moving = False

    def add(
        self,
        t: float,
        position: FloatArray,
        velocity: FloatArray,
        rotation: FloatArray,
        moving: bool,
    ) -> None:
        self.moving = moving
        if not moving:
            self.t, self.p, self.v, self.r = [t], [position], [velocity], [rotation]
            return
        i = len(self.t)
        if self.t and t <= self.t[-1]:
            i = bisect_left(self.t, t)
            if i < len(self.t) and self.t[i] == t:
                return
        self.t.insert(i, t)
        self.p.insert(i, position)
        self.v.insert(i, velocity)
        self.r.insert(i, rotation)

    def __len__(self) -> int:
        return len(self.t)

    def at(self, t: float, max_gap: float) -> tuple[FloatArray, FloatArray] | None:
        """(position, rotation) at ``t``, or None when no sample brackets it."""
        if not self.t:
            return None
        if not self.moving:
            return self.p[0], self.r[0]
        i = bisect_left(self.t, t)
        if i < len(self.t) and abs(self.t[i] - t) < 1e-9:
            return self.p[i], self.r[i]
        if i > 0 and abs(self.t[i - 1] - t) < 1e-9:
            return self.p[i - 1], self.r[i - 1]
        if i == 0 or i == len(self.t):
            return None
        t0, t1 = self.t[i - 1], self.t[i]
        h = t1 - t0
        if h > max_gap:
            return None
        s = (t - t0) / h
        h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
        h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
        pos = h00 * self.p[i - 1] + h10 * h * self.v[i - 1] + h01 * self.p[i] + h11 * h * self.v[i]
        r0 = self.r[i - 1]
        rot = r0 @ _expm(s * _rotvec(r0.T @ self.r[i]))
        return pos, rot

    def prune(self, before: float) -> None:
        if not self.moving or len(self.t) < 3:
            return
        k = max(0, bisect_left(self.t, before) - 1)
        if k:
            del self.t[:k], self.p[:k], self.v[:k], self.r[:k]
