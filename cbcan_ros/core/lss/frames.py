"""LSS (CiA 305) on the wire: requests sent on 0x7E5, answers matched on 0x7E4, Fastscan.

The frames and command specifiers are python-canopen's (``canopen.lss``); its ``LssMaster``
is not used because it does not fit a gateway (see docs/library_gaps.md): it waits
0.5 s on every unanswered request, and a Fastscan probes bit by bit (silence means a 1 bit),
so a scan finding nothing took 0.5 s and one device tens of seconds; it keeps one queue for
every answer, so a late or foreign frame answers the next request; it returns nothing for
requests nobody answers and raises on others, and drops the error code of a refusal.

Here answers are matched by command specifier and only frames the bus thread took after the
request went out count (frames carry the host's monotonic receive time). A Fastscan probe
waits a short time that fits the bus's bit rate; every other request waits longer.
"""

from collections import deque
import struct
import threading
import time
from typing import Optional

from canopen import lss as cia305

from ..bus import BusDown, prompt
from .requests import Identity, UNCONFIGURED

MASTER_COB = cia305.LssMaster.LSS_TX_COBID  # 0x7E5, master to devices
SLAVE_COB = cia305.LssMaster.LSS_RX_COBID   # 0x7E4, devices to master
WAITING = cia305.LssMaster.WAITING_STATE

# A probe and its answer are two 8-byte frames: at most 135 bits each with stuffing. The bit
# rate of a bus the gateway does not set (SocketCAN) is not known: take the slowest.
FRAME_BITS = 135
SLOWEST_BIT_RATE = 10000
# python-can buses without a wire: frames take no time on them.
SIMULATED_INTERFACES = frozenset({'virtual', 'udp_multicast'})
# What a device may take to answer, on top of the frames' time on the wire: generous, so a
# busy machine (or a device stack in Python) is not taken for an absent device.
DEVICE_MARGIN = 0.04
# Requests other than Fastscan probes are few: they may wait longer for their answer.
ANSWER_WAIT_MIN = 0.5
ANSWER_WAIT_PROBES = 8
# The shortest time answers to one probe are taken in after the first (see _probe).
SETTLE_MIN = 0.002


def probe_wait(interface: str, bitrate: int, configured: float = 0.0) -> float:
    """Return the seconds a Fastscan probe waits for an answer (``configured`` if > 0)."""
    if configured > 0:
        return configured
    if interface in SIMULATED_INTERFACES:
        return DEVICE_MARGIN
    return 2 * FRAME_BITS / (bitrate or SLOWEST_BIT_RATE) + DEVICE_MARGIN


class Cancelled(Exception):
    """The operation was ended from outside: the bus went down, or shutdown began."""


class Disturbed(Exception):
    """Answers on 0x7E4 did not add up; the scan starts again."""


class _Responses:
    """Frames on 0x7E4 while a request waits; only those taken after it was sent count."""

    def __init__(self):
        self._changed = threading.Condition()
        self._frames: deque = deque(maxlen=64)
        self._cancelled: Optional[str] = None

    @prompt
    def on_frame(self, _can_id: int, data: bytearray, timestamp: float) -> None:
        with self._changed:
            self._frames.append((timestamp, bytes(data)))
            self._changed.notify_all()

    def cancel(self, reason: Optional[str]) -> None:
        """Make waiting and later requests raise :class:`Cancelled` (None: allow again)."""
        with self._changed:
            self._cancelled = reason
            self._changed.notify_all()

    def pause(self, seconds: float) -> None:
        """Wait ``seconds``; raise :class:`Cancelled` at once when cancelled meanwhile."""
        deadline = time.monotonic() + seconds
        with self._changed:
            while self._cancelled is None and time.monotonic() < deadline:
                self._changed.wait(deadline - time.monotonic())
            if self._cancelled is not None:
                raise Cancelled(self._cancelled)

    def check(self) -> None:
        """Raise :class:`Cancelled` when cancelled."""
        with self._changed:
            if self._cancelled is not None:
                raise Cancelled(self._cancelled)

    def wait(self, sent: float, command: int, size: int, wait: float,
             settle: Optional[float] = None) -> Optional[bytes]:
        """Return the first answer with ``command`` and ``size`` bytes or more, or None.

        With ``settle``, further answers of that kind are taken in until none came for that
        long (several devices answering one request, one after the other), or for ``wait``
        seconds in all with ``settle`` < 0; so none of them is left to seem to answer the
        next request.
        """
        deadline = time.monotonic() + wait
        first = None
        with self._changed:
            while True:
                if self._cancelled is not None:
                    raise Cancelled(self._cancelled)
                while self._frames:
                    taken, data = self._frames.popleft()
                    if taken >= sent and len(data) >= size and data[0] == command:
                        if settle is None:
                            return data
                        first = first or data
                        if settle >= 0:
                            deadline = time.monotonic() + settle
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return first
                self._changed.wait(remaining)


