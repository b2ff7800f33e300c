"""EMCY: the emergency messages of every device, decoded by canopen's own EMCY consumer.

A device sends an EMCY (COB-ID 0x80 + node id, CiA 301) when an error occurs and one with
error code 0x00xx (error reset) when its errors are gone. Each device gets a
``canopen.emcy.EmcyConsumer`` (through ``canopen_gaps.EmcyDecoder``), which decodes the
frame, names the error code's class (``EmcyError.get_desc()``) and tells an active error
from an error reset. Here the last
EMCY and the latest active error of every device are kept for diagnostics, and listeners (the
ROS layer) hear of every EMCY as it arrives.
"""

from dataclasses import dataclass
import logging
import threading
from typing import Callable, Dict, List, Optional

from canopen.emcy import EmcyError

from .bus import wall_clock
from .canopen_gaps.emcy import EmcyDecoder, MalformedEmcy

LOGGER = logging.getLogger(__name__)

EMCY_COB_BASE = 0x80  # 0x80 itself is SYNC; devices 1..127 use 0x81..0xFF


@dataclass(frozen=True)
class Emergency:
    """One EMCY as a device sent it."""

    node_id: int
    error_code: int
    error_register: int
    manufacturer_data: bytes  # the 5 manufacturer-specific bytes
    received: float           # time.time() when the gateway received it
    description: str          # the CiA 301 class of the error code, e.g. 'Voltage'

    @property
    def summary(self) -> str:
        """Return the code and its meaning, e.g. '0x3120 Voltage'."""
        return f'0x{self.error_code:04X} {self.description}'.rstrip()


@dataclass(frozen=True)
class EmcyStatus:
    """What is known of one device's emergencies."""

    node_id: int
    last: Optional[Emergency] = None    # the last EMCY, an error reset included
    active: Optional[Emergency] = None  # the latest error not cleared by an error reset
    malformed: int = 0                  # frames on the EMCY COB-ID that were no EMCY


class _Device:
    __slots__ = ('decoder', 'last', 'active', 'malformed')

    def __init__(self):
        self.decoder = EmcyDecoder()
        self.last: Optional[Emergency] = None
        self.active: Optional[Emergency] = None
        self.malformed = 0


class EmcyMonitor:
    """Receives the EMCY of every node id and keeps each device's last and active error.

    Listeners are called with each :class:`Emergency` from the bus thread, without locks
    held. A frame that is no EMCY (shorter than 8 bytes) is counted, logged once per device
    and ignored.
    """

    def __init__(self, network):
        self._network = network
        self._lock = threading.Lock()
        self._devices: Dict[int, _Device] = {}
        self._listeners: List[Callable[[Emergency], None]] = []

    def add_listener(self, listener: Callable[[Emergency], None]) -> None:
        """Call ``listener(emergency)`` for every EMCY received."""
        self._listeners.append(listener)

    def start(self) -> None:
        """Listen to the EMCY COB-ID of every node id."""
        for node_id in range(1, 128):
            self._network.subscribe(EMCY_COB_BASE + node_id, self._on_frame)

    def stop(self) -> None:
        """Stop listening."""
        for node_id in range(1, 128):
            self._network.unsubscribe(EMCY_COB_BASE + node_id, self._on_frame)

    def status(self, node_id: int) -> EmcyStatus:
        """Return what is known of ``node_id``'s emergencies (nothing if it sent none)."""
        with self._lock:
            device = self._devices.get(node_id)
            return _status(node_id, device) if device else EmcyStatus(node_id)

    def statuses(self) -> List[EmcyStatus]:
        """Return every device that sent anything on its EMCY COB-ID, sorted by node id."""
        with self._lock:
            return [_status(node_id, device) for node_id, device in sorted(self._devices.items())]

    def _on_frame(self, can_id: int, data: bytearray, timestamp: float) -> None:
        node_id = can_id - EMCY_COB_BASE
        with self._lock:
            device = self._devices.get(node_id)
            if device is None:
                device = self._devices[node_id] = _Device()
        try:
            error, is_active = device.decoder.decode(can_id, data, timestamp)
        except MalformedEmcy:
            with self._lock:
                device.malformed += 1
                first = device.malformed == 1
            if first:
                LOGGER.warning('node %d sent an EMCY of %d bytes (CiA 301: 8): ignored, as are '
                               'further malformed ones from it', node_id, len(data))
            return
        emergency = _emergency(node_id, error)
        with self._lock:
            device.last = emergency
            device.active = emergency if is_active else None
        for listener in self._listeners:
            listener(emergency)


def _emergency(node_id: int, error: EmcyError) -> Emergency:
    # canopen keeps the frame's stamp (when the bus thread took it) as the error's timestamp.
    return Emergency(node_id, error.code, error.register, bytes(error.data),
                     wall_clock(error.timestamp), error.get_desc())


def _status(node_id: int, device: _Device) -> EmcyStatus:
    return EmcyStatus(node_id, device.last, device.active, device.malformed)
