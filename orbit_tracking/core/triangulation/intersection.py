"""Triangulation: lines of sight from several stations intersected into position fixes
with covariance (seed 003, generalised to N stations and weighted by each line's
accuracy).

A line of sight ``o + s u`` comes with the Jacobian ``J = du/dθ`` (3×2) of its unit
direction with respect to the two measured angles θ and their covariance Σθ. At a
distance ρ along the line, the angular noise displaces the target laterally with
covariance ``C = ρ² J Σθ Jᵀ`` (rank 2, perpendicular to ``u``); its pseudo-inverse

    W = ρ⁻² J (JᵀJ)⁻¹ Σθ⁻¹ (JᵀJ)⁻¹ Jᵀ

is the line's information. The fix minimises ``Σ (x − o_i)ᵀ W_i (x − o_i)``:

    x = (Σ W_i)⁻¹ Σ W_i o_i,        P = (Σ W_i)⁻¹,

iterated a few times because ρ_i depends on x. A station that also measures range
(pulse radar) contributes a full-rank point ``o + R u`` with its 3×3 information, so a
single radar gives a fix by itself. With two lines and equal weights (``W_i = I − u uᵀ``)
the solution is the midpoint of the common perpendicular, whose length is seed 003's
inconsistency measure (:func:`midpoint`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from itertools import combinations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbit_tracking.core.chi2 import chi2_ppf
from orbit_tracking.core.errors import GeometryError

__all__ = [
    'Fix',
    'cramer_rao_bound',
    'Gates',
    'LineOfSight',
    'TriangulationResult',
    'angle_jacobian_local',
    'intersect',
    'line_information',
    'midpoint',
    'triangulate',
]

FloatArray = NDArray[np.float64]

REASONS = (
    'too_few_lines',
    'degenerate_geometry',
    'small_intersection_angle',
    'high_gdop',
    'miss_distance',
)
"""Why an epoch gave no fix (counted by the node and the offline tool)."""


@dataclass(frozen=True)
class LineOfSight:
    """One station's line of sight to a target at one epoch (world frame).

    Attributes
    ----------
    station_id : str
    origin : ndarray, shape (3,)
        Station position [m].
    direction : ndarray, shape (3,)
        Unit direction (its sign is irrelevant for intersection).
    jacobian : ndarray, shape (3, 2)
        ``d direction / d (angle1, angle2)`` in the world frame.
    angle_cov : ndarray, shape (2, 2)
        Covariance of the two angles [rad² or 1 for los_alpha/beta].
    range_m : float
        Measured range along the line (NaN if the station does not measure range).
    range_var : float
        Variance of the range [m²] (NaN without range).
    """

    station_id: str
    origin: FloatArray
    direction: FloatArray
    jacobian: FloatArray
    angle_cov: FloatArray
    range_m: float = float('nan')
    range_var: float = float('nan')

    @cached_property
    def has_range(self) -> bool:
        return bool(math.isfinite(self.range_m) and math.isfinite(self.range_var))

    def point(self) -> FloatArray:
        """``origin + range * direction`` (only with a range)."""
        return self.origin + self.range_m * self.direction

    def point_covariance(self) -> FloatArray:
        """3×3 covariance of :meth:`point` from the range and angle variances."""
        jac = np.column_stack([self.direction, self.range_m * self.jacobian])
        cov = np.zeros((3, 3))
        cov[0, 0] = self.range_var
        cov[1:, 1:] = self.angle_cov
        return jac @ cov @ jac.T


def angle_jacobian_local(kind: str, a: float, b: float) -> tuple[FloatArray, FloatArray]:
    """Unit direction and its Jacobian w.r.t. the two angles, in the station frame.

    Parameters
    ----------
    kind : {'angles', 'los'}
        ``'angles'``: (azimuth from y toward x, elevation); ``'los'``: seed 003's
        (alpha, beta) with ``u ∝ (1, alpha, beta)``.
    a, b : float
        The two measured values.

    Returns
    -------
    u : ndarray, shape (3,)
    jac : ndarray, shape (3, 2)
    """
    if kind == 'angles':
        ca, sa, ce, se = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
        u = np.array([ce * sa, ce * ca, se])
        jac = np.array([[ce * ca, -se * sa], [-ce * sa, -se * ca], [0.0, ce]])
        return u, jac
    if kind == 'los':
        v = np.array([1.0, a, b])
        n = np.linalg.norm(v)
        u = v / n
        proj = (np.eye(3) - np.outer(u, u)) / n
        return u, proj[:, 1:3]
    raise ValueError(f"kind must be 'angles' or 'los'; got {kind!r}")


def midpoint(
    o1: ArrayLike, u1: ArrayLike, o2: ArrayLike, u2: ArrayLike
) -> tuple[FloatArray, float]:
    """Seed 003's two-line intersection (its eqs. 5-13 to 5-20).

    Returns the midpoint of the common perpendicular of the lines ``o1 + s u1`` and
    ``o2 + t u2`` and the perpendicular's length (the miss distance) [m].

    Raises
    ------
    GeometryError
        If the lines are parallel (no unique common perpendicular).
    """
    o1, u1, o2, u2 = (np.asarray(v, dtype=np.float64) for v in (o1, u1, o2, u2))
    u1 = u1 / np.linalg.norm(u1)
    u2 = u2 / np.linalg.norm(u2)
    b = float(u1 @ u2)
    denom = 1.0 - b * b
    if denom < 1e-12:
        raise GeometryError(f'lines are parallel (cos angle = {b:.12f}); no intersection')
    w0 = o1 - o2
    d, e = float(u1 @ w0), float(u2 @ w0)
    s = (b * e - d) / denom
    t = (e - b * d) / denom
    pa, pb = o1 + s * u1, o2 + t * u2
    return 0.5 * (pa + pb), float(np.linalg.norm(pa - pb))


def line_information(line: LineOfSight, distance: float) -> FloatArray:
    """The 3×3 information (inverse lateral covariance, rank 2) of a line at ``distance``."""
    jac = line.jacobian
    g = np.linalg.inv(jac.T @ jac)
    return jac @ g @ np.linalg.inv(line.angle_cov) @ g @ jac.T / distance**2


def intersect(
    origins: ArrayLike,
    informations: ArrayLike,
) -> tuple[FloatArray, FloatArray]:
    """Weighted least-squares point of several lines or points.

    Parameters
    ----------
    origins : array_like, shape (n, 3)
        A point of each line (or the point itself for a full-rank observation).
    informations : array_like, shape (n, 3, 3)
        Information matrices (rank 2 for lines, ``w (I − u uᵀ)`` for plain weights).

    Returns
    -------
    position : ndarray, shape (3,)
    covariance : ndarray, shape (3, 3)
        ``(Σ W_i)⁻¹``.

    Raises
    ------
    GeometryError
        If ``Σ W_i`` is singular (parallel lines, a single line).
    """
    o = np.asarray(origins, dtype=np.float64)
    w = np.asarray(informations, dtype=np.float64)
    centre = o.mean(axis=0)  # solve about the centroid: no cancellation of large coordinates
    total = w.sum(axis=0)
    rhs = np.einsum('nij,nj->i', w, o - centre)
    try:
        chol = np.linalg.cholesky(total)
    except np.linalg.LinAlgError:
        raise GeometryError('singular normal matrix; the lines are parallel') from None
    d = np.diag(chol) ** 2
    if d.min() <= 1e-12 * d.max():
        raise GeometryError(f'near-singular normal matrix (pivots {d}); the lines are parallel')
    cov = np.linalg.inv(total)
    cov = 0.5 * (cov + cov.T)
    return centre + cov @ rhs, cov


def cramer_rao_bound(lines: Sequence[LineOfSight], position: ArrayLike) -> FloatArray:
    """Cramér–Rao bound (3×3) of a single-epoch fix from these lines at the true position.

    The inverse of the total information ``Σ W_i`` evaluated at the truth: no unbiased
    estimator using only these lines can have a smaller covariance (to first order).
    """
    x = np.asarray(position, dtype=np.float64)
    infos = []
    for ln in lines:
        if ln.has_range:
            infos.append(np.linalg.inv(ln.point_covariance()))
        else:
            infos.append(line_information(ln, abs(float(ln.direction @ (x - ln.origin)))))
    return np.asarray(np.linalg.inv(np.sum(infos, axis=0)), dtype=np.float64)


@dataclass(frozen=True)
class Gates:
    """Quality gates of a fix.

    Attributes
    ----------
    min_intersection_angle_deg : float
        The widest angle between any two lines must reach this (not applied when a
        station measures range).
    max_gdop : float
        ``sqrt(trace P)`` divided by the best line's lateral sigma must not exceed this.
    miss_probability : float
        The weighted misfit χ² (which for two lines is the squared miss distance over
        its expected variance) must lie below this quantile of χ²(dof).
    """

    min_intersection_angle_deg: float = 1.0
    max_gdop: float = 100.0
    miss_probability: float = 0.9999

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_intersection_angle_deg < 90.0:
            raise ValueError(
                'min_intersection_angle_deg must be in [0, 90); '
                f'got {self.min_intersection_angle_deg}'
            )
        if not self.max_gdop > 0.0:
            raise ValueError(f'max_gdop must be positive; got {self.max_gdop}')
        if not 0.0 < self.miss_probability <= 1.0:
            raise ValueError(f'miss_probability must be in (0, 1]; got {self.miss_probability}')


@dataclass(frozen=True)
class Fix:
    """A position fix.

    Attributes
    ----------
    position : ndarray, shape (3,)
        World frame [m].
    covariance : ndarray, shape (3, 3)
        [m²].
    miss_distance : float
        Largest common-perpendicular length between any two lines (or distance from a
        radar point to a line) [m]; 0 for a single radar.
    n_lines : int
        Lines (and radar points) used.
    stations : tuple of str
    chi2, dof : float, int
        Weighted misfit and its degrees of freedom.
    gdop : float
    max_angle_deg : float
        Widest angle between two lines [deg] (90 for a single radar point).
    """

    position: FloatArray
    covariance: FloatArray
    miss_distance: float
    n_lines: int
    stations: tuple[str, ...]
    chi2: float
    dof: int
    gdop: float
    max_angle_deg: float


@dataclass(frozen=True)
class TriangulationResult:
    """Outcome of one epoch: ``fix`` when ``success``, else ``reason`` (one of REASONS)."""

    success: bool
    reason: str
    message: str
    fix: Fix | None = None
    candidate: Fix | None = field(default=None, repr=False)


def _pairwise(lines: Sequence[LineOfSight]) -> tuple[float, float]:
    """(widest angle between lines [deg], largest miss distance [m])."""
    widest, miss = 0.0, 0.0
    for a, b in combinations(lines, 2):
        c = abs(float(a.direction @ b.direction))
        widest = max(widest, float(np.degrees(np.arccos(min(c, 1.0)))))
        if a.has_range and b.has_range:
            d = float(np.linalg.norm(a.point() - b.point()))
        elif a.has_range or b.has_range:
            p, ln = (a, b) if a.has_range else (b, a)
            r = p.point() - ln.origin
            d = float(np.linalg.norm(r - (r @ ln.direction) * ln.direction))
        else:
            try:
                _, d = midpoint(a.origin, a.direction, b.origin, b.direction)
            except GeometryError:
                d = 0.0
        miss = max(miss, d)
    return widest, miss


@lru_cache(maxsize=256)
def _chi2_limit(probability: float, dof: int) -> float:
    return chi2_ppf(probability, dof)


def _information(
    lines: Sequence[LineOfSight], x: FloatArray, origins: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Information matrices (n, 3, 3) of every line at the current fix ``x`` and the
    lateral variance (n,) of each observation, for the GDOP."""
    n = len(lines)
    infos = np.empty((n, 3, 3))
    lateral = np.empty(n)
    ang = [i for i, ln in enumerate(lines) if not ln.has_range]
    if ang:
        jac = np.stack([lines[i].jacobian for i in ang])
        cov = np.stack([lines[i].angle_cov for i in ang])
        u = np.stack([lines[i].direction for i in ang])
        dist = np.abs(np.einsum('ni,ni->n', u, x - origins[ang]))
        if np.any(dist <= 0.0):
            raise GeometryError('the fix coincides with a station')
        jtj = np.einsum('nki,nkj->nij', jac, jac)
        g = np.linalg.inv(jtj)
        m = g @ np.linalg.inv(cov) @ g
        infos[ang] = jac @ m @ np.swapaxes(jac, 1, 2) / dist[:, None, None] ** 2
        lateral[ang] = dist**2 * np.einsum('nii->n', cov @ jtj) / 2.0
    for i, ln in enumerate(lines):
        if ln.has_range:
            c = ln.point_covariance()
            infos[i] = np.linalg.inv(c)
            lateral[i] = np.trace(c) / 3.0
    return infos, lateral


