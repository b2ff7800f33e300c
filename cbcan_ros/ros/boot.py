"""The boot service's ROS side: ``~/boot`` runs boots again, ``~/boot_states`` shows them.

``~/boot_states`` is transient local: a subscriber that comes late gets the last picture. It
is published on every change, by a thread of its own (``publish_on_change``).
"""

import threading
from typing import Callable, Optional

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.time import Time

from ..core.boot.service import BootAnswer
from ..core.boot.service import BootState as CoreBootState
from ..core.sdo.request_queue import resolved
from ..msg import BootState, BootStates
from .publish_on_change import PublishOnChange

BOOT_STATES_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)


def boot_state(state: CoreBootState) -> BootState:
    """Return the message of one device's boot state."""
    return BootState(node_id=state.node_id, name=state.name, state=state.state,
                     error_status=state.error_status, message=state.message,
                     writes=state.writes, boots=state.boots,
                     stamp=Time(nanoseconds=int(state.stamp * 1e9)).to_msg())


def fill_boot(answer: BootAnswer, response) -> None:
    """Write a boot's answer into the ``~/boot`` response."""
    response.success = answer.success
    response.message = answer.message
    response.states = [boot_state(state) for state in answer.states]


class BootTopics:
    """``~/boot_states`` and the start of ``~/boot`` calls, over the gateway's boot service."""

    def __init__(self, node: Node, boots, inactive: Callable[[], Optional[str]]):
        self._node = node
        self._boots = boots
        self._inactive = inactive
        self._publisher = node.create_publisher(BootStates, '~/boot_states', BOOT_STATES_QOS)
        self._lock = threading.Lock()
        self._changes = PublishOnChange(self._publish, 'boot states')
        boots.add_listener(self._changes.changed)
        self._changes.changed()

    def start_boot(self, request):
        """Start a ``~/boot`` call: a Future of its BootAnswer."""
        refusal = self._inactive()
        if refusal:
            return resolved(BootAnswer(False, refusal))
        return self._boots.boot(request.node_id, request.timeout)

    def publish(self) -> None:
        """Publish every device's boot state now (a managed node's activation)."""
        self._changes.changed()

    def close(self) -> None:
        """Stop publishing; the publisher is destroyed."""
        self._changes.close()
        with self._lock:
            publisher, self._publisher = self._publisher, None
        if publisher is not None:
            self._node.destroy_publisher(publisher)

    def _publish(self) -> None:
        with self._lock:
            if self._inactive() or self._publisher is None:
                return
            self._publisher.publish(BootStates(
                stamp=self._node.get_clock().now().to_msg(),
                states=[boot_state(state) for state in self._boots.states()]))
