"""The fused telemetry of one target in a window's least-squares problem (issue 14): its
rows, its error model and their derivatives.

A telemetry epoch at ``t`` gives a position and a velocity, modelled as

    position = p(t) + e(t) - d_p v(t) + d_p^2 a(t) / 2
    velocity = v(t) + e'(t) + w(t) - d_v a(t)

with ``p, v, a`` the trajectory and its derivatives and

* ``e``: a slow error of the position (a cubic spline), whose derivative is the velocity's
  error when both come from one source (the velocity integrated into the position);
* ``w``: a velocity error of its own (piecewise linear; only when a score test asks for it,
  :mod:`~orbit_tracking.core.estimation.telemetry_velocity`);
* ``d_p, d_v``: time-tag delays of the position and the velocity [s] (only when a score test
  asks for them, :mod:`~orbit_tracking.core.estimation.telemetry_delays`): a position
  tagged ``t`` that was the vehicle's at ``t - d_p`` (to second order in ``d_p``).

The error coefficients have a zero-mean prior (:func:`error_prior_matrix`). The coefficients
of one block follow each other in the problem's unknowns: ``e`` (3 per coefficient of its
axis), ``w`` (likewise), then ``d_p, d_v``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from orbit_tracking.core.data.tables import TargetStates
from orbit_tracking.core.estimation.bspline import SplineAxis, SplineTrajectory
from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.knots import uniform_knots

__all__ = [
    'DELAY_PRIOR_S',
    'VELOCITY_ERROR_PRIOR',
    'TelemetryBlock',
    'error_prior_matrix',
    'error_step_matrix',
    'shift_columns',
    'telemetry_block',
    'velocity_error_axis',
]

FloatArray = NDArray[np.float64]

VELOCITY_ERROR_PRIOR = 0.1
"""Prior sigma [m/s] of a separate telemetry velocity error's coefficients: weak (the
velocity rows determine it), only so that a span without telemetry stays regular."""

DELAY_PRIOR_S = 0.1
"""Prior sigma [s] of a time-tag delay: weak (a skew of a tenth of a second is already a
gross fault of a telemetry chain), only so that a window without motion stays regular."""


@dataclass
class TelemetryBlock:
    """One target's telemetry in a window (see the module docstring)."""

    target: int
    time: FloatArray
    position: FloatArray
    velocity: FloatArray
    pw: sp.csr_matrix  # (3m, n_t) trajectory position design
    vw: sp.csr_matrix
    ew: sp.csr_matrix  # (3m, 3 n_e) error design (position)
    edw: sp.csr_matrix
    axis: SplineAxis
    offset: int  # first error coefficient
    prior_sigma: tuple[float, float]  # e's level and step sigmas [m] (error_prior_matrix)
    noise: list[float]  # [position, velocity] white sigma
    valid_p: NDArray[np.bool_]
    valid_v: NDArray[np.bool_]
    # a velocity error of its own (velocity from another source than the position): a
    # piecewise-linear spline per axis, coefficients after those of e (None: e' only)
    w_axis: SplineAxis | None = None
    w_design: sp.csr_matrix | None = None  # (3m, 3 n_w)
    declared_sigma: float = 1.0  # the telemetry's declared position sigma (median) [m]
    aw: sp.csr_matrix | None = None  # acceleration design: time-tag delays estimated
    # log evidence of the error sizes carried from the previous windows, on the grid of
    # telemetry_evidence.evidence_grid (None: none carried; see that module)
    size_prior: FloatArray | None = None

    @property
    def delays(self) -> bool:
        """True when the block estimates its time-tag delays."""
        return self.aw is not None

    @property
    def n_error(self) -> int:
        """Telemetry error coefficients: e, then w if any, then the delays if any."""
        n = 3 * self.axis.n_coef + (0 if self.w_axis is None else 3 * self.w_axis.n_coef)
        return n + (2 if self.delays else 0)

    @property
    def delay_offset(self) -> int:
        """Index of ``d_p`` in the problem's unknowns (``d_v`` follows); only with delays."""
        return self.offset + self.n_error - 2

    def velocity_error(self, beta: FloatArray) -> FloatArray:
        """The separate velocity error at the telemetry epochs, (3m,) (zeros without)."""
        if self.w_design is None or self.w_axis is None:
            return np.zeros(3 * self.time.size)
        o = self.offset + 3 * self.axis.n_coef
        return np.asarray(self.w_design @ beta[o : o + 3 * self.w_axis.n_coef])

    def delay_values(self, beta: FloatArray) -> tuple[float, float]:
        """``(d_p, d_v)`` [s] (zeros without delays)."""
        if not self.delays:
            return 0.0, 0.0
        o = self.delay_offset
        return float(beta[o]), float(beta[o + 1])

    def predict(
        self, coef: FloatArray, beta: FloatArray, origin: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Modelled telemetry position and velocity, (m, 3) each, for the trajectory
        coefficients ``coef`` and the problem's unknowns ``beta``."""
        m = self.time.size
        ecoef = beta[self.offset : self.offset + 3 * self.axis.n_coef]
        v = self.vw @ coef
        pred_p = self.pw @ coef + self.ew @ ecoef
        pred_v = v + self.edw @ ecoef + self.velocity_error(beta)
        if self.aw is not None:
            d_p, d_v = self.delay_values(beta)
            a = self.aw @ coef
            pred_p = pred_p - d_p * v + 0.5 * d_p**2 * a
            pred_v = pred_v - d_v * a
        return pred_p.reshape(m, 3) + origin, pred_v.reshape(m, 3)

    def jacobians(
        self,
        coef: FloatArray,
        beta: FloatArray,
        rows_p: NDArray[np.int_],
        rows_v: NDArray[np.int_],
        traj_offset: int,
        n: int,
    ) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """Derivatives of the modelled position rows ``rows_p`` and velocity rows
        ``rows_v`` (indices into the 3m components) by all ``n`` unknowns (not whitened)."""
        pw, vw = self.pw, self.vw
        d_p, d_v = self.delay_values(beta)
        if self.aw is not None:
            pw = pw - d_p * vw + 0.5 * d_p**2 * self.aw
            vw = vw - d_v * self.aw
        jp = shift_columns(pw[rows_p], traj_offset, n) + shift_columns(
            self.ew[rows_p], self.offset, n
        )
        jv = shift_columns(vw[rows_v], traj_offset, n) + shift_columns(
            self.edw[rows_v], self.offset, n
        )
        if self.w_design is not None:
            jv = jv + shift_columns(self.w_design[rows_v], self.offset + 3 * self.axis.n_coef, n)
        if self.aw is not None:
            a = np.asarray(self.aw @ coef)
            dd_p = -np.asarray(self.vw @ coef) + d_p * a
            o = self.delay_offset
            jp = jp + sp.csr_matrix(
                (dd_p[rows_p], (np.arange(rows_p.size), np.full(rows_p.size, o))),
                shape=(rows_p.size, n),
            )
            jv = jv + sp.csr_matrix(
                (-a[rows_v], (np.arange(rows_v.size), np.full(rows_v.size, o + 1))),
                shape=(rows_v.size, n),
            )
        return jp.tocsr(), jv.tocsr()


def velocity_error_axis(
    t0: float, t1: float, cfg: EstimatorConfig, events: Sequence[float] = ()
) -> SplineAxis:
    """The separate telemetry velocity error's spline: piecewise linear, knots on the
    multiples of ``telemetry_velocity_error_spacing`` s, and one at each event (free to
    turn there: a velocity time-tag skew is the acceleration times the skew, which jumps
    where the acceleration does; a piecewise-linear spline cannot jump, so the knot test
    and ``e'``, which can, share that)."""
    knots = uniform_knots(t0, t1, cfg.telemetry_velocity_error_spacing, events=events, degree=2)
    return SplineAxis.from_interior(knots, t0, t1, 1)


def error_prior_matrix(tb: TelemetryBlock) -> sp.csr_matrix:
    """The square root ``M`` of the prior information of the block's error coefficients
    (the prior rows are ``0 - M x``): for ``e``, per axis, its first coefficient over
    ``prior_sigma[0]`` (the level) and each later one minus its predecessor over
    ``prior_sigma[1]`` (the steps: a random walk of the coefficients, so that a large but
    slow error, a bias or a drift, does not also allow a fast one); then a separate
    velocity error's coefficients over :data:`VELOCITY_ERROR_PRIOR` and the delays over
    :data:`DELAY_PRIOR_S`."""
    n_c = tb.axis.n_coef
    level, step = tb.prior_sigma
    m_e = sp.vstack([sp.eye(3, 3 * n_c) / level, error_step_matrix(n_c) / step], format='csr')
    rest = np.full(tb.n_error - 3 * n_c, 1.0 / VELOCITY_ERROR_PRIOR)
    if tb.delays:
        rest[-2:] = 1.0 / DELAY_PRIOR_S
    if not rest.size:
        return m_e
    return sp.block_diag([m_e, sp.diags(rest)], format='csr')


def error_step_matrix(n_coef: int) -> sp.csr_matrix:
    """Differences of consecutive coefficients of ``e`` (3 per coefficient, interleaved by
    axis): ``(3 (n_coef - 1), 3 n_coef)``."""
    m = 3 * (n_coef - 1)
    return sp.diags([-np.ones(m), np.ones(m)], [0, 3], shape=(m, 3 * n_coef), format='csr')


def telemetry_block(
    tid: int,
    tel: TargetStates,
    traj: SplineTrajectory,
    axis: SplineAxis,
    offset: int,
    w_axis: SplineAxis | None,
    delays: bool,
) -> TelemetryBlock:
    """The block of target ``tid``'s telemetry ``tel`` on the trajectory ``traj``, with
    the error spline ``e`` on ``axis``, a separate velocity error on ``w_axis`` (None:
    without) and time-tag delays if ``delays``; its error coefficients start at
    ``offset``. The white sigmas and ``e``'s prior start at the declared medians."""
    e0, e1 = axis.design(tel.time, 0), axis.design(tel.time, 1)
    i3 = sp.identity(3, format='csr')
    sig_p = float(np.median(tel.position_sigma))
    sig_v = float(np.median(tel.velocity_sigma))
    return TelemetryBlock(
        tid,
        tel.time,
        tel.position,
        tel.velocity,
        traj.world_design(tel.time, 0),
        traj.world_design(tel.time, 1),
        sp.kron(e0, i3, format='csr'),
        sp.kron(e1, i3, format='csr'),
        axis,
        offset,
        (sig_p, sig_p),
        [sig_p, sig_v],
        np.asarray(np.isfinite(tel.position).all(axis=1)),
        np.asarray(np.isfinite(tel.velocity).all(axis=1)),
        w_axis,
        None if w_axis is None else sp.kron(w_axis.design(tel.time, 0), i3, format='csr'),
        sig_p,
        traj.world_design(tel.time, 2) if delays else None,
    )


def shift_columns(mat: sp.spmatrix, offset: int, n: int) -> sp.csr_matrix:
    """``mat`` as rows of an ``n``-column matrix, its columns moved right by ``offset``."""
    coo = mat.tocoo()
    return sp.csr_matrix((coo.data, (coo.row, coo.col + offset)), shape=(coo.shape[0], n))
