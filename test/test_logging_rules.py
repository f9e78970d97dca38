"""rclpy ties a severity to each logging call site and raises ``ValueError: Logger severity
cannot be changed between calls`` when one site logs at two severities (the estimator once
died that way when a failed window followed a good one). No call site in the package may
pick its logger method at run time.

The first test shows the hazard in rclpy itself, so that the rule is not folklore; the
second finds every call site that picks a severity (``log = a.info if ok else a.warning``,
``(a.info if ok else a.warning)(text)``) with ``ast``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / 'orbit_tracking'
SEVERITIES = frozenset({'debug', 'info', 'warn', 'warning', 'error', 'fatal'})


def _picks_severity(node: ast.AST) -> bool:
    return (
        isinstance(node, ast.IfExp)
        and isinstance(node.body, ast.Attribute)
        and isinstance(node.orelse, ast.Attribute)
        and node.body.attr in SEVERITIES
        and node.orelse.attr in SEVERITIES
    )


def severity_pickers(source: str) -> list[int]:
    """Line numbers where a logger method is chosen by a conditional expression."""
    return [n.lineno for n in ast.walk(ast.parse(source)) if _picks_severity(n)]


def test_rclpy_refuses_two_severities_from_one_call_site():
    import rclpy

    context = rclpy.Context()
    rclpy.init(context=context, args=[])
    try:
        node = rclpy.create_node('severity_probe', context=context)
        logger = node.get_logger()

        def emit(ok: bool) -> None:
            (logger.info if ok else logger.warning)('probe')  # one call site, two severities

        emit(True)
        with pytest.raises(ValueError, match='severity cannot be changed'):
            emit(False)
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def test_the_rule_finds_a_severity_picked_at_run_time():
    assert severity_pickers('log = lg.info if ok else lg.warning\nlog("x")\n') == [1]
    assert severity_pickers('(lg.info if ok else lg.error)("x")\n') == [1]
    assert severity_pickers('if ok:\n    lg.info("x")\nelse:\n    lg.warning("x")\n') == []


@pytest.mark.parametrize('path', sorted(PACKAGE.rglob('*.py')), ids=lambda p: p.name)
def test_no_call_site_logs_at_two_severities(path: Path):
    lines = severity_pickers(path.read_text())
    assert not lines, (
        f'{path.relative_to(PACKAGE.parent)}:{lines}: a logger method picked at run time; '
        'use one call per severity (if ok: log.info(...) else: log.warning(...))'
    )