def triangulate(
    lines: Sequence[LineOfSight], gates: Gates | None = None, iterations: int = 2
) -> TriangulationResult:
    """Fix from the lines of sight of one target at one epoch.

    Parameters
    ----------
    lines : sequence of LineOfSight
        At least two lines, or one line with a range.
    gates : Gates
    iterations : int
        Re-weighting passes (each updates the distances ρ_i; the first already starts from
        the unweighted fix, whose distances are right to ~1e-4 relative).
    """
    gates = gates or Gates()
    n_points = sum(1 for ln in lines if ln.has_range)
    if len(lines) < 2 and n_points == 0:
        return TriangulationResult(False, 'too_few_lines', f'{len(lines)} line(s) of sight')
    origins = np.stack([ln.point() if ln.has_range else ln.origin for ln in lines])
    try:
        # start from the unweighted solution, then re-weight with the distances
        infos = np.stack(
            [
                np.eye(3) if ln.has_range else np.eye(3) - np.outer(ln.direction, ln.direction)
                for ln in lines
            ]
        )
        x, cov = intersect(origins, infos)
        # a radar point's information does not depend on the fix: one pass is exact then
        for _ in range(1 if n_points == len(lines) else iterations):
            infos, lateral = _information(lines, x, origins)
            x, cov = intersect(origins, infos)
    except (GeometryError, np.linalg.LinAlgError) as exc:
        return TriangulationResult(False, 'degenerate_geometry', str(exc))
    resid = x - origins
    # only the part across each line counts (W u = 0 holds to rounding only, and the
    # along-line part is the whole distance to the target)
    for i, ln in enumerate(lines):
        if not ln.has_range:
            resid[i] -= (resid[i] @ ln.direction) * ln.direction
    chi2 = float(np.einsum('ni,nij,nj->', resid, infos, resid))
    dof = 2 * (len(lines) - n_points) + 3 * n_points - 3
    widest, miss = _pairwise(lines)
    if n_points:
        widest = 90.0
    gdop = float(np.sqrt(np.trace(cov) / lateral.min()))
    fix = Fix(
        position=x,
        covariance=cov,
        miss_distance=miss,
        n_lines=len(lines),
        stations=tuple(ln.station_id for ln in lines),
        chi2=chi2,
        dof=dof,
        gdop=gdop,
        max_angle_deg=widest,
    )
    if not n_points and widest < gates.min_intersection_angle_deg:
        return TriangulationResult(
            False, 'small_intersection_angle', f'widest angle {widest:.3f} deg', candidate=fix
        )
    if gdop > gates.max_gdop:
        return TriangulationResult(False, 'high_gdop', f'GDOP {gdop:.1f}', candidate=fix)
    if dof > 0 and gates.miss_probability < 1.0:
        limit = _chi2_limit(gates.miss_probability, dof)
        if chi2 > limit:
            return TriangulationResult(
                False,
                'miss_distance',
                f'misfit chi2 {chi2:.1f} > {limit:.1f} (dof {dof}); miss distance {miss:.2f} m',
                candidate=fix,
            )
    return TriangulationResult(True, 'ok', 'ok', fix)
