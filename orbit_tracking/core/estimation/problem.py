"""The least-squares problem of one window (seed 000, eq. 7): the unknowns (spline
coefficients of every target, telemetry error splines, station biases), the whitened
measurement rows of stations, telemetry, fixes and the thrust constraint, and their sparse
Jacobian. :class:`Problem` evaluates residuals and Jacobians, tells which rows are
measurements (:data:`ROBUST_KINDS`, what a robust loss and the residual gate act on) and
gives the whitened residual of every unit the gate may reject (:meth:`Problem.gate_units`);
the solver is in :mod:`~orbit_tracking.core.estimation.gauss_newton`, the telemetry's rows
and error model in :mod:`~orbit_tracking.core.estimation.telemetry_block`."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.estimation.bspline import SplineAxis, SplineTrajectory
from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.knots import uniform_knots
from orbit_tracking.core.estimation.motion_rows import jerk_parts, thrust_normal
from orbit_tracking.core.estimation.telemetry_block import (
    VELOCITY_ERROR_PRIOR,
    TelemetryBlock,
    error_prior_matrix,
    shift_columns,
    telemetry_block,
    velocity_error_axis,
)
from orbit_tracking.core.models.measurements import StationPose, predict, residual
from orbit_tracking.core.models.systematic import CLOCK, BiasModel

__all__ = [
    'ROBUST_KINDS',
    'VELOCITY_ERROR_PRIOR',
    'GateKey',
    'GateUnits',
    'Problem',
    'Tag',
    'thrust_normal',
    'velocity_error_axis',
]

FloatArray = NDArray[np.float64]

GateKey = int | tuple[str, int]
"""Key of a block in :attr:`Problem.gated`: a station block's index, or
``('telemetry_position' | 'telemetry_velocity' | 'fix', target id)``."""

Tag = tuple[str, int, NDArray[np.bool_]]
"""What :meth:`Problem.evaluate` says about a run of its rows: kind, station block index or
target id, and the mask of the block's entries the rows come from (in order)."""

GateUnits = tuple[GateKey, str, FloatArray, NDArray[np.bool_]]
"""One block as the residual gate sees it: its key, its kind (one of
:data:`ROBUST_KINDS`), the whitened residual of each unit it may reject and which units
are measured (same shape)."""

ROBUST_KINDS: tuple[str, ...] = ('station', 'telemetry_position', 'telemetry_velocity', 'fix')
"""Kinds of rows that are measurements (a robust loss and the residual gate act on them);
the other rows (priors, the thrust constraint) are always taken at face value."""

_ROWS_PER_ENTRY = {
    'station': 1,
    'telemetry_position': 3,
    'telemetry_velocity': 3,
    'telemetry_prior': 1,
    'fix': 3,
    'thrust': 3,
    'bias_prior': 1,
    'jerk_prior': 1,
}


