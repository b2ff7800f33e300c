"""PDOs (CiA 301 process data) as a service: mappings kept current, frames carried.

For every device served (``pdo.nodes``) the PDO parameters are read (``parameters``)
when it is first heard and again after every boot-up message; a device the boot service
configures (``core/boot``) is read when its boot asks (``read_again``), after its writes.

The device's transmit PDOs arrive through ``network.subscribe`` with the host's monotonic
receive time; the bus thread only checks a frame's length and hands it to the listeners as a
:class:`~cbcan_ros.core.pdo.mapping.ReceivedPdo`, which is decoded when read, in the
listener's own thread. Its receive PDOs are sent on request: asynchronous ones at once,
synchronous ones right after a SYNC the gateway produces (``sync.py``).

A stream of synchronous frames (a drive's targets, one a control cycle) goes out at once
instead, when it is in before the next SYNC, so a target reaches the drive in the cycle its
caller sent it; and a cycle the caller leaves without a frame gets the last one sent again,
a quarter period before the SYNC, as a PLC master sends its RPDOs every cycle. A stream lasts
until a while after its last frame (the caller says how long), a write of another kind to
the device, a boot, a mapping read or shutdown.

The stream frames of one command message for several devices (``one_cycle``) are all built
first and then sent back to back: a SYNC the machine let pass while the message was being
worked on then finds either none of them sent or all of them.
"""

from concurrent.futures import Future
import contextlib
from dataclasses import dataclass, field
import logging
import re
import threading
import time
from typing import Callable, Dict, Iterator, List, Optional, Sequence, Tuple

from canopen.objectdictionary import ObjectDictionary

from ..bus import BusDown, BusStatus, prompt
from ..nmt import BOOT_UP, HEARTBEAT_COB_BASE
from ..sdo import abort_codes
from ..sdo.request_queue import answer, resolved
from ..sdo.requests import SdoResult
from ..text import SHUTTING_DOWN
from .mapping import describe, encode, EntryValue, PdoMapping, ReceivedPdo
from .parameters import ParametersFailed, PdoParameters

LOGGER = logging.getLogger(__name__)

# A mapping read that failed (device busy, timeout) is tried again on a later heartbeat, at
# most this often.
REREAD_INTERVAL = 2.0

# Why a target waiting to be sent was dropped: a newer one for the same frame came first.
REPLACED = 'a newer target replaced it before it was sent'


@dataclass(frozen=True)
class PdoStatistics:
    """What diagnostics show of one device's PDOs (counters since the gateway started)."""

    received: int = 0
    sent: int = 0
    short_frames: int = 0     # received frames shorter than their mapping (not published)
    refused: int = 0          # writes refused (bad value, unknown PDO, bus down...)
    unusable: int = 0         # frames of a PDO whose mapping cannot be used
    tpdos: int = 0
    rpdos: int = 0
    mapping: str = 'not read yet'
    late: Tuple[Tuple[int, int, float], ...] = ()  # (tpdo, event timer ms, silent for s)


@dataclass
class _Device:
    node_id: int
    dictionary: Optional[ObjectDictionary]
    tpdos: Dict[int, PdoMapping] = field(default_factory=dict)
    rpdos: Dict[int, PdoMapping] = field(default_factory=dict)
    last_sent: Dict[int, bytes] = field(default_factory=dict)  # RPDO: its newest frame
    # RPDO: the frame last sent (the newest may wait for the SYNC, or for its message's end)
    on_bus: Dict[int, bytes] = field(default_factory=dict)
    # RPDO: the frame of its stream last sent, which the stream's repeat sends again: not a
    # frame from before the stream (a command's, whose controlword is no longer the drive's)
    stream_on_bus: Dict[int, bytes] = field(default_factory=dict)
    last_received: Dict[int, float] = field(default_factory=dict)
    sent_at: Dict[int, float] = field(default_factory=dict)  # RPDO: when its frame last went
    heard: bool = False
    wanted: int = 0       # mapping reads asked for (first heard, every boot-up)
    done: int = 0         # the request the current mapping answers
    booted: bool = False  # configured by the boot service: read when it asks
    readers: List[Tuple[int, Future]] = field(default_factory=list)  # (request, its answer)
    # RPDO: (its mapping, why a write of it is refused or None), worked out at its first write
    refusals: Dict[int, Tuple[PdoMapping, Optional[SdoResult]]] = field(default_factory=dict)
    life: int = 0         # boot-ups heard: each wipes the RPDOs' frames
    streams_ended: int = 0  # times a stop, command or outage ended its streams (not time)
    failed_at: float = 0.0
    mapping_text: str = 'not read yet'
    received: int = 0
    sent: int = 0
    short_frames: int = 0
    refused: int = 0
    unusable: int = 0
    logged: set = field(default_factory=set)


