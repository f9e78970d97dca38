"""Parameter declarations with descriptions and ranges, shared by every node."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

__all__ = ['declare', 'diagnostics_timer']


def declare(
    node: Node,
    name: str,
    default: Any,
    description: str,
    *,
    read_only: bool = False,
    min_value: float | None = None,
    max_value: float | None = None,
    step: float | None = None,
    param_type: Parameter.Type | None = None,
) -> Any:
    """Declare a parameter with a descriptor and return its value.

    ``min_value``/``max_value`` become a FloatingPointRange (float default) or an
    IntegerRange (int default), so ``ros2 param describe`` shows them and rclpy rejects
    out-of-range values at start-up and at run time.
    """
    desc = ParameterDescriptor(name=name, description=description, read_only=read_only)
    if min_value is not None or max_value is not None:
        lo = -1e300 if min_value is None else min_value
        hi = 1e300 if max_value is None else max_value
        if isinstance(default, bool):
            raise ValueError(f'parameter {name}: a range makes no sense for a bool')
        if isinstance(default, int):
            desc.integer_range = [
                IntegerRange(
                    from_value=int(max(lo, -(2**62))),
                    to_value=int(min(hi, 2**62)),
                    step=int(step or 0),
                )
            ]
        else:
            desc.floating_point_range = [
                FloatingPointRange(
                    from_value=float(lo), to_value=float(hi), step=float(step or 0.0)
                )
            ]
    if param_type is not None:
        # declared by type (e.g. an empty-list default has no type of its own); an unset
        # parameter of that kind cannot be read with get_parameter, so fall back
        node.declare_parameter(name, param_type, desc)
        value = node.get_parameter_or(name, Parameter(name, param_type, default)).value
        return default if value is None else value
    return node.declare_parameter(name, default, desc).value


def diagnostics_timer(node: Node, publish: Callable[[], None]) -> float:
    """Declare ``diagnostics_period`` and publish the node's ``/diagnostics`` status at that
    period; the period [s]."""
    period = float(
        declare(
            node,
            'diagnostics_period',
            1.0,
            'Wall seconds between two /diagnostics statuses of the node.',
            read_only=True,
            min_value=0.05,
            max_value=60.0,
        )
    )
    node.create_timer(period, publish)
    return period
