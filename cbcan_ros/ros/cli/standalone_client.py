"""The gateway's client of one ``cbcan_cli`` run: its own ROS context and node."""

from rcl_interfaces.srv import GetParameters
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import parameter_value_to_python

from ..client import GatewayClient


class Client(GatewayClient):
    """The gateway's client on a node of its own, in a private context (one per CLI run)."""

    def __init__(self, gateway: str, wait: float):
        self._context = rclpy.Context()
        rclpy.init(args=[], context=self._context)
        self._cli_node = rclpy.create_node('cbcan_cli', context=self._context,
                                           start_parameter_services=False,
                                           enable_rosout=False)
        super().__init__(self._cli_node, gateway, wait)

    def close(self) -> None:
        """Close the client, destroy the node and shut the private context down."""
        super().close()
        self._cli_node.destroy_node()
        rclpy.try_shutdown(context=self._context)

    def parameter(self, name: str):
        """Return the value of the gateway's parameter ``name``; None if it has none."""
        response = self.call(GetParameters, 'get_parameters', GetParameters.Request(
            names=[name]), self.wait)
        return parameter_value_to_python(response.values[0]) if response.values else None

    def follow(self, message_type, topic: str, qos, handle, count: int = 0) -> None:
        """Call ``handle(message)`` for messages of ``gateway/topic``; stop after ``count``.

        ``count`` 0 follows until interrupted (Ctrl-C).
        """
        received = []
        subscription = self._cli_node.create_subscription(
            message_type, f'{self.gateway}/{topic}', received.append, qos)
        executor = SingleThreadedExecutor(context=self._context)
        executor.add_node(self._cli_node)
        handled = 0
        try:
            while not count or handled < count:
                executor.spin_once(timeout_sec=0.1)
                while received and (not count or handled < count):
                    handle(received.pop(0))
                    handled += 1
        finally:
            executor.shutdown(timeout_sec=1.0)
            self._cli_node.destroy_subscription(subscription)
