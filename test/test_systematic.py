"""Unit tests of orbit_tracking.core.models.systematic.BiasModel: seed 003's relation, inverse
and Jacobians against finite differences."""

from __future__ import annotations

import numpy as np
import pytest

from orbit_tracking.core.errors import MeasurementError
from orbit_tracking.core.models.systematic import BIAS_PARAMETERS, BiasModel

# seed 003 (SCENARIOS.md): (d_alpha, d_beta, d_theta) of satellites 06 and 09
SAT06 = {'los_alpha': 2.89e-4, 'los_beta': 3.23e-4, 'los_theta': -3.46e-4}
SAT09 = {'los_alpha': -3.51e-4, 'los_beta': 4.70e-4, 'los_theta': 4.68e-4}
LOS = ['los_alpha', 'los_beta']


def _los_values(rng: np.random.Generator, m: int = 200) -> np.ndarray:
    return rng.uniform(-0.5, 0.5, size=(m, 2))


@pytest.mark.parametrize(
    'values', [SAT06, SAT09, {'los_theta': 0.3}], ids=['sat06', 'sat09', 'rot']
)
def test_seed003_relation_gives_true_los_from_measured(values: dict[str, float]) -> None:
    rng = np.random.default_rng(3)
    true = _los_values(rng)
    measured = BiasModel(values).apply(LOS, true)
    a1, b1 = measured.T
    da, db, dt = values.get('los_alpha', 0.0), values.get('los_beta', 0.0), values['los_theta']
    # seed 003 eq. 5-39, written out by hand
    a0 = a1 * np.cos(dt) - b1 * np.sin(dt) - da
    b0 = a1 * np.sin(dt) + b1 * np.cos(dt) - db
    np.testing.assert_allclose(np.column_stack([a0, b0]), true, rtol=0.0, atol=1e-15)


def test_measured_los_is_the_true_los_plus_offsets_turned_by_minus_dtheta() -> None:
    true = np.array([[0.1, -0.2]])
    da, db, dt = SAT09['los_alpha'], SAT09['los_beta'], SAT09['los_theta']
    shifted = true[0] + [da, db]
    turn = np.array([[np.cos(dt), np.sin(dt)], [-np.sin(dt), np.cos(dt)]])
    np.testing.assert_allclose(BiasModel(SAT09).apply(LOS, true)[0], turn @ shifted, atol=1e-16)


@pytest.mark.parametrize(
    ('fields', 'values'),
    [
        (LOS, SAT06),
        (['los_beta', 'los_alpha'], SAT09),  # column order does not matter
        (['range', 'range_rate'], {'range': 3.0, 'range_rate': -0.02}),
        (['range', 'azimuth', 'elevation'], {'azimuth': 1.454e-5, 'elevation': -9.7e-6}),
    ],
)
def test_apply_then_remove_is_the_identity(fields: list[str], values: dict[str, float]) -> None:
    rng = np.random.default_rng(9)
    true = rng.uniform(0.1, 1.0, size=(100, len(fields))) * [
        1e4 if f == 'range' else 1.0 for f in fields
    ]
    model = BiasModel(values)
    measured = model.apply(fields, true)
    assert not np.allclose(measured, true, rtol=0.0, atol=1e-7)
    np.testing.assert_allclose(model.remove(fields, measured), true, rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(
        model.apply(fields, model.remove(fields, true)), true, rtol=1e-15, atol=1e-15
    )


def test_apply_and_remove_do_not_modify_their_input() -> None:
    true = np.array([[0.1, 0.2], [0.3, 0.4]])
    copy = true.copy()
    model = BiasModel(SAT06)
    model.remove(LOS, model.apply(LOS, true))
    np.testing.assert_array_equal(true, copy)


def test_offsets_without_rotation_add_to_each_field() -> None:
    model = BiasModel({'range': 3.0, 'azimuth': -2e-5})
    out = model.apply(['range', 'azimuth', 'elevation'], np.array([[1000.0, 1.0, 0.5]]))
    np.testing.assert_allclose(out, [[1003.0, 1.0 - 2e-5, 0.5]], rtol=0.0, atol=1e-15)
    assert model.get('elevation') == 0.0


def _fd_jacobians(
    model_values: dict[str, float], fields: list[str], true: np.ndarray, parameters: list[str]
) -> tuple[np.ndarray, np.ndarray]:
    m, k = true.shape
    d_true = np.empty((m, k, k))
    d_param = np.empty((m, k, len(parameters)))
    h = 1e-6
    model = BiasModel(model_values)
    for j in range(k):
        plus, minus = true.copy(), true.copy()
        plus[:, j] += h
        minus[:, j] -= h
        d_true[:, :, j] = (model.apply(fields, plus) - model.apply(fields, minus)) / (2 * h)
    for q, name in enumerate(parameters):
        up = {**model_values, name: model_values.get(name, 0.0) + h}
        down = {**model_values, name: model_values.get(name, 0.0) - h}
        d_param[:, :, q] = (
            BiasModel(up).apply(fields, true) - BiasModel(down).apply(fields, true)
        ) / (2 * h)
    return d_true, d_param


@pytest.mark.parametrize(
    ('fields', 'values', 'parameters'),
    [
        (LOS, SAT06, ['los_alpha', 'los_beta', 'los_theta']),
        (['los_beta', 'los_alpha'], SAT09, ['los_theta', 'los_beta', 'los_alpha']),
        (LOS, {'los_theta': 0.4, 'los_alpha': 0.01}, ['los_theta', 'los_alpha', 'los_beta']),
        (LOS, {}, ['los_alpha', 'los_beta', 'los_theta']),  # derivatives at zero bias
        (['range', 'range_rate'], {'range': 3.0}, ['range', 'range_rate']),
        (['azimuth', 'elevation'], {'azimuth': 1e-5}, ['elevation', 'azimuth']),
    ],
)
def test_bias_jacobian_matches_finite_differences(
    fields: list[str], values: dict[str, float], parameters: list[str]
) -> None:
    rng = np.random.default_rng(21)
    true = rng.uniform(-0.5, 0.5, size=(30, len(fields)))
    d_true, d_param = BiasModel(values).jacobian(fields, true, parameters)
    fd_true, fd_param = _fd_jacobians(values, fields, true, parameters)
    np.testing.assert_allclose(d_true, fd_true, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(d_param, fd_param, rtol=0.0, atol=1e-9)


def test_los_theta_without_both_los_fields_is_an_error() -> None:
    model = BiasModel({'los_theta': 1e-4})
    with pytest.raises(MeasurementError, match='los_alpha and los_beta'):
        model.apply(['los_alpha'], np.zeros((1, 1)))
    with pytest.raises(MeasurementError, match='los_alpha and los_beta'):
        model.remove(['los_alpha'], np.zeros((1, 1)))
    with pytest.raises(MeasurementError, match='los_theta'):
        model.jacobian(['range'], np.zeros((1, 1)), ['los_theta'])


def test_unknown_bias_parameter_is_rejected() -> None:
    with pytest.raises(MeasurementError, match='rnge'):
        BiasModel({'rnge': 1.0})
    assert set(BIAS_PARAMETERS) >= {'range', 'azimuth', 'los_alpha', 'los_theta'}
