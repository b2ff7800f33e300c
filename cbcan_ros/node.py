"""The ROS 2 node: maps parameters, services and the node-state topic onto the gateway core.

Service callbacks are coroutines. An SDO is handed to the device's worker thread and the
callback awaits its completion, so the executor keeps serving other calls, timers and
publishers while a slow device takes its time.

Shutdown (SIGINT, SIGTERM or ``destroy_node``) answers every waiting call before rclpy goes
away: ROS can only deliver an answer while the node still exists.
"""

from concurrent.futures import Future as ConcurrentFuture
import logging
import os
import signal
import sys
import threading
import time

from builtin_interfaces.msg import Time
import rclpy
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
import rclpy.task

from .config import NodeParameters
from .gateway import Gateway
from .mailbox import Mailbox
from .msg import NodeState, NodeStates
from .msg import SdoResult as SdoResultMessage
from .nmt import state_name
from .sdo import Access, check_node_id
from .simulation import SimulatedDevice
from .srv import NmtCommand, NmtState, RegisterMailbox, SdoBatch, SdoRead, SdoWrite

NODE_STATES_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)

# The default service QoS keeps 10 requests: a burst of calls (one per device, say) loses
# the oldest before the executor takes them. KEEP_ALL loses none: every request that
# reaches the node is answered (a full device queue is answered "busy"). Clients sending
# bursts need a history deep enough for their answers too.
SERVICE_QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)

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


def _counted_call(callback):
    """Count the calls in progress, so shutdown can wait for their answers to leave."""
    async def counted(self, request, response):
        with self._calls_lock:
            self._calls_in_progress += 1
        try:
            return await callback(self, request, response)
        finally:
            with self._calls_lock:
                self._calls_in_progress -= 1
    return counted


class CbcanNode(Node):
    """One CAN bus as ROS 2 services and a node-state topic."""

    def __init__(self, **kwargs):
        super().__init__('cbcan', **kwargs)
        self._calls_in_progress = 0
        self._calls_lock = threading.Lock()
        self._destroyed = False
        self._log_handler = _RosLogHandler(self.get_logger())
        core_logger = logging.getLogger(__package__)
        core_logger.setLevel(logging.INFO)
        core_logger.addHandler(self._log_handler)
        parameters = NodeParameters(self)
        self.gateway = Gateway(parameters.gateway_config())
        self._simulated = [
            SimulatedDevice(node_id, parameters.simulation_eds(), self.gateway.config.interface,
                            self.gateway.config.channel)
            for node_id in parameters.node_ids('simulation.devices')]
        self.gateway.start()
        for device in self._simulated:
            device.start()

        calls = ReentrantCallbackGroup()
        for service_type, name, callback in (
                (SdoRead, 'sdo_read', self._on_sdo_read),
                (SdoWrite, 'sdo_write', self._on_sdo_write),
                (SdoBatch, 'sdo_batch', self._on_sdo_batch),
                (NmtCommand, 'nmt_command', self._on_nmt_command),
                (NmtState, 'nmt_state', self._on_nmt_state),
                (RegisterMailbox, 'plc_mailbox', self._on_plc_mailbox)):
            self.create_service(service_type, f'~/{name}', callback, qos_profile=SERVICE_QOS,
                                callback_group=calls)
        self._mailbox = Mailbox(self.gateway, self._completion)

        self._states_publisher = self.create_publisher(NodeStates, '~/node_states',
                                                       NODE_STATES_QOS)
        self._states_changed = self.create_guard_condition(self._publish_states)
        self.gateway.monitor.add_listener(self._states_changed.trigger)
        self.create_timer(parameters.value('state_publish_period'), self._publish_states)
        self._publish_states()
        config = self.gateway.config
        self.get_logger().info(
            f'CANopen gateway on {config.interface} channel {config.channel!r}; '
            f'simulated devices: {[d.node_id for d in self._simulated] or "none"}')

    def shut_down_gateway(self) -> None:
        """Answer every waiting call ("shutting down"), abort running transfers, close the bus.

        While the executor still spins, the answers reach their callers; this waits up to
        ``ANSWER_GRACE`` seconds for them to leave.
        """
        self.gateway.stop()
        deadline = time.monotonic() + ANSWER_GRACE
        while self._calls_in_progress and time.monotonic() < deadline:
            time.sleep(0.005)

    def destroy_node(self) -> None:
        """Answer waiting calls, close the bus, stop the simulated devices (once)."""
        if self._destroyed:
            return
        self._destroyed = True
        self.shut_down_gateway()
        for device in self._simulated:
            device.stop()
        logging.getLogger(__package__).removeHandler(self._log_handler)
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

    @_counted_call
    async def _on_sdo_read(self, request, response):
        result = await self._completion(self.gateway.sdo_read(
            request.node_id, request.index, request.subindex, request.max_size,
            request.timeout))
        response.success = result.success
        response.abort_code = result.abort_code
        response.message = result.message
        response.data = list(result.data)
        return response

    @_counted_call
    async def _on_sdo_write(self, request, response):
        result = await self._completion(self.gateway.sdo_write(
            request.node_id, request.index, request.subindex, bytes(request.data),
            request.timeout))
        response.success = result.success
        response.abort_code = result.abort_code
        response.message = result.message
        return response

    @_counted_call
    async def _on_sdo_batch(self, request, response):
        accesses = [Access(a.node_id, a.index, a.subindex, a.write, bytes(a.data), a.max_size)
                    for a in request.accesses]
        results = await self._completion(self.gateway.sdo_batch(accesses, request.timeout))
        response.results = [
            SdoResultMessage(success=r.success, abort_code=r.abort_code, message=r.message,
                             data=list(r.data))
            for r in results]
        return response

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

    @_counted_call
    async def _on_plc_mailbox(self, request, response):
        response.registers, response.message = await self._mailbox.execute(
            request.format, list(request.registers))
        return response

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

    def spin() -> None:
        try:
            executor.spin()
        finally:
            stop.set()

    spinner = threading.Thread(target=spin, name='executor', daemon=True)
    spinner.start()
    stop.wait()  # the main thread only waits: signal handlers run here at once
    node.get_logger().info('shutting down: answering waiting calls')
    node.shut_down_gateway()
    executor.shutdown(timeout_sec=ANSWER_GRACE)
    spinner.join(ANSWER_GRACE)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0
