"""Simulated CANopen devices, for trying the gateway and testing it without hardware.

Each device is a canopen ``LocalNode`` built from an EDS file, on a canopen Network of its
own (so one slow device never stalls another), behaving as a real slave does: it sends a
boot-up message and heartbeats (0x1017), obeys NMT commands (a reset boots it again),
answers node guarding requests while its heartbeat is off, and handles the PDOs of its EDS
while operational: event-driven TPDOs every event timer period with the current values, RPDOs
written into its objects (canopen's ``PdoMap`` classes, read from the EDS).
"""

import logging
import threading
import time
from typing import Dict, Optional

import can
import canopen
from canopen.objectdictionary import datatypes, ODVariable

from ..core import eds, nmt
from ..core.gateway import NOTIFIER_CYCLE

LOGGER = logging.getLogger(__name__)
SLOW_INDEX = 0x2200
HEARTBEAT_TIME = 0x1017
PDO_COMMUNICATION = (range(0x1400, 0x1600), range(0x1800, 0x1A00))  # RPDOs, TPDOs
MAPPING_OFFSET = 0x200  # a PDO's mapping object follows its communication object by this
COMMUNICATION_PROFILE = range(0x1000, 0x2000)


class SimulatedDevice:
    """One simulated CANopen slave on the bus."""

    def __init__(self, node_id: int, eds_path: str, interface: str = 'virtual',
                 channel: str = 'cbcan', slow_read_delay: float = 0.4,
                 bus_options: Optional[Dict[str, str]] = None):
        self.node_id = node_id
        self.slow_read_delay = slow_read_delay
        self._bus_options = dict(interface=interface, channel=channel, **(bus_options or {}))
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = NOTIFIER_CYCLE
        self._eds_path = eds_path
        self.node = canopen.LocalNode(node_id, self._simulatable(eds.load(eds_path, node_id)))
        self.node.add_read_callback(self._on_read)
        self._guard_toggle = 0
        self._nmt_lock = threading.Lock()
        self._stopped = threading.Event()
        self._pdo_thread = threading.Thread(target=self._send_tpdos,
                                            name=f'simulated-{node_id}-tpdos', daemon=True)

    @property
    def state(self) -> int:
        """Return the NMT state the device is in."""
        return self.node.nmt._state

    def start(self) -> None:
        """Connect to the bus and boot (boot-up message, then pre-operational)."""
        self.network.connect(**self._bus_options)
        self.network.add_node(self.node)
        self.network.subscribe(0, self._on_nmt_command)
        self.network.notifier.add_listener(_RemoteFrameListener(self))
        try:
            self.node.tpdo.read(from_od=True)
            self.node.rpdo.read(from_od=True)
        except Exception as error:  # noqa: BLE001 - canopen's PDO reading of a file it took
            # A vendor file whose PDO objects canopen cannot read (a communication object
            # without its mapping, entries without values): the device runs without PDOs.
            LOGGER.warning('simulated device %d: the PDOs of %s are not simulated: %s',
                           self.node_id, self._eds_path, error)
        else:
            for rpdo in self.node.rpdo.map.values():
                rpdo.add_callback(self._apply_rpdo)
            self._pdo_thread.start()
        self.boot()

    def stop(self) -> None:
        """Stop heartbeats and leave the bus (the device goes silent)."""
        self._stopped.set()
        self.node.nmt.stop_heartbeat()
        if self._pdo_thread.is_alive():
            self._pdo_thread.join()
        self.network.disconnect()

    def _simulatable(self, dictionary):
        """Return ``dictionary`` with what canopen's ``LocalNode`` needs of it.

        canopen's NMT slave reads the producer heartbeat time (0x1017) as it boots, which a
        device that only takes part in node guarding may lack (it gets 0 here), and its PDO
        classes fail on a PDO communication object without its mapping object (such PDOs
        are left out, said once).
        """
        heartbeat = dictionary.get(HEARTBEAT_TIME)
        if heartbeat is None:
            heartbeat = ODVariable('Producer heartbeat time', HEARTBEAT_TIME)
            heartbeat.data_type = datatypes.UNSIGNED16
            dictionary.add_object(heartbeat)
        if heartbeat.default is None and heartbeat.value is None:
            heartbeat.default = 0
        unmapped = [index for index in dictionary
                    if any(index in pdos for pdos in PDO_COMMUNICATION)
                    and index + MAPPING_OFFSET not in dictionary]
        for index in unmapped:
            del dictionary[index]
        if unmapped:
            LOGGER.warning('simulated device %d: PDO communication objects without a mapping '
                           'object in %s are not simulated: %s', self.node_id, self._eds_path,
                           ', '.join(f'0x{index:04X}' for index in unmapped))
        return dictionary

    def _apply_rpdo(self, rpdo) -> None:
        if self.state != nmt.OPERATIONAL or len(rpdo.data) < (rpdo.length + 7) // 8:
            return  # CiA 301: only an operational device takes PDOs; a short one is dropped
        for variable in rpdo.map:
            self.node.set_data(variable.index, variable.subindex, variable.get_data())

    def _send_tpdos(self) -> None:
        timed = [tpdo for tpdo in self.node.tpdo.map.values()
                 if tpdo.enabled and tpdo.event_timer and tpdo.map]
        if not timed:
            return
        due = {id(tpdo): time.monotonic() for tpdo in timed}
        while not self._stopped.wait(max(min(due.values()) - time.monotonic(), 0.0)):
            now = time.monotonic()
            for tpdo in timed:
                if due[id(tpdo)] > now:
                    continue
                due[id(tpdo)] = now + tpdo.event_timer / 1000
                if self.state != nmt.OPERATIONAL:
                    continue
                for variable in tpdo.map:
                    variable.set_data(self.node.get_data(variable.index, variable.subindex))
                try:
                    tpdo.transmit()
                except Exception:  # noqa: BLE001, S112 - a full bus: the next period sends
                    continue

    def boot(self, clear: range = range(0x0000, 0x10000)) -> None:
        """Boot as after power-on or reset: values in ``clear`` return to their defaults."""
        with self._nmt_lock:
            for index in [index for index in self.node.data_store if index in clear]:
                del self.node.data_store[index]
            self.node.nmt.send_command(nmt.RESET_NODE)  # state 0, sends the boot-up message
            self.node.nmt.send_command(nmt.ENTER_PRE_OPERATIONAL)  # starts heartbeats (0x1017)

    def _on_nmt_command(self, _can_id: int, data: bytearray, _timestamp: float) -> None:
        if len(data) < 2 or data[1] not in (0, self.node_id):
            return
        if data[0] == nmt.RESET_NODE:
            self.boot()
        elif data[0] == nmt.RESET_COMMUNICATION:
            self.boot(COMMUNICATION_PROFILE)

    def _on_read(self, index: int, subindex: int, od) -> Optional[int]:
        if index == SLOW_INDEX:
            time.sleep(self.slow_read_delay)  # a slow device: the answer is late on purpose
        return None

    def answer_node_guarding(self) -> None:
        """Reply to a node guarding request: state with the alternating toggle bit."""
        if self.node.sdo[0x1017].raw:
            return  # CiA 301: a node producing heartbeats does not take part in guarding
        self.network.send_message(nmt.HEARTBEAT_COB_BASE + self.node_id,
                                  [self.state | self._guard_toggle])
        self._guard_toggle ^= 0x80


class _RemoteFrameListener(can.Listener):
    """canopen's network drops remote frames, so guarding requests are heard here."""

    def __init__(self, device: SimulatedDevice):
        self._device = device

    def on_message_received(self, msg: can.Message) -> None:
        if (msg.is_remote_frame
                and msg.arbitration_id == nmt.HEARTBEAT_COB_BASE + self._device.node_id):
            self._device.answer_node_guarding()
