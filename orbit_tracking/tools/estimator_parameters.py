"""The estimator node's parameters as the offline tools' settings: a parameter file (or
the live node's parameters) read into the ``EstimatorConfig`` and ``WindowConfig`` a node
started with them would use, so that ``orbit-tracking estimate --params-file``, the demo's
offline cross-check and the benchmarks run what the node runs."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

import yaml

from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.knots import KnotConfig
from orbit_tracking.core.estimation.windows import WindowConfig

__all__ = ['NODE_ONLY_PARAMETERS', 'estimator_configs', 'read_parameters_file']

_KNOT_PARAMETERS = (
    'degree',
    'base_spacing',
    'gap_spacing',
    'delta_position',
    'delta_velocity',
    'solver',
    'sparse',
)
_WINDOW_PARAMETERS = {
    'window_length': 'length',
    'window_overlap': 'overlap',
    'latency': 'latency',
    'output_step': 'output_step',
}
_CONFIG_FIELDS = frozenset(
    f.name
    for f in fields(EstimatorConfig)
    if f.name not in ('knots', 'segments', 'coverage', 'biases')
)
NODE_ONLY_PARAMETERS = frozenset(
    {
        # how the live node takes its streams: nothing of it exists in a bag's replay
        'stations',
        'time_reference',
        'time_reset_tolerance',
        'silent_after',
        'flush_after',
        'solve_in_background',
        'max_targets',
        'max_stations',
        'journal_dir',
        'journal_max_mb',
        'window_history',
        'diagnostics_period',
        # relative to the live node's time_reference, which a bag does not carry
        'segments',
        # chosen by the caller: ``estimate --model`` runs a whole-bag fit instead
        'model',
        'stages',
        # the target: the offline run solves every target and reports the lowest id
        'target_id',
        # returned on its own
        'bias_file',
    }
)
"""Estimator node parameters that :func:`estimator_configs` does not turn into settings,
with the reason in the source; every other node parameter is mapped."""


def _typed(name: str, value: Any, default: Any) -> Any:
    """``value`` as the type of the core's default (a YAML ``5`` for a float setting)."""
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ValueError(f'parameter {name} must be true or false; got {value!r}')
        return value
    if isinstance(default, int) and isinstance(value, float) and not value.is_integer():
        raise ValueError(f'parameter {name} must be an integer; got {value!r}')
    if isinstance(default, int | float) and not isinstance(value, bool):
        return type(default)(value)
    return value


def estimator_configs(
    parameters: Mapping[str, Any],
) -> tuple[EstimatorConfig, WindowConfig, str]:
    """The settings of :func:`estimate_bag` that match an estimator node started with
    ``parameters`` (its parameter names; missing ones keep the defaults, which are the
    node's): ``(estimator config, window config, bias_file)``. Every node parameter but
    those in :data:`NODE_ONLY_PARAMETERS` is mapped; an unknown name raises ``ValueError``
    (a typo would otherwise run on the default)."""
    p = dict(parameters)
    unknown = sorted(
        set(p)
        - set(_KNOT_PARAMETERS)
        - set(_WINDOW_PARAMETERS)
        - _CONFIG_FIELDS
        - NODE_ONLY_PARAMETERS
        - {'max_knot_spacing'}
    )
    if unknown:
        raise ValueError(f'not an estimator node parameter: {", ".join(unknown)}')
    kdef, edef, wdef = KnotConfig(), EstimatorConfig(), WindowConfig()
    knots = KnotConfig(
        **{k: _typed(k, p[k], getattr(kdef, k)) for k in _KNOT_PARAMETERS if k in p}
    )
    if 'max_knot_spacing' in p:
        knots = replace(knots, max_spacing=float(p['max_knot_spacing']))
    est = EstimatorConfig(
        knots=knots,
        **{k: _typed(k, p[k], getattr(edef, k)) for k in sorted(_CONFIG_FIELDS) if k in p},
    )
    win = WindowConfig(
        **{f: _typed(k, p[k], getattr(wdef, f)) for k, f in _WINDOW_PARAMETERS.items() if k in p}
    )
    return est, win, str(p.get('bias_file') or '')


def read_parameters_file(path: str | Path, node: str = 'estimator') -> dict[str, Any]:
    """The ``ros__parameters`` of ``node`` in a ROS 2 parameter file (its sections
    ``node``, ``/node`` and the wildcards ``/**`` and ``**``, later ones winning as the
    file lists them); ``ValueError`` when the file has none for it."""
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f'cannot read parameter file {path}: {exc}') from exc
    if not isinstance(data, dict):
        raise ValueError(f'{path} is not a ROS 2 parameter file (no node sections)')
    params: dict[str, Any] = {}
    found = False
    for name, section in data.items():
        if str(name).lstrip('/') in (node, '**') and isinstance(section, dict):
            inner = section.get('ros__parameters')
            if isinstance(inner, dict):
                params.update(inner)
                found = True
    if not found:
        raise ValueError(
            f'{path} has no ros__parameters for node {node!r} (sections: '
            f'{", ".join(map(str, data)) or "none"})'
        )
    return params
