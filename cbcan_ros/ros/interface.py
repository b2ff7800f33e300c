"""The one mapping of the gateway core onto a ROS node: its services, topics and timers.

Both the plain node (``node.py``) and the managed node (``lifecycle_node.py``) build a
:class:`GatewayInterface`; only when it is made and whether it is active differ. While
inactive every call gets a clear "inactive" answer and nothing is published.

An SDO call is handed to the device's worker thread and answered from there when it is done
(``deferred.py``), so the executor keeps serving other calls, timers and publishers while a
slow device takes its time, and holds nothing per waiting call. The mailbox, which chains
several SDOs, runs as a coroutine on its own event loop and is answered the same way, as
are the LSS services, which run on the core's LSS worker and may take seconds.
"""

import array
import asyncio
from concurrent.futures import Future
import logging
import threading
import time
from typing import Tuple

from builtin_interfaces.msg import Time
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from ..core.coroutine_runner import CoroutineRunner
from ..core.gateway import Gateway
from ..core.lss.requests import Identity, LssResult
from ..core.nmt import state_name
from ..core.sdo.request_queue import resolved
from ..core.sdo.requests import Access, check_node_id, SdoResult
from ..core.text import SHUTTING_DOWN
from ..msg import LssIdentity, NodeState, NodeStates
from ..msg import SdoResult as SdoResultMessage
from ..plc.mailbox import Mailbox
from ..srv import (
    Boot,
    DriveCommand,
    LssConfigure,
    LssInquire,
    LssScan,
    NmtCommand,
    NmtState,
    PdoWrite,
    RegisterMailbox,
    SdoBatch,
    SdoRead,
    SdoWrite,
)
from .answer_retry import AnswerRetry
from .boot import BootTopics, fill_boot
from .config import NodeParameters
from .deferred import CallsInProgress, DeferredService
from .diagnostics import Diagnostics
from .drives import DriveTopics, fill_command
from .emcy import EmcyPublisher
from .pdo import check_request, entry_values, PdoTopics
from .program import ProgramAction
from .publish_on_change import PublishOnChange
from .raw_frames import RawFrameTopics
from .rclpy_gaps import drain
from .service_qos import SERVICE_QOS

NODE_STATES_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)


# The logger every module of the package logs under, shown through the node's ROS logger.
PACKAGE = __package__.partition('.')[0]

# How long shutdown waits for answers already decided to leave the node.
ANSWER_GRACE = 1.0

# How long shutdown keeps the services after handing ROS its last answers, so that answers
# still inside the middleware reach their callers: a service's writer goes with the service,
# and what it has not delivered yet goes with it. rmw cannot say when a service's answers are
# acknowledged (rclpy_gaps 5), so the wait is fixed. Twice at most: once more for requests
# that arrived while it waited.
ANSWER_LINGER = 0.5
LINGER_ROUNDS = 2

# What a call gets while a managed node is configured but not active. 0x08000022: "data
# cannot be transferred because of the present device state", as during shutdown.
INACTIVE = ('the gateway is inactive (lifecycle state inactive): activate it to use the bus; '
            'nothing was sent')
INACTIVE_ABORT = 0x08000022


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
                             data=_octets(r.data))
            for r in result]
        return
    response.success = result.success
    response.abort_code = result.abort_code
    response.message = result.message
    if hasattr(response, 'data'):
        response.data = _octets(result.data)


def _refuse_changes(parameters) -> SetParametersResult:
    """Refuse a parameter change while the gateway runs: it reads them when it starts."""
    names = ', '.join(parameter.name for parameter in parameters)
    return SetParametersResult(successful=False, reason=(
        f'{names}: the gateway reads its parameters when it starts; they keep their values '
        f'until it is started again (a managed node: cleanup, then configure)'))


def _octets(data: bytes) -> array.array:
    """Return ``data`` as a uint8[] field takes it without checking each byte (64 KiB reads)."""
    return array.array('B', data)


def _fill_registers(result, response) -> None:
    response.registers, response.message = result


