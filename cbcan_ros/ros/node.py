"""The ROS 2 node: maps parameters, services and the node-state topic onto the gateway core.

An SDO call is handed to the device's worker thread and answered from there when it is done
(``deferred.py``), so the executor keeps serving other calls, timers and publishers while a
slow device takes its time, and holds nothing per waiting call. The mailbox, which chains
several SDOs, is a coroutine that awaits them.

Shutdown (SIGINT, SIGTERM or ``destroy_node``) answers every waiting call before rclpy goes
away: ROS can only deliver an answer while the node still exists.
"""

from concurrent.futures import Future as ConcurrentFuture
import logging
import os
import signal
import sys
import threading

from builtin_interfaces.msg import Time
import rclpy
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
import rclpy.task

from ..core.gateway import Gateway
from ..core.nmt import state_name
from ..core.sdo import Access, check_node_id
from ..msg import NodeState, NodeStates
from ..msg import SdoResult as SdoResultMessage
from ..plc.mailbox import Mailbox
from ..srv import NmtCommand, NmtState, RegisterMailbox, SdoBatch, SdoRead, SdoWrite
from .config import NodeParameters
from .deferred import CallsInProgress, DeferredService
from .diagnostics import Diagnostics
from .emcy import EmcyPublisher

NODE_STATES_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)

# The default service QoS keeps 10 requests: a burst of calls (one per device, say) loses
# the oldest before the executor takes them. A deep history keeps every request of a burst
# (a full device queue is answered "busy"). Not keep-all: the answers share one history, and
# a client killed mid-call stays matched until its DDS lease ends (about 20 s) without ever
# acknowledging, so under keep-all its unacknowledged answers filled the history and every
# later answer to everyone failed. Clients sending bursts need a history this deep too.
SERVICE_DEPTH = 4096
SERVICE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=SERVICE_DEPTH,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)

# The logger every module of the package logs under, shown through the node's ROS logger.
PACKAGE = __package__.partition('.')[0]

# The longest an idle executor sleeps before it looks whether shutdown began (it is woken
# at once anyway; this only bounds a missed wake-up).
SPIN_CHECK = 1.0

# How long shutdown waits for answers already decided to leave the node.
ANSWER_GRACE = 1.0


def _time(seconds: float) -> Time:
    whole = int(seconds)
    return Time(sec=whole, nanosec=int((seconds - whole) * 1e9))


class _RosLogHandler(logging.Handler):
    """Sends the core's Python log records (bus faults, recoveries) to the node's ROS logger."""

    def __init__(self, logger):
        super().__init__(logging.INFO)
        self._logger = logger

    def emit(self, record: logging.LogRecord) -> None:
        if record.levelno >= logging.ERROR:
            self._logger.error(record.getMessage())
        elif record.levelno >= logging.WARNING:
            self._logger.warning(record.getMessage())
        else:
            self._logger.info(record.getMessage())


def _fill_result(result, response) -> None:
    """Write an SdoResult (or a batch's list of them) into a service response."""
    if isinstance(result, list):
        response.results = [
            SdoResultMessage(success=r.success, abort_code=r.abort_code, message=r.message,
                             data=list(r.data))
            for r in result]
        return
    response.success = result.success
    response.abort_code = result.abort_code
    response.message = result.message
    if hasattr(response, 'data'):
        response.data = list(result.data)


