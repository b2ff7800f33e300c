"""The gateway's client of one ``cbcan_cli`` run: its own ROS context and node."""

import contextlib
import time

from rcl_interfaces.srv import GetParameters
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import parameter_value_to_python

from ..client import GatewayClient

# Seconds between looks at a condition while the CLI's node is spun (Ctrl-C is taken
# between two spins).
SPIN_PERIOD = 0.1


class Client(GatewayClient):
    """The gateway's client on a node of its own, in a private context (one per CLI run)."""

    def __init__(self, gateway: str, wait: float):
        self._context = rclpy.Context()
        rclpy.init(args=[], context=self._context)
        self._cli_node = rclpy.create_node('cbcan_cli', context=self._context,
                                           start_parameter_services=False,
                                           enable_rosout=False)
        super().__init__(self._cli_node, gateway, wait)

    @property
    def node(self):
        """Return the CLI's own node (topics, actions and the graph of the run)."""
        return self._cli_node

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
                executor.spin_once(timeout_sec=SPIN_PERIOD)
                while received and (not count or handled < count):
                    handle(received.pop(0))
                    handled += 1
        finally:
            executor.shutdown(timeout_sec=1.0)
            self._cli_node.destroy_subscription(subscription)

    @contextlib.contextmanager
    def spinning(self):
        """Yield ``spin_until(condition, timeout) -> bool`` for the CLI's node.

        It runs the node's callbacks (subscriptions, the action client) until
        ``condition()`` holds (True) or ``timeout`` seconds pass (False).
        """
        executor = SingleThreadedExecutor(context=self._context)
        executor.add_node(self._cli_node)

        def spin_until(condition, timeout: float) -> bool:
            deadline = time.monotonic() + timeout
            while not condition():
                left = deadline - time.monotonic()
                if left <= 0.0:
                    return False
                executor.spin_once(timeout_sec=min(SPIN_PERIOD, left))
            return True
        try:
            yield spin_until
        finally:
            executor.shutdown(timeout_sec=1.0)
