"""Callbacks that cannot take a node down.

rclpy lets an exception raised in a subscription, timer or service callback out of
``spin``, which ends the node. Input the nodes anticipate is rejected and counted where it
is decoded; :func:`guarded` is the net below that: anything else is a bug, logged with its
traceback and counted as ``internal_error``, and the node goes on with the next message.
"""

from __future__ import annotations

import traceback
from collections import Counter
from collections.abc import Callable

from rclpy.node import Node

__all__ = ['guarded']


def guarded(
    node: Node, counts: Counter[str], what: str, fn: Callable[..., object], *args: object
) -> None:
    """Call ``fn(*args)``; an exception is logged (ERROR, with traceback) and counted."""
    try:
        fn(*args)
    except Exception as exc:
        if not node.context.ok():
            # shutting down (SIGINT): a callback that was running when the context went
            # invalid cannot publish any more; that is the end of the node, not a bug
            return
        counts['internal_error'] += 1
        node.get_logger().error(
            f'{what}: internal error {exc!r} ({counts["internal_error"]} so far)\n'
            + traceback.format_exc()
        )
