"""The gateway core: one CAN bus, one canopen Network, SDO channels, NMT, node states, EMCY.

Knows nothing of ROS. The ROS node (``node.py``) and the PLC mailbox (``mailbox.py``) are
both thin layers over :class:`Gateway`, so there is exactly one SDO and one NMT code path.
The bus itself is owned by a :class:`~cbcan_ros.bus.BusSupervisor`, which reopens it after
any fault; the gateway answers every waiting call when the bus goes down or shuts down.
"""

from concurrent.futures import Future
from dataclasses import dataclass, field
import logging
import threading
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import can
import canopen
from canopen import objectdictionary as od

from . import eds, nmt
from .boot.description import BusDescription
from .boot.plan import boot_settings, HEARTBEAT_PERIODS
from .boot.service import BootService
from .bus import BusDown, BusStatus, BusSupervisor
from .canopen_gaps import version_problem
from .canopen_gaps.local_node import without_heartbeat_producer
from .canopen_gaps.sdo_client import StrictSdoClient
from .drives.service import DriveService
from .drives.status import DriveSettings
from .emcy import EmcyMonitor
from .heartbeat_producer import HeartbeatProducer
from .lss.frames import is_all_waiting, probe_wait
from .lss.master import LssMaster
from .pdo.service import PdoService
from .pdo.sync import SyncProducer
from .program.download import ProgramSettings, Progress
from .program.service import ProgramService
from .python_can_gaps.own_frames import drop_own_frames
from .python_can_gaps.receive_buffer import deepen_receive_buffer
from .raw.frames import canopen_ids, echoes, RawFrames, RawSettings
from .sdo import abort_codes
from .sdo.channel import SdoChannel, SdoStatistics
from .sdo.request_queue import answer, Deadlines, resolved
from .sdo.requests import Access, batch_refusal, check_node_id, one_each, refusal, SdoResult
from .sdo.transfer import run_local
from .sdo.write_protection import WriteProtection
from .text import HEARTBEAT_SILENT, SHUTTING_DOWN

LOGGER = logging.getLogger(__name__)

VERSION = '0.1.0'

# canopen's notifier thread polls the bus once a second by default, and closing the
# network waits for that poll: a shorter cycle lets a simulated device stop at once.
NOTIFIER_CYCLE = 0.05


@dataclass(frozen=True)
class GatewayConfig:
    """Everything the core needs to know; the ROS node fills it from parameters."""

    interface: str = 'virtual'
    channel: str = 'cbcan'
    bitrate: int = 0
    sdo_timeout: float = 0.5
    block_transfer: bool = False
    heartbeat_timeout: float = 3.0
    expected_nodes: Tuple[int, ...] = ()
    guarded_nodes: Tuple[int, ...] = ()
    guard_period: float = 1.0
    queue_limit: int = 64
    read_retries: int = 0
    write_protection: WriteProtection = WriteProtection()
    bus_options: Dict[str, object] = field(default_factory=dict)
    lss_probe_timeout: float = 0.0  # 0: derived from the bit rate
    pdo_nodes: Tuple[int, ...] = ()
    pdo_configure: bool = False  # the PDO parameters of each one's file written at each boot
    device_files: Dict[int, str] = field(default_factory=dict)  # node id: EDS/DCF path
    sync_period: float = 0.0
    sync_counter_overflow: int = 0
    heartbeat_node_id: int = 0  # the gateway's own heartbeat (0x700 + id); 0: none
    heartbeat_period: float = 0.1
    drives: DriveSettings = DriveSettings()  # its nodes are watched and PDO-served as well
    raw: RawSettings = RawSettings()  # raw CAN frames beside CANopen (raw.filters, send_allow)
    # Every device it names checked, configured and started at each boot (bus_config)
    bus_description: Optional[BusDescription] = None
    program: ProgramSettings = ProgramSettings()  # program downloads (CiA 302-3)


@dataclass(frozen=True)
class NmtResult:
    """The answer to an NMT command (``abort_code`` set when write protection refused it)."""

    success: bool
    message: str = ''
    abort_code: int = 0


def _closes_a_running_operation(message: can.Message) -> bool:
    """Return whether ``message`` may go out after shutdown began.

    Only what closes an operation that was running: an SDO transfer's abort, or the LSS
    switch of every device back to waiting.
    """
    sdo_abort = 0x600 <= message.arbitration_id <= 0x67F and message.data[:1] == b'\x80'
    return sdo_abort or is_all_waiting(message)