@dataclass
class _StationBlock:
    station: str
    target: int
    fields: tuple[str, ...]
    time: FloatArray
    values: FloatArray
    sigmas: FloatArray
    pose: StationPose
    pw: sp.csr_matrix  # (3m, n_t) world position design
    vw: sp.csr_matrix
    valid: NDArray[np.bool_]  # (m, k)
    bias_index: list[int] = field(default_factory=list)  # into Problem.biases
    clock: int | None = None  # position of the clock bias in bias_index
    tau: float = 0.0  # clock offset the designs pw, vw (and aw) are evaluated at
    aw: sp.csr_matrix | None = None  # acceleration design (clock Jacobian)
    # the sigmas as declared, and the factor per field they are used with (``sigmas =
    # declared * factor``): above 1 when the residuals show white noise larger than declared
    declared: FloatArray = field(default_factory=lambda: np.zeros((0, 0)))
    factor: FloatArray = field(default_factory=lambda: np.ones(0))
    # pw and vw per epoch as dense rows over the columns either touches (see _compact)
    compact: tuple[object, object, NDArray[np.intp], FloatArray, FloatArray] | None = None

    def __post_init__(self) -> None:
        self.declared = self.sigmas.copy()
        self.factor = np.ones(len(self.fields))

    def jacobian(
        self, hw: FloatArray, use: NDArray[np.bool_], offset: int, n: int
    ) -> sp.csr_matrix:
        """Rows ``d (whitened value) / d beta`` of the used (epoch, field) pairs: row
        ``(i, j)`` is ``sum_c hw[i, j, c] pw[3 i + c] + hw[i, j, 3 + c] vw[3 i + c]``, its
        columns moved right by ``offset`` in an ``n``-column matrix.

        The same numbers, and the same sparsity (exact zeros left out), as the sparse
        products ``_row_contract(hw[..., :3], pw) + _row_contract(hw[..., 3:], vw)`` with the
        rows selected and shifted (``shift_columns``), each term added in the same order;
        built from a dense (epochs, 3, touched columns) copy of the designs made once per
        design, without a sparse product per evaluation."""
        if (
            self.compact is None
            or self.compact[0] is not self.pw
            or self.compact[1] is not self.vw
        ):
            self.compact = (self.pw, self.vw, *_compact(self.pw, self.vw))
        _, _, cols, pd, vd = self.compact
        i, j = np.nonzero(use)
        hp, hv = hw[i, j, :3], hw[i, j, 3:]
        p, v = pd[i], vd[i]  # (rows, 3, w)
        pos = hp[:, 0, None] * p[:, 0] + hp[:, 1, None] * p[:, 1] + hp[:, 2, None] * p[:, 2]
        vel = hv[:, 0, None] * v[:, 0] + hv[:, 1, None] * v[:, 1] + hv[:, 2, None] * v[:, 2]
        data = pos + vel
        keep = data != 0
        counts = keep.sum(axis=1)
        indptr = np.zeros(i.size + 1, dtype=np.int64)
        np.cumsum(counts, out=indptr[1:])
        return sp.csr_matrix((data[keep], (cols[i] + offset)[keep], indptr), shape=(i.size, n))


