"""A simulated CANopen device built on durand, a device stack independent of python-canopen.

The devices of ``simulation.py`` run on python-canopen, the library our SDO client is built
on, so a defect the two sides share stays hidden. :class:`DurandDevice` answers with durand's
SDO server (expedited, segmented, block both ways), NMT slave, heartbeat and EMCY producers,
on a python-can bus of its own, with the dictionary of ``config/simulated_device.eds``.

durand 0.5.0 needs a few guards, all kept in this module (durand itself is not patched):

- ``SyncScheduler`` sleeps until the earliest timer it knew of when it went to sleep, so a
  timer added meanwhile (another device's shorter heartbeat) fires up to the longest period
  late; and cancelling a timer while it fires fails inside durand, which then silently keeps
  the old heartbeat. :class:`_Scheduler` wakes on every new timer and fires timers under one
  lock that everything driving durand holds.
- Its SDO server ends a block upload with n=7 when the last segment is full (sizes that are a
  multiple of 7): the client drops 7 bytes and fails its CRC check. Rewritten on the way out.
- It ignores an SDO abort whose index it does not know (python-canopen's client aborts with
  0000:00), so the block transfer stays open and answers the next request; and a transfer a
  master abandons stays open for ever. Both are dropped here.
- ``CANBusNetwork`` drops remote frames (node guarding) and polls with a 1 s cycle, so
  closing it waits up to 1 s: :class:`_Network` replaces it.
- LSS (``lss=True``): a durand node with node id 255 (unconfigured) still sends a boot-up
  message and heartbeats, on 0x7FF; a device without a node id sends nothing but LSS answers,
  so everything else is held back until it has one. When LSS gives it an id, durand boots it
  (boot-up, heartbeats, SDO server on the new id), but the SDO guards here stay keyed to
  the old id: they follow the id on every boot.
- Its TPDOs have no event timer (0x1800+n sub 5): added here, transmitting an event-driven
  TPDO every event timer period while it is active. Its PDO parameters survive a reset; a
  device restores its stored ones: :class:`PdoConfig` lists those, applied at every boot.
"""

from dataclasses import dataclass
import logging
import sched
import struct
import threading
import time
from typing import Callable, Dict, Optional, Sequence, Tuple, Union

import can
import durand
from durand.datatypes import DatatypeEnum as DT
from durand.network import NetworkABC
from durand.node import NodeCapabilities
from durand.object_dictionary import Record, Variable
from durand.services.nmt import StateEnum
from durand.services.sdo.server import SDODomainAbort, TransferState

from ..core import nmt

LOGGER = logging.getLogger(__name__)

SLOW_INDEX = 0x2200
DOMAIN_INDEX = 0x2020
DOMAIN_MAX_SIZE = 65536
DOMAIN_DEFAULT = bytes(range(200))
HEARTBEAT_INDEX = 0x1017
HEARTBEAT_DEFAULT = 200  # ms, as config/simulated_device.eds
EMCY_INHIBIT_INDEX = 0x1015
COMMUNICATION_PROFILE = range(0x1000, 0x2000)
WHOLE_DICTIONARY = range(0x0000, 0x10000)
NMT_COB = 0x000
SDO_RX_BASE = 0x600
SDO_TX_BASE = 0x580
LSS_MASTER_COB = 0x7E5
LSS_SLAVE_COB = 0x7E4
UNCONFIGURED = 0xFF
IDENTITY_INDEX = 0x1018
IDENTITY = (0x0, 0x51, 0x10000, 0x0)  # 0x1018:1..4 as config/simulated_device.eds

ABORT_LENGTH_TOO_HIGH = 0x06070012

# One SDO server, 4 PDOs each way (the predefined connection set) and no LSS: durand's
# defaults (128 SDO servers, 512 PDOs each way) would only slow the construction down.
PDOS = 4
CAPABILITIES = NodeCapabilities(sdo_servers=1, rpdos=PDOS, tpdos=PDOS)
TPDO_COMMUNICATION = 0x1800
EVENT_TIMER_SUB = 5


