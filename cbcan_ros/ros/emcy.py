"""``~/emcy``: every emergency message (EMCY) of every device, published as it arrives."""

from typing import Callable

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.time import Time

from ..core.emcy import Emergency
from ..core.gateway import Gateway
from ..msg import Emcy

# Reliable and deep: an EMCY is an event a subscriber must not miss, and one fault (a power
# dip, a cut cable) can make every device of the bus send one at once: 128 hold one from each
# of 127 devices. Volatile: an EMCY from before a subscriber started is no news to it; the
# latest of each device stays on /diagnostics.
EMCY_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=128,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def emcy_message(emergency: Emergency) -> Emcy:
    """Return the ``cbcan_ros/msg/Emcy`` message of one EMCY."""
    return Emcy(node_id=emergency.node_id, error_code=emergency.error_code,
                error_register=emergency.error_register,
                manufacturer_data=list(emergency.manufacturer_data),
                stamp=Time(nanoseconds=int(emergency.received * 1e9)).to_msg(),
                description=emergency.description)


class EmcyPublisher:
    """Publishes on ``~/emcy`` every EMCY the gateway receives.

    Created before the gateway starts, so an EMCY a device sends at boot is published too. It
    is published from the bus thread at once (rclpy publishers may be used from any thread),
    so an EMCY never waits for the executor.
    """

    def __init__(self, node: Node, gateway: Gateway, active: Callable[[], bool]):
        self._node = node
        self._active = active
        self._publisher = node.create_publisher(Emcy, '~/emcy', EMCY_QOS)
        gateway.emcy.add_listener(self.publish)

    def publish(self, emergency: Emergency) -> None:
        """Publish one EMCY (only while the node is active)."""
        if self._active():
            self._publisher.publish(emcy_message(emergency))

    def destroy(self) -> None:
        """Take the topic away (after the bus is closed: no EMCY comes any more)."""
        self._node.destroy_publisher(self._publisher)