def _variable(name, index, subindex, data_type, access, default):
    variable = od.ODVariable(name, index, subindex)
    variable.data_type = data_type
    variable.access_type = access
    variable.default = default
    return variable


def own_dictionary(heartbeat_time: int = 0) -> canopen.LocalNode:
    """Build the gateway's own object dictionary (node id 0 in the services).

    The dictionary is not on the bus: its services answer as node 0 whatever the node id of
    the gateway's heartbeat. 0x1017 holds ``heartbeat_time`` (ms) at start and is writable as
    CiA 301 requires; it only informs: the heartbeat follows its parameters, not writes.
    """
    dictionary = od.ObjectDictionary()
    dictionary.add_object(_variable('Device type', 0x1000, 0, od.UNSIGNED32, 'ro', 0))
    dictionary.add_object(_variable('Error register', 0x1001, 0, od.UNSIGNED8, 'ro', 0))
    dictionary.add_object(_variable('Manufacturer device name', 0x1008, 0,
                                    od.VISIBLE_STRING, 'const', 'cbcan_ros gateway'))
    dictionary.add_object(_variable('Manufacturer software version', 0x100A, 0,
                                    od.VISIBLE_STRING, 'const', VERSION))
    dictionary.add_object(_variable('Producer heartbeat time', 0x1017, 0,
                                    od.UNSIGNED16, 'rw', heartbeat_time))
    identity = od.ODRecord('Identity object', 0x1018)
    for subindex, name, data_type, value in (
            (0, 'Highest sub-index supported', od.UNSIGNED8, 4),
            (1, 'Vendor-ID', od.UNSIGNED32, 0),
            (2, 'Product code', od.UNSIGNED32, 0xCBCA),
            (3, 'Revision number', od.UNSIGNED32, 0x00010000),
            (4, 'Serial number', od.UNSIGNED32, 0)):
        identity.add_member(_variable(name, 0x1018, subindex, data_type,
                                      'const' if subindex == 0 else 'ro', value))
    dictionary.add_object(identity)
    dictionary.node_id = 0  # canopen reads a node id of 0 as "take it from the dictionary"
    return without_heartbeat_producer(canopen.LocalNode(0, dictionary))


