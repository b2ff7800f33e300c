"""The managed gateway node (``cbcan_lifecycle_node``), as ROS hardware drivers ship one.

Same parameters, services and topics as ``cbcan_node`` (one :class:`GatewayInterface`),
driven by the standard lifecycle transitions (``ros2 lifecycle set /can0/cbcan configure``):

- configure: check the parameters and open the bus; the services exist but answer "inactive";
- activate: serve the services and publish the topics;
- deactivate: answer every new call "inactive" (calls under way finish, but transfers with a
  drive that gets its stop), stop the drives and stop publishing;
- cleanup, shutdown: answer waiting calls, close the bus, take the services away; the
  actions stay, answering every goal that the gateway is not configured (``goals``).

A wrong parameter fails configure with the reason in the log; fix it (``ros2 param set``)
and configure again.
"""

from rclpy.lifecycle import LifecycleNode, State, TransitionCallbackReturn

from .answer_retry import retry_the_node_services
from .config import NodeParameters
from .goals import KeptActionServer
from .interface import GatewayInterface
from .node import run
from .rclpy_gaps import refuse_unavailable_transitions, without_default_event_handlers


class CbcanLifecycleNode(LifecycleNode):
    """One CAN bus as a managed node: the bus is open from configure to cleanup."""

    def __init__(self, **kwargs):
        super().__init__('cbcan', **kwargs)
        self._node_parameters = NodeParameters(self)
        self.interface = None
        # rclpy's change_state raises for a transition the current state does not have
        # (configure twice), which would end the node; rclcpp answers success false.
        refuse_unavailable_transitions(self)
        # Its transitions destroy publishers and subscriptions while the executor spins.
        without_default_event_handlers(self)
        self._answers = retry_the_node_services(self)

    @property
    def gateway(self):
        """The CANopen core this node maps (None while unconfigured)."""
        return self.interface.gateway if self.interface else None

    def on_configure(self, state: State) -> TransitionCallbackReturn:
        """Check the parameters, open the bus; services answer "inactive" until activate."""
        try:
            self.interface = GatewayInterface(self, self._node_parameters, active=False)
        except Exception as error:  # noqa: BLE001 - rclpy would swallow it without a word
            self.get_logger().error(f'cannot configure: {error}')
            return TransitionCallbackReturn.FAILURE
        return super().on_configure(state)

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        """Serve calls and publish."""
        self.interface.activate()
        return super().on_activate(state)

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        """Answer new calls "inactive"; the bus stays open and node states stay watched."""
        self.interface.deactivate()
        return super().on_deactivate(state)

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        """Close the bus and take the services and topics away."""
        self._close()
        return super().on_cleanup(state)

    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        """Close the bus (from any state)."""
        self._close()
        return super().on_shutdown(state)

    def on_error(self, state: State) -> TransitionCallbackReturn:
        """Close the bus after a failed transition, so configure can start afresh."""
        self._close()
        return TransitionCallbackReturn.SUCCESS

    def shut_down_gateway(self) -> None:
        """Answer every waiting call ("shutting down"), abort running transfers, close the bus."""
        if self.interface:
            self.interface.shut_down()

    def destroy_node(self) -> None:
        """Close the bus if it is open, then destroy the node."""
        self._close()
        KeptActionServer.destroy_all(self)
        self._answers.close()
        super().destroy_node()

    def _close(self) -> None:
        interface, self.interface = self.interface, None
        if interface:
            interface.destroy()


def main(args=None) -> int:
    """Run the managed gateway node until SIGINT or SIGTERM (it starts unconfigured)."""
    return run(CbcanLifecycleNode, 'cbcan_lifecycle_node', args)