class LssFrames:
    """The LSS master's frames on ``network``: one request and its answers at a time.

    A Fastscan probe waits ``probe_wait`` seconds for answers, any other request
    ``answer_wait``. :meth:`cancel` ends the request waiting and refuses the next ones.
    """

    def __init__(self, network, probe_wait_s: float):
        self._network = network
        self._responses = _Responses()
        self.probe_wait = probe_wait_s
        self.answer_wait = max(ANSWER_WAIT_MIN, ANSWER_WAIT_PROBES * probe_wait_s)

    def start(self) -> None:
        """Listen on 0x7E4."""
        self._network.subscribe(SLAVE_COB, self._responses.on_frame)

    def cancel(self, reason: Optional[str]) -> None:
        """Make waiting and later requests raise :class:`Cancelled` (None: allow again)."""
        self._responses.cancel(reason)

    def pause(self, seconds: float) -> None:
        """Wait ``seconds``; raise :class:`Cancelled` at once when cancelled meanwhile."""
        self._responses.pause(seconds)

    def send(self, data: bytes) -> float:
        """Send one LSS request (8 bytes); return the time before it went out."""
        self._responses.check()
        sent = time.monotonic()
        self._network.send_message(MASTER_COB, data.ljust(8, b'\0'))
        return sent

    def _request(self, data: bytes, command: int, size: int, wait: float,
                 deadline: float) -> Optional[bytes]:
        sent = self.send(data)
        return self._responses.wait(sent, command, size,
                                    max(0.0, min(wait, deadline - time.monotonic())))

    def all_waiting(self) -> None:
        """Switch every device to the waiting state; the only frame sent after a failure."""
        try:
            self._network.send_message(MASTER_COB, bytes([cia305.CS_SWITCH_STATE_GLOBAL,
                                                          WAITING]).ljust(8, b'\0'))
        except BusDown:
            pass  # the bus is gone, or shutdown forbids it: nothing more can be done

    def switch_all_waiting(self) -> None:
        """Switch every device to the waiting state."""
        self.send(bytes([cia305.CS_SWITCH_STATE_GLOBAL, WAITING]))

    def select(self, identity: Identity, deadline: float) -> bool:
        """Switch the device with ``identity`` (only it) to the configuration state."""
        commands = (cia305.CS_SWITCH_STATE_SELECTIVE_VENDOR_ID,
                    cia305.CS_SWITCH_STATE_SELECTIVE_PRODUCT_CODE,
                    cia305.CS_SWITCH_STATE_SELECTIVE_REVISION_NUMBER)
        for command, value in zip(commands, identity.parts()[:3], strict=True):
            self.send(struct.pack('<BI', command, value))
        return self._request(struct.pack('<BI', cia305.CS_SWITCH_STATE_SELECTIVE_SERIAL_NUMBER,
                                         identity.serial),
                             cia305.CS_SWITCH_STATE_SELECTIVE_RESPONSE, 1, self.answer_wait,
                             deadline) is not None

    def inquire_node_id(self, deadline: float) -> Optional[int]:
        """Return the node id of the device in the configuration state, None if silent."""
        data = self._request(bytes([cia305.CS_INQUIRE_NODE_ID]), cia305.CS_INQUIRE_NODE_ID,
                             2, self.answer_wait, deadline)
        return None if data is None else data[1]

    def inquire_identity(self, deadline: float) -> Optional[Identity]:
        """Return the identity of the device in the configuration state, None if silent."""
        parts = []
        for command in (cia305.CS_INQUIRE_VENDOR_ID, cia305.CS_INQUIRE_PRODUCT_CODE,
                        cia305.CS_INQUIRE_REVISION_NUMBER, cia305.CS_INQUIRE_SERIAL_NUMBER):
            data = self._request(bytes([command]), command, 5, self.answer_wait, deadline)
            if data is None:
                return None
            parts.append(struct.unpack_from('<I', data, 1)[0])
        return Identity(*parts)

    def configure_step(self, command: int, argument: bytes, deadline: float) -> Optional[int]:
        """Send a configure or store request; return the device's error code, None if silent."""
        data = self._request(bytes([command]) + argument, command, 2, self.answer_wait,
                             deadline)
        return None if data is None else data[1]

    def _probe(self, id_number: int, bit: int, sub: int, next_sub: int, deadline: float,
               careful: bool) -> bool:
        """Send one Fastscan probe; return whether any device answered.

        Every device matching a probe answers it. On a real bus identical answers sent at
        once are one frame, but a slower device's answer (always, on a bus that does not
        merge frames, such as python-can's virtual one) comes after: answers are taken in
        until none came for twice the time the first took, or (``careful``) for the whole
        probe wait.
        """
        if time.monotonic() >= deadline:
            raise TimeoutError
        frame = struct.pack('<BIBBB', cia305.CS_FAST_SCAN, id_number, bit, sub, next_sub)
        sent = self.send(frame)
        wait = max(0.0, min(self.probe_wait, deadline - time.monotonic()))
        if careful:
            return self._responses.wait(sent, cia305.CS_IDENTIFY_SLAVE, 1, wait,
                                        -1.0) is not None
        answered = self._responses.wait(sent, cia305.CS_IDENTIFY_SLAVE, 1, wait)
        if answered is None:
            return False
        settle = min(self.probe_wait, max(SETTLE_MIN, 2 * (time.monotonic() - sent)))
        self._responses.wait(time.monotonic(), cia305.CS_IDENTIFY_SLAVE, 1, settle, settle)
        return True

    def fastscan(self, deadline: float, careful: bool) -> Optional[Identity]:
        """Find the unconfigured device with the lowest identity and switch it to configuration.

        CiA 305: after the reset probe (bit 0x80) every unconfigured device answers; then, part
        by part and bit by bit from the top, a probe asks for the bits so far with this bit 0:
        an answer means some device has it 0, silence that it is 1. Every part is confirmed
        (the devices matching it move on to the next part); the device matching all four
        parts enters the configuration state. The identity is then read back from it, so a
        late or foreign answer cannot make up a device.
        """
        if not self._probe(0, 0x80, 0, 0, deadline, careful):
            return None
        parts = [0, 0, 0, 0]
        for sub in range(4):
            for bit in range(31, -1, -1):
                if not self._probe(parts[sub], bit, sub, sub, deadline, careful):
                    parts[sub] |= 1 << bit
            if not self._probe(parts[sub], 0, sub, (sub + 1) % 4, deadline, careful):
                raise Disturbed(f'no device confirmed part {sub + 1} of the identity')
        found = Identity(*parts)
        read_back = self.inquire_identity(deadline)
        if read_back != found:
            raise Disturbed(f'the device found as {found} read back as {read_back}')
        node_id = self.inquire_node_id(deadline)
        if node_id != UNCONFIGURED:
            raise Disturbed(f'the device found as {found} reports node id {node_id}')
        return found


def is_all_waiting(message) -> bool:
    """Return whether ``message`` is the LSS switch of every device to the waiting state."""
    return (message.arbitration_id == MASTER_COB
            and bytes(message.data[:2]) == bytes([cia305.CS_SWITCH_STATE_GLOBAL, WAITING]))
