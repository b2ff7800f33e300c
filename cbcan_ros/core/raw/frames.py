"""Raw CAN frames beside CANopen on the gateway's one bus (CAN layer 2).

A robot's bus often carries frames of devices that speak no CANopen (a battery, a joystick).
The adapter has one owner, the gateway, so their programs receive and send through it:

- received: every frame the bus supervisor takes (data, remote, extended and error frames)
  is offered here by the receive thread, with the host's monotonic receive time, before
  CANopen sees it; frames that pass ``raw.filters`` go to the listeners, in bus order. A
  listener runs on the receive thread, so it only notes the frame (the ROS layer queues it
  for a publishing thread of its own). Frames the gateway sent itself are not handed back,
  also on buses that echo every frame to its sender (udp_multicast where the kernel could
  not drop them, ``own_frames.py``; a bus opened with ``receive_own_messages``).
- sent: :meth:`RawFrames.send` checks every frame of a call before the first goes out (one
  refused, none sent), then sends them in order; an adapter that fails midway stops there
  and the answer says how many went out.

What may be sent: ids that match ``raw.send_allow``, never with ``read_only``. The ids the
gateway itself uses for CANopen stay refused even when a wide entry covers them, unless an
entry with the full mask names the id itself: a frame on such an id is taken by the gateway
and the devices as CANopen (an NMT command, an SDO answer, a heartbeat) and confuses both.
"""

from collections import deque
from dataclasses import dataclass
import logging
import threading
import time
from typing import AbstractSet, Callable, Deque, Dict, FrozenSet, List, Optional, Sequence, Tuple

import can

from ..bus import BusDown, BusSupervisor
from ..sdo.write_protection import WriteProtection
from ..text import SHUTTING_DOWN
from .filters import exact_entry, EXTENDED_MASK, FrameFilters, STANDARD_MASK

LOGGER = logging.getLogger(__name__)

# Frames one send_frames call may carry: a call's frames leave in one go, holding others'.
MAX_FRAMES = 1024
MAX_DLC = 8

# How long a frame this process sent is looked for among the frames an echoing bus hands
# back; the echo comes within milliseconds, seconds on a machine under heavy load.
ECHO_WINDOW = 2.0
ECHO_SWEEP = 1000  # sends between sweeps for echoes that never came

# Interfaces that hand a process its own frames back (udp_multicast does so even when told
# not to; the gateway has the kernel drop them where it can: own_frames.py), and the
# python-can option that asks others to.
ECHOING_INTERFACES = frozenset({'udp_multicast'})
OWN_MESSAGES_OPTION = 'receive_own_messages'

# The default COB-ID bases of the four TPDOs and RPDOs of a device (CiA 301).
PDO_BASES = (0x180, 0x200, 0x280, 0x300, 0x380, 0x400, 0x480, 0x500)
NODE_IDS = range(1, 128)
# CANopen ids of the gateway whatever its devices: NMT, SYNC, TIME, the EMCY, SDO and
# heartbeat (node guarding) ids of every node (the gateway talks SDO to any node a caller
# names and watches every EMCY and heartbeat), and LSS.
FIXED_CANOPEN_IDS = frozenset({0x000, 0x080, 0x100, 0x7E4, 0x7E5}.union(
    *(range(base + 1, base + 128) for base in (0x080, 0x580, 0x600, 0x700))))


def echoes(interface: str, options: Dict[str, object]) -> bool:
    """Return whether a bus, as python-can opens it, hands the gateway the frames it sent."""
    return interface in ECHOING_INTERFACES or bool(options.get(OWN_MESSAGES_OPTION))


@dataclass(frozen=True)
class RawSettings:
    """The raw bridge's parameters: what is received and what may be sent."""

    filters: FrameFilters = FrameFilters()
    send_allow: FrameFilters = FrameFilters()


@dataclass(frozen=True)
class Frame:
    """One frame to send, as a caller gives it (``data`` longer than ``dlc`` is cut)."""

    can_id: int
    data: bytes = b''
    dlc: int = 0
    is_extended: bool = False
    is_rtr: bool = False
    is_error: bool = False

    def describe(self) -> str:
        """Return how messages name the frame, e.g. '0x123' or '0x18FF0001 (extended)'."""
        if self.is_extended:
            return f'0x{self.can_id:08X} (extended)'
        return f'0x{self.can_id:03X}'


@dataclass(frozen=True)
class SendResult:
    """The answer to a call: whether all went out, how many did, and why not."""

    success: bool
    sent: int = 0
    message: str = ''


@dataclass(frozen=True)
class Refusal:
    """Why a frame may not be sent: ``kind`` groups refusals for the log, ``text`` says it."""

    kind: str
    text: str


@dataclass(frozen=True)
class RawStatistics:
    """What /diagnostics shows of the raw bridge."""

    received: int = 0  # frames that passed raw.filters (handed to the listeners)
    sent: int = 0
    refused: int = 0   # frames refused before sending (from the service and the topic)
    lost: int = 0      # frames the ROS layer could not publish (its queue was full)


