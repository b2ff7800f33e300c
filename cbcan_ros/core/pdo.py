"""PDOs (CiA 301 process data): mappings read from the devices, frames decoded and sent.

For every device served (``pdo.nodes``) the communication and mapping parameters of all its
PDOs (0x1400-0x17FF, 0x1800-0x1BFF, from number 1 up to the first one it does not have) are
read over SDO when it is first heard and again after every boot-up message. They are read
through the gateway's own SDO channels, so they queue behind (and never race) a user's SDO
calls. With ``pdo.configure`` the PDO parameters of the device's EDS/DCF file are written
first whenever it boots.

The device's transmit PDOs arrive through ``network.subscribe`` with the host's monotonic
receive time; the bus thread only checks a frame's length and hands it to the listeners as a
:class:`ReceivedPdo`, which is decoded when read (bit-exact, any entry width up to 64 bits,
types from the EDS when given, else unsigned), in the listener's own thread.
Its receive PDOs are sent on request: asynchronous ones at once, synchronous ones right after
a SYNC the gateway produces (``sync.py``).

python-canopen's ``PdoMap`` is not used for this: it reads mappings through canopen's own SDO
client (a second client on the device's SDO channel, racing the gateway's), needs every
mapped object in an EDS, drops dummy entries, and decodes bit fields through the object's
full type; see the README's library gaps.
"""

from concurrent.futures import Future
from dataclasses import dataclass, field, replace
import logging
import math
import re
import struct
import sys
import threading
import time
from typing import Callable, Dict, List, Optional, Sequence, Tuple

from canopen.objectdictionary import datatypes, ObjectDictionary

from . import abort_codes
from .bus import BusDown, BusStatus, prompt
from .nmt import BOOT_UP, HEARTBEAT_COB_BASE
from .request_queue import answer, resolved
from .sdo import Access, SdoResult

LOGGER = logging.getLogger(__name__)

MAX_PDOS = 512
MAX_ENTRIES = 64          # CiA 301: sub-indices 1..64 of a mapping record
MAX_BITS = 64             # a classic CAN frame
RPDO_COMMUNICATION, RPDO_MAPPING = 0x1400, 0x1600
TPDO_COMMUNICATION, TPDO_MAPPING = 0x1800, 0x1A00
DUMMY_INDICES = range(0x0001, 0x0008)
COB_INVALID = 1 << 31     # bit 31 of the COB-ID entry: the PDO is not valid (disabled)
COB_EXTENDED = 1 << 29    # bit 29: a 29-bit identifier
NO_SUCH_OBJECT = 0x06020000
SYNCHRONOUS_MAX = 240     # transmission types 0..240 are synchronous, 254/255 event-driven
# A mapping read that failed (device busy, timeout) is tried again on a later heartbeat, at
# most this often.
REREAD_INTERVAL = 2.0

SHUTTING_DOWN = 'the gateway is shutting down'

_SIGNED = frozenset(datatypes.SIGNED_TYPES)
_FLOATS = {datatypes.REAL32: (32, '<f'), datatypes.REAL64: (64, '<d')}