class CbcanNode(Node):
    """One CAN bus as ROS 2 services and a node-state topic."""

    def __init__(self, **kwargs):
        super().__init__('cbcan', **kwargs)
        self._calls = CallsInProgress()
        self._destroyed = False
        self._log_handler = _RosLogHandler(self.get_logger())
        core_logger = logging.getLogger(PACKAGE)
        core_logger.setLevel(logging.INFO)
        core_logger.addHandler(self._log_handler)
        parameters = NodeParameters(self)
        self.gateway = Gateway(parameters.gateway_config())
        self._emcy = EmcyPublisher(self, self.gateway)  # before start: boot-time EMCYs too
        self._simulated = self._simulated_devices(parameters)
        self.gateway.start()
        for device in self._simulated:
            device.start()

        # Calls must overlap: a slow device never holds up the others or the state topic.
        options = dict(qos_profile=SERVICE_QOS, callback_group=ReentrantCallbackGroup())
        self._deferred = [
            DeferredService(self, service_type, f'~/{name}', start, _fill_result, self._calls,
                            **options)
            for service_type, name, start in (
                (SdoRead, 'sdo_read', self._start_read),
                (SdoWrite, 'sdo_write', self._start_write),
                (SdoBatch, 'sdo_batch', self._start_batch))]
        for service_type, name, callback in (
                (NmtCommand, 'nmt_command', self._on_nmt_command),
                (NmtState, 'nmt_state', self._on_nmt_state),
                (RegisterMailbox, 'plc_mailbox', self._on_plc_mailbox)):
            self.create_service(service_type, f'~/{name}', callback, **options)
        self._mailbox = Mailbox(self.gateway, self._completion)

        self._states_publisher = self.create_publisher(NodeStates, '~/node_states',
                                                       NODE_STATES_QOS)
        self._states_changed = self.create_guard_condition(self._publish_states)
        self.gateway.monitor.add_listener(self._states_changed.trigger)
        self.create_timer(parameters.value('state_publish_period'), self._publish_states)
        self._publish_states()
        self._diagnostics = Diagnostics(self, self.gateway)
        self.create_timer(parameters.value('diagnostics_period'), self._diagnostics.publish)
        config = self.gateway.config
        self.get_logger().info(
            f'CANopen gateway on {config.interface} channel {config.channel!r}; '
            f'simulated devices: {[d.node_id for d in self._simulated] or "none"}')

    def _simulated_devices(self, parameters: NodeParameters) -> list:
        node_ids = parameters.node_ids('simulation.devices')
        if not node_ids:
            return []
        # Only for trying the gateway without hardware: a real bus never loads the simulator.
        from ..simulation.canopen_device import SimulatedDevice
        return [SimulatedDevice(node_id, parameters.simulation_eds(),
                                self.gateway.config.interface, self.gateway.config.channel)
                for node_id in node_ids]

    def shut_down_gateway(self) -> None:
        """Answer every waiting call ("shutting down"), abort running transfers, close the bus.

        SDO answers leave from the thread that resolves them; a mailbox call needs the
        executor to finish. This waits up to ``ANSWER_GRACE`` seconds for all to leave.
        """
        self.gateway.stop()
        self._calls.wait_until_idle(ANSWER_GRACE)

    def destroy_node(self) -> None:
        """Answer waiting calls, close the bus, stop the simulated devices (once)."""
        if self._destroyed:
            return
        self._destroyed = True
        self.shut_down_gateway()
        for device in self._simulated:
            device.stop()
        logging.getLogger(PACKAGE).removeHandler(self._log_handler)
        super().destroy_node()

    async def _completion(self, future: ConcurrentFuture):
        """Await a worker's future without holding an executor thread."""
        if future.done():
            return future.result()
        executor = self.executor
        done = rclpy.task.Future(executor=executor)

        def hand_over(finished: ConcurrentFuture) -> None:
            done.set_result(finished.result())
            executor.wake()  # the executor re-runs waiting coroutines only when woken

        future.add_done_callback(hand_over)
        return await done

    def _start_read(self, request) -> ConcurrentFuture:
        return self.gateway.sdo_read(request.node_id, request.index, request.subindex,
                                     request.max_size, request.timeout)

    def _start_write(self, request) -> ConcurrentFuture:
        return self.gateway.sdo_write(request.node_id, request.index, request.subindex,
                                      bytes(request.data), request.timeout)

    def _start_batch(self, request) -> ConcurrentFuture:
        return self.gateway.sdo_batch(
            [Access(a.node_id, a.index, a.subindex, a.write, bytes(a.data), a.max_size)
             for a in request.accesses], request.timeout)

    def _on_nmt_command(self, request, response):
        result = self.gateway.nmt_command(request.node_id, request.command)
        response.success = result.success
        response.message = result.message
        return response

    def _on_nmt_state(self, request, response):
        problem = check_node_id(request.node_id, '1..127', lowest=1)
        if problem:
            response.success = False
            response.state = NmtState.Response.NOT_DETECTED
            response.state_name = state_name(response.state)
            response.last_seen_age = -1.0
            response.message = problem
            return response
        status = self.gateway.monitor.status(request.node_id)
        response.success = True
        response.state = status.state
        response.state_name = status.state_name
        response.last_seen_age = status.last_seen_age
        return response

    async def _on_plc_mailbox(self, request, response):
        self._calls.begin()
        try:
            response.registers, response.message = await self._mailbox.execute(
                request.format, list(request.registers))
            return response
        finally:
            self._calls.end()

    def _publish_states(self) -> None:
        message = NodeStates(stamp=self.get_clock().now().to_msg())
        message.nodes = [
            NodeState(node_id=status.node_id, state=status.state,
                      state_name=status.state_name,
                      last_seen=_time(status.last_seen) if status.last_seen else Time())
            for status in self.gateway.monitor.statuses()]
        self._states_publisher.publish(message)


def main(args=None) -> int:
    """Run the gateway node until SIGINT or SIGTERM; a second signal ends it at once."""
    stop = threading.Event()

    def on_signal(signum, _frame) -> None:
        if stop.is_set():
            os._exit(128 + signum)  # the impatient second Ctrl-C: no cleanup, no traceback
        stop.set()

    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, on_signal)
    # rclpy's own handler would shut the context down first, and a node without a context
    # can answer nobody: shutdown is ours, in order.
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        node = CbcanNode()
    except Exception as error:  # noqa: BLE001 - a configuration error ends the process cleanly
        print(f'cbcan_node: cannot start: {error}', file=sys.stderr)
        rclpy.try_shutdown()
        return 1
    executor = SingleThreadedExecutor()
    executor.add_node(node)

    spinning = threading.Event()
    spinning.set()

    def spin() -> None:
        try:
            while spinning.is_set():
                executor.spin_once(timeout_sec=SPIN_CHECK)
        finally:
            stop.set()

    spinner = threading.Thread(target=spin, name='executor', daemon=True)
    spinner.start()
    stop.wait()  # the main thread only waits: signal handlers run here at once
    node.get_logger().info('shutting down: answering waiting calls')
    node.shut_down_gateway()
    # rclpy 7.1.6's Executor.shutdown() does not wait for a spin in progress and destroys
    # what that spin uses: end the spinning first, then shut the executor down.
    spinning.clear()
    executor.wake()
    spinner.join(ANSWER_GRACE)
    executor.shutdown(timeout_sec=ANSWER_GRACE)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0