@dataclass(frozen=True)
class PdoConfig:
    """One PDO's parameters as a device stores them (applied at every boot).

    ``kind`` 'tpdo' (the device sends it) or 'rpdo' (it receives it); ``number`` 1..4;
    ``mapping`` the mapped objects (index, subindex), each its full size.
    """

    kind: str
    number: int
    mapping: Tuple[Tuple[int, int], ...]
    transmission_type: int = 255
    event_timer: int = 0  # ms, TPDOs only
    enabled: bool = True

# (index, subindex, datatype, access, default, name), as config/simulated_device.eds.
OBJECTS = (
    (0x1000, 0, DT.UNSIGNED32, 'ro', 0x00020192, 'Device type'),
    (0x1001, 0, DT.UNSIGNED8, 'ro', 0, 'Error register'),
    (0x1008, 0, DT.VISIBLE_STRING, 'const', b'cbcan simulated device',
     'Manufacturer device name'),
    (0x100A, 0, DT.VISIBLE_STRING, 'const', b'1.0', 'Manufacturer software version'),
    (HEARTBEAT_INDEX, 0, DT.UNSIGNED16, 'rw', HEARTBEAT_DEFAULT, 'Producer heartbeat time'),
    (0x1018, 1, DT.UNSIGNED32, 'ro', 0x0, 'Vendor-ID'),
    (0x1018, 2, DT.UNSIGNED32, 'ro', 0x51, 'Product code'),
    (0x1018, 3, DT.UNSIGNED32, 'ro', 0x10000, 'Revision number'),
    (0x1018, 4, DT.UNSIGNED32, 'ro', 0x0, 'Serial number'),
    (0x2000, 0, DT.UNSIGNED8, 'rw', 0x12, 'Demo UNSIGNED8'),
    (0x2001, 0, DT.UNSIGNED16, 'rw', 0x1234, 'Demo UNSIGNED16'),
    (0x2002, 0, DT.UNSIGNED32, 'rw', 0x12345678, 'Demo UNSIGNED32'),
    (0x2003, 0, DT.INTEGER32, 'rw', -2, 'Demo INTEGER32'),
    (0x2010, 0, DT.UNSIGNED32, 'ro', 0xCAFEBABE, 'Demo read-only UNSIGNED32'),
    (0x2011, 0, DT.UNSIGNED32, 'wo', 0, 'Demo write-only UNSIGNED32'),
    (DOMAIN_INDEX, 0, DT.DOMAIN, 'rw', DOMAIN_DEFAULT, 'Demo DOMAIN (large data)'),
    (0x2021, 0, DT.VISIBLE_STRING, 'rw', b'hello from the bus', 'Demo VISIBLE_STRING'),
    (SLOW_INDEX, 0, DT.UNSIGNED32, 'ro', 0x51057, 'Slow value (answers after a delay)'),
)

RECORD_NAMES = {0x1018: 'Identity object'}

# Client's block upload acknowledgement (ccs 5, cs 2) and the server's end of a block upload
# as durand words it for a full last segment (scs 6, n 7, ss 1) and as it should be (n 0).
BLOCK_UPLOAD_ACK = 0xA2
BLOCK_UPLOAD_END_N7 = 0xDD
BLOCK_UPLOAD_END_N0 = 0xC1
SDO_ABORT = 0x80

RECEIVE_CYCLE = 0.05


class _Timer:
    """One scheduled callback; the flag lets a cancel win over a firing already under way."""

    def __init__(self, callback: Callable, args: tuple, kwargs: dict):
        self.callback = callback
        self.args = args
        self.kwargs = kwargs
        self.cancelled = False
        self.event: Optional[sched.Event] = None