@dataclass(frozen=True)
class MappedEntry:
    """One object mapped into a PDO, at bit ``offset`` of the frame."""

    index: int
    subindex: int
    bits: int
    offset: int
    name: str = ''
    data_type: int = 0  # CiA 301 code from the EDS; 0 unknown

    @property
    def dummy(self) -> bool:
        """Return whether this is a dummy entry (a placeholder, never decoded)."""
        return self.index in DUMMY_INDICES

    @property
    def label(self) -> str:
        """Return the entry as a user sees it: 0x6040:0, with its EDS name when known."""
        return f'0x{self.index:04X}:{self.subindex}' + (f' ({self.name})' if self.name else '')

    def decode(self, frame: int) -> Tuple[float, bytes]:
        """Return the value and the bytes of this entry in a frame given as one integer."""
        raw = (frame >> self.offset) & ((1 << self.bits) - 1)
        data = raw.to_bytes((self.bits + 7) // 8, 'little')
        if self.dummy:
            return 0.0, data
        width, code = _FLOATS.get(self.data_type, (0, ''))
        if width == self.bits:
            return struct.unpack(code, data)[0], data
        if self.data_type in _SIGNED and raw >> (self.bits - 1):
            return float(raw - (1 << self.bits)), data
        return float(raw), data

    def encode(self, value: Optional[float], data: bytes) -> int:
        """Return the entry's bits for ``data`` (exact bytes) if given, else for ``value``.

        Raises ValueError naming the entry when the value does not fit it.
        """
        if data:
            size = (self.bits + 7) // 8
            raw = int.from_bytes(data, 'little')
            if len(data) != size or raw >> self.bits:
                raise ValueError(f'{self.label}: data has {len(data)} bytes, the entry takes '
                                 f'{self.bits} bits ({size} bytes)')
            return raw
        width, code = _FLOATS.get(self.data_type, (0, ''))
        if width == self.bits:
            try:
                return int.from_bytes(struct.pack(code, value), 'little')
            except (OverflowError, struct.error):
                raise ValueError(f'{self.label}: {value} does not fit a '
                                 f'{self.bits}-bit float') from None
        if not math.isfinite(value) or not float(value).is_integer():
            hint = ''
            if 0 < abs(value) < sys.float_info.min:
                whole = struct.unpack('<q', struct.pack('<d', value))[0]
                hint = (f' (rclpy sends a Python int put in a float64 field as its bits: '
                        f'was {whole} meant? Give it as a float, {whole}.0)')
            raise ValueError(f'{self.label}: {value} is not a whole number{hint}')
        number = int(value)
        signed = self.data_type in _SIGNED
        low = -(1 << (self.bits - 1)) if signed else 0
        high = (1 << (self.bits - (1 if signed else 0))) - 1
        if not low <= number <= high:
            raise ValueError(f'{self.label}: {number} does not fit: allowed {low}..{high} '
                             f'({"signed" if signed else "unsigned"} {self.bits} bits)')
        return number & ((1 << self.bits) - 1)


@dataclass(frozen=True)
class PdoMapping:
    """One PDO of a device as read from it: ``kind`` 'tpdo' (it sends) or 'rpdo' (it receives).

    ``problem`` says why it cannot be used (longer than a frame, a 29-bit COB-ID...);
    frames of such a PDO are counted, not decoded, and writes are refused.
    """

    node_id: int
    kind: str
    number: int
    cob_id: int
    enabled: bool
    transmission_type: int
    event_timer: int = 0  # ms; 0 = none
    entries: Tuple[MappedEntry, ...] = ()
    problem: str = ''

    @property
    def name(self) -> str:
        """Return e.g. 'TPDO 1 of node 5'."""
        return f'{self.kind.upper()} {self.number} of node {self.node_id}'

    @property
    def bits(self) -> int:
        """Return the mapped length in bits."""
        return sum(entry.bits for entry in self.entries)

    @property
    def size(self) -> int:
        """Return the bytes a frame of this PDO needs."""
        return (self.bits + 7) // 8

    @property
    def synchronous(self) -> bool:
        """Return whether its transmission type is synchronous (0..240)."""
        return self.transmission_type <= SYNCHRONOUS_MAX


# The two classes made for every received frame are plain slotted classes: a frozen
# dataclass costs several times as much to build, in the bus thread.
@dataclass(slots=True)
class DecodedEntry:
    """One mapped object's value in a received frame."""

    entry: MappedEntry
    value: float
    data: bytes


@dataclass(slots=True)
class ReceivedPdo:
    """One frame a device sent on one of its TPDOs, at least as long as its mapping.

    Decoded when ``entries`` is read (by the publishing thread, not the bus thread).
    """

    mapping: PdoMapping
    data: bytes
    timestamp: float  # time.monotonic() when the bus thread took the frame

    @property
    def entries(self) -> Tuple[DecodedEntry, ...]:
        """Return every mapped entry decoded, in mapping order."""
        return decode(self.mapping, self.data)


@dataclass(frozen=True)
class EntryValue:
    """A value to send for one mapped object: ``data`` (exact bytes) if given, else ``value``."""

    index: int
    subindex: int
    value: float = 0.0
    data: bytes = b''


def decode(mapping: PdoMapping, data: bytes) -> Tuple[DecodedEntry, ...]:
    """Decode a frame by its mapping; the caller has checked it is long enough."""
    frame = int.from_bytes(data[:mapping.size], 'little')
    return tuple(DecodedEntry(entry, *entry.decode(frame)) for entry in mapping.entries)


def encode(mapping: PdoMapping, previous: bytes, values: Sequence[EntryValue]) -> bytes:
    """Return the frame with ``values`` put into ``previous`` (the frame last sent).

    Raises ValueError naming the entry that is not mapped or whose value does not fit.
    """
    frame = int.from_bytes(previous, 'little')
    for given in values:
        targets = [entry for entry in mapping.entries
                   if (entry.index, entry.subindex) == (given.index, given.subindex)
                   and not entry.dummy]
        if not targets:
            mapped = ', '.join(entry.label for entry in mapping.entries if not entry.dummy)
            raise ValueError(f'0x{given.index:04X}:{given.subindex} is not mapped to '
                             f'{mapping.name} (mapped: {mapped or "nothing"})')
        for entry in targets:
            bits = entry.encode(given.value, given.data)
            mask = ((1 << entry.bits) - 1) << entry.offset
            frame = (frame & ~mask) | (bits << entry.offset)
    return frame.to_bytes(mapping.size, 'little')


def parse_mapping(node_id: int, kind: str, number: int, cob_entry: int,
                  transmission_type: int, event_timer: int, mapped: Sequence[int],
                  dictionary: Optional[ObjectDictionary] = None) -> PdoMapping:
    """Return a PDO from its raw parameters (COB-ID entry, mapping entries as UNSIGNED32)."""
    entries = []
    offset = 0
    for value in mapped:
        index, subindex, bits = value >> 16, (value >> 8) & 0xFF, value & 0xFF
        if not bits:
            continue  # takes no room in the frame (devices fill unused entries with 0)
        variable = dictionary.get_variable(index, subindex) if dictionary else None
        name = ''
        data_type = index if index in DUMMY_INDICES else 0
        if variable is not None:
            name, data_type = variable.qualname, variable.data_type or 0
        entries.append(MappedEntry(index, subindex, bits, offset, name, data_type))
        offset += bits
    problem = ''
    if offset > MAX_BITS:
        problem = (f'its mapping is {offset} bits long: a CAN frame carries at most '
                   f'{MAX_BITS}; refused')
    elif cob_entry & COB_EXTENDED:
        problem = 'it uses a 29-bit COB-ID, which the gateway does not support'
    mapping = PdoMapping(node_id, kind, number, cob_entry & 0x7FF, not cob_entry & COB_INVALID,
                         transmission_type, event_timer, tuple(entries))
    if problem:
        return replace(mapping, problem=f'{mapping.name}: {problem}')
    return mapping


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
    last_sent: Dict[int, bytes] = field(default_factory=dict)
    last_received: Dict[int, float] = field(default_factory=dict)
    heard: bool = False
    wanted: int = 0       # mapping reads asked for (first heard, every boot-up)
    done: int = 0         # the request the current mapping answers
    boots: int = 0        # boot-ups asked to configure
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
                 sync, dictionaries: Dict[int, ObjectDictionary], configure: bool = False):
        self._network = network
        self._sdo_batch = sdo_batch
        self._protection = write_protection
        self._sync = sync
        self._configure = configure
        self._lock = threading.Condition()
        self._devices = {node_id: _Device(node_id, dictionaries.get(node_id))
                         for node_id in sorted(set(node_ids))}
        self._by_cob: Dict[int, PdoMapping] = {}
        self._subscribed: set = set()
        self._listeners: List[Callable[[ReceivedPdo], None]] = []
        self._closing = False
        self._pending_sync: Dict[Tuple[int, int], List[Future]] = {}
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
        """Answer every write still waiting for a SYNC; stop reading, receiving, sending."""
        with self._lock:
            self._closing = True
            pending, self._pending_sync = self._pending_sync, {}
            self._lock.notify_all()
            self._by_cob.clear()
            self._follow_cob_ids()
        for futures in pending.values():
            for future in futures:
                answer(future, SdoResult.failed(f'{SHUTTING_DOWN}; it was not sent'))
        for node_id in self._devices:
            self._network.unsubscribe(HEARTBEAT_COB_BASE + node_id, self._on_heartbeat)
        # The mapping reader is not waited for: it may wait for an SDO answer, which the
        # gateway gives ("shutting down") right after this; it then installs nothing.

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
            for device in self._devices.values():
                device.heard = False

    def mappings(self, node_id: int) -> Tuple[Dict[int, PdoMapping], Dict[int, PdoMapping]]:
        """Return the TPDOs and RPDOs of a device served, by number (empty before read)."""
        with self._lock:
            device = self._devices[node_id]
            return dict(device.tpdos), dict(device.rpdos)

    def statistics(self) -> Dict[int, PdoStatistics]:
        """Return the statistics of every device served, by node id."""
        now = time.monotonic()
        with self._lock:
            return {node_id: self._statistics(device, now)
                    for node_id, device in self._devices.items()}

    def refuse(self, node_id: int, problem: str) -> None:
        """Count (and log once per kind) a write refused before it reached :meth:`write`."""
        with self._lock:
            device = self._devices.get(node_id)
            if device is not None:
                device.refused += 1
        self.log_refusal(node_id, problem)

    def log_refusal(self, node_id: int, problem: str) -> None:
        """Log a refused write from a topic, once per kind (the numbers in it not counted)."""
        self._log_once(node_id, re.sub(r'\d', '', problem)[:80], problem)

    def write(self, node_id: int, number: int, values: Sequence[EntryValue] = (),
              data: bytes = b'') -> 'Future[SdoResult]':
        """Send RPDO ``number`` of ``node_id`` with ``values`` (or the whole frame ``data``).

        Resolves once the frame went out (a synchronous RPDO: after the next SYNC) or why
        not; never raises.
        """
        result = self._prepare(node_id, number, values, data)
        if isinstance(result, SdoResult):
            with self._lock:
                device = self._devices.get(node_id)
                if device is not None:
                    device.refused += 1
            return resolved(result)
        mapping, frame = result
        future: Future = Future()
        if mapping.synchronous and self._sync.producing:
            with self._lock:
                key = (node_id, number)
                first = key not in self._pending_sync
                self._pending_sync.setdefault(key, []).append(future)
            if first and not self._sync.after_next_sync(lambda: self._flush(key, mapping)):
                self._flush(key, mapping)  # SYNC is paused (bus down): fails at once
            return future
        answer(future, self._send(mapping, frame))
        return future

    def _prepare(self, node_id: int, number: int, values: Sequence[EntryValue], data: bytes):
        """Return (mapping, frame) to send, or the SdoResult that refuses the write."""
        if node_id not in self._devices:
            served = ', '.join(map(str, self._devices)) or 'none'
            return SdoResult.failed(f'node_id {node_id} is not in the parameter pdo.nodes '
                                    f'(served: {served})')
        with self._lock:
            if self._closing:
                return SdoResult.failed(f'{SHUTTING_DOWN}; nothing was sent')
            device = self._devices[node_id]
            mapping = device.rpdos.get(number)
            known = ', '.join(map(str, device.rpdos)) or 'none'
            text = device.mapping_text
        if mapping is None:
            return SdoResult.failed(f'pdo {number}: node {node_id} has no RPDO {number} '
                                    f'(its RPDOs: {known}; PDO mapping {text})')
        refusal = self._write_refusal(mapping)
        if refusal is not None:
            return refusal
        if data and values:
            return SdoResult.failed('give entries or data (the whole frame), not both')
        if data and len(data) != mapping.size:
            return SdoResult.failed(f'data has {len(data)} bytes, {mapping.name} takes '
                                    f'{mapping.size} ({mapping.bits} bits)')
        with self._lock:  # read, merge and store at once: concurrent writes lose nothing
            previous = device.last_sent.get(number) or bytes(mapping.size)
            try:
                frame = bytes(data) if data else encode(mapping, previous, values)
            except ValueError as error:
                return SdoResult.failed(f'entries: {error}')
            device.last_sent[number] = frame
        return mapping, frame

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

    def _send(self, mapping: PdoMapping, frame: bytes) -> SdoResult:
        with self._lock:
            if self._closing:
                return SdoResult.failed(f'{SHUTTING_DOWN}; nothing was sent')
        try:
            self._network.send_message(mapping.cob_id, frame)
        except BusDown as error:
            with self._lock:
                self._devices[mapping.node_id].refused += 1
            return SdoResult.failed(f'{mapping.name} was not sent: {error}')
        with self._lock:
            self._devices[mapping.node_id].sent += 1
        return SdoResult.ok()

    def _flush(self, key: Tuple[int, int], mapping: PdoMapping) -> None:
        with self._lock:
            futures = self._pending_sync.pop(key, [])
            frame = self._devices[key[0]].last_sent.get(key[1], bytes(mapping.size))
        if not futures:
            return
        result = self._send(mapping, frame)
        for future in futures:
            answer(future, result)

    @prompt
    def _on_heartbeat(self, can_id: int, data: bytearray, _timestamp: float) -> None:
        if not data:
            return
        boot = data[0] == BOOT_UP
        with self._lock:
            device = self._devices[can_id - HEARTBEAT_COB_BASE]
            first = not device.heard
            device.heard = True
            retry = (device.done < 0 and
                     time.monotonic() - device.failed_at >= REREAD_INTERVAL)
            if boot or first or retry:
                device.wanted += 1
                if boot:
                    device.boots = device.wanted
                self._lock.notify_all()

    def _read_mappings(self) -> None:
        while True:
            with self._lock:
                while not self._closing and not any(
                        device.wanted > abs(device.done) for device in self._devices.values()):
                    self._lock.wait()
                if self._closing:
                    return
                device = next(device for device in self._devices.values()
                              if device.wanted > abs(device.done))
                request, configure = device.wanted, device.boots == device.wanted
            self._read_device(device, request, configure and self._configure)

    def _read_device(self, device: _Device, request: int, configure: bool) -> None:
        node_id = device.node_id
        if configure and device.dictionary is not None:
            try:
                self._write_configuration(device)
            except _ReadFailed as error:
                # What the device has is still worth reading: it is what it will send.
                self._log_once(node_id, 'configure', f'node {node_id}: PDO parameters not '
                               f'written: {error}; the mapping the device has is used')
        try:
            tpdos = self._read_kind(device, 'tpdo', TPDO_COMMUNICATION, TPDO_MAPPING)
            rpdos = self._read_kind(device, 'rpdo', RPDO_COMMUNICATION, RPDO_MAPPING)
        except _ReadFailed as error:
            with self._lock:
                if self._closing:
                    return  # shutdown ended the read: no fault of the device
                device.done = -request
                device.failed_at = time.monotonic()
                device.mapping_text = f'read failed: {error}'
            self._log_once(node_id, 'mapping', f'node {node_id}: PDO mapping not read: '
                           f'{error}; tried again on a later heartbeat')
            return
        with self._lock:
            if self._closing:
                return
            old = [mapping.cob_id for mapping in device.tpdos.values()]
            device.tpdos, device.rpdos = tpdos, rpdos
            device.last_sent = {number: data for number, data in device.last_sent.items()
                                if number in rpdos and len(data) == rpdos[number].size}
            device.last_received.clear()
            device.done = request
            device.mapping_text = (f'read: {len(tpdos)} TPDOs, {len(rpdos)} RPDOs at '
                                   f'{time.strftime("%H:%M:%S")}')
            for cob_id in old:
                self._by_cob.pop(cob_id, None)
            for mapping in tpdos.values():
                if mapping.enabled:
                    self._by_cob[mapping.cob_id] = mapping
            self._follow_cob_ids()
        device.logged.discard('mapping')
        LOGGER.info('node %d: PDO mapping read: %s', node_id, ', '.join(
            _describe(mapping) for mapping in [*tpdos.values(), *rpdos.values()]) or 'no PDOs')
        for mapping in [*tpdos.values(), *rpdos.values()]:
            if mapping.problem and mapping.enabled:
                LOGGER.warning('%s', mapping.problem)

    def _read_kind(self, device: _Device, kind: str, communication: int,
                   mapping_index: int) -> Dict[int, PdoMapping]:
        found = {}
        for number in range(1, MAX_PDOS + 1):
            com = communication + number - 1
            subs = (1, 2, 5) if kind == 'tpdo' else (1, 2)
            results = self._batch(device.node_id, [(com, sub) for sub in subs], optional={5})
            if results is None:
                break
            cob_entry, transmission_type, *rest = results
            event_timer = rest[0] if rest else 0
            counted = self._batch(device.node_id, [(mapping_index + number - 1, 0)])
            if counted is None:
                raise _ReadFailed(f'{kind.upper()} {number} has communication parameters '
                                  f'but no mapping object 0x{mapping_index + number - 1:04X}')
            count = counted[0]
            if count > MAX_ENTRIES:
                raise _ReadFailed(f'{kind.upper()} {number} has {count} mapping entries: '
                                  f'CiA 301 allows {MAX_ENTRIES}')
            mapped = self._batch(device.node_id, [(mapping_index + number - 1, sub)
                                                  for sub in range(1, count + 1)]) if count \
                else []
            found[number] = parse_mapping(device.node_id, kind, number, cob_entry,
                                          transmission_type & 0xFF, event_timer, mapped,
                                          device.dictionary)
        return found

    def _batch(self, node_id: int, objects: Sequence[Tuple[int, int]],
               optional: frozenset = frozenset()) -> Optional[List[int]]:
        """Read objects as unsigned numbers; None when the first does not exist."""
        results = self._sdo_batch([Access(node_id, index, sub, max_size=4)
                                   for index, sub in objects]).result()
        numbers = []
        for (index, sub), result in zip(objects, results, strict=True):
            if result.success:
                numbers.append(int.from_bytes(result.data[:4], 'little'))
            elif sub in optional:
                numbers.append(0)
            elif result.abort_code == NO_SUCH_OBJECT and (index, sub) == objects[0]:
                return None
            else:
                raise _ReadFailed(f'0x{index:04X}:{sub}: {result.message}')
        return numbers

    def _write_configuration(self, device: _Device) -> None:
        """Write the PDO parameters of the device's file (disabled while changed)."""
        accesses = []
        dictionary = device.dictionary
        for communication, mapping_index in ((RPDO_COMMUNICATION, RPDO_MAPPING),
                                             (TPDO_COMMUNICATION, TPDO_MAPPING)):
            for number in range(MAX_PDOS):
                com = dictionary.get(communication + number)
                mapped = dictionary.get(mapping_index + number)
                if com is None or mapped is None:
                    continue
                accesses += _configuration(device.node_id, com, mapped,
                                           communication + number, mapping_index + number)
        if not accesses:
            return
        results = self._sdo_batch(accesses).result()
        failed = [(access, result) for access, result in zip(accesses, results, strict=True)
                  if not result.success]
        if failed:
            access, result = failed[0]
            raise _ReadFailed(f'configuring from node_{device.node_id}.eds: writing '
                              f'0x{access.index:04X}:{access.subindex} failed: '
                              f'{result.message}')
        LOGGER.info('node %d: PDO parameters of its EDS written (%d objects)',
                    device.node_id, len(accesses))

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


