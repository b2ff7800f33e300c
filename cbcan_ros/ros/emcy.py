"""``~/emcy``: every emergency message (EMCY) of every device, published as it arrives."""

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.time import Time

from ..core.emcy import Emergency
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
    """Publishes EMCYs on ``~/emcy``.

    The node calls :meth:`publish` from the bus thread as each EMCY arrives (rclpy publishers
    may be used from any thread), so an EMCY never waits for the executor.
    """

    def __init__(self, node: Node):
        self._node = node
        self._publisher = node.create_publisher(Emcy, '~/emcy', EMCY_QOS)

    def publish(self, emergency: Emergency) -> None:
        """Publish one EMCY."""
        self._publisher.publish(emcy_message(emergency))

    def destroy(self) -> None:
        """Take the topic away (after the bus is closed: no EMCY comes any more)."""
        self._node.destroy_publisher(self._publisher)