class _Scheduler(durand.scheduler.SyncScheduler):
    """durand's SyncScheduler, woken by every new timer, firing each timer under ``lock``.

    Everything that drives durand (received frames, device methods) holds ``lock`` too, so a
    timer never fires in the middle of a change to the state it works on, and a cancel comes
    either before a firing (which then does nothing) or after it.
    """

    def __init__(self):
        super().__init__(lock=threading.RLock())
        self._interrupt = threading.Event()
        self._sched = sched.scheduler(time.monotonic, self._delay)

    def add(self, delay: float, callback, args=(), kwargs=None) -> _Timer:
        """Schedule ``callback(*args, **kwargs)`` in ``delay`` seconds; returns its handle."""
        timer = _Timer(callback, tuple(args), dict(kwargs or {}))
        timer.event = super().add(delay, self._fire, (timer,))
        self._interrupt.set()  # the runner may be asleep until a later timer
        return timer

    def cancel(self, entry: _Timer) -> None:
        """Cancel a timer; harmless when it has fired or is firing already."""
        entry.cancelled = True
        try:
            super().cancel(entry.event)
        except ValueError:
            pass  # already off the queue: _fire sees the flag

    def pending(self) -> list:
        """Return the callbacks of the timers still to fire (for tests)."""
        return [event.argument[0].callback for event in self._sched.queue
                if not event.argument[0].cancelled]

    def _delay(self, seconds: float) -> None:
        if seconds > 0:
            self._interrupt.wait(seconds)
            self._interrupt.clear()

    def _fire(self, timer: _Timer) -> None:
        with self.lock:
            if timer.cancelled:
                return
            try:
                timer.callback(*timer.args, **timer.kwargs)
            except Exception:
                # An exception here would end the runner thread and every device's timers.
                LOGGER.exception('durand timer %r failed', timer.callback)


_scheduler_lock = threading.Lock()
_scheduler: Optional[_Scheduler] = None


def shared_scheduler() -> _Scheduler:
    """Return the process-wide durand scheduler, installing and starting it on first use."""
    global _scheduler
    with _scheduler_lock:
        if _scheduler is None:
            scheduler = _Scheduler()
            durand.set_scheduler(scheduler)
            threading.Thread(target=scheduler.run, name='durand-scheduler',
                             daemon=True).start()
            _scheduler = scheduler
        return _scheduler


