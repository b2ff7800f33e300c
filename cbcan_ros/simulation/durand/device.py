"""A simulated CANopen device built on durand, a device stack independent of python-canopen.

The devices of ``simulation.py`` run on python-canopen, the library our SDO client is built
on, so a defect the two sides share stays hidden. :class:`DurandDevice` answers with durand's
SDO server (expedited, segmented, block both ways), NMT slave, heartbeat and EMCY producers,
on a python-can bus of its own (``network``), with the dictionary of
``config/simulated_device.eds`` (``dictionary``) and the PDOs it stores
(``pdos``), on the timers of the scheduler all such devices share
(``scheduler``).

durand 0.5.0 needs a few guards, kept in those modules and in this one (durand itself is not
patched). Here:

- Its SDO server ends a block upload with n=7 when the last segment is full (sizes that are a
  multiple of 7): the client drops 7 bytes and fails its CRC check. Rewritten on the way out.
- It ignores an SDO abort whose index it does not know (python-canopen's client aborts with
  0000:00), so the block transfer stays open and answers the next request; and a transfer a
  master abandons stays open for ever. Both are dropped here.
- LSS (``lss=True``): a durand node with node id 255 (unconfigured) still sends a boot-up
  message and heartbeats, on 0x7FF; a device without a node id sends nothing but LSS answers,
  so everything else is held back until it has one. When LSS gives it an id, durand boots it
  (boot-up, heartbeats, SDO server on the new id), but the SDO guards here stay keyed to
  the old id: they follow the id on every boot.
- Its NMT slave boots again on a reset but keeps every value: a reset here restores the
  defaults first, or the values stored with 0x1010:1 "save" (its PDOs as ``pdos``
  configures them); 0x1011:1 "load" drops the stored values, so the next reset restores the
  factory defaults. The stored values outlive ``stop()``/``start()`` (a power cycle), as a
  device's non-volatile memory does.
"""

import struct
import time
from typing import Callable, Dict, Optional, Sequence, Tuple, Union

import can
import durand
from durand.node import NodeCapabilities
from durand.object_dictionary import Variable
from durand.services.nmt import StateEnum
from durand.services.sdo.server import SDODomainAbort, TransferState

from ...core import nmt
from ...core.python_can_gaps.foreign_datagrams import drop_foreign_datagrams
from ...core.python_can_gaps.receive_buffer import deepen_receive_buffer
from .dictionary import (
    ABORT_LENGTH_TOO_HIGH,
    add_objects,
    DOMAIN_INDEX,
    DOMAIN_MAX_SIZE,
    HEARTBEAT_DEFAULT,
    HEARTBEAT_INDEX,
    IDENTITY,
    restore_defaults,
    RESTORE_INDEX,
    SAVES_ON_COMMAND,
    SLOW_INDEX,
    STORE_INDEX,
)
from .network import BusNetwork
from .pdos import EVENT_TIMER_SUB, PdoConfig, PDOS, StoredPdos, TPDO_COMMUNICATION
from .scheduler import shared_scheduler

EMCY_INHIBIT_INDEX = 0x1015
COMMUNICATION_PROFILE = range(0x1000, 0x2000)
WHOLE_DICTIONARY = range(0x0000, 0x10000)
NMT_COB = 0x000
SDO_RX_BASE = 0x600
SDO_TX_BASE = 0x580
LSS_MASTER_COB = 0x7E5
LSS_SLAVE_COB = 0x7E4
UNCONFIGURED = 0xFF

# One SDO server, the PDOs of the predefined connection set and no LSS: durand's defaults
# (128 SDO servers, 512 PDOs each way) would only slow the construction down.
CAPABILITIES = NodeCapabilities(sdo_servers=1, rpdos=PDOS, tpdos=PDOS)