class _ReadFailed(Exception):
    """A device's PDO mapping could not be read (or its file's written)."""


def _describe(mapping: PdoMapping) -> str:
    state = '' if mapping.enabled else ' (disabled)'
    return (f'{mapping.kind.upper()}{mapping.number} 0x{mapping.cob_id:03X} type '
            f'{mapping.transmission_type} {mapping.bits} bits{state}')


def _file_value(variable) -> int:
    value = variable.value if variable.value is not None else variable.default
    return int(value or 0)


def _configuration(node_id: int, com, mapped, com_index: int,
                   map_index: int) -> List[Access]:
    """Return the writes that put one PDO of a file onto the device (CiA 301 order)."""
    def write(index: int, sub: int, value: int, size: int) -> Access:
        return Access(node_id, index, sub, True, value.to_bytes(size, 'little'))

    cob_entry = _file_value(com[1])
    accesses = [write(com_index, 1, cob_entry | COB_INVALID, 4)]
    for sub, size in ((2, 1), (3, 2), (5, 2)):
        if sub in com.subindices:
            accesses.append(write(com_index, sub, _file_value(com[sub]), size))
    count = _file_value(mapped[0])
    accesses.append(write(map_index, 0, 0, 1))
    accesses += [write(map_index, sub, _file_value(mapped[sub]), 4)
                 for sub in range(1, count + 1) if sub in mapped.subindices]
    accesses.append(write(map_index, 0, count, 1))
    accesses.append(write(com_index, 1, cob_entry, 4))
    return accesses
