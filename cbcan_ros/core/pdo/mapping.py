"""PDO mappings (CiA 301): what a device maps into each PDO, and the frames it describes.

A mapping is made from the raw parameters read from the device (``parameters``); a
frame is decoded and encoded by it bit-exact, any entry width up to 64 bits, with the types
from the EDS when given, else unsigned.
"""

from dataclasses import dataclass, replace
from functools import cached_property
import math
import struct
from typing import Dict, Optional, Sequence, Tuple

from canopen.objectdictionary import datatypes, ObjectDictionary

from ..values import int_given_as_float

MAX_PDOS = 512
MAX_ENTRIES = 64          # CiA 301: sub-indices 1..64 of a mapping record
MAX_BITS = 64             # a classic CAN frame
RPDO_COMMUNICATION, RPDO_MAPPING = 0x1400, 0x1600
TPDO_COMMUNICATION, TPDO_MAPPING = 0x1800, 0x1A00
DUMMY_INDICES = range(0x0001, 0x0008)
COB_INVALID = 1 << 31     # bit 31 of the COB-ID entry: the PDO is not valid (disabled)
COB_EXTENDED = 1 << 29    # bit 29: a 29-bit identifier
SYNCHRONOUS_MAX = 240     # transmission types 0..240 are synchronous, 254/255 event-driven

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
            hint = int_given_as_float('the value', value)
            raise ValueError(f'{self.label}: {value} is not a whole number'
                             + (f' ({hint})' if hint else ''))
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

    # Worked out once a mapping (never changed, replaced by a read): a stream of targets
    # asks for them with every frame.
    @cached_property
    def bits(self) -> int:
        """Return the mapped length in bits."""
        return sum(entry.bits for entry in self.entries)

    @cached_property
    def size(self) -> int:
        """Return the bytes a frame of this PDO needs."""
        return (self.bits + 7) // 8

    @cached_property
    def synchronous(self) -> bool:
        """Return whether its transmission type is synchronous (0..240)."""
        return self.transmission_type <= SYNCHRONOUS_MAX

    @cached_property
    def entries_of(self) -> Dict[Tuple[int, int], Tuple[MappedEntry, ...]]:
        """Return the (non-dummy) entries mapping each object, by (index, subindex)."""
        found: Dict[Tuple[int, int], Tuple[MappedEntry, ...]] = {}
        for entry in self.entries:
            if not entry.dummy:
                key = (entry.index, entry.subindex)
                found[key] = found.get(key, ()) + (entry,)
        return found


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


# Slotted for the same reason: a stream of targets makes a few for every frame it sends.
@dataclass(slots=True)
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
    entries_of = mapping.entries_of
    for given in values:
        targets = entries_of.get((given.index, given.subindex))
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


def describe(mapping: PdoMapping) -> str:
    """Return a PDO in a few words for the log, e.g. 'TPDO1 0x181 type 255 16 bits'."""
    state = '' if mapping.enabled else ' (disabled)'
    return (f'{mapping.kind.upper()}{mapping.number} 0x{mapping.cob_id:03X} type '
            f'{mapping.transmission_type} {mapping.bits} bits{state}')