class _Network(NetworkABC):
    """The bus as durand sees it, with a receive thread of our own.

    Frames are handed to durand's subscribers under the scheduler's lock. A ``hook`` set for a
    COB-ID sees the frame first, with durand's subscriber for it (or None). A ``rewrite`` may
    change an outgoing frame. Nothing raised while receiving or handling ends the thread.
    """

    def __init__(self, bus: can.BusABC, lock, on_remote: Callable[[can.Message], None]):
        self._bus = bus
        self._lock = lock
        self._on_remote = on_remote
        self._subscriptions: Dict[int, Callable] = {}
        self.hooks: Dict[int, Callable] = {}
        self.rewrite: Optional[Callable[[int, bytes], bytes]] = None
        self.allowed: Callable[[int], bool] = lambda cob_id: True
        self.muted = True  # nothing leaves while the device is being built or after stop
        self._running = False
        self._thread: Optional[threading.Thread] = None

    def add_subscription(self, cob_id: int, callback) -> None:
        """Deliver frames on ``cob_id`` to ``callback(cob_id, data)``."""
        self._subscriptions[cob_id] = callback

    def remove_subscription(self, cob_id: int) -> None:
        """Stop delivering frames on ``cob_id``."""
        self._subscriptions.pop(cob_id, None)

    def send(self, cob_id: int, msg: bytes) -> None:
        """Send a data frame, unless muted; a bus error is logged, never raised into durand."""
        if self.muted or not self.allowed(cob_id):
            return
        if self.rewrite is not None:
            msg = self.rewrite(cob_id, msg)
        try:
            self._bus.send(can.Message(arbitration_id=cob_id, data=msg, is_extended_id=False))
        except Exception:
            LOGGER.warning('durand device could not send 0x%03X %s', cob_id, bytes(msg).hex(),
                           exc_info=True)

    def start(self) -> None:
        """Start the receive thread."""
        self._running = True
        self._thread = threading.Thread(target=self._receive, name='durand-device-rx',
                                        daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the receive thread and wait for it."""
        self._running = False
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)

    @property
    def receiving(self) -> bool:
        """Return whether the receive thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    def _receive(self) -> None:
        while self._running:
            try:
                message = self._bus.recv(RECEIVE_CYCLE)
            except Exception:
                # python-can's Notifier would end here for good and leave the device deaf.
                LOGGER.warning('durand device: receive failed', exc_info=True)
                time.sleep(RECEIVE_CYCLE)
                continue
            if message is not None and self._running:
                self._dispatch(message)

    def _dispatch(self, message: can.Message) -> None:
        if message.is_error_frame or message.is_fd or message.is_extended_id:
            return
        cob_id = message.arbitration_id
        try:
            with self._lock:
                if message.is_remote_frame:
                    self._on_remote(message)
                    return
                data = bytes(message.data)
                callback = self._subscriptions.get(cob_id)
                hook = self.hooks.get(cob_id)
                if hook is not None:
                    hook(callback, cob_id, data)
                elif callback is not None:
                    callback(cob_id, data)
        except Exception:
            LOGGER.exception('durand device failed on %r', message)


class DurandDevice:
    """One simulated CANopen slave on the bus, built on durand (not on python-canopen).

    Same surface as :class:`cbcan_ros.simulation.SimulatedDevice`: a boot-up message then
    heartbeats (0x1017), NMT commands obeyed (a reset boots again and restores defaults),
    node guarding answered while the heartbeat is off, and the EDS's demo objects.

    With ``lss=True`` it is also an LSS slave (durand's) with ``identity`` (0x1018:1..4);
    node id 255 makes it unconfigured. ``lss_store`` and ``lss_bit_rates`` say whether it
    can store its configuration and set a bit rate; without, it refuses with LSS error 1.
    What it stored is in :attr:`stored`.
    """

    #: Seconds of silence after which a transfer a master left open is dropped.
    SDO_SERVER_TIMEOUT = 1.0

    def __init__(self, node_id: int, interface: str = 'virtual', channel: str = 'cbcan',
                 bus_options: Optional[Dict[str, str]] = None, slow_read_delay: float = 0.4,
                 lss: bool = False, identity: Tuple[int, int, int, int] = IDENTITY,
                 lss_store: bool = True, lss_bit_rates: bool = True,
                 pdos: Sequence[PdoConfig] = ()):
        self._node_id = node_id
        self.lss = lss
        self.identity = tuple(identity)
        self._lss_store = lss_store
        self._lss_bit_rates = lss_bit_rates
        self.stored: Dict[str, Optional[int]] = {}
        self._sdo_cob = SDO_RX_BASE + node_id
        self.pdos = tuple(pdos)
        self._event_timers: Dict[int, object] = {}
        self.slow_read_delay = slow_read_delay
        self._bus_options = dict(interface=interface, channel=channel, **(bus_options or {}))
        self.node: Optional[durand.Node] = None
        self._bus: Optional[can.BusABC] = None
        self._network: Optional[_Network] = None
        self._lock = None
        self._guard_toggle = 0
        self._last_sdo_frame = 0.0
        self._slow_value = 0

    @property
    def node_id(self) -> int:
        """Return the node id the device has now (255: unconfigured)."""
        return self.node.node_id if self.node is not None else self._node_id

    @property
    def lss_waiting(self) -> bool:
        """Return whether the device's LSS slave is in the waiting state."""
        return self.node.lss._state == 0  # durand's LSSState.WAITING

    @property
    def state(self) -> int:
        """Return the NMT state byte (0 boot-up, 4 stopped, 5 operational, 127 pre-op)."""
        return int(self.node.nmt.state) if self.node is not None else nmt.BOOT_UP

    @property
    def running(self) -> bool:
        """Return whether the device is on the bus and receiving."""
        return self._network is not None and self._network.receiving

    def start(self) -> None:
        """Open the bus and boot: boot-up message, pre-operational, heartbeats from 0x1017."""
        if self._network is not None:
            return
        scheduler = shared_scheduler()
        bus = can.Bus(**self._bus_options)
        network = _Network(bus, scheduler.lock, self._on_remote_frame)
        with scheduler.lock:
            # Built muted: durand sends a boot-up while still constructing, before our
            # dictionary is in place; the real boot-up follows once it is.
            node = durand.Node(network, self.node_id, capabilities=CAPABILITIES)
            self._lock = scheduler.lock
            self._bus, self._network, self.node = bus, network, node
            self._build_dictionary(node.object_dictionary)
            if self.lss:
                self._setup_lss(node)
            else:
                network.remove_subscription(LSS_MASTER_COB)  # the EDS says LSS_Supported=0
            network.hooks[NMT_COB] = self._on_nmt_frame
            network.hooks[self._sdo_cob] = self._on_sdo_frame
            node.nmt.state_callbacks.add(self._follow_node_id)
            network.muted = False
            network.start()
            self._boot(WHOLE_DICTIONARY, durand_reset=node.nmt.reset)

    def _setup_lss(self, node: durand.Node) -> None:
        if self._lss_store:
            node.lss.set_store_configuration_callback(self._store)
        if self._lss_bit_rates:
            # Only LSS activate bit timing would call it, which the gateway never sends.
            node.lss.set_baudrate_change_callback(lambda bitrate, delay: None)
        self._network.allowed = (lambda cob_id: self.node.node_id != UNCONFIGURED
                                 or cob_id == LSS_SLAVE_COB)

    def _store(self, bitrate: Optional[int], node_id: int) -> None:
        self.stored = {'bitrate': bitrate, 'node_id': node_id}

    def _follow_node_id(self, state: StateEnum) -> None:
        # durand sets the new node id on entering INITIALISATION (a reset, or LSS).
        cob_id = SDO_RX_BASE + self.node.node_id
        if state == StateEnum.INITIALISATION and cob_id != self._sdo_cob:
            self._network.hooks.pop(self._sdo_cob, None)
            self._network.hooks[cob_id] = self._on_sdo_frame
            self._sdo_cob = cob_id

    def stop(self) -> None:
        """Go silent: cancel this device's timers and close its bus (other devices go on)."""
        network, bus = self._network, self._bus
        if network is None:
            return
        with self._lock:
            od = self.node.object_dictionary
            for number in list(self._event_timers):
                self._set_event_timer(number, 0)
            od.write(HEARTBEAT_INDEX, 0, 0)  # cancels the heartbeat timer
            od.write(EMCY_INHIBIT_INDEX, 0, od.read(EMCY_INHIBIT_INDEX, 0))  # and EMCY's
            network.muted = True
            self._network = self._bus = None
        network.stop()
        bus.shutdown()

    def value(self, index: int, subindex: int = 0) -> bytes:
        """Return the stored value of an object as it goes over the bus (little-endian)."""
        node = self._started()
        with self._lock:
            od = node.object_dictionary
            variable = od.lookup(index, subindex)
            if not isinstance(variable, Variable):
                raise KeyError(f'0x{index:04X}:{subindex} is not a variable')
            if (index, subindex) == (SLOW_INDEX, 0):
                raw = self._slow_value  # od.read would run the slow read callback
            else:
                raw = od.read(index, subindex)
            return variable.pack(raw)

    def set_value(self, index: int, subindex: int,
                  value: Union[bytes, bytearray, str, int, float]) -> None:
        """Store a value as the device itself would: bytes as on the bus, or a plain value."""
        node = self._started()
        with self._lock:
            od = node.object_dictionary
            variable = od.lookup(index, subindex)
            if isinstance(value, str):
                value = value.encode()
            if isinstance(value, (bytes, bytearray)):
                try:
                    value = variable.unpack(bytes(value))
                except struct.error as exc:
                    raise ValueError(f'{len(value)} bytes do not fit '
                                     f'{variable.datatype.name}') from exc
            try:
                od.write(index, subindex, value)
            except SDODomainAbort as exc:
                raise ValueError(f'refused with abort code 0x{exc.code:08X}') from exc

    def configure_pdos(self, pdos: Sequence[PdoConfig]) -> None:
        """Store and apply PDO parameters, as a tool writing and saving them (0x1010) would."""
        node = self._started()
        with self._lock:
            self.pdos = tuple(pdos)
            self._apply_pdos(node)

    def _apply_pdos(self, node: durand.Node) -> None:
        for config in self.pdos:
            pdo = (node.tpdo if config.kind == 'tpdo' else node.rpdo)[config.number - 1]
            pdo.enable = False
            pdo.mapping = config.mapping
            pdo.transmission_type = config.transmission_type
            if config.kind == 'tpdo':
                node.object_dictionary.write(TPDO_COMMUNICATION + config.number - 1,
                                             EVENT_TIMER_SUB, config.event_timer)
            pdo.enable = config.enabled

    def _add_event_timers(self, od) -> None:
        for number in range(1, PDOS + 1):
            index = TPDO_COMMUNICATION + number - 1
            od.lookup(index)[EVENT_TIMER_SUB] = Variable(DT.UNSIGNED16, 'rw', 0,
                                                         name='Event timer')
            od.update_callbacks[(index, EVENT_TIMER_SUB)].add(
                lambda value, number=number: self._set_event_timer(number, value))

    def _set_event_timer(self, number: int, milliseconds: int) -> None:
        scheduler = shared_scheduler()
        timer = self._event_timers.pop(number, None)
        if timer is not None:
            scheduler.cancel(timer)
        if milliseconds:
            self._event_timers[number] = scheduler.add(
                milliseconds / 1000, self._event_timer_fired, (number, milliseconds))

    def _event_timer_fired(self, number: int, milliseconds: int) -> None:
        tpdo = self.node.tpdo[number - 1]
        if tpdo._cache is not None and tpdo.transmission_type >= 254:  # active, event-driven
            tpdo.transmit()
        self._event_timers[number] = shared_scheduler().add(
            milliseconds / 1000, self._event_timer_fired, (number, milliseconds))

    def emergency(self, error_code: int, error_register: Optional[int] = None,
                  manufacturer: bytes = b'') -> None:
        """Send an EMCY through durand's producer; error code 0 is the error reset.

        ``error_register`` (also stored in 0x1001) defaults to the generic error bit for an
        error and to 0 for the reset. ``manufacturer`` holds up to 5 bytes.
        """
        if len(manufacturer) > 5:
            raise ValueError('an EMCY carries at most 5 manufacturer-specific bytes')
        if error_register is None:
            error_register = 0x01 if error_code else 0x00
        node = self._started()
        with self._lock:
            node.emcy.set(error_code, error_register, bytes(manufacturer))

    def answer_node_guarding(self) -> None:
        """Reply to a node guarding request: state with the alternating toggle bit."""
        node = self.node
        if node is None or self._network is None:
            return
        if node.object_dictionary.read(HEARTBEAT_INDEX, 0):
            return  # CiA 301: a node producing heartbeats does not take part in guarding
        self._network.send(nmt.HEARTBEAT_COB_BASE + self.node_id,
                           bytes([self.state | self._guard_toggle]))
        self._guard_toggle ^= 0x80

    def _started(self) -> durand.Node:
        if self.node is None:
            raise RuntimeError('the device has not been started')
        return self.node

    def _build_dictionary(self, od) -> None:
        # durand's Node put its own 0x1000/0x1008/0x1017/0x1018 in place; ours replace them.
        records: Dict[int, Record] = {}
        for index, subindex, datatype, access, default, name in OBJECTS:
            if index == IDENTITY_INDEX:
                default = self.identity[subindex - 1]
            variable = Variable(datatype, access, default, name=name)
            if subindex:
                records.setdefault(index, Record(name=RECORD_NAMES[index]))[subindex] = variable
            else:
                od[index] = variable
        for index, record in records.items():
            od[index] = record
        od.validate_callbacks[(DOMAIN_INDEX, 0)].add(self._check_domain_size)
        od.update_callbacks[(SLOW_INDEX, 0)].add(self._store_slow_value)
        od.set_read_callback(SLOW_INDEX, 0, self._read_slow)
        self._slow_value = od.lookup(SLOW_INDEX, 0).value
        self._add_event_timers(od)

    def _boot(self, clear: range, durand_reset: Callable[[], None]) -> None:
        """Boot as after power-on or reset: objects in ``clear`` return to their defaults."""
        od = self.node.object_dictionary
        od.write(HEARTBEAT_INDEX, 0, 0)  # no heartbeat of the old state around the boot-up
        for index, obj in od:
            if index not in clear or index == HEARTBEAT_INDEX:
                continue
            for subindex, variable in ([(0, obj)] if isinstance(obj, Variable) else list(obj)):
                if od.has_value(index, subindex):
                    od.write(index, subindex, _default_of(variable))
        self._drop_sdo_transfers()
        self._guard_toggle = 0
        if clear.start <= TPDO_COMMUNICATION < clear.stop:
            self._apply_pdos(self.node)
        durand_reset()  # state 0 with the boot-up message, then pre-operational
        od.write(HEARTBEAT_INDEX, 0, HEARTBEAT_DEFAULT)  # starts heartbeats at the default

    def _on_nmt_frame(self, durand_handler, cob_id: int, data: bytes) -> None:
        # durand's NMT slave boots again on a reset but keeps every value and the old
        # heartbeat; a real device restores its defaults first.
        if (len(data) == 2 and data[1] in (0, self.node_id)
                and data[0] in (nmt.RESET_NODE, nmt.RESET_COMMUNICATION)):
            clear = WHOLE_DICTIONARY if data[0] == nmt.RESET_NODE else COMMUNICATION_PROFILE
            self._boot(clear, durand_reset=lambda: durand_handler(cob_id, data))
        elif durand_handler is not None:
            durand_handler(cob_id, data)

    def _on_sdo_frame(self, durand_handler, cob_id: int, data: bytes) -> None:
        if durand_handler is None:
            return  # durand unsubscribes its SDO server while stopped: no answer, as CiA 301
        now = time.monotonic()
        if now - self._last_sdo_frame > self.SDO_SERVER_TIMEOUT:
            self._drop_sdo_transfers()  # whatever was open, its master has given up
        self._last_sdo_frame = now
        if data[:1] == bytes([SDO_ABORT]):
            self._drop_sdo_transfers()  # whatever index the abort names; never answered
            return
        too_long = _announced_size(data, DOMAIN_INDEX) > DOMAIN_MAX_SIZE
        if too_long:
            self._network.send(SDO_TX_BASE + self.node_id, struct.pack(
                '<BHBI', SDO_ABORT, DOMAIN_INDEX, 0, ABORT_LENGTH_TOO_HIGH))
            return
        if self._block_upload_ends_with_full_segment(data):
            self._network.rewrite = _fix_block_upload_end
        try:
            durand_handler(cob_id, data)
        finally:
            self._network.rewrite = None

    def _block_upload_ends_with_full_segment(self, data: bytes) -> bool:
        manager = self.node.sdo_servers[0].upload_manager
        if (len(data) < 2 or data[0] != BLOCK_UPLOAD_ACK
                or manager._state != TransferState.BLOCK or manager._stream is None):
            return False
        acknowledged = data[1] * 7
        remaining = len(manager._stream.peek(acknowledged + 1))
        return 0 < remaining <= acknowledged and remaining % 7 == 0

    def _drop_sdo_transfers(self) -> None:
        server = self.node.sdo_servers[0]
        for manager in (server.upload_manager, server.download_manager):
            manager.on_abort(manager._multiplexor)

    def _on_remote_frame(self, message: can.Message) -> None:
        if message.arbitration_id == nmt.HEARTBEAT_COB_BASE + self.node_id:
            self.answer_node_guarding()

    def _check_domain_size(self, value: bytes) -> None:
        if len(value) > DOMAIN_MAX_SIZE:
            raise SDODomainAbort(ABORT_LENGTH_TOO_HIGH, (DOMAIN_INDEX, 0))

    def _store_slow_value(self, value: int) -> None:
        self._slow_value = value

    def _read_slow(self) -> int:
        # A slow device: the answer is late on purpose. The lock is let go meanwhile, so
        # heartbeats and the other devices go on.
        self._lock.release()
        try:
            time.sleep(self.slow_read_delay)
        finally:
            self._lock.acquire()
        return self._slow_value


def _default_of(variable: Variable):
    if variable.value is not None:
        return variable.value
    return b'' if variable.size is None else 0


def _announced_size(data: bytes, index: int) -> int:
    """Return the size a download request for ``index``:0 announces, or -1."""
    if len(data) < 8 or struct.unpack_from('<HB', data, 1) != (index, 0):
        return -1
    segmented = data[0] & 0xE3 == 0x21  # ccs 1, not expedited, size indicated
    block = data[0] & 0xE3 == 0xC2  # ccs 6, initiate, size indicated
    return struct.unpack_from('<I', data, 4)[0] if segmented or block else -1


def _fix_block_upload_end(cob_id: int, msg: bytes) -> bytes:
    if msg[:1] == bytes([BLOCK_UPLOAD_END_N7]):
        return bytes([BLOCK_UPLOAD_END_N0]) + bytes(msg[1:])
    return msg