# Client's block upload acknowledgement (ccs 5, cs 2) and the server's end of a block upload
# as durand words it for a full last segment (scs 6, n 7, ss 1) and as it should be (n 0).
BLOCK_UPLOAD_ACK = 0xA2
BLOCK_UPLOAD_END_N7 = 0xDD
BLOCK_UPLOAD_END_N0 = 0xC1
SDO_ABORT = 0x80
SAVE = int.from_bytes(b'save', 'little')  # the signatures 0x1010 and 0x1011 take (CiA 301)
LOAD = int.from_bytes(b'load', 'little')
ABORT_NOT_STORED = 0x08000020
NOT_STORED = range(0x1400, 0x1C00)  # the PDO parameters: ``pdos`` sets them up at each boot


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
    #: Objects that are commands (0x1010 save, 0x1011 load): they hold no value of their
    #: own, so a boot restores none and "save" stores none.
    COMMANDS: Tuple[int, ...] = (STORE_INDEX, RESTORE_INDEX)

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
        self._pdos = StoredPdos(pdos)
        self._factory_pdos = tuple(pdos)
        self.slow_read_delay = slow_read_delay
        self._bus_options = dict(interface=interface, channel=channel, **(bus_options or {}))
        self.node: Optional[durand.Node] = None
        self._bus: Optional[can.BusABC] = None
        self._network: Optional[BusNetwork] = None
        self._lock = None
        self._guard_toggle = 0
        self._last_sdo_frame = 0.0
        self._slow_value = 0
        self._saved: Dict[Tuple[int, int], object] = {}  # 0x1010 "save": kept across boots

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
        deepen_receive_buffer(bus)  # a device answers SDO requests sent in a flood, too
        # Another program's datagrams on the group are dropped, not a receive failure each
        # (a traceback and a pause: 20 a second kept the device from answering).
        drop_foreign_datagrams(bus, lambda: None)
        network = BusNetwork(bus, scheduler.lock, self._on_remote_frame)
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
            self._pdos.stop_event_timers()
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
        self._started()
        with self._lock:
            self._pdos.configs = tuple(pdos)
            self._pdos.apply()

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
        add_objects(od, self.identity)
        od.update_callbacks[(SLOW_INDEX, 0)].add(self._store_slow_value)
        od.set_read_callback(SLOW_INDEX, 0, self._read_slow)
        self._slow_value = od.lookup(SLOW_INDEX, 0).value
        self._pdos.install(self.node)
        for index, signature, command in ((STORE_INDEX, SAVE, self._save),
                                          (RESTORE_INDEX, LOAD, self._forget_saved)):
            od.validate_callbacks[(index, 1)].add(
                lambda value, i=index, s=signature: self._check_signature(i, s, value))
            od.update_callbacks[(index, 1)].add(lambda _value, c=command: c())
            od.set_read_callback(index, 1, lambda: SAVES_ON_COMMAND)

    @staticmethod
    def _check_signature(index: int, signature: int, value: int) -> None:
        if value != signature:  # CiA 301: any other value is refused with 0x08000020
            raise SDODomainAbort(ABORT_NOT_STORED, (index, 1))

    def _save(self) -> None:
        od = self.node.object_dictionary
        self._saved = {(index, subindex): od.read(index, subindex)
                       for index, obj in od if index not in NOT_STORED
                       and index not in self.COMMANDS
                       for subindex, variable in ([(0, obj)] if isinstance(obj, Variable)
                                                  else list(obj))
                       if variable.access in ('rw', 'wo') and od.has_value(index, subindex)}

        node = self.node
        self._pdos.configs = tuple(
            PdoConfig(kind, number, tuple(pdo.mapping), pdo.transmission_type,
                      od.read(TPDO_COMMUNICATION + number - 1, EVENT_TIMER_SUB)
                      if kind == 'tpdo' else 0, pdo.enable)
            for kind, pdos in (('tpdo', node.tpdo), ('rpdo', node.rpdo))
            for number, pdo in enumerate(pdos[:PDOS], 1))

    def _forget_saved(self) -> None:
        self._saved = {}
        self._pdos.configs = self._factory_pdos

    def _boot(self, clear: range, durand_reset: Callable[[], None]) -> None:
        """Boot as after power-on or reset: objects in ``clear`` return to their defaults."""
        od = self.node.object_dictionary
        od.write(HEARTBEAT_INDEX, 0, 0)  # no heartbeat of the old state around the boot-up
        # Nor a PDO: a device taking a reset sends nothing more before its boot-up, while
        # restoring its defaults here would send every TPDO of an operational one.
        self.node.nmt.set_state(StateEnum.STOPPED)
        restore_defaults(od, clear, keep=(HEARTBEAT_INDEX, *self.COMMANDS))
        heartbeat = HEARTBEAT_DEFAULT
        for (index, subindex), value in self._saved.items():
            if index == HEARTBEAT_INDEX:
                heartbeat = value
            elif index in clear:
                od.write(index, subindex, value)
        self._drop_sdo_transfers()
        self._guard_toggle = 0
        if clear.start <= TPDO_COMMUNICATION < clear.stop:
            self._pdos.apply()
        durand_reset()  # state 0 with the boot-up message, then pre-operational
        od.write(HEARTBEAT_INDEX, 0, heartbeat)  # starts heartbeats (the default, or saved)

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