class _EchoFilter:
    """Frames this process sent, to know them when an echoing bus hands them back."""

    def __init__(self):
        self._lock = threading.Lock()
        self._sent: Dict[Tuple, Deque[float]] = {}
        self._since_sweep = 0

    def sent(self, message: can.Message) -> None:
        now = time.monotonic()
        with self._lock:
            self._sent.setdefault(_key(message), deque()).append(now)
            self._since_sweep += 1
            if self._since_sweep >= ECHO_SWEEP:
                self._since_sweep = 0
                for key in list(self._sent):
                    self._expire(key, now)

    def is_own(self, message: can.Message) -> bool:
        key = _key(message)
        with self._lock:
            if key not in self._sent:
                return False
            times = self._expire(key, time.monotonic())
            if not times:
                return False
            times.popleft()
            if not times:
                del self._sent[key]
            return True

    def _expire(self, key: Tuple, now: float) -> Deque[float]:
        times = self._sent[key]
        while times and now - times[0] > ECHO_WINDOW:
            times.popleft()
        if not times:
            del self._sent[key]
        return times


def _key(message: can.Message) -> Tuple:
    return (message.arbitration_id, message.is_extended_id, message.is_remote_frame,
            bytes(message.data))


def canopen_ids(pdo) -> FrozenSet[int]:
    """Return the standard ids the gateway uses for CANopen now.

    ``pdo`` is the gateway's PDO service: the default PDO ids of every device it serves,
    and the ids the devices' PDOs actually have (read from them), are the gateway's too.
    """
    ids = set(FIXED_CANOPEN_IDS)
    for node_id in pdo.node_ids:
        ids.update(base + node_id for base in PDO_BASES)
        for mappings in pdo.mappings(node_id):
            ids.update(mapping.cob_id for mapping in mappings.values()
                       if mapping.cob_id <= STANDARD_MASK)
    return frozenset(ids)


