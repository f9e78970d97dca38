"""The cost of seed 003's adjoint assimilation and its gradient (:mod:`.adjoint` states
the equations): whitened residuals of the raw measurements, bias prior rows and the
optional smoothness prior; the gradient by the costate (adjoint) integration, and the
Gauss-Newton Jacobian by the forward sensitivities (for the preconditioner and the
covariance, and as an independent check of the adjoint gradient)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.dynamics.fit import _Group, _Problem
from orbit_tracking.core.dynamics.rocket import FlightError, RocketModel
from orbit_tracking.core.dynamics.thrust_spline import ThrustSplineModel
from orbit_tracking.core.models.measurements import predict, residual
from orbit_tracking.core.models.systematic import BiasModel, BiasParameter

__all__ = ['AdjointProblem']

FloatArray = NDArray[np.float64]


def _rows(
    g: _Group, x: FloatArray, bm: BiasModel, names: Sequence[str], deriv: bool
) -> tuple[FloatArray, FloatArray | None, FloatArray | None]:
    """Whitened residual (n, k) of one group (0 where not kept), and its derivatives by the
    state (n, k, 6) and by the group's station biases ``names`` (n, k, q)."""
    h, dh = predict(g.fields, x, g.pose, jacobian=deriv)
    r = residual(g.fields, g.values, bm.apply(g.fields, h)) / g.sigmas
    r = np.where(g.keep, r, 0.0)
    if not deriv:
        return r, None, None
    assert dh is not None
    d_true, d_param = bm.jacobian(g.fields, h, names)
    mask = np.where(g.keep, 1.0 / np.where(g.keep, g.sigmas, 1.0), 0.0)[:, :, None]
    return r, -np.einsum('mab,mbc->mac', d_true, dh) * mask, -d_param * mask


