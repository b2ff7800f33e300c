"""Simulated CANopen devices, for trying the gateway and testing it without hardware.

Each device is a canopen ``LocalNode`` built from an EDS file, on a canopen Network of its
own (so one slow device never stalls another), behaving as a real slave does: it sends a
boot-up message and heartbeats (0x1017), obeys NMT commands (a reset boots it again),
answers node guarding requests while its heartbeat is off, and handles the PDOs of its EDS
while operational: event-driven TPDOs every event timer period with the current values, RPDOs
written into its objects (canopen's ``PdoMap`` classes, read from the EDS).
"""

import threading
import time
from typing import Dict, Optional

import can
import canopen

from ..core import eds, nmt
from ..core.gateway import NOTIFIER_CYCLE

SLOW_INDEX = 0x2200
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
        self.node = canopen.LocalNode(node_id, eds.load(eds_path, node_id))
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
        self.node.tpdo.read(from_od=True)
        self.node.rpdo.read(from_od=True)
        for rpdo in self.node.rpdo.map.values():
            rpdo.add_callback(self._apply_rpdo)
        self.boot()
        self._pdo_thread.start()

    def stop(self) -> None:
        """Stop heartbeats and leave the bus (the device goes silent)."""
        self._stopped.set()
        self.node.nmt.stop_heartbeat()
        if self._pdo_thread.is_alive():
            self._pdo_thread.join()
        self.network.disconnect()

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