class RawFrames:
    """The raw bridge of one gateway: received frames to listeners, frames sent on request.

    ``canopen_ids()`` returns the ids no wide ``raw.send_allow`` entry opens (see
    :func:`canopen_ids`). ``echoing()``: whether the bus open now hands the gateway its own
    frames (it may change when the bus is opened again).
    """

    def __init__(self, supervisor: BusSupervisor, settings: RawSettings,
                 protection: WriteProtection, canopen_ids: Callable[[], AbstractSet[int]],
                 echoing: Callable[[], bool]):
        self.settings = settings
        self._supervisor = supervisor
        self._protection = protection
        self._canopen_ids = canopen_ids
        self._echoing = echoing
        self._echo = _EchoFilter()
        self._listeners: List[Callable[[can.Message, float], None]] = []
        self._send_lock = threading.Lock()  # one call's frames leave together, in order
        self._lock = threading.Lock()
        self._closing = False
        self._received = 0  # the receive thread's alone: no lock
        self._sent = 0
        self._refused = 0
        self._lost = 0
        self._logged: set = set()
        if not settings.filters.empty:
            supervisor.watch_frames(self._on_frame, self._on_sent)

    @property
    def receiving(self) -> bool:
        """Return whether any received frame is handed on (``raw.filters`` is set)."""
        return not self.settings.filters.empty

    def add_listener(self, listener: Callable[[can.Message, float], None]) -> None:
        """Call ``listener(message, stamp)`` for every received frame that passes the filters.

        It runs on the bus receive thread, in bus order; ``stamp`` is ``time.monotonic()``
        when the frame was taken from the driver. It must return at once.
        """
        self._listeners.append(listener)

    def statistics(self) -> RawStatistics:
        """Return the counts /diagnostics shows."""
        with self._lock:
            return RawStatistics(self._received, self._sent, self._refused, self._lost)

    def lost(self, count: int = 1) -> None:
        """Count frames received but not published (the ROS layer's queue was full)."""
        with self._lock:
            self._lost += count

    def stop(self) -> None:
        """Refuse every send from now on (shutdown); return once no frame of a call goes out.

        A call under way stops before its next frame: the drives' stops, sent after this,
        are the last word a drive gets.
        """
        with self._lock:
            self._closing = True
        with self._send_lock:
            pass

    def _shutting_down(self) -> bool:
        with self._lock:
            return self._closing

    def refusal(self, frame: Frame, index: Optional[int] = None) -> Optional[Refusal]:
        """Return why ``frame`` may not be sent (``index``: its place in a call), or None."""
        where = f'frame {index} ' if index is not None else 'frame '
        kind, text = self._check(frame)
        if kind:
            return Refusal(kind, f'{where}{frame.describe()}: {text}')
        return None

    def send(self, frames: Sequence[Frame]) -> SendResult:
        """Check every frame, then send them in order; never raises.

        One refused frame and none is sent. An adapter error midway stops there: ``sent``
        says how many went out.
        """
        if len(frames) > MAX_FRAMES:
            return self._refused_call(len(frames), f'frames: {len(frames)} frames, at most '
                                                   f'{MAX_FRAMES} per call; nothing was sent')
        for index, frame in enumerate(frames):
            refused = self.refusal(frame, index)
            if refused is not None:
                return self._refused_call(len(frames), f'{refused.text}; nothing was sent')
        status = self._supervisor.status
        if frames and not status.up:
            return self._refused_call(len(frames), f'the CAN bus is down: {status.reason}; '
                                                   f'nothing was sent')
        sent = 0
        with self._send_lock:
            for frame in frames:
                if self._shutting_down():  # it began during the call: the rest stays here
                    self._count(sent, len(frames) - sent)
                    return SendResult(False, sent, f'frame {sent} {frame.describe()}: the '
                                                   f'gateway is shutting down; {sent} of '
                                                   f'{len(frames)} frames sent')
                try:
                    self._supervisor.send(_message(frame))
                except BusDown as error:
                    self._count(sent, len(frames) - sent)
                    return SendResult(False, sent, f'frame {sent} {frame.describe()}: {error}; '
                                                   f'{sent} of {len(frames)} frames sent')
                sent += 1
        self._count(sent, 0)
        return SendResult(True, sent)

    def send_one(self, frame: Frame) -> Optional[Refusal]:
        """Send one frame (from a topic): return why it was refused or not sent, or None.

        A refusal is not counted here: the caller hands it to :meth:`refuse`.
        """
        try:
            with self._send_lock:  # checked here: shutdown waits for this lock (stop)
                refused = self.refusal(frame)
                if refused is not None:
                    return refused
                self._supervisor.send(_message(frame))
        except BusDown as error:
            return Refusal('not sent', f'frame {frame.describe()}: {error}')
        self._count(1, 0)
        return None

    def refuse(self, source: str, refused: Refusal) -> None:
        """Count a frame from ``source`` (a topic) refused, and log it once per kind."""
        with self._lock:
            self._refused += 1
            if refused.kind in self._logged:
                return
            self._logged.add(refused.kind)
        LOGGER.error('%s: %s (later refusals of this kind are counted in /diagnostics, not '
                     'logged)', source, refused.text)

    def _check(self, frame: Frame) -> Tuple[str, str]:
        """Return (kind, why) when ``frame`` may not be sent, else ('', '')."""
        if self._shutting_down():
            return 'shutting down', SHUTTING_DOWN
        if frame.is_error:
            return 'error frame', 'is_error: error frames come from adapters, none is sent'
        highest = EXTENDED_MASK if frame.is_extended else STANDARD_MASK
        if not 0 <= frame.can_id <= highest:
            kind = 'extended' if frame.is_extended else 'standard'
            return 'bad id', f'id {frame.can_id:#x} is out of range for a {kind} frame ' \
                             f'(0..{highest:#x})'
        if not 0 <= frame.dlc <= MAX_DLC:
            return 'bad dlc', f'dlc {frame.dlc} is out of range (0..{MAX_DLC})'
        if not frame.is_rtr and len(frame.data) < frame.dlc:
            return 'bad dlc', f'dlc {frame.dlc} but {len(frame.data)} data bytes'
        if self._protection.read_only:
            return 'read only', 'the gateway is read-only (parameter read_only): no raw ' \
                                'frame is sent'
        allow = self.settings.send_allow
        if not allow.matches(frame.can_id, frame.is_extended, frame.is_rtr, False):
            if allow.empty:
                return 'not allowed', 'nothing may be sent: parameter raw.send_allow is empty'
            return 'not allowed', 'the id is not in parameter raw.send_allow'
        if not frame.is_extended and frame.can_id in self._canopen_ids() and \
                exact_entry(allow, frame.can_id, False, frame.is_rtr) is None:
            return 'canopen id', (
                'the gateway uses this id for CANopen; only an entry of raw.send_allow '
                f'with the full mask naming it ({frame.can_id:03X}:7FF) opens it')
        return '', ''

    def _refused_call(self, count: int, text: str) -> SendResult:
        self._count(0, count)
        return SendResult(False, 0, text)

    def _count(self, sent: int, refused: int) -> None:
        with self._lock:
            self._sent += sent
            self._refused += refused

    def _on_sent(self, message: can.Message) -> None:
        if self._echoing():
            self._echo.sent(message)

    def _on_frame(self, message: can.Message, stamp: float) -> None:
        # The bus receive thread, for every frame taken: no lock on the way of a frame that
        # is not one's own (the echo filter's lock only on buses that echo).
        if self._echoing() and self._echo.is_own(message):
            return
        if not self.settings.filters.matches(message.arbitration_id, message.is_extended_id,
                                             message.is_remote_frame, message.is_error_frame):
            return
        self._received += 1
        for listener in self._listeners:
            listener(message, stamp)


def _message(frame: Frame) -> can.Message:
    if frame.is_rtr:
        return can.Message(arbitration_id=frame.can_id, is_extended_id=frame.is_extended,
                           is_remote_frame=True, dlc=frame.dlc)
    return can.Message(arbitration_id=frame.can_id, is_extended_id=frame.is_extended,
                       data=bytes(frame.data[:frame.dlc]))
