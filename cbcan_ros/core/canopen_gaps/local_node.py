"""canopen 2.4.1's ``LocalNode``, for the gateway's own dictionary (node 0), on no bus.

A ``LocalNode`` starts a heartbeat producer when 0x1017 is written, also for a dictionary
that is on no bus: :func:`without_heartbeat_producer`.
"""

import canopen


def without_heartbeat_producer(node: canopen.LocalNode) -> canopen.LocalNode:
    """Return ``node`` with no heartbeat producer behind its 0x1017 (a node on no bus)."""
    node._write_callbacks.remove(node.nmt.on_write)
    return node
