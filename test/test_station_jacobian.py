"""The station rows of the Gauss-Newton Jacobian (``_StationBlock.jacobian``) against the
sparse products they replace: the same numbers to the last bit and the same sparsity; and
the normal matrix built from such a Jacobian (``scaling.normal_matrix``) against the
sparse product it replaces."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from orbit_tracking.core.estimation.bspline import SplineAxis, SplineTrajectory
from orbit_tracking.core.estimation.problem import _row_contract, _StationBlock
from orbit_tracking.core.estimation.scaling import normal_matrix
from orbit_tracking.core.estimation.telemetry_block import shift_columns


def _axis(rng: np.random.Generator, n: int, degree: int = 3) -> SplineAxis:
    inner = np.sort(rng.uniform(0.0, 60.0, n))
    return SplineAxis(np.concatenate([[0.0] * (degree + 1), inner, [60.0] * (degree + 1)]), degree)


def _block(rng: np.random.Generator, rotation: np.ndarray, m: int, k: int) -> _StationBlock:
    traj = SplineTrajectory((_axis(rng, 9), _axis(rng, 14), _axis(rng, 5)), np.zeros(3), rotation)
    t = np.sort(rng.uniform(0.0, 60.0, m))
    t[:3] = [0.0, 0.0, 60.0]  # the ends and a repeated epoch
    return _StationBlock(
        station='s',
        target=0,
        fields=('range',) * k,
        time=t,
        values=np.zeros((m, k)),
        sigmas=np.ones((m, k)),
        pose=None,  # type: ignore[arg-type]
        pw=traj.world_design(t, 0),
        vw=traj.world_design(t, 1),
        valid=np.ones((m, k), dtype=bool),
    )


@pytest.mark.parametrize(
    'rotation',
    [
        np.eye(3),
        Rotation.from_euler('z', 90, degrees=True).as_matrix(),
        Rotation.random(random_state=3).as_matrix(),
    ],
    ids=['identity', 'axis_swap', 'general'],
)
@pytest.mark.parametrize('k', [1, 3])
def test_station_rows_equal_the_sparse_products_bit_for_bit(rotation: np.ndarray, k: int) -> None:
    rng = np.random.default_rng(k)
    b = _block(rng, rotation, 300, k)
    hw = rng.normal(size=(300, k, 6)) * 10.0 ** rng.integers(-8, 8, size=(300, k, 6))
    hw[5, 0, :] = 0.0  # a row of zeros
    hw[6, 0, :3] = 0.0  # a row with only a velocity part
    use = rng.random((300, k)) > 0.2
    offset, n = 7, 7 + b.pw.shape[1] + 4
    want = _row_contract(hw[:, :, :3], b.pw) + _row_contract(hw[:, :, 3:], b.vw)
    want = shift_columns(want[np.flatnonzero(use.ravel())], offset, n)
    for _ in range(2):  # again from the kept dense copy
        got = b.jacobian(hw, use, offset, n)
        assert got.shape == want.shape
        np.testing.assert_array_equal(got.indptr, want.indptr)
        np.testing.assert_array_equal(got.indices, want.indices)
        assert got.data.tobytes() == want.data.tobytes()
    # new designs (a clock moved them) are picked up
    b.pw, b.vw = b.pw * 2.0, sp.csr_matrix(b.vw * 0.5)
    want2 = _row_contract(hw[:, :, :3], b.pw) + _row_contract(hw[:, :, 3:], b.vw)
    want2 = shift_columns(want2[np.flatnonzero(use.ravel())], offset, n)
    assert b.jacobian(hw, use, offset, n).data.tobytes() == want2.data.tobytes()


@pytest.mark.parametrize('full_rows', [0, 1, 40])
def test_the_normal_matrix_equals_the_sparse_product(full_rows: int) -> None:
    """A window's Jacobian: thin rows of a few coefficients each (as the station rows)
    with ``full_rows`` rows over every column (as the jerk prior's square root), and an
    empty row; ``J^T J`` equals the sparse product to rounding and stays symmetric."""
    rng = np.random.default_rng(full_rows)
    m, n, w = 3000, 300, 15
    start = rng.integers(0, n - w, m)
    cols = (start[:, None] + np.arange(w)).ravel()
    rows = np.repeat(np.arange(m), w)
    thin = sp.csr_matrix((rng.normal(size=m * w), (rows, cols)), shape=(m, n))
    full = sp.csr_matrix(rng.normal(size=(full_rows, n)) * 1e3)
    jac = sp.vstack([thin, full, sp.csr_matrix((1, n))]).tocsr()
    jac = jac[rng.permutation(jac.shape[0])]
    ref = (jac.T @ jac).toarray()
    got = normal_matrix(jac)
    assert got.shape == (n, n)
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-9 * np.abs(ref).max())
    np.testing.assert_array_equal(got, got.T)
