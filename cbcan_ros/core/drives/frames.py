"""Which receive PDOs carry one write to a drive, and in what order: nothing committed early.

A drive acts on its controlword as a frame carrying it arrives (an event-driven RPDO) or at
the SYNC after it (a synchronous one): a rising bit 4 takes the target position the drive
holds then, bit 7 resets a fault, the enable bits start the power stage in the mode it holds.
So for one write the values the controlword commits must be in the drive before the
controlword is. Real drives map the controlword into several RPDOs, and rarely next to the
object a write needs (a Maxon EPOS2 ships RPDO1 = 0x6040, RPDO2 = 0x6040 + 0x6060, RPDO3 =
0x6040 + 0x607A, RPDO4 = 0x6040 + 0x60FF), so the plan for a write is:

- the fewest usable RPDOs that carry its objects (ties: fewest frames carrying the
  controlword, then the smallest frames, then the lowest numbers);
- the write's controlword in exactly one of them, the last one sent; an earlier frame that
  maps the controlword too repeats the one the gateway commanded before the write (no edge);
- objects no usable RPDO carries go by SDO first, and the frames wait for their confirmation;
- when no usable RPDO carries the controlword, the whole write goes by SDO, in order, the
  controlword last (an SDO write is applied as it is confirmed);
- a synchronous frame before an event-driven controlword frame would be applied after it
  (at the next SYNC): such a set of frames is not used.

An RPDO is usable when it is enabled, sound, synchronous only while the gateway produces SYNC,
and maps nothing but objects whose values the gateway knows: those it commands (subindex 0),
and others (0x6072 max torque, an offset, a vendor object) whose bytes it read from the drive
when it heard it; those go out as the drive holds them. A frame carries every object it maps,
and one the gateway holds no value for would go out as a value of the gateway's making.
"""

from dataclasses import dataclass, field
from itertools import combinations
import struct
from typing import Dict, Iterable, List, Mapping, Optional, Sequence, Tuple

from ..pdo.mapping import PdoMapping
from . import cia402

# Beyond this many candidate RPDOs the cover is chosen greedily (CiA 301 allows 512; drives
# have 4 to 8).
EXACT_SEARCH_LIMIT = 12


@dataclass(frozen=True)
class Frame:
    """One RPDO of a write: the commanded objects it maps, and the others it repeats."""

    number: int
    indexes: Tuple[int, ...]
    synchronous: bool
    held: Tuple[Tuple[int, int], ...] = ()  # (index, subindex) sent as read from the drive
    # The whole frame packed at once (``frame_data``), when every entry it maps lies on whole
    # bytes in the size of its type: the struct and, in mapped order, each entry's source
    # (a commanded object's index, or a held object's (index, subindex)).
    layout: Optional[Tuple[struct.Struct, Tuple]] = field(default=None, compare=False)

    @property
    def controlword(self) -> bool:
        """Return whether the frame maps the controlword."""
        return cia402.CONTROLWORD in self.indexes


@dataclass(frozen=True)
class Plan:
    """How one write goes out: ``by_sdo`` first (in order), then ``frames`` in order.

    When the write has a controlword and ``frames`` is not empty, the last frame carries it
    and the others repeat the one commanded before.
    """

    by_sdo: Tuple[int, ...]
    frames: Tuple[Frame, ...]


def usable_frames(rpdos: Mapping[int, PdoMapping], commanded: Iterable[int],
                  sync_producing: bool, held: Mapping[Tuple[int, int], bytes] = None
                  ) -> List[Frame]:
    """Return the RPDOs a write may use, as frames.

    ``commanded``: the objects the gateway commands and has a value for; ``held``: other
    objects' bytes as read from the drive, by (index, subindex).
    """
    known, held = set(commanded), held or {}
    frames = []
    for number, mapping in sorted(rpdos.items()):
        if (not mapping.enabled or mapping.problem or not mapping.entries
                or (mapping.synchronous and not sync_producing)):
            continue
        entries = [entry for entry in mapping.entries if not entry.dummy]
        ours = [entry for entry in entries if entry.subindex == 0 and entry.index in known]
        others = [entry for entry in entries if entry not in ours]
        if any(len(held.get((entry.index, entry.subindex), b'')) != (entry.bits + 7) // 8
               for entry in others):
            continue
        frames.append(Frame(number, tuple(entry.index for entry in ours), mapping.synchronous,
                            tuple((entry.index, entry.subindex) for entry in others),
                            _layout(mapping, ours)))
    return frames