def _fill_lss(result: LssResult, response) -> None:
    """Write an LssResult into the response of any of the three LSS services."""
    response.success = result.success
    response.message = result.message
    if hasattr(response, 'devices'):
        response.devices = [LssIdentity(vendor_id=d.vendor_id, product_code=d.product_code,
                                        revision=d.revision, serial=d.serial)
                            for d in result.devices]
        response.node_ids = list(result.node_ids)
    if hasattr(response, 'error_code'):
        response.error_code = result.error_code
    if hasattr(response, 'node_id'):
        response.node_id = result.node_id


def _identity(message) -> Identity:
    return Identity(message.vendor_id, message.product_code, message.revision, message.serial)


class GatewayInterface:
    """The gateway's services, topics and timers on ``node``, made from its parameters.

    Raises ValueError naming the parameter when one is wrong; then nothing is left open.
    """

    def __init__(self, node: Node, parameters: NodeParameters, active: bool = True):
        self._node = node
        self.active = active
        self._shutting_down = False
        self._answered_before_shutdown = 0
        self._downloads_answered_before_shutdown = 0
        self._log_handler = _RosLogHandler(node.get_logger())
        core_logger = logging.getLogger(PACKAGE)
        core_logger.setLevel(logging.INFO)
        core_logger.addHandler(self._log_handler)
        try:
            self.gateway = Gateway(parameters.gateway_config())
            self.simulated_devices = self._simulated_devices(parameters)
        except Exception:
            core_logger.removeHandler(self._log_handler)
            raise
        # Before the bus opens, so an EMCY a device sends as it boots is published too.
        self._emcy = EmcyPublisher(node)
        self.gateway.emcy.add_listener(self._publish_emcy)
        self.gateway.set_operational(active)  # a managed node's first heartbeat says so
        self.gateway.start()
        for device in self.simulated_devices:
            device.start()

        self._calls = CallsInProgress()
        self._retry = AnswerRetry()
        self._mailbox_loop = CoroutineRunner('plc mailbox')
        self._mailbox = Mailbox(self.gateway, asyncio.wrap_future)
        self._drives = DriveTopics(node, self.gateway.drives, parameters.joints(),
                                   lambda: None if self.active else INACTIVE)
        self._boots = BootTopics(node, self.gateway.boot,
                                 lambda: None if self.active else INACTIVE)
        self._program = ProgramAction(node, self.gateway.program,
                                      lambda: None if self.active else INACTIVE)
        # Calls must overlap: a slow device never holds up the others or the state topic.
        options = dict(qos_profile=SERVICE_QOS, callback_group=ReentrantCallbackGroup())
        self._deferred = [
            DeferredService(node, service_type, f'~/{name}', start, fill, self._calls,
                            self._retry, **options)
            for service_type, name, start, fill in (
                (SdoRead, 'sdo_read', self._start_read, _fill_result),
                (SdoWrite, 'sdo_write', self._start_write, _fill_result),
                (SdoBatch, 'sdo_batch', self._start_batch, _fill_result),
                (PdoWrite, 'pdo_write', self._start_pdo_write, _fill_result),
                (RegisterMailbox, 'plc_mailbox', self._start_mailbox, _fill_registers),
                (LssScan, 'lss_scan', self._start_lss_scan, _fill_lss),
                (LssConfigure, 'lss_configure', self._start_lss_configure, _fill_lss),
                (LssInquire, 'lss_inquire', self._start_lss_inquire, _fill_lss),
                (DriveCommand, 'drive_command', self._drives.start_command, fill_command),
                (Boot, 'boot', self._boots.start_boot, fill_boot))]
        self._services = [
            node.create_service(service_type, f'~/{name}', callback, **options)
            for service_type, name, callback in (
                (NmtCommand, 'nmt_command', self._on_nmt_command),
                (NmtState, 'nmt_state', self._on_nmt_state))]
        # Raw CAN frames: ~/send_frames answers at once, drained with the services above.
        self._raw = RawFrameTopics(node, self.gateway.raw, lambda: None if self.active
                                   else INACTIVE, self.gateway.config.channel, **options)
        self._services.append(self._raw.service)
        for service in self._services:
            self._retry.retry_dropped_answers(service)

        self._states_publisher = node.create_publisher(NodeStates, '~/node_states',
                                                       NODE_STATES_QOS)
        # Changes are published by a thread of their own, not the bus thread; the lock
        # keeps the timer's publication from overtaking a newer picture.
        self._states_lock = threading.Lock()
        self._states_changed = PublishOnChange(self._publish_states, 'node states')
        self.gateway.monitor.add_listener(self._states_changed.changed)
        self.gateway.program.add_listener(self._states_changed.changed)
        self.gateway.boot.add_listener(self._states_changed.changed)  # a boot's download
        self._pdo_topics = PdoTopics(node, self.gateway.pdo, self._on_tpdo_message,
                                     lambda: self.active)
        self._diagnostics = Diagnostics(node, self.gateway, parameters.joints())
        self._timers = [node.create_timer(parameters.value('state_publish_period'),
                                          self._publish_states),
                        node.create_timer(parameters.value('diagnostics_period'),
                                          self._publish_diagnostics)]
        self._publish_states()
        config = self.gateway.config
        node.get_logger().info(
            f'CANopen gateway on {config.interface} channel {config.channel!r}; '
            f'simulated devices: {[d.node_id for d in self.simulated_devices] or "none"}')
        # Last: every parameter was read above, and a change now would be taken and ignored.
        self._parameters_read = node.add_on_set_parameters_callback(_refuse_changes)

    def _simulated_devices(self, parameters: NodeParameters) -> list:
        node_ids = parameters.node_ids('simulation.devices')
        bus = dict(interface=self.gateway.config.interface,
                   channel=self.gateway.config.channel)
        devices = []
        # Only for trying the gateway without hardware: a real bus never loads the simulator.
        if node_ids:
            from ..simulation.canopen_device import SimulatedDevice
            devices = [SimulatedDevice(node_id, parameters.simulation_eds(), **bus)
                       for node_id in node_ids]
        drive_ids = parameters.node_ids('simulation.drives')
        if drive_ids:
            from ..simulation.simulated_drives import simulated_drives
            devices += simulated_drives(drive_ids, self._node.get_logger().warning,
                                        parameters.value('simulation.drive_layout'), **bus)
        bootloader_ids = parameters.node_ids('simulation.bootloaders')
        if bootloader_ids:
            from ..simulation.durand.bootloader import BootloaderDevice
            devices += [BootloaderDevice(node_id, **bus) for node_id in bootloader_ids]
        return devices

    def activate(self) -> None:
        """Serve calls and publish (a managed node's activate transition)."""
        self.active = True
        self.gateway.set_operational(True)
        self._publish_states()
        self._drives.publish_states()  # changes while inactive were not published
        self._boots.publish()

    def deactivate(self) -> None:
        """Answer every new call "inactive", stop the drives and publishing.

        SDO calls under way finish, but for those with a drive that gets a stop (ended, so
        that its stop goes first); drive commands and moves under way are answered.
        """
        self.active = False
        self.gateway.drives.pause('the gateway was deactivated')
        self.gateway.set_operational(False)

    def shut_down(self) -> None:
        """Answer every waiting call ("shutting down"), abort running transfers, close the bus.

        SDO and mailbox answers leave from the thread that resolves them; this waits up to
        ``ANSWER_GRACE`` seconds for all to leave.
        """
        if not self._shutting_down:
            self._shutting_down = True
            self._answered_before_shutdown = self._calls.answered
            self._downloads_answered_before_shutdown = self._program.answered
        self.gateway.stop()
        self._program.wait_until_answered(ANSWER_GRACE)
        self._calls.wait_until_idle(ANSWER_GRACE)
        self._mailbox_loop.close()

    def destroy(self) -> None:
        """Shut down, stop the simulated devices and take the services and topics away."""
        refusing, self._parameters_read = self._parameters_read, None
        if refusing is not None:  # destroyed once before (a managed node's error, then exit)
            self._node.remove_on_set_parameters_callback(refusing)
        self.shut_down()
        for device in self.simulated_devices:
            device.stop()
        self._answer_the_last_requests()
        node = self._node
        for service in [deferred.service for deferred in self._deferred] + self._services:
            node.destroy_service(service)
        self._states_changed.close()
        for timer in self._timers:
            node.destroy_timer(timer)
        with self._states_lock:
            publisher, self._states_publisher = self._states_publisher, None
        node.destroy_publisher(publisher)
        self._emcy.destroy()
        self._drives.destroy()
        self._program.destroy()
        self._boots.close()
        self._pdo_topics.destroy()
        self._raw.destroy()
        self._diagnostics.destroy()
        logging.getLogger(PACKAGE).removeHandler(self._log_handler)

    def _answer_the_last_requests(self) -> None:
        """Answer requests the executor never took, and give every answer time to leave.

        Logs how many calls shutdown answered, and any call taken but never answered.
        """
        lingered = 0.0
        answered_then = self._answered_before_shutdown
        # A download's result leaves through the action's own writer, which goes with it.
        downloads_then = self._downloads_answered_before_shutdown
        plain = 0  # drained calls of the services answered in the callback (NMT)
        for _ in range(LINGER_ROUNDS):
            drained, plain_drained = self._drain()
            plain += plain_drained
            if (not drained and self._calls.answered == answered_then
                    and self._program.answered == downloads_then
                    and not self._retry.waiting):
                break
            answered_then = self._calls.answered
            downloads_then = self._program.answered
            time.sleep(ANSWER_LINGER)
            lingered += ANSWER_LINGER
        else:  # what arrived during the last wait is answered, not waited for
            plain += self._drain()[1]
        self._retry.close()
        answered = self._calls.answered - self._answered_before_shutdown + plain
        logger = self._node.get_logger()
        logger.info(f'shutdown: {answered} calls answered while shutting down; services kept '
                    f'{lingered:.1f} s for the answers to reach their callers')
        if self._calls.waiting:
            logger.error(f'shutdown: {self._calls.waiting} calls taken were never answered')

    def _drain(self) -> Tuple[int, int]:
        """Answer the requests waiting in the services; return (how many, how many of NMT)."""
        plain = sum(drain(service) for service in self._services)
        drained = plain + sum(drain(deferred.service) for deferred in self._deferred)
        self._calls.wait_until_idle(ANSWER_GRACE)
        return drained, plain

    def _start_read(self, request) -> Future:
        if not self.active:
            return resolved(SdoResult.aborted(INACTIVE_ABORT, INACTIVE))
        return self.gateway.sdo_read(request.node_id, request.index, request.subindex,
                                     request.max_size, request.timeout)

    def _start_write(self, request) -> Future:
        if not self.active:
            return resolved(SdoResult.aborted(INACTIVE_ABORT, INACTIVE))
        return self.gateway.sdo_write(request.node_id, request.index, request.subindex,
                                      bytes(request.data), request.timeout)

    def _start_batch(self, request) -> Future:
        if not self.active:
            return resolved([SdoResult.aborted(INACTIVE_ABORT, INACTIVE)
                             for _ in request.accesses])
        return self.gateway.sdo_batch(
            [Access(a.node_id, a.index, a.subindex, a.write, bytes(a.data), a.max_size)
             for a in request.accesses], request.timeout)

    def _start_pdo_write(self, request) -> Future:
        if not self.active:
            return resolved(SdoResult.aborted(INACTIVE_ABORT, INACTIVE))
        problem = check_request(request.node_id, request.pdo)
        if problem:
            return resolved(SdoResult.failed(problem))
        return self.gateway.pdo.write(request.node_id, request.pdo,
                                      entry_values(request.entries), bytes(request.data))

    def _on_tpdo_message(self, node_id: int, message) -> None:
        """Send what arrived on ~/node_<id>/tpdo; a refusal is logged once and counted."""
        topic = f'node_{node_id}/tpdo'
        if not self.active:
            problem = INACTIVE
        elif message.node_id not in (0, node_id):
            problem = f'node_id {message.node_id} is not the node of the topic ({node_id})'
        else:
            problem = check_request(node_id, message.pdo)
        if problem:
            self.gateway.pdo.refuse(node_id, f'{topic}: {problem}')
            return
        try:
            written = self.gateway.pdo.write(node_id, message.pdo,
                                             entry_values(message.entries), bytes(message.data))
        except Exception as error:  # noqa: BLE001 - it would end the node's executor
            self.gateway.pdo.refuse(node_id, f'{topic}: internal error of the gateway: '
                                             f'{type(error).__name__}: {error}')
            return
        written.add_done_callback(lambda done: self._log_refused(node_id, topic, done))

    def _log_refused(self, node_id: int, topic: str, done: Future) -> None:
        result = done.result()
        if not result.success:
            self.gateway.pdo.log_refusal(node_id, f'{topic}: {result.message}')

    def _start_mailbox(self, request) -> Future:
        registers = list(request.registers)
        if not self.active:
            return resolved((registers, INACTIVE))
        running = self._mailbox_loop.submit(self._execute_mailbox(request.format, registers))
        return running or resolved((registers, SHUTTING_DOWN))

    def _start_lss_scan(self, request) -> Future:
        if not self.active:
            return resolved(LssResult(False, INACTIVE))
        return self.gateway.lss.scan(request.first_node_id, request.store, request.timeout)

    def _start_lss_configure(self, request) -> Future:
        if not self.active:
            return resolved(LssResult(False, INACTIVE))
        return self.gateway.lss.configure(_identity(request.identity), request.node_id,
                                          request.bitrate, request.store, request.timeout)

    def _start_lss_inquire(self, request) -> Future:
        if not self.active:
            return resolved(LssResult(False, INACTIVE))
        return self.gateway.lss.inquire(_identity(request.identity), request.timeout)

    async def _execute_mailbox(self, block_format: str, registers: list):
        if self._shutting_down:  # its turn came after shutdown began: it sent nothing
            return registers, f'{SHUTTING_DOWN}; nothing was sent'
        try:
            return await self._mailbox.execute(block_format, registers)
        except asyncio.CancelledError:  # shutdown ends the loop: answer, do not vanish
            return registers, SHUTTING_DOWN

    def _on_nmt_command(self, request, response):
        if not self.active:
            response.success, response.abort_code, response.message = (False, INACTIVE_ABORT,
                                                                        INACTIVE)
            return response
        result = self.gateway.nmt_command(request.node_id, request.command)
        response.success = result.success
        response.abort_code = result.abort_code
        response.message = result.message
        return response

    def _on_nmt_state(self, request, response):
        problem = INACTIVE if not self.active else check_node_id(request.node_id, '1..127',
                                                                 lowest=1)
        if not self.active:
            response.abort_code = INACTIVE_ABORT
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

    def _publish_emcy(self, emergency) -> None:
        if self.active:
            self._emcy.publish(emergency)

    def _publish_diagnostics(self) -> None:
        if self.active:
            self._diagnostics.publish()
        else:
            self._diagnostics.skip()

    def _publish_states(self) -> None:
        with self._states_lock:
            if not self.active or self._states_publisher is None:
                return
            message = NodeStates(stamp=self._node.get_clock().now().to_msg())
            programming = self.gateway.programming()
            message.nodes = [
                NodeState(node_id=status.node_id, state=status.state,
                          state_name=status.state_name,
                          last_seen=_time(status.last_seen) if status.last_seen else Time(),
                          programming=status.node_id in programming)
                for status in self.gateway.monitor.statuses()]
            self._states_publisher.publish(message)
