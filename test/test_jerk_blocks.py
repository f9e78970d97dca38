"""The white-jerk prior per block of the window (``motion_rows.jerk_rows`` with a block
length, ``priors.block_factors``): the blocks' rows add up to the window's penalty, and the
block test raises the density only where the data show a jerk the prior flattens."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from orbit_tracking.core.estimation.bspline import SplineAxis, SplineTrajectory
from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.motion_rows import JERK_EVENT_MARGIN, jerk_rows
from orbit_tracking.core.estimation.priors import JERK_BLOCK_REACH, block_factors

SIGMA = 0.05  # m, position noise per axis
RATE = 20.0  # Hz
SPAN = 40.0  # s
BLOCK = 4.0  # s


def _trajectory(events: tuple[float, ...] = ()) -> SplineTrajectory:
    interior = np.sort(np.concatenate([np.arange(0.5, SPAN, 0.5), np.repeat(events, 3)]))
    ax = SplineAxis.from_interior(interior, 0.0, SPAN, 4)
    c, s = np.cos(0.4), np.sin(0.4)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return SplineTrajectory((ax, ax, ax), np.zeros(3), rot)


def test_the_blocks_rows_add_up_to_the_windows_penalty() -> None:
    traj = _trajectory(events=(17.3,))
    whole = jerk_rows(traj, 0.0, SPAN, 0.25)
    blocks = jerk_rows(traj, 0.0, SPAN, 0.25, BLOCK)
    assert whole.n_blocks == 1 and not whole.block.any()
    assert blocks.n_blocks == int(SPAN / BLOCK)
    assert blocks.rank == whole.rank
    pw = whole.rows.T @ whole.rows
    pb = blocks.rows.T @ blocks.rows
    assert np.allclose(pb, pw, rtol=1e-9, atol=1e-9 * np.abs(pw).max())
    # a row touches only the coefficients under its block; the block holding the event's
    # margin on both sides of 17.3 s (16-20 s) keeps rows only from 16 s to its margin
    for b in range(blocks.n_blocks):
        t = np.arange(b * BLOCK, (b + 1) * BLOCK, 0.01)
        t = t[np.abs(t - 17.3) > JERK_EVENT_MARGIN]
        under = np.flatnonzero(np.abs(traj.world_design(t, 3).toarray()).sum(axis=0))
        rows = blocks.rows[blocks.block == b]
        touched = np.flatnonzero(np.abs(rows).sum(axis=0))
        assert set(touched) <= set(under), b


def _posterior(jump: np.ndarray, t_jump: float, q: float, seed: int):
    """The linear fit of noisy positions of a path whose acceleration jumps by ``jump`` at
    ``t_jump`` (no knot there), with the white-jerk prior of density ``q`` in blocks; its
    rows, covariance and solution, and the error and sigma of the fitted positions."""
    traj = _trajectory()
    t = np.arange(0.0, SPAN + 1e-9, 1.0 / RATE)
    truth = np.column_stack([150.0 * t + 1.0 * t**2, -40.0 * t + 0.2 * t**2, 3.0 * t])
    truth = truth + 0.5 * np.maximum(t - t_jump, 0.0)[:, None] ** 2 * jump[None, :]
    rng = np.random.default_rng(seed)
    y = truth + SIGMA * rng.standard_normal(truth.shape)
    design = traj.world_design(t, 0).toarray() / SIGMA
    jr = jerk_rows(traj, 0.0, SPAN, 0.25, BLOCK)

    def fit(scale: np.ndarray):
        w = (1.0 / np.sqrt(q * scale[jr.block]))[:, None] * jr.rows
        cov = np.linalg.inv(design.T @ design + w.T @ w)
        x = cov @ (design.T @ (y.reshape(-1) / SIGMA))
        return cov, x

    return traj, t, truth, jr, fit


def _worst_mahalanobis(traj, t, truth, cov, x) -> float:
    d = traj.world_design(t, 0).toarray()
    err = (d @ x).reshape(-1, 3) - truth
    dc = (d @ cov).reshape(t.size, 3, -1)
    cm = np.einsum('kin,kjn->kij', dc, d.reshape(t.size, 3, -1))
    return float(np.sqrt(np.einsum('ki,kij,kj->k', err, np.linalg.inv(cm), err)).max())


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_a_jump_no_knot_marks_raises_the_blocks_around_it_and_no_others(seed: int) -> None:
    q, t_jump = 0.01, 21.3
    traj, t, truth, jr, fit = _posterior(np.array([6.0, -4.0, 3.0]), t_jump, q, seed)
    threshold = float(chi2.isf(2.0 * EstimatorConfig().jerk_block_alpha, 1))
    scale = np.ones(jr.n_blocks)
    cov, x = fit(scale)
    before = _worst_mahalanobis(traj, t, truth, cov, x)
    for _ in range(6):  # to the fixed point, as the estimator does
        new = block_factors(jr, 1.0 / np.sqrt(q * scale[jr.block]), scale, cov, x, threshold)
        if np.array_equal(new, scale):
            break
        scale = new
        cov, x = fit(scale)
    home = int(t_jump // BLOCK)
    raised = set(np.flatnonzero(scale > 1.0).tolist())
    assert home in raised
    assert raised <= set(range(home - 2 * JERK_BLOCK_REACH, home + 2 * JERK_BLOCK_REACH + 1))
    after = _worst_mahalanobis(traj, t, truth, cov, x)
    # without any prior the knots (0.5 s apart, none at the jump) leave their own
    # representation error; the raised prior comes close to that, the flat one is far off
    free = _worst_mahalanobis(traj, t, truth, *fit(np.full(jr.n_blocks, 1e8)))
    assert before > 4.0 * free
    assert after < 1.5 * free


def test_without_a_jump_no_block_is_raised() -> None:
    q = 0.01
    threshold = float(chi2.isf(2.0 * EstimatorConfig().jerk_block_alpha, 1))
    raised = 0
    for seed in range(5):
        _, _, _, jr, fit = _posterior(np.zeros(3), 0.0, q, seed)
        scale = np.ones(jr.n_blocks)
        cov, x = fit(scale)
        new = block_factors(jr, 1.0 / np.sqrt(q * scale[jr.block]), scale, cov, x, threshold)
        raised += int(np.count_nonzero(new > 1.0))
    assert raised == 0