def _layout(mapping: PdoMapping, ours: Sequence) -> Optional[Tuple[struct.Struct, Tuple]]:
    """Return the frame's ``Frame.layout``, or None when an entry is no whole bytes of its type.

    Such a frame goes entry by entry (``PdoService`` merges them into the frame last sent),
    which also refuses a commanded object mapped in another width than its type's.
    """
    formats, sources = ['<'], []
    for entry in mapping.entries:
        if entry.dummy or entry.bits % 8:
            return None
        if entry in ours:
            code = cia402.FORMATS[entry.index][1:]
            if struct.calcsize(code) * 8 != entry.bits:
                return None
            formats.append(code)
            sources.append(entry.index)
        else:
            formats.append(f'{entry.bits // 8}s')
            sources.append((entry.index, entry.subindex))
    return struct.Struct(''.join(formats)), tuple(sources)


def frame_data(frame: Frame, values: Dict[int, int],
               held: Mapping[Tuple[int, int], bytes]) -> bytes:
    """Return the whole frame of a ``frame.layout`` with ``values`` (``frame_values``)."""
    packer, sources = frame.layout
    try:
        return packer.pack(*[values[source] if source.__class__ is int else held[source]
                             for source in sources])
    except struct.error:
        raise ValueError(f'RPDO {frame.number}: the values {values} do not fit its '
                         f'mapping') from None


def plan(values: Sequence[int], frames: Sequence[Frame], controlword_known: bool) -> Plan:
    """Return how to send the objects ``values`` (in the write's order) over ``frames``.

    ``frames`` are the usable ones (``usable_frames``, with the write's values known);
    ``controlword_known``: the gateway commanded a controlword before this write, which an
    earlier frame mapping it can repeat.
    """
    wanted = list(dict.fromkeys(values))
    candidates = [frame for frame in frames if set(frame.indexes) & set(wanted)]
    coverable = {index for frame in candidates for index in frame.indexes} & set(wanted)
    has_controlword = cia402.CONTROLWORD in wanted
    # The controlword by SDO is applied at once: everything before it goes by SDO too.
    all_by_sdo = Plan(tuple(sorted(wanted, key=lambda index: index == cia402.CONTROLWORD)), ())
    if has_controlword and cia402.CONTROLWORD not in coverable:
        return all_by_sdo
    chosen = _cover(candidates, coverable, has_controlword, controlword_known)
    if chosen is None:
        return all_by_sdo
    by_sdo = tuple(index for index in wanted if index not in coverable)
    return Plan(by_sdo, chosen)


def _cover(candidates: List[Frame], coverable: set, has_controlword: bool,
           controlword_known: bool) -> Optional[Tuple[Frame, ...]]:
    """Return the best ordered set of frames carrying ``coverable``, None when none fits."""
    if not coverable:
        return ()
    if len(candidates) > EXACT_SEARCH_LIMIT:
        return _greedy(candidates, coverable, has_controlword, controlword_known)
    for size in range(1, len(candidates) + 1):
        best: Optional[Tuple[Tuple, Tuple[Frame, ...]]] = None
        for combo in combinations(candidates, size):
            if not coverable <= {index for frame in combo for index in frame.indexes}:
                continue
            ordered = _ordered(combo, has_controlword, controlword_known)
            if ordered is None:
                continue
            score = (sum(frame.controlword for frame in ordered),
                     sum(len(frame.indexes) for frame in ordered),
                     tuple(frame.number for frame in ordered))
            if best is None or score < best[0]:
                best = (score, ordered)
        if best is not None:
            return best[1]
    return None


def _greedy(candidates: List[Frame], coverable: set, has_controlword: bool,
            controlword_known: bool) -> Optional[Tuple[Frame, ...]]:
    left, combo = set(coverable), []
    while left:
        frame = max(candidates, key=lambda f: (len(left & set(f.indexes)), -f.number))
        if not left & set(frame.indexes):
            return None
        combo.append(frame)
        left -= set(frame.indexes)
    return _ordered(combo, has_controlword, controlword_known)


def _ordered(combo: Iterable[Frame], has_controlword: bool,
             controlword_known: bool) -> Optional[Tuple[Frame, ...]]:
    """Return ``combo`` in sending order, the controlword's frame last; None when unfit."""
    frames = sorted(combo, key=lambda frame: frame.number)
    if not has_controlword:
        if not controlword_known and any(frame.controlword for frame in frames):
            return None
        return tuple(frames)
    carriers = sorted((frame for frame in frames if frame.controlword),
                      key=lambda frame: (frame.synchronous, frame.number), reverse=True)
    for last in carriers:
        before = [frame for frame in frames if frame is not last]
        if any(frame.controlword for frame in before) and not controlword_known:
            return None
        if last.synchronous or not any(frame.synchronous for frame in before):
            return (*before, last)
        # Else a synchronous frame, applied at the next SYNC, would come after the controlword.
    return None


def frame_values(frame: Frame, commanded: Dict[int, int], previous_controlword: Optional[int],
                 carries_write_controlword: bool) -> Dict[int, int]:
    """Return the values ``frame`` carries: the commanded ones, the controlword as it goes."""
    values = {index: commanded[index] for index in frame.indexes}
    if frame.controlword and not carries_write_controlword:
        values[cia402.CONTROLWORD] = previous_controlword
    return values