def _compact(
    pw: sp.csr_matrix, vw: sp.csr_matrix
) -> tuple[NDArray[np.intp], FloatArray, FloatArray]:
    """For each epoch ``i`` the sorted columns rows ``3 i .. 3 i + 2`` of ``pw`` or ``vw``
    touch (padded with column 0 and zero values to the widest), and those rows' values
    there: ``cols`` (m, w), ``p``, ``v`` (m, 3, w)."""
    m = pw.shape[0] // 3
    touched = np.zeros((m, pw.shape[1]), dtype=bool)
    for d in (pw, vw):
        rows = np.repeat(np.arange(d.shape[0]), np.diff(d.indptr))
        touched[rows // 3, d.indices] = True
    counts = touched.sum(axis=1)
    w = int(counts.max()) if m else 0
    ti, tc = np.nonzero(touched)  # row-major: columns ascending within each epoch
    slot = np.arange(ti.size) - np.repeat(np.cumsum(counts) - counts, counts)
    cols = np.zeros((m, w), dtype=np.intp)
    cols[ti, slot] = tc
    out = []
    for d in (pw, vw):
        dense = d.toarray().reshape(m, 3, -1)
        vals = np.zeros((m, 3, w))
        vals[ti, :, slot] = dense[ti, :, tc]
        out.append(vals)
    return cols, out[0], out[1]


@dataclass
class _FixBlock:
    target: int
    time: FloatArray
    position: FloatArray
    whiten: FloatArray  # (m, 3, 3), W^T W = weight * inv(cov)
    pw: sp.csr_matrix
    valid: NDArray[np.bool_]


def _row_contract(h: FloatArray, design: sp.csr_matrix) -> sp.csr_matrix:
    """Rows ``sum_c h[i, j, c] design[3 i + c]`` for every (i, j): (m k, n)."""
    m, k, _ = h.shape
    indptr = np.arange(m * k + 1) * 3
    indices = (3 * np.arange(m)[:, None, None] + np.arange(3)[None, None, :]).repeat(k, axis=1)
    s = sp.csr_matrix((h.ravel(), indices.ravel(), indptr), shape=(m * k, 3 * m))
    return (s @ design).tocsr()


class Problem:
    def __init__(
        self,
        obs: Observations,
        solutions: dict[int, tuple[SplineTrajectory, FloatArray]],
        cfg: EstimatorConfig,
        t0: float,
        t1: float,
        tel_axes: Mapping[int, SplineAxis] | None = None,
        tel_separate: Mapping[int, bool] | None = None,
        tel_events: Mapping[int, Sequence[float]] | None = None,
        tel_delays: Mapping[int, bool] | None = None,
    ) -> None:
        self.cfg = cfg
        # the telemetry error may bend where the acceleration jumps (an error proportional
        # to the state: a time-tag skew, a scale factor)
        self.tel_events = dict(tel_events or {})
        self.offsets: dict[int, int] = {}
        n = 0
        for tid, (traj, _) in solutions.items():
            self.offsets[tid] = n
            n += traj.n_coef
        self.trajs = {tid: s[0] for tid, s in solutions.items()}
        self.origin = {tid: tr.origin for tid, tr in self.trajs.items()}
        self.stations: list[_StationBlock] = []
        picks = [
            (s, tid, np.flatnonzero(s.table.target_id == tid))
            for s in obs.stations
            for tid in self.trajs
        ]
        picks = [(s, tid, idx) for s, tid, idx in picks if idx.size]
        # one design per target and derivative for the epochs of all its stations (a row
        # depends on its epoch alone), cut into the stations' blocks
        designs = {}
        for tid, traj in self.trajs.items():
            parts = [s.table.time[idx] for s, k, idx in picks if k == tid]
            t_all = np.concatenate(parts) if parts else np.zeros(0)
            if t_all.size:
                designs[tid] = (traj.world_design(t_all, 0), traj.world_design(t_all, 1))
        start = dict.fromkeys(self.trajs, 0)
        for s, tid, idx in picks:
            tab = s.table
            r0, r1 = start[tid], start[tid] + idx.size
            start[tid] = r1
            valid = np.isfinite(tab.values[idx]) & (tab.sigmas[idx] > 0)
            self.stations.append(
                _StationBlock(
                    tab.station_id,
                    tid,
                    tab.fields,
                    tab.time[idx],
                    tab.values[idx],
                    tab.sigmas[idx],
                    s.pose.take(idx),
                    designs[tid][0][3 * r0 : 3 * r1],
                    designs[tid][1][3 * r0 : 3 * r1],
                    valid,
                )
            )
        self.telemetry: list[TelemetryBlock] = []
        if cfg.use_telemetry:
            for tid, tel in obs.telemetry.items():
                if tid not in self.trajs or len(tel) < 4:
                    continue
                if tel_axes and tid in tel_axes:
                    axis = tel_axes[tid]
                else:
                    knots = uniform_knots(t0, t1, cfg.telemetry_error_spacing, degree=3)
                    axis = SplineAxis.from_interior(knots, t0, t1, 3)
                separate = (
                    tel_separate.get(tid, False)
                    if tel_separate is not None
                    else cfg.telemetry_velocity_error == 'separate'
                )
                delays = (
                    tel_delays.get(tid, False)
                    if tel_delays is not None
                    else cfg.telemetry_delays == 'on'
                )
                w_axis = (
                    velocity_error_axis(t0, t1, cfg, self.tel_events.get(tid, ()))
                    if separate
                    else None
                )
                self.telemetry.append(
                    telemetry_block(tid, tel, self.trajs[tid], axis, n, w_axis, delays)
                )
                n += self.telemetry[-1].n_error
        self.fixes: list[_FixBlock] = []
        if cfg.fix_weight > 0.0:
            for tid, fx in obs.fixes.items():
                if tid not in self.trajs or not len(fx):
                    continue
                inv = np.linalg.inv(fx.covariance) * cfg.fix_weight
                w = np.transpose(np.linalg.cholesky(inv), (0, 2, 1))
                self.fixes.append(
                    _FixBlock(
                        tid,
                        fx.time,
                        fx.position,
                        w,
                        self.trajs[tid].world_design(fx.time, 0),
                        np.asarray(np.isfinite(fx.position).all(axis=1)),
                    )
                )
        # the white-jerk prior: per target and part (key (tid, near_events)), rows M with
        # |M c|^2 = int |p'''|^2 dt over the part, and its density q (None until the
        # first solve has estimated it: no rows before)
        self.jerk: dict[tuple[int, bool], FloatArray] = {}
        self.jerk_q: dict[tuple[int, bool], float | None] = {}
        if cfg.jerk_prior:
            for tid, traj in self.trajs.items():
                jerk_part = jerk_parts(traj, t0, t1, cfg.jerk_grid)
                for near, mj in zip((False, True), jerk_part, strict=True):
                    if mj.shape[0] or not near:
                        self.jerk[tid, near] = mj
                        self.jerk_q[tid, near] = None
        # the thrust-along-velocity constraint: designs on a grid per target
        self.dynamics: list[tuple[int, sp.csr_matrix, sp.csr_matrix, sp.csr_matrix]] = []
        if cfg.thrust_along_velocity > 0.0:
            for tid, traj in self.trajs.items():
                tg = np.arange(t0 + 0.5 * cfg.thrust_grid, t1, cfg.thrust_grid)
                self.dynamics.append((tid, *(traj.world_design(tg, nu) for nu in (0, 1, 2))))
        present = {b.station for b in self.stations}
        self.biases = [bp for bp in cfg.biases if bp.station in present]
        for b in self.stations:
            b.bias_index = [q for q, bp in enumerate(self.biases) if bp.station == b.station]
            names = [self.biases[q].name for q in b.bias_index]
            b.clock = names.index(CLOCK) if CLOCK in names else None
        self.bias_offset = n
        n += len(self.biases)
        # prior sigma of each bias; a frozen or known bias gets a vanishing one
        self.bias_sigma = np.array(
            [bp.sigma if bp.estimate else bp.sigma * 1e-9 for bp in self.biases], dtype=float
        )
        self.bias_prior = np.array([bp.prior for bp in self.biases], dtype=float)
        self.bias_status = ['estimated' if bp.estimate else 'known' for bp in self.biases]
        self.bias_lower = np.array([bp.bounds[0] for bp in self.biases], dtype=float)
        self.bias_upper = np.array([bp.bounds[1] for bp in self.biases], dtype=float)
        self.n = n
        # units the residual gate rejected: station values (m, k), telemetry and fix epochs (m,)
        self.gated: dict[GateKey, NDArray[np.bool_]] = {}
        self.gate_refused = 0.0
        self.rows: list[tuple[int, FloatArray, FloatArray, FloatArray, bool]] = []

    # -- evaluation ------------------------------------------------------------------

    def predict_block(
        self, bi: int, beta: FloatArray, jacobian: bool = False
    ) -> tuple[FloatArray, FloatArray | None, FloatArray | None]:
        """Measured values predicted for station block ``bi`` (biases applied), with
        ``d/d state`` (m, k, 6) and ``d/d biases`` (m, k, p) of the block's biases."""
        b = self.stations[bi]
        coef = self._coef(beta, b.target)
        idx = self.bias_offset + np.asarray(b.bias_index, dtype=int)
        if b.clock is not None:
            self._clock_designs(b, float(beta[idx[b.clock]]))
        m = b.time.size
        p = (b.pw @ coef).reshape(m, 3) + self.origin[b.target]
        v = (b.vw @ coef).reshape(m, 3)
        true, h = predict(b.fields, np.hstack([p, v]), b.pose, jacobian=jacobian)
        if not b.bias_index:
            return true, h, None
        names = [self.biases[q].name for q in b.bias_index]
        keep = [j for j, name in enumerate(names) if name != CLOCK]
        values = beta[idx]
        model = BiasModel({names[j]: float(values[j]) for j in keep})
        measured = model.apply(b.fields, true)
        if not jacobian or h is None:
            return measured, None, None
        d_true, d_value = model.jacobian(b.fields, true, [names[j] for j in keep])
        h_meas = np.einsum('mkj,mjs->mks', d_true, h)
        d_param = np.zeros((m, len(b.fields), len(names)))
        d_param[:, :, keep] = d_value
        if b.clock is not None:
            # the row tagged t measured the target at t + clock: d/d clock = H [v; a]
            assert b.aw is not None
            a = (b.aw @ coef).reshape(m, 3)
            d_param[:, :, b.clock] = np.einsum('mks,ms->mk', h_meas, np.hstack([v, a]))
        return measured, h_meas, d_param

    def _clock_designs(self, b: _StationBlock, tau: float) -> None:
        """Designs of a block at its rows' true epochs ``t + tau`` (rebuilt when the
        clock estimate moves)."""
        if b.aw is not None and tau == b.tau:
            return
        traj = self.trajs[b.target]
        t = np.clip(b.time + tau, traj.t0, traj.t1)  # a row at the edge stays on it
        b.pw, b.vw, b.aw = (traj.world_design(t, nu) for nu in (0, 1, 2))
        b.tau = tau

    def project(self, beta: FloatArray) -> FloatArray:
        """``beta`` with every bias clipped into its declared bounds."""
        if self.biases:
            sl = slice(self.bias_offset, self.bias_offset + len(self.biases))
            beta[sl] = np.clip(beta[sl], self.bias_lower, self.bias_upper)
        return beta

    def _coef(self, beta: FloatArray, tid: int) -> FloatArray:
        o = self.offsets[tid]
        return beta[o : o + self.trajs[tid].n_coef]

    def evaluate(
        self, beta: FloatArray, jacobian: bool
    ) -> tuple[FloatArray, sp.csr_matrix | None, list[Tag]]:
        """Whitened residuals of the rows not gated (and Jacobian of the model,
        ``d F / d beta``), with the :data:`Tag` of each run of rows."""
        res: list[FloatArray] = []
        jac: list[sp.csr_matrix] = []
        tags: list[Tag] = []
        # per residual row: target, time, dF/dp and dF/dv (whitened), for the knot test
        rows: list[tuple[int, FloatArray, FloatArray, FloatArray, bool]] = []
        for bi, b in enumerate(self.stations):
            pred, h, dpar = self.predict_block(bi, beta, jacobian)
            with np.errstate(over='ignore', invalid='ignore'):  # only in rows not used
                r = residual(b.fields, np.nan_to_num(b.values), pred) / b.sigmas
            use = b.valid & ~self.gated.get(bi, np.zeros_like(b.valid))
            res.append(r[use])
            tags.append(('station', bi, use))
            if jacobian:
                assert h is not None
                hw = h / b.sigmas[:, :, None]
                jm = b.jacobian(hw, use, self.offsets[b.target], self.n)
                if dpar is not None:
                    dw = (dpar / b.sigmas[:, :, None])[use]  # (rows, p)
                    cols = self.bias_offset + np.asarray(b.bias_index)
                    rr, cc = np.nonzero(dw)
                    jm = jm + sp.csr_matrix(
                        (dw[rr, cc], (rr, cols[cc])), shape=(dw.shape[0], self.n)
                    )
                jac.append(jm)
                tt = np.broadcast_to(b.time[:, None], use.shape)[use]
                rows.append((b.target, tt, hw[:, :, :3][use], hw[:, :, 3:][use], False))
        for tb in self.telemetry:
            ecoef = beta[tb.offset : tb.offset + tb.n_error]
            dp, dv = self.telemetry_residuals(tb, beta)
            sp_, sv_ = tb.noise
            use_p, use_v = self.telemetry_use(tb)
            rp = dp[use_p].ravel() / sp_
            rv = dv[use_v].ravel() / sv_
            prior_m = error_prior_matrix(tb)
            prior = prior_m @ ecoef
            res.extend([rp, rv, -prior])
            tags.append(('telemetry_position', tb.target, use_p))
            tags.append(('telemetry_velocity', tb.target, use_v))
            tags.append(('telemetry_prior', tb.target, np.ones(prior.size, dtype=bool)))
            if jacobian:
                rows_p = np.flatnonzero(np.repeat(use_p, 3))
                rows_v = np.flatnonzero(np.repeat(use_v, 3))
                jp, jv = tb.jacobians(
                    self._coef(beta, tb.target),
                    beta,
                    rows_p,
                    rows_v,
                    self.offsets[tb.target],
                    self.n,
                )
                jac.extend([jp / sp_, jv / sv_])
                # the prior rows are 0 - M e: their model M e has derivative M
                jac.append(shift_columns(prior_m, tb.offset, self.n))
                eye = np.eye(3)
                for valid, sig, vel in ((use_p, sp_, False), (use_v, sv_, True)):
                    nv = int(valid.sum())
                    unit = np.tile(eye / sig, (nv, 1))
                    zero = np.zeros_like(unit)
                    tt = np.repeat(tb.time[valid], 3)
                    rows.append(
                        (tb.target, tt, zero if vel else unit, unit if vel else zero, True)
                    )
                z = np.zeros((prior.size, 3))
                rows.append((-1, np.zeros(prior.size), z, z, False))
        for fb in self.fixes:
            use = fb.valid & ~self.gated.get(('fix', fb.target), np.zeros_like(fb.valid))
            r = self._fix_residuals(fb, beta)[use].ravel()
            res.append(r)
            tags.append(('fix', fb.target, use))
            if jacobian:
                wblk = sp.block_diag(list(fb.whiten), format='csr')
                jm = (wblk @ fb.pw)[np.flatnonzero(np.repeat(use, 3))]
                jac.append(shift_columns(jm, self.offsets[fb.target], self.n))
                wv = fb.whiten[use].reshape(-1, 3)
                tt = np.repeat(fb.time[use], 3)
                rows.append((fb.target, tt, wv, np.zeros_like(wv), False))
        for tid, dp, dv, da in self.dynamics:
            coef = self._coef(beta, tid)
            c, jp, jv, ja = thrust_normal(
                (dp @ coef).reshape(-1, 3) + self.origin[tid],
                (dv @ coef).reshape(-1, 3),
                (da @ coef).reshape(-1, 3),
                self.cfg.gm,
                jacobian,
            )
            sig = self.cfg.thrust_along_velocity
            res.append(-c.ravel() / sig)
            tags.append(('thrust', tid, np.ones(c.shape[0], dtype=bool)))
            if jacobian:
                jm = (
                    _row_contract(jp / sig, dp)
                    + _row_contract(jv / sig, dv)
                    + _row_contract(ja / sig, da)
                )
                jac.append(shift_columns(jm, self.offsets[tid], self.n))
                z = np.zeros((c.size, 3))
                rows.append((-1, np.zeros(c.size), z, z, False))
        for (tid, near), mj in self.jerk.items():
            qj = self.jerk_q[tid, near]
            if qj is None or not mj.shape[0]:
                continue
            w = 1.0 / math.sqrt(qj)
            res.append(-w * (mj @ self._coef(beta, tid)))
            tags.append(('jerk_prior', tid, np.ones(mj.shape[0], dtype=bool)))
            if jacobian:
                jac.append(shift_columns(sp.csr_matrix(w * mj), self.offsets[tid], self.n))
                z = np.zeros((mj.shape[0], 3))
                rows.append((-1, np.zeros(mj.shape[0]), z, z, False))
        if self.biases:
            bvals = beta[self.bias_offset : self.bias_offset + len(self.biases)]
            res.append((self.bias_prior - bvals) / self.bias_sigma)
            tags.append(('bias_prior', -1, np.ones(len(self.biases), dtype=bool)))
            if jacobian:
                q = np.arange(len(self.biases))
                jac.append(
                    sp.csr_matrix(
                        (1.0 / self.bias_sigma, (q, self.bias_offset + q)),
                        shape=(q.size, self.n),
                    )
                )
                z = np.zeros((q.size, 3))
                rows.append((-1, np.zeros(q.size), z, z, False))
        r_all = np.concatenate(res) if res else np.zeros(0)
        j_all = sp.vstack(jac).tocsr() if jacobian and jac else None
        if jacobian:
            self.rows = rows
        return r_all, j_all, tags

    def cost(self, beta: FloatArray) -> float:
        r, _, _ = self.evaluate(beta, False)
        return float(r @ r)

    # -- what the robust loss and the residual gate act on ------------------------------

    def telemetry_residuals(
        self, tb: TelemetryBlock, beta: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Telemetry position and velocity minus the model (trajectory plus telemetry
        error), (m, 3) each, not whitened (rows not measured hold garbage)."""
        pred_p, pred_v = tb.predict(self._coef(beta, tb.target), beta, self.origin[tb.target])
        return np.nan_to_num(tb.position) - pred_p, np.nan_to_num(tb.velocity) - pred_v

    def telemetry_use(self, tb: TelemetryBlock) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
        """Telemetry epochs whose position and velocity are measured and not gated."""
        gp = self.gated.get(('telemetry_position', tb.target))
        gv = self.gated.get(('telemetry_velocity', tb.target))
        return (
            tb.valid_p if gp is None else tb.valid_p & ~gp,
            tb.valid_v if gv is None else tb.valid_v & ~gv,
        )

    def _fix_residuals(self, fb: _FixBlock, beta: FloatArray) -> FloatArray:
        coef = self._coef(beta, fb.target)
        m = fb.time.size
        d = fb.position - (fb.pw @ coef).reshape(m, 3) - self.origin[fb.target]
        return np.asarray(np.einsum('mij,mj->mi', fb.whiten, d))

    def gate_units(self, beta: FloatArray) -> list[GateUnits]:
        """Every block the residual gate may reject from, with the whitened residual of
        each unit: a station's single value, or the largest whitened component of a
        telemetry position, telemetry velocity or fix epoch (rejected as a whole). A
        residual that is not finite stays so (NaN, inf)."""
        out: list[GateUnits] = []
        with np.errstate(over='ignore', invalid='ignore'):
            for bi, b in enumerate(self.stations):
                pred, _, _ = self.predict_block(bi, beta)
                r = residual(b.fields, np.nan_to_num(b.values), pred) / b.sigmas
                out.append((bi, 'station', r, b.valid))
            for tb in self.telemetry:
                dp, dv = self.telemetry_residuals(tb, beta)
                for kind, d, sig, valid in (
                    ('telemetry_position', dp, tb.noise[0], tb.valid_p),
                    ('telemetry_velocity', dv, tb.noise[1], tb.valid_v),
                ):
                    out.append(((kind, tb.target), kind, _largest(d / sig), valid))
            for fb in self.fixes:
                w = self._fix_residuals(fb, beta)
                out.append((('fix', fb.target), 'fix', _largest(w), fb.valid))
        return out

    @staticmethod
    def row_kinds(tags: Sequence[Tag]) -> NDArray[np.int_]:
        """For every row :meth:`evaluate` returned with ``tags``: the index of its kind in
        :data:`ROBUST_KINDS`, or -1 for a row that is not a measurement."""
        parts = []
        for kind, _, mask in tags:
            n = int(np.count_nonzero(mask)) * _ROWS_PER_ENTRY[kind]
            k = ROBUST_KINDS.index(kind) if kind in ROBUST_KINDS else -1
            parts.append(np.full(n, k, dtype=int))
        return np.concatenate(parts) if parts else np.zeros(0, dtype=int)


def _largest(r: FloatArray) -> FloatArray:
    """Largest absolute component per row of (m, 3); NaN if any component is NaN."""
    return np.asarray(np.max(np.abs(r), axis=1))