class Gateway:
    """One CAN bus with its CANopen devices, as seen by the master.

    SDO requests return ``concurrent.futures.Future`` objects that always resolve to exactly
    one :class:`SdoResult`, within the request's timeout; they never raise and never block
    the caller.
    """

    def __init__(self, config: GatewayConfig):
        problem = version_problem()
        if problem:  # canopen_gaps would patch internals this release may not have
            raise RuntimeError(problem)
        self.config = config
        self.network = canopen.Network()
        self.bus = BusSupervisor(self.network, self._open_bus,
                                 f'{config.interface}:{config.channel}')
        self.heartbeat = HeartbeatProducer(self.bus, config.heartbeat_node_id,
                                           config.heartbeat_period)
        own_id = config.heartbeat_node_id
        self.dictionary = own_dictionary(round(config.heartbeat_period * 1000) if own_id else 0)
        drives = config.drives.node_ids
        # The gateway's own heartbeat comes back on buses that echo (udp_multicast): it is no
        # device, and LSS must never give its node id to one.
        self.monitor = nmt.HeartbeatMonitor(self.network, config.heartbeat_timeout,
                                            sorted({*config.expected_nodes, *drives}),
                                            ignored=(own_id,))
        self._guarding = nmt.NodeGuarding(self.network, config.guarded_nodes,
                                          config.guard_period)
        self.emcy = EmcyMonitor(self.network)
        self.sync = SyncProducer(self.bus, self.network, config.sync_period,
                                 config.sync_counter_overflow)
        pdo_nodes = {*config.pdo_nodes, *drives}
        described = {device.node_id for device in (
            config.bus_description.devices if config.bus_description else ())}
        dictionaries = {node_id: eds.load(path, node_id) for node_id, path
                        in config.device_files.items()
                        if node_id in pdo_nodes or node_id in described}
        boots = boot_settings(
            config.bus_description, sorted(pdo_nodes) if config.pdo_configure else (),
            dictionaries, own_id,
            lambda node_id: round(1000 * (config.drives.consumer_time if node_id in drives
                                          else HEARTBEAT_PERIODS * config.heartbeat_period)),
            drives, pdo_nodes,
            drives if config.drives.abort_connection is not None else ())
        self._watch_as_booted(boots, config)
        self.pdo = PdoService(self.network, sorted(pdo_nodes), self.sdo_batch,
                              config.write_protection, self.sync,
                              {node_id: dictionaries[node_id] for node_id in pdo_nodes
                               if node_id in dictionaries},
                              [plan.node_id for plan in boots.plans if plan.pdos and plan.boot])
        self.drives = DriveService(self.network, config.drives, self.monitor, self.pdo,
                                   lambda accesses, timeout, stop=None: self._batch(
                                       accesses, timeout, True, stop),
                                   self.sync, config.write_protection, self._bus_down,
                                   self.heartbeat.beat_now, self._end_drive_transfers)
        self.emcy.add_listener(lambda emergency: self.drives.on_emcy(
            emergency.node_id, emergency.error_code))
        if self.heartbeat.producing and config.drives.consumer_time:
            # Drives watch the gateway's heartbeat: held up longer than they watch it, the
            # gateway finds them stopped by themselves, and sends nothing that enables.
            self.heartbeat.watch_silence(config.drives.consumer_time,
                                         self.drives.after_gateway_silence)
            self.pdo.hold_frames_while(self._silent_too_long)
            self.drives.hold_back_while(self._silent_too_long)
            self.sync.hold_while(self._silent_too_long)
        self._deadlines = Deadlines()
        self.boot = BootService(self.network, boots, self.sdo_batch, self._send_nmt,
                                self.pdo, self.monitor, self._deadlines, config.sdo_timeout,
                                self.drives.enabled, self.sdo_stream, config.program)
        self.program = ProgramService(self.network, self.sdo_batch, self.sdo_stream,
                                      self.monitor, self.drives.enabled,
                                      config.write_protection.refuses_write, config.program)
        self.drives.refuse_enable_when(
            lambda node_id: self.boot.refusal(node_id) or self.program.refusal(node_id))
        # A device's boot and a program download of it never run at once.
        self.boot.hold_while(self.program.refusal, self.program.cleared)
        self.program.refuse_when(lambda request: self.boot.booting(request.node_id)
                                 or self.boot.program_conflict(
                                     request.node_id, request.program,
                                     request.expected_software_id))
        self.program.add_listener(self.boot.program_changed)
        echoing = echoes(config.interface, config.bus_options)
        # Set at every open of the bus: whether the kernel drops the frames the gateway sent.
        self._own_frames_dropped = False
        self.raw = RawFrames(self.bus, config.raw, config.write_protection,
                             lambda: canopen_ids(self.pdo),
                             lambda: echoing and not self._own_frames_dropped)
        self.lss = LssMaster(
            self.network, self._deadlines,
            probe_wait(config.interface, config.bitrate, config.lss_probe_timeout),
            used_ids=lambda: {s.node_id for s in self.monitor.statuses()}.union(
                config.guarded_nodes, (own_id,) if own_id else ()),
            detected=lambda node_id: (bool(own_id) and node_id == own_id
                                      or self.monitor.status(node_id).detected),
            refusal=self._lss_refusal)
        self._channels: Dict[int, SdoChannel] = {}
        self._lock = threading.Lock()
        self._closing = False
        self._stopping_drives = False
        self.bus.add_listener(self._on_bus_change)

    def _silent_too_long(self) -> Optional[str]:
        """Return why nothing but a stop goes out now: the heartbeat silent too long.

        Not while the bus is down: that is the cause a caller is told, and nothing goes out.
        """
        silent = self.heartbeat.silent_too_long()
        return None if silent is None or self.bus.down_reason is not None else (
            f'{HEARTBEAT_SILENT} for {silent:.2f} s, longer than the drives watch it: they '
            f'stopped by themselves, and are quick-stopped as it goes on')

    @property
    def bus_status(self) -> BusStatus:
        """Return whether the bus is up, why not, and how often it was reopened."""
        return self.bus.status

    def programming(self) -> Dict[int, Progress]:
        """Return the devices being programmed now (an action's download or a boot's)."""
        return {**self.boot.programming(), **self.program.programming()}

    def sdo_statistics(self) -> Dict[int, SdoStatistics]:
        """Return the SDO statistics of every device that was sent a request, by node id."""
        with self._lock:
            channels = dict(self._channels)
        return {node_id: channel.statistics() for node_id, channel in sorted(channels.items())}

    def start(self) -> None:
        """Open the bus (or keep trying in the background) and watch node states."""
        self.monitor.start()
        self.emcy.start()
        self.sync.start()
        self.pdo.start()
        self.drives.start()
        self._guarding.start()
        self.lss.start()
        self.bus.start()
        self.heartbeat.start()  # on the open bus, so the first beat goes out
        self.boot.start()

    def set_operational(self, active: bool) -> None:
        """Say OPERATIONAL (active) or PRE_OPERATIONAL (a managed node inactive) in heartbeats."""
        self.heartbeat.set_operational(active)

    def stop(self) -> None:
        """Answer every waiting call, abort running transfers, then close the bus.

        From the first moment of shutdown no caller's request is sent. What may still go out:
        the drives' stop commands (``drives.on_shutdown``, first, with the heartbeat still
        beating), then only the aborts of transfers that were running.
        """
        with self._lock:
            if self._closing:
                return
            self._closing = True
            self._stopping_drives = True
        # The downloads, the boots and the PDO service first: a download ends between two
        # segments with an abort and is answered, nothing more is written for a boot, and
        # mapping reads, refused from here on, are no failures.
        self.program.stop()
        self.boot.stop()
        self.pdo.stop()
        # No caller's raw frame after this (a call under way ends before its next frame):
        # one to a drive after its stop would undo it.
        self.raw.stop()
        # The drives' stop commands go next, while the bus is open; callers' requests are
        # refused from here on, the drive service's are taken until its stops are sent, and
        # TPDOs until the drives' statuswords show them.
        self.drives.stop()
        self.pdo.stop_receiving()
        with self._lock:
            self._stopping_drives = False
            channels = list(self._channels.values())
        # The drives were told to stop before their heartbeat consumers see the gateway fall
        # silent; then no heartbeat frame after the first moment of shutdown.
        self.heartbeat.stop()
        self.sync.stop()
        self.bus.restrict_sending(_closes_a_running_operation, SHUTTING_DOWN)
        self._guarding.stop()
        self.lss.close(SHUTTING_DOWN)
        for channel in channels:
            channel.close(SHUTTING_DOWN, abort_codes.DEVICE_STATE)
        for channel in channels:
            channel.join(1.0)
        self.monitor.stop()
        self.emcy.stop()
        self._deadlines.stop()
        self.bus.stop()

    def _end_drive_transfers(self, reason: str, node_ids: List[int]) -> None:
        """End the transfers under way with drives ``node_ids``; answer what waits, ``reason``.

        Before their stops, at shutdown and when a managed node is deactivated (see
        ``DriveService._stop_motion``).
        """
        with self._lock:
            channels = [self._channels[node_id] for node_id in node_ids
                        if node_id in self._channels]
        for channel in channels:
            channel.fail_all(reason, abort_codes.DEVICE_STATE)

    def sdo_read(self, node_id: int, index: int, subindex: int, max_size: int = 0,
                 timeout: float = 0.0) -> 'Future[SdoResult]':
        """Read ``index:subindex`` of ``node_id`` (0 = the gateway's own dictionary)."""
        return self._single(Access(node_id, index, subindex, max_size=max_size), timeout)

    def sdo_write(self, node_id: int, index: int, subindex: int, data: bytes,
                  timeout: float = 0.0) -> 'Future[SdoResult]':
        """Write ``data`` to ``index:subindex`` of ``node_id`` (0 = own dictionary)."""
        access = Access(node_id, index, subindex, True, bytes(data))
        settle = self._followed_by_drives([access])
        written = self._single(access, timeout)
        written.add_done_callback(settle)
        return written

    def sdo_stream(self, access: Access, answer_within: float,
                   written: Callable[[int], Optional[str]]) -> 'Future[SdoResult]':
        """Write a large object (a program image) to a device: ``SdoChannel.stream``."""
        refused = refusal(access, answer_within, self.config.write_protection)
        if refused is None and access.node_id == 0:
            refused = SdoResult.failed("node_id 0 (the gateway's own dictionary) takes no "
                                       'stream; nothing was sent')
        if refused is not None:
            return resolved(refused)
        return self._channel_for(access.node_id, None, lambda channel: channel.stream(
            access, answer_within, written))

    def sdo_batch(self, accesses: Sequence[Access], timeout: float = 0.0,
                  stop=None) -> 'Future[List[SdoResult]]':
        """Run ``accesses``: in order per device, devices in parallel; one result each.

        The timeout bounds the whole batch. Each device's part waits in that device's queue
        as one request. A batch of more than ``sdo.MAX_BATCH`` accesses is refused whole.
        ``stop(results so far)``, asked before each access of a device's part is sent, says
        why the rest of that part must not be sent, or None.
        """
        settle = self._followed_by_drives(accesses)
        done = self._batch(accesses, timeout, False, stop)
        done.add_done_callback(settle)
        return done

    def _followed_by_drives(self, accesses: Sequence[Access]) -> Callable[[Future], None]:
        """Have the drive service follow what ``accesses`` write to drives, as they are sent.

        So nothing the gateway keeps of a drive undoes a caller's write
        (``DriveService.writing``). Return what tells it, given the write's future (one
        result, or a batch's list), which writes succeeded.
        """
        following = {}
        for position, access in enumerate(accesses):
            if access.write:
                settle = self.drives.writing(access.node_id, access.index, access.subindex,
                                             access.data)
                if settle is not None:
                    following[position] = settle

        def settle_all(done: Future) -> None:
            if not following or done.cancelled():  # a caller gave up on it: it may have gone
                return
            results = done.result()
            results = results if isinstance(results, list) else [results]
            for position, settle in following.items():
                settle(results[position].success)
        return settle_all

    def _batch(self, accesses: Sequence[Access], timeout: float,
               drive_stop: bool, stop=None) -> 'Future[List[SdoResult]]':
        """Run a batch; ``drive_stop``: the drive service's, taken while it stops the drives."""
        refused = batch_refusal(accesses, timeout)
        if refused is not None:
            return resolved(one_each(refused, len(accesses)))
        results: List[Optional[SdoResult]] = [None] * len(accesses)
        per_device: Dict[int, List[int]] = {}
        for position, access in enumerate(accesses):
            refused = refusal(access, timeout, self.config.write_protection)
            if refused is not None:
                results[position] = refused
            elif access.node_id == 0:
                results[position] = run_local(self.dictionary, access)
            else:
                per_device.setdefault(access.node_id, []).append(position)
        done: Future = Future()
        parts = {node_id: self._channel_for(node_id, len(positions), lambda channel, p=positions:
                                            channel.batch([accesses[i] for i in p],
                                                          timeout or self.config.sdo_timeout,
                                                          stop),
                                            drive_stop)
                 for node_id, positions in per_device.items()}
        remaining = [len(parts)]
        lock = threading.Lock()

        def collect(node_id: int, part: Future) -> None:
            for position, result in zip(per_device[node_id], part.result(), strict=True):
                results[position] = result
            with lock:
                remaining[0] -= 1
                finished = remaining[0] == 0
            if finished:  # a caller may have cancelled it (asyncio.wrap_future does)
                answer(done, results)

        if not parts:
            done.set_result(results)
        for node_id, part in parts.items():
            part.add_done_callback(lambda future, n=node_id: collect(n, future))
        return done

    def _watch_as_booted(self, boots, config: GatewayConfig) -> None:
        """Lose a booted device after 3 of the heartbeat periods its boot gives it.

        A device given none (0) and not guarded sends nothing to watch: it is never lost.
        """
        timeouts = {}
        for plan in boots.plans:
            if not plan.boot or plan.node_id in config.guarded_nodes:
                continue
            timeouts[plan.node_id] = loss_time = plan.loss_time(config.heartbeat_timeout)
            if loss_time is None:
                LOGGER.warning('node %s: its heartbeat_producer is 0 in the bus description and '
                               'it is not in node_guarding: the gateway cannot tell when it is '
                               'gone, and shows the last state it reported', plan.label)
        self.monitor.set_timeouts(timeouts)

    def nmt_command(self, node_id: int, command: int) -> NmtResult:
        """Send NMT ``command`` to ``node_id`` (0 = all nodes); checked before sending.

        A caller's command: STOP to an enabled drive is refused.
        """
        problem = check_node_id(node_id, '0..127 (0 = all nodes)')
        if problem:
            return NmtResult(False, problem)
        if command not in nmt.COMMAND_NAMES:
            known = ', '.join(f'{code} {name}' for code, name in nmt.COMMAND_NAMES.items())
            return NmtResult(False, f'command {command} is not an NMT command: allowed {known}')
        enabled = [drive for drive in self.drives.node_ids if command == nmt.STOP
                   and node_id in (0, drive) and self.drives.enabled(drive)]
        if enabled:
            # STOPPED, it takes neither PDO nor SDO: no target, halt or stop reaches it, and
            # many drives run on at their last target. (Pre-operational and the resets leave
            # SDO, which the drive service then uses: ``HeartbeatMonitor.commanded``.)
            return NmtResult(False, f'drive {enabled[0]} is OPERATION_ENABLED: NMT STOP would '
                                    f"cut it off from the gateway's targets and stops (no PDO, "
                                    f'no SDO) while it may run on; disable it first '
                                    f'(drive_command disable or quick_stop)',
                             abort_codes.DEVICE_STATE)
        return self._send_nmt(node_id, command)

    def _send_nmt(self, node_id: int, command: int) -> NmtResult:
        """Send a valid NMT ``command`` (the boot's own, and callers' once checked)."""
        refusal = self.config.write_protection.refuses_nmt()
        if refusal:
            return NmtResult(False, refusal, abort_codes.LOCAL_CONTROL)
        try:
            self.network.send_message(0, bytes([command, node_id]))
        except BusDown as error:
            return NmtResult(False, f'the NMT command was not sent: {error}')
        finally:  # sent or not: a heartbeat from before it tells nothing of after it
            self.monitor.commanded(node_id, command)
        return NmtResult(True)

    def _lss_refusal(self) -> Optional[str]:
        refusal = self.config.write_protection.refuses_lss()
        if refusal:
            return refusal
        if self._closing:
            return SHUTTING_DOWN
        return self._bus_down()

    def _bus_down(self) -> Optional[str]:
        reason = self.bus.down_reason
        return None if reason is None else f'the CAN bus is down: {reason}'

    def _silence_of(self, node_id: int) -> str:
        """Return how long ``node_id`` has not been heard on the bus, '' while it is heard."""
        status = self.monitor.status(node_id)
        if status.detected:
            return ''
        if status.last_seen is None:
            return (f'node {node_id} has not been heard on the bus since the gateway started '
                    f'(no heartbeat, boot-up or node guarding reply): check its node id, bit '
                    f'rate, power and wiring')
        return (f'node {node_id} has not been heard for {status.last_seen_age:.1f} s '
                f'(NOT_DETECTED)')

    def _open_bus(self) -> can.BusABC:
        options = dict(self.config.bus_options)
        if self.config.bitrate:
            options['bitrate'] = self.config.bitrate
        bus = can.Bus(interface=self.config.interface, channel=self.config.channel, **options)
        deepen_receive_buffer(bus)
        self._own_frames_dropped = drop_own_frames(bus)
        return bus

    def _on_bus_change(self, status: BusStatus) -> None:
        self.boot.on_bus_change(status)
        if status.up:
            return
        with self._lock:
            channels = list(self._channels.values())
        for channel in channels:
            channel.fail_all(f'the CAN bus is down: {status.reason}')
        self.lss.fail_all(f'the CAN bus is down: {status.reason}')
        self.monitor.lose_all()
        self.pdo.on_bus_change(status)

    def _single(self, access: Access, timeout: float) -> 'Future[SdoResult]':
        refused = refusal(access, timeout, self.config.write_protection)
        if refused is not None:
            return resolved(refused)
        if access.node_id == 0:
            return resolved(run_local(self.dictionary, access))
        return self._channel_for(access.node_id, None, lambda channel: channel.single(
            access, timeout or self.config.sdo_timeout))

    def _channel_for(self, node_id: int, count: Optional[int], request,
                     drive_stop: bool = False) -> Future:
        """Hand a request to the device's channel; ``count`` accesses (None: one).

        ``drive_stop``: the drive service's request, which may still go while it sends its
        stops at the start of shutdown.
        """
        def refused(message: str) -> Future:
            return resolved(one_each(SdoResult.failed(message), count))

        down = self._bus_down()
        with self._lock:
            if self._closing and not (drive_stop and self._stopping_drives):
                return refused(f'{SHUTTING_DOWN}; nothing was sent')
            if down:
                return refused(f'{down}; nothing was sent')
            channel = self._channels.get(node_id)
            if channel is None:
                client = StrictSdoClient(0x600 + node_id, 0x580 + node_id,
                                         od.ObjectDictionary())
                client.network = self.network
                self.network.subscribe(client.tx_cobid, client.on_response)
                channel = SdoChannel(client, node_id, self._deadlines,
                                     self.config.block_transfer, self.config.queue_limit,
                                     self.config.read_retries,
                                     lambda: self._silence_of(node_id))
                self._channels[node_id] = channel
        return request(channel)