class PdoService:
    """The PDOs of the devices in ``node_ids``, on the gateway's network.

    ``sdo_batch(accesses)`` is the gateway's, so mapping reads and configuration writes go
    through its SDO channels and its write protection; frames go out through the network's
    ``send_message`` (the bus supervisor: BusDown when there is no bus); ``sync`` is the
    gateway's SYNC producer, which synchronous RPDOs wait for.
    """

    def __init__(self, network, node_ids: Sequence[int], sdo_batch, write_protection,
                 sync, dictionaries: Dict[int, ObjectDictionary], booted: Sequence[int] = ()):
        self._network = network
        self._parameters = PdoParameters(sdo_batch)
        self._protection = write_protection
        self._sync = sync
        # Entered thousands of times a second (each frame sent and received): a plain RLock,
        # whose ``with`` is cheaper than a Condition's; ``_changed`` waits on it.
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        # Held from reading a frame to send until it is sent, so the last frame the device
        # gets is always the newest (a SYNC flush of a drive's run frame never follows the
        # frame of its stop). Taken before the lock, never while holding it.
        self._frames = threading.Lock()
        self._devices = {node_id: _Device(node_id, dictionaries.get(node_id),
                                          booted=node_id in booted)
                         for node_id in sorted(set(node_ids))}
        self._by_cob: Dict[int, PdoMapping] = {}
        self._subscribed: set = set()
        self._listeners: List[Callable[[ReceivedPdo], None]] = []
        self._closing = False
        # (node, RPDO): the writes waiting for the SYNC, each with its device's boot count
        # and the mapping it was written on
        self._pending_sync: Dict[Tuple[int, int], List[Tuple[Future, int, PdoMapping]]] = {}
        # (node, RPDO) of the streams: repeated each cycle without a frame, until this time
        self._streams: Dict[Tuple[int, int], float] = {}
        self._repeating = False  # a repeat of the streams waits for the next SYNC
        self._repeated_at = 0.0
        # Within ``one_cycle``, this thread's stream frames built and not sent yet
        self._burst = threading.local()
        self._held_back: Callable[[], Optional[str]] = lambda: None
        self._thread = threading.Thread(target=self._read_mappings, name='pdo-mappings',
                                        daemon=True)

    @property
    def node_ids(self) -> List[int]:
        """Return the devices served."""
        return list(self._devices)

    def add_listener(self, listener: Callable[[ReceivedPdo], None]) -> None:
        """Call ``listener(received)`` for every frame received (from the bus thread)."""
        self._listeners.append(listener)

    def start(self) -> None:
        """Listen to the devices' heartbeats (they trigger mapping reads)."""
        for node_id in self._devices:
            self._network.subscribe(HEARTBEAT_COB_BASE + node_id, self._on_heartbeat)
        if self._devices:
            self._thread.start()

    def stop(self) -> None:
        """Answer every write still waiting for a SYNC; stop reading mappings and sending.

        TPDOs are still taken until :meth:`stop_receiving`: the statuswords that show the
        drives' stops at shutdown, written after this.
        """
        with self._lock:
            self._closing = True
            self._streams.clear()
            pending, self._pending_sync = self._pending_sync, {}
            self._changed.notify_all()
        for futures in pending.values():
            for future, *_ in futures:
                answer(future, SdoResult.failed(f'{SHUTTING_DOWN}; it was not sent'))
        for device in self._devices.values():
            self._answer_readers(device, device.wanted, SHUTTING_DOWN)
        for node_id in self._devices:
            self._network.unsubscribe(HEARTBEAT_COB_BASE + node_id, self._on_heartbeat)
        # The mapping reader is not waited for: it may wait for an SDO answer, which the
        # gateway gives ("shutting down") right after this; it then installs nothing.

    def stop_receiving(self) -> None:
        """Take no more TPDOs (after :meth:`stop`)."""
        with self._lock:
            self._by_cob.clear()
            self._follow_cob_ids()

    def _follow_cob_ids(self) -> None:
        """Subscribe to exactly the COB-IDs of ``_by_cob`` (called with the lock held).

        Under the lock, so a mapping installed while shutting down is never left subscribed,
        and each COB-ID is subscribed once, whatever the devices map (canopen would call a
        callback subscribed twice twice).
        """
        wanted = set(self._by_cob)
        for cob_id in self._subscribed - wanted:
            self._network.unsubscribe(cob_id, self._on_frame)
        for cob_id in wanted - self._subscribed:
            self._network.subscribe(cob_id, self._on_frame)
        self._subscribed = wanted

    def on_bus_change(self, status: BusStatus) -> None:
        """Re-read every device heard after the bus was down: it may have booted meanwhile."""
        if status.up:
            return
        with self._lock:
            self._streams.clear()  # a stream resumes with its caller's next target
            for device in self._devices.values():
                device.heard = False
                device.streams_ended += 1
                device.stream_on_bus.clear()

    def mappings(self, node_id: int) -> Tuple[Dict[int, PdoMapping], Dict[int, PdoMapping]]:
        """Return the TPDOs and RPDOs of a device served, by number (empty before read)."""
        with self._lock:
            device = self._devices[node_id]
            return dict(device.tpdos), dict(device.rpdos)

    def serves(self, node_id: int) -> bool:
        """Return whether ``node_id`` is a device served."""
        return node_id in self._devices

    def transmit_mappings(self, node_id: int) -> Dict[int, PdoMapping]:
        """Return the TPDOs of a device served as read (replaced by a read, never changed)."""
        with self._lock:
            return self._devices[node_id].tpdos

    def receive_mappings(self, node_id: int) -> Dict[int, PdoMapping]:
        """Return the RPDOs of a device served as read (replaced by a read, never changed)."""
        with self._lock:
            return self._devices[node_id].rpdos

    def read_again(self, node_id: int) -> 'Future[str]':
        """Read the mapping of ``node_id`` again; resolves to '' once read, or why not."""
        future: Future = Future()
        with self._lock:
            if self._closing:
                return resolved(SHUTTING_DOWN)
            device = self._devices[node_id]
            device.wanted += 1
            device.readers.append((device.wanted, future))
            self._changed.notify_all()
        return future

    def mapping_read(self, node_id: int) -> 'Future[str]':
        """Return a future of the mapping read asked for last: '' once done, or why not.

        Resolved at once when no read is under way or waiting.
        """
        with self._lock:
            if self._closing:
                return resolved(SHUTTING_DOWN)
            device = self._devices[node_id]
            if abs(device.done) >= device.wanted:
                return resolved('' if device.done >= 0 else device.mapping_text)
            future: Future = Future()
            device.readers.append((device.wanted, future))
        return future

    def _answer_readers(self, device: _Device, request: int, problem: str) -> None:
        with self._lock:
            answered = [future for wanted, future in device.readers if wanted <= request]
            device.readers = [(wanted, future) for wanted, future in device.readers
                              if wanted > request]
        for future in answered:
            answer(future, problem)

    def mapping_reads(self, node_id: int) -> int:
        """Return how many times the mapping of a device served was read (each a new one)."""
        with self._lock:
            return self._devices[node_id].done

    def statistics(self) -> Dict[int, PdoStatistics]:
        """Return the statistics of every device served, by node id."""
        now = time.monotonic()
        with self._lock:
            return {node_id: self._statistics(device, now)
                    for node_id, device in self._devices.items()}

    def refuse(self, node_id: int, problem: str) -> None:
        """Count (and log once per kind) a write refused before it reached :meth:`write`."""
        self._refused(node_id, SdoResult.failed(problem))
        self.log_refusal(node_id, problem)

    def log_refusal(self, node_id: int, problem: str) -> None:
        """Log a refused write from a topic, once per kind (the numbers in it not counted)."""
        self._log_once(node_id, re.sub(r'\d', '', problem)[:80], problem)

    def write(self, node_id: int, number: int, values: Sequence[EntryValue] = (),
              data: bytes = b'', stream: float = 0.0) -> 'Future[SdoResult]':
        """Send RPDO ``number`` of ``node_id`` with ``values`` (or the whole frame ``data``).

        Resolves once the frame went out (a synchronous RPDO: after the next SYNC) or why
        not; never raises. ``stream`` (seconds): the frame is one of a stream of a frame a
        cycle, which the next ``stream`` seconds may repeat (see the module's text); a write
        without it ends the streams of the device.
        """
        checked = self._check(node_id, number, values, data)
        if isinstance(checked, SdoResult):
            return resolved(self._refused(node_id, checked))
        mapping = checked
        key = (node_id, number)
        if mapping.synchronous and self._sync.producing:
            if stream and (self._message_frames() is not None
                           or self._sync.open_for_rpdos()):
                return self._send_stream(mapping, values, data, stream)
            future: Future = Future()
            with self._lock:
                frame = self._merge(mapping, values, data)
                if isinstance(frame, SdoResult):
                    return resolved(self._refused(node_id, frame))
                self._follow_stream(key, stream)
                first = key not in self._pending_sync
                self._pending_sync.setdefault(key, []).append(
                    (future, self._devices[node_id].life, mapping))
            if first and not self._sync.after_next_sync(lambda: self._flush(key)):
                self._flush(key)  # SYNC is paused (bus down): fails at once
            return future
        with self._frames:
            with self._lock:
                frame = self._merge(mapping, values, data)
                if not isinstance(frame, SdoResult):
                    self._follow_stream(key, 0.0)
            if isinstance(frame, SdoResult):
                return resolved(self._refused(node_id, frame))
            return resolved(self._send(mapping, frame))

    @contextlib.contextmanager
    def one_cycle(self) -> Iterator[None]:
        """Have the stream frames written within reach the devices in one SYNC cycle.

        For the targets of one command message: its synchronous stream frames are built
        first and sent together when the block ends, so a SYNC that comes meanwhile finds
        all of them sent or none. Whether they go at once is decided on entry
        (``SyncProducer.one_cycle``, which holds its SYNC while they are written). Those
        too late for the next SYNC go together right after a SYNC: the next one, or at
        once when it went out while they were built (they are in time for the one after).
        """
        if self._message_frames() is not None:
            yield  # within one already: its frames go with its own
            return
        frames: List[Tuple[PdoMapping, bytes, Future, int]] = []
        opened = False
        try:
            with self._sync.one_cycle():
                opened = self._sync.open_for_rpdos()
                self._burst.frames = frames
                try:
                    yield
                finally:
                    self._burst.frames = None
                    if opened and frames:
                        self._send_burst(frames)
        finally:
            if frames and not opened:
                self._send_after_sync(frames)

    def _message_frames(self) -> Optional[List[Tuple[PdoMapping, bytes, Future, int]]]:
        """Return the frames of this thread's ``one_cycle`` block, None outside one."""
        return getattr(self._burst, 'frames', None)

    def _send_after_sync(self, burst: List[Tuple[PdoMapping, bytes, Future, int]]) -> None:
        """Send a message's frames that came too late for the SYNC, right after one."""
        if self._sync.open_for_rpdos():  # the SYNC went out while they were built
            self._send_burst(burst)
        elif not self._sync.after_next_sync(lambda: self._send_burst(burst)):
            self._send_burst(burst)  # no SYNC comes (the bus is down): the send says so

    def _send_stream(self, mapping: PdoMapping, values: Sequence[EntryValue], data: bytes,
                     seconds: float) -> 'Future[SdoResult]':
        """Send a stream's synchronous frame at once (it is in before the next SYNC).

        Within ``one_cycle``: when the block ends, with the other frames written in it.
        """
        with self._frames:
            with self._lock:
                frame = self._merge(mapping, values, data)
                if isinstance(frame, SdoResult):
                    return resolved(self._refused(mapping.node_id, frame))
                self._follow_stream((mapping.node_id, mapping.number), seconds)
                ended = self._devices[mapping.node_id].streams_ended
            burst = self._message_frames()
            if burst is None:
                return resolved(self._send(mapping, frame))
        future: Future = Future()
        burst.append((mapping, frame, future, ended))
        return future

    def _send_burst(self, burst: List[Tuple[PdoMapping, bytes, Future, int]]) -> None:
        """Send the stream frames a ``one_cycle`` block built, back to back.

        A frame goes only while no stop, command, outage, boot, mapping read or shutdown
        ended its device's streams since it was built: sent after it, it would undo it. A
        stream that merely ran out of time meanwhile (the message held up longer than the
        stream is kept) does not keep it back: it is the newest target. When a newer message
        replaced any of the frames (it came before these went out), none of them goes: the
        devices take the newer one together. One already sent (a SYNC's flush of its RPDO) is
        not sent twice. The gateway's SYNC thread waits for them (python-can's and the
        kernel's periodic tasks cannot be held).
        """
        results = []
        with self._frames, self._sync.between_two_syncs():
            with self._lock:
                closing = self._closing
                stopped, replaced, sent = set(), False, set()
                for position, (mapping, frame, _, ended) in enumerate(burst):
                    device = self._devices[mapping.node_id]
                    if (device.streams_ended != ended
                            or device.rpdos.get(mapping.number) is not mapping):
                        stopped.add(position)
                    elif device.last_sent.get(mapping.number) is not frame:
                        replaced = True  # by a newer message's, being written or sent
                    elif device.on_bus.get(mapping.number) is frame:
                        sent.add(position)  # by a SYNC's flush of its RPDO
            for position, (mapping, frame, future, _) in enumerate(burst):
                if closing:
                    result = SdoResult.failed(f'{SHUTTING_DOWN}; nothing was sent')
                elif position in stopped:
                    result = SdoResult.failed(
                        f'{mapping.name}: a command, stop or boot of node {mapping.node_id} '
                        f'came while this target was being written; it was not sent')
                elif replaced:  # the whole message: its drives take the newer one together
                    result = SdoResult.failed(f'{mapping.name}: {REPLACED}')
                else:
                    result = SdoResult.ok() if position in sent else self._send(mapping, frame)
                results.append((future, result))
        for future, result in results:
            answer(future, result)

    def end_streams(self, node_id: int) -> None:
        """Repeat no frame of ``node_id`` any more (its drive left the state streams are for)."""
        with self._lock:
            self._follow_stream((node_id, 0), 0.0)

    def _follow_stream(self, key: Tuple[int, int], seconds: float) -> None:
        """Start, prolong (``seconds``) or end (0) the streams of a device (lock held)."""
        if not seconds:
            for other in [other for other in self._streams if other[0] == key[0]]:
                del self._streams[other]
            device = self._devices[key[0]]
            device.streams_ended += 1
            device.stream_on_bus.clear()
            return
        self._streams[key] = time.monotonic() + seconds
        if not self._repeating:
            self._repeating = self._sync.before_next_sync(self._repeat_streams)

    def _repeat_streams(self) -> None:
        """Send again the frame of every stream that got none this cycle (the SYNC thread)."""
        again = []
        with self._frames:
            with self._lock:
                now = time.monotonic()
                for key, until in list(self._streams.items()):
                    device = self._devices[key[0]]
                    mapping = device.rpdos.get(key[1])
                    if self._closing or now > until or mapping is None:
                        del self._streams[key]
                        device.stream_on_bus.pop(key[1], None)
                    elif (key[1] in device.stream_on_bus
                          and device.sent_at.get(key[1], 0.0) < self._repeated_at):
                        # What the drive got last of the stream: a newer frame waiting for
                        # the SYNC (or its message's end) is the next cycle's; one from
                        # before the stream (its first frame still waits) carries an older
                        # controlword, which could switch the drive off.
                        again.append((mapping, device.stream_on_bus[key[1]]))
                self._repeating = bool(self._streams) and self._sync.before_next_sync(
                    self._repeat_streams)
                if not self._repeating:
                    again = []  # no SYNC comes (the bus is down, or shutdown)
            for mapping, frame in again:
                self._send(mapping, frame)
            with self._lock:  # frames sent from now on are the next cycle's
                self._repeated_at = time.monotonic()

    def carry(self, node_id: int, values: Sequence[EntryValue], skip=(),
              resend: bool = True) -> None:
        """Put ``values``, written to ``node_id`` another way, into its other RPDOs' frames.

        Another way: by SDO, or in RPDO ``skip`` (numbers). So no frame undoes that write (a
        stop, then a frame with the controlword that ran the drive): one waiting for the next
        SYNC goes out carrying them, and while SYNC is produced a synchronous RPDO's frame is
        sent again at once, since the device keeps the last one it received until the next
        SYNC applies it (those it holds unapplied first); at shutdown too (the drives' stops
        are written after this service stopped, SYNC goes on until after them). ``resend``
        False (the write's own frame waits for the next SYNC): frames still to be sent carry
        them, and a frame the device got since the last SYNC (a stream's, sent at once) is
        sent again carrying them right after the write's frame, so no RPDO applied at the
        same SYNC undoes it.
        """
        later = []  # frames the device holds for the next SYNC: sent again after it
        with self._frames:  # a SYNC flush of the frame before these values cannot come last
            again = []
            with self._lock:
                device = self._devices.get(node_id)
                self._follow_stream((node_id, 0), 0.0)
                for number, mapping in (device.rpdos.items() if device else ()):
                    if number in skip:
                        continue
                    mapped = [value for value in values if any(
                        (entry.index, entry.subindex) == (value.index, value.subindex)
                        and not entry.dummy for entry in mapping.entries)]
                    if not mapped or number not in device.last_sent:
                        continue  # a frame never sent is built afresh by its next write
                    try:
                        device.last_sent[number] = encode(mapping, device.last_sent[number],
                                                          mapped)
                    except ValueError:  # mapped at another size: no frame of ours has them
                        continue
                    if not (mapping.synchronous and self._sync.producing):
                        continue
                    held = self._waits_for_sync(device, number)
                    if resend:
                        again.append((not held, mapping, device.last_sent[number]))
                    elif held:
                        later.append((number, device.life, mapping))
            # The frames the device holds go first: a SYNC between two of these would apply
            # the older controlword of one held after one carrying them; after those, one
            # held again carries the new values. Where the gateway's thread sends SYNC, none
            # comes between them at all.
            if again:
                with self._sync.between_two_syncs():
                    for _, mapping, frame in sorted(again, key=lambda each: each[0]):
                        self._send(mapping, frame, stopping=True)
        for number, life, mapping in later:
            self._sync.after_next_sync(lambda n=number, lf=life, m=mapping: self._send_again(
                node_id, n, lf, m))

    def _waits_for_sync(self, device: _Device, number: int) -> bool:
        """Return whether the device holds a frame of the RPDO it has not applied yet.

        A frame sent after the last SYNC (a stream's, sent at once) comes into force at the
        next one, with the controlword from before the values carried. One waiting for the
        SYNC in this service goes out carrying them anyway. Called with the lock held.
        """
        following = self._sync.next_point(0.0)
        return (following is not None and (device.node_id, number) not in self._pending_sync
                and device.sent_at.get(number, 0.0) >= following - self._sync.period)

    def _send_again(self, node_id: int, number: int, life: int, mapping: PdoMapping) -> None:
        """Send RPDO ``number``'s frame again after a SYNC (``carry``), unless it changed."""
        with self._frames:
            with self._lock:
                device = self._devices[node_id]
                frame = device.last_sent.get(number)
                if device.life != life or device.rpdos.get(number) is not mapping:
                    frame = None  # booted or read again since: the frame is gone
            if frame is not None:
                self._send(mapping, frame, stopping=True)

    def _check(self, node_id: int, number: int, values: Sequence[EntryValue], data: bytes):
        """Return the mapping of RPDO ``number`` to write, or the SdoResult that refuses it."""
        if node_id not in self._devices:
            served = ', '.join(map(str, self._devices)) or 'none'
            return SdoResult.failed(f'node_id {node_id} is not in the parameter pdo.nodes '
                                    f'(served: {served})')
        with self._lock:
            if self._closing:
                return SdoResult.failed(f'{SHUTTING_DOWN}; nothing was sent')
            device = self._devices[node_id]
            mapping = device.rpdos.get(number)
            if mapping is None:
                known = ', '.join(map(str, device.rpdos)) or 'none'
                return SdoResult.failed(f'pdo {number}: node {node_id} has no RPDO {number} '
                                        f'(its RPDOs: {known}; PDO mapping '
                                        f'{device.mapping_text})')
            # Fixed for a mapping (the write rules are the gateway's): worked out once, not
            # for each of a stream's thousands of frames a second.
            refused = device.refusals.get(number)
            if refused is None or refused[0] is not mapping:
                refused = device.refusals[number] = (mapping, self._write_refusal(mapping))
        if refused[1] is not None:
            return refused[1]
        if data and values:
            return SdoResult.failed('give entries or data (the whole frame), not both')
        if data and len(data) != mapping.size:
            return SdoResult.failed(f'data has {len(data)} bytes, {mapping.name} takes '
                                    f'{mapping.size} ({mapping.bits} bits)')
        return mapping

    def _merge(self, mapping: PdoMapping, values: Sequence[EntryValue], data: bytes):
        """Store and return the frame with ``values`` (or ``data``), or the SdoResult why not.

        Called with the lock held: read, merge and store at once, so concurrent writes lose
        nothing.
        """
        device = self._devices[mapping.node_id]
        current = device.rpdos.get(mapping.number)
        if current is not mapping and current != mapping:  # read again since it was checked
            return SdoResult.failed(f'{mapping.name}: its PDO mapping changed while the write '
                                    f'was checked; nothing was sent')
        previous = device.last_sent.get(mapping.number) or bytes(mapping.size)
        try:
            frame = bytes(data) if data else encode(mapping, previous, values)
        except ValueError as error:
            return SdoResult.failed(f'entries: {error}')
        device.last_sent[mapping.number] = frame
        return frame

    def _refused(self, node_id: int, result: SdoResult) -> SdoResult:
        """Count a write refused by this service; return its answer."""
        with self._lock:
            device = self._devices.get(node_id)
            if device is not None:
                device.refused += 1
        return result

    def _write_refusal(self, mapping: PdoMapping) -> Optional[SdoResult]:
        if mapping.problem:
            return SdoResult.failed(mapping.problem)
        if not mapping.enabled:
            return SdoResult.failed(f'{mapping.name} is disabled on the device (bit 31 of its '
                                    f'COB-ID entry is set); nothing was sent')
        if not mapping.entries:
            return SdoResult.failed(f'{mapping.name} maps no object (its mapping is empty); '
                                    f'nothing was sent')
        for entry in mapping.entries:
            if entry.dummy:
                continue
            refusal = self._protection.refuses_write(mapping.node_id, entry.index)
            if refusal:
                return SdoResult.aborted(abort_codes.LOCAL_CONTROL,
                                         f'{mapping.name} maps {entry.label}: {refusal}')
        return None

    def _send(self, mapping: PdoMapping, frame: bytes, stopping: bool = False) -> SdoResult:
        """Send ``frame``; ``stopping``: a stop's frame, sent even once shutdown has begun.

        Nothing else while ``hold_frames_while`` says why not.
        """
        held = None if stopping else self._held_back()
        if held:
            with self._lock:
                self._devices[mapping.node_id].refused += 1
            return SdoResult.failed(f'{mapping.name} was not sent: {held}')
        with self._lock:
            if self._closing and not stopping:
                return SdoResult.failed(f'{SHUTTING_DOWN}; nothing was sent')
        try:
            self._network.send_message(mapping.cob_id, frame)
        except BusDown as error:
            with self._lock:
                self._devices[mapping.node_id].refused += 1
            return SdoResult.failed(f'{mapping.name} was not sent: {error}')
        with self._lock:
            device = self._devices[mapping.node_id]
            device.sent += 1
            device.sent_at[mapping.number] = time.monotonic()
            device.on_bus[mapping.number] = frame
            if (mapping.node_id, mapping.number) in self._streams:
                device.stream_on_bus[mapping.number] = frame
        return SdoResult.ok()

    def _flush(self, key: Tuple[int, int]) -> None:
        node_id, number = key
        with self._frames:
            with self._lock:
                device = self._devices[node_id]
                futures = self._pending_sync.pop(key, [])
                frame = device.last_sent.get(number)
                # The mapping as it is now: a boot may have moved the RPDO since the first write.
                mapping = device.rpdos.get(number)
                # Written before a boot, or on entries read again since (the frame was
                # dropped with them): gone, whatever came since.
                current = [future for future, life, layout in futures if life == device.life
                           and mapping is not None and layout.entries == mapping.entries]
                lost = [future for future, *_ in futures if future not in current]
                if frame is None:  # its mapping changed: nothing is left
                    lost, current = lost + current, []
            result = self._send(mapping, frame) if current else None
        for future in current:
            answer(future, result)
        for future in lost:
            answer(future, SdoResult.failed(f'node {node_id} booted (or its PDO mapping '
                                            f'changed) before the SYNC: its RPDO {number} '
                                            f'was not sent'))

    @prompt
    def _on_heartbeat(self, can_id: int, data: bytearray, _timestamp: float) -> None:
        if not data:
            return
        boot = data[0] == BOOT_UP
        with self._lock:
            device = self._devices[can_id - HEARTBEAT_COB_BASE]
            first = not device.heard
            device.heard = True
            if boot:
                device.last_sent.clear()  # its RPDOs hold nothing of before
                device.on_bus.clear()
                device.life += 1
                self._follow_stream((device.node_id, 0), 0.0)
            retry = (device.done < 0 and
                     time.monotonic() - device.failed_at >= REREAD_INTERVAL)
            if (boot or first or retry) and not device.booted:
                device.wanted += 1
                self._changed.notify_all()

    def hold_frames_while(self, why: Callable[[], Optional[str]]) -> None:
        """Send no frame but a stop while ``why()`` says why not (a str; None: send)."""
        self._held_back = why

    def _read_mappings(self) -> None:
        while True:
            with self._lock:
                while not self._closing and not any(
                        device.wanted > abs(device.done) for device in self._devices.values()):
                    self._changed.wait()
                if self._closing:
                    return
                device = next(device for device in self._devices.values()
                              if device.wanted > abs(device.done))
                request = device.wanted
            self._read_device(device, request)

    def _read_device(self, device: _Device, request: int) -> None:
        node_id = device.node_id
        try:
            tpdos, rpdos = self._parameters.read(node_id, device.dictionary)
        except ParametersFailed as error:
            with self._lock:
                if self._closing:
                    return  # shutdown ended the read: no fault of the device
                device.done = -request
                device.failed_at = time.monotonic()
                device.mapping_text = f'read failed: {error}'
            self._answer_readers(device, request, f'PDO mapping not read: {error}')
            self._log_once(node_id, 'mapping', f'node {node_id}: PDO mapping not read: '
                           f'{error}; tried again on a later heartbeat')
            return
        with self._lock:
            if self._closing:
                return
            old = [mapping.cob_id for mapping in device.tpdos.values()]
            # A frame built on another layout would put its values into the wrong entries.
            device.last_sent = {number: data for number, data in device.last_sent.items()
                                if number in rpdos and number in device.rpdos
                                and rpdos[number].entries == device.rpdos[number].entries}
            device.on_bus = {number: data for number, data in device.on_bus.items()
                             if number in device.last_sent}
            device.tpdos, device.rpdos = tpdos, rpdos
            device.last_received.clear()
            self._follow_stream((node_id, 0), 0.0)
            device.done = request
            device.mapping_text = (f'read: {len(tpdos)} TPDOs, {len(rpdos)} RPDOs at '
                                   f'{time.strftime("%H:%M:%S")}')
            for cob_id in old:
                self._by_cob.pop(cob_id, None)
            for mapping in tpdos.values():
                if mapping.enabled:
                    self._by_cob[mapping.cob_id] = mapping
            self._follow_cob_ids()
        self._answer_readers(device, request, '')
        device.logged.discard('mapping')
        LOGGER.info('node %d: PDO mapping read: %s', node_id, ', '.join(
            describe(mapping) for mapping in [*tpdos.values(), *rpdos.values()]) or 'no PDOs')
        for mapping in [*tpdos.values(), *rpdos.values()]:
            if mapping.problem and mapping.enabled:
                LOGGER.warning('%s', mapping.problem)

    @prompt
    def _on_frame(self, can_id: int, data: bytearray, timestamp: float) -> None:
        mapping = self._by_cob.get(can_id)
        if mapping is None:
            return
        device = self._devices[mapping.node_id]
        if mapping.problem:
            device.unusable += 1
            self._log_once(mapping.node_id, f'unusable {mapping.number}', mapping.problem)
            return
        if len(data) < mapping.size:
            device.short_frames += 1
            self._log_once(mapping.node_id, f'short {mapping.number}',
                           f'{mapping.name} arrived with {len(data)} bytes, its mapping '
                           f'takes {mapping.size}: not published (nor later short ones)')
            return
        device.received += 1
        device.last_received[mapping.number] = timestamp
        received = ReceivedPdo(mapping, bytes(data), timestamp)
        for listener in self._listeners:
            listener(received)

    def _log_once(self, node_id: int, kind: str, message: str) -> None:
        device = self._devices.get(node_id)
        if device is None or kind in device.logged:
            return
        device.logged.add(kind)
        LOGGER.warning('%s', message)

    def _statistics(self, device: _Device, now: float) -> PdoStatistics:
        late = []
        for number, mapping in device.tpdos.items():
            if (mapping.enabled and not mapping.synchronous and mapping.event_timer
                    and device.heard):
                last = device.last_received.get(number)
                if last is not None and now - last > 2 * mapping.event_timer / 1000:
                    late.append((number, mapping.event_timer, now - last))
        return PdoStatistics(device.received, device.sent, device.short_frames,
                             device.refused, device.unusable, len(device.tpdos),
                             len(device.rpdos), device.mapping_text, tuple(late))