class AdjointProblem:
    """The cost ``J(p)``, ``p = [theta of each target..., estimated biases...]``, with its
    adjoint gradient and Gauss-Newton Jacobian (see the module docstring).

    Raises
    ------
    ValueError
        A target measured before its model's epoch or after its control span.
    """

    def __init__(
        self,
        obs: Observations,
        models: Mapping[int, ThrustSplineModel],
        biases: Sequence[BiasParameter] = (),
        smoothness_sigma: float | None = None,
    ) -> None:
        # the rocket problem's grouping of the rows (the models there only name targets)
        base = _Problem(obs, {t: RocketModel(m.epoch) for t, m in models.items()}, biases)
        self.models = dict(models)
        self.tids, self.groups, self.times = base.tids, base.groups, base.times
        self.biases, self.free = base.biases, base.free
        sizes = [self.models[t].n_parameters for t in self.tids]
        self.offsets = dict(zip(self.tids, np.cumsum([0, *sizes[:-1]]).tolist(), strict=True))
        self.n_traj = int(sum(sizes))
        self.n = self.n_traj + len(self.free)
        for tid in self.tids:
            c, tt = self.models[tid].control, self.times[tid]
            if tt[0] < c.t0 - 1e-9 or tt[-1] > c.t1 + 1e-9:
                raise ValueError(
                    f'target {tid} is measured over [{tt[0]:.3f}, {tt[-1]:.3f}] s, outside its '
                    f'model span [{c.t0:.3f}, {c.t1:.3f}] s (the epoch must not follow the '
                    'first measurement)'
                )
        self.smooth = np.zeros((0, self.n))
        if smoothness_sigma is not None:
            blocks = []
            for tid in self.tids:
                ctl = self.models[tid].control
                d2 = np.diff(np.eye(ctl.n_coef), 2, axis=0)
                blk = np.zeros((d2.shape[0] * ctl.components, self.n))
                col = self.offsets[tid] + 6
                blk[:, col : col + ctl.n_parameters] = np.kron(d2, np.eye(ctl.components))
                blocks.append(blk / smoothness_sigma)
            self.smooth = np.vstack(blocks)

    def theta(self, p: FloatArray, tid: int) -> FloatArray:
        k = self.offsets[tid]
        return p[k : k + self.models[tid].n_parameters]

    def _biases(self, p: FloatArray) -> tuple[dict[str, BiasModel], dict[str, list[int]]]:
        vals: dict[str, dict[str, float]] = {}
        cols: dict[str, list[int]] = {}
        free = dict(zip(self.free, p[self.n_traj :], strict=True))
        for i, b in enumerate(self.biases):
            vals.setdefault(b.station, {})[b.name] = float(free.get(i, b.prior))
        for j, i in enumerate(self.free):
            cols.setdefault(self.biases[i].station, []).append(j)
        return {s: BiasModel(v) for s, v in vals.items()}, cols

    def bias_values(self, p: FloatArray) -> FloatArray:
        free = dict(zip(self.free, p[self.n_traj :], strict=True))
        return np.array([free.get(i, b.prior) for i, b in enumerate(self.biases)])

    def _prior(self, p: FloatArray) -> FloatArray:
        b = [self.biases[i] for i in self.free]
        return np.array([(p[self.n_traj + j] - x.prior) / x.sigma for j, x in enumerate(b)])

    def residuals(self, p: FloatArray) -> list[FloatArray]:
        """Whitened residual (n, k) of every group at ``p`` (NaN where not kept)."""
        bm, _ = self._biases(p)
        out = []
        states = {t: self.models[t].forward(self.theta(p, t))(self.times[t]) for t in self.tids}
        for g in self.groups:
            x = states[g.target][np.searchsorted(self.times[g.target], g.time), :6]
            r, _, _ = _rows(g, x, bm.get(g.station, BiasModel()), (), False)
            out.append(np.where(g.keep, r, np.nan))
        return out

    def cost(self, p: ArrayLike) -> float:
        """``J(p)`` (infinite where the model cannot fly ``p``)."""
        pp = np.asarray(p, dtype=np.float64)
        try:
            res = self.residuals(pp)
        except FlightError:
            return math.inf
        data = sum(float(np.nansum(r**2)) for r in res)
        prior, smooth = self._prior(pp), self.smooth @ pp
        return 0.5 * (data + float(prior @ prior) + float(smooth @ smooth))

    def gradient(self, p: ArrayLike) -> tuple[float, FloatArray]:
        """``J(p)`` and ``dJ/dp`` (n,) by the adjoint method (forward state, backward
        costate with jumps at the epochs, quadrature of ``G^T lambda_v``)."""
        pp = np.asarray(p, dtype=np.float64)
        bm, cols = self._biases(pp)
        flights = {t: self.models[t].forward(self.theta(pp, t)) for t in self.tids}
        states = {t: flights[t](self.times[t])[:, :6] for t in self.tids}
        jumps = {t: np.zeros((self.times[t].size, 6)) for t in self.tids}
        grad = np.zeros(self.n)
        total = 0.0
        for g in self.groups:
            idx = np.searchsorted(self.times[g.target], g.time)
            names = [self.biases[self.free[j]].name for j in cols.get(g.station, [])]
            r, dx, db = _rows(
                g, states[g.target][idx], bm.get(g.station, BiasModel()), names, True
            )
            assert dx is not None and db is not None
            total += float(np.sum(r**2))
            np.add.at(jumps[g.target], idx, np.einsum('mk,mkj->mj', r, dx))
            if names:
                grad[[self.n_traj + j for j in cols[g.station]]] += np.einsum('mk,mkq->q', r, db)
        for tid in self.tids:
            th = self.theta(pp, tid)
            lam0, gc = self.models[tid].costate(th, flights[tid], self.times[tid], jumps[tid])
            k = self.offsets[tid]
            grad[k : k + th.size] += np.concatenate([lam0, gc])
        prior, smooth = self._prior(pp), self.smooth @ pp
        grad[self.n_traj :] += prior / np.array([self.biases[i].sigma for i in self.free])
        grad += self.smooth.T @ smooth
        return 0.5 * (total + float(prior @ prior) + float(smooth @ smooth)), grad

    def jacobian(self, p: FloatArray) -> tuple[FloatArray, FloatArray, int]:
        """Residual vector (kept values, bias prior rows, smoothness rows), its Jacobian
        (rows, n) from the forward sensitivities, and the number of measurement rows."""
        bm, cols = self._biases(p)
        fl = {t: self.models[t].propagate(self.theta(p, t), self.times[t]) for t in self.tids}
        res, blocks = [], []
        for g in self.groups:
            f = fl[g.target]
            assert f.sensitivity is not None
            idx = np.searchsorted(self.times[g.target], g.time)
            names = [self.biases[self.free[j]].name for j in cols.get(g.station, [])]
            r, dx, db = _rows(g, f.state[idx], bm.get(g.station, BiasModel()), names, True)
            assert dx is not None and db is not None
            blk = np.zeros((g.time.size, len(g.fields), self.n))
            k, n_p = self.offsets[g.target], self.models[g.target].n_parameters
            blk[:, :, k : k + n_p] = np.einsum('mkj,mjp->mkp', dx, f.sensitivity[idx])
            if names:
                blk[:, :, [self.n_traj + j for j in cols[g.station]]] = db
            res.append(r[g.keep])
            blocks.append(blk[g.keep])
        prior_rows = np.zeros((len(self.free), self.n))
        for j, i in enumerate(self.free):
            prior_rows[j, self.n_traj + j] = 1.0 / self.biases[i].sigma
        n_data = int(sum(r.size for r in res))
        vec = np.concatenate([*res, self._prior(p), self.smooth @ p])
        return vec, np.vstack([*blocks, prior_rows, self.smooth]), n_data
