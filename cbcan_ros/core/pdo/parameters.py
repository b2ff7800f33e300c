"""A device's PDO parameters over SDO: its mappings read.

The communication and mapping parameters of all its PDOs (0x1400-0x17FF, 0x1800-0x1BFF,
from number 1 up to the first one it does not have) are read through the gateway's own SDO
channels, so they queue behind (and never race) a user's SDO calls and pass its write
protection. Writing them is a step of a device's boot (``core/boot/plan.py``).

python-canopen's ``PdoMap`` is not used for this: it reads mappings through canopen's own SDO
client (a second client on the device's SDO channel, racing the gateway's), needs every
mapped object in an EDS, drops dummy entries, and decodes bit fields through the object's
full type; see docs/library_gaps.md.
"""

import logging
from typing import Dict, List, Optional, Sequence, Tuple

from canopen.objectdictionary import ObjectDictionary

from ..sdo.requests import Access
from .mapping import (
    MAX_ENTRIES,
    MAX_PDOS,
    parse_mapping,
    PdoMapping,
    RPDO_COMMUNICATION,
    RPDO_MAPPING,
    TPDO_COMMUNICATION,
    TPDO_MAPPING,
)

LOGGER = logging.getLogger(__name__)

NO_SUCH_OBJECT = 0x06020000


class ParametersFailed(Exception):
    """A device's PDO mapping could not be read."""


class PdoParameters:
    """Reads and writes PDO parameters with ``sdo_batch(accesses)``, the gateway's."""

    def __init__(self, sdo_batch):
        self._sdo_batch = sdo_batch

    def read(self, node_id: int, dictionary: Optional[ObjectDictionary]
             ) -> Tuple[Dict[int, PdoMapping], Dict[int, PdoMapping]]:
        """Return the device's TPDOs and RPDOs by number; raise :class:`ParametersFailed`.

        ``dictionary`` (its EDS, if any) names the mapped objects and gives their types.
        """
        return (self._read_kind(node_id, dictionary, 'tpdo', TPDO_COMMUNICATION,
                                TPDO_MAPPING),
                self._read_kind(node_id, dictionary, 'rpdo', RPDO_COMMUNICATION,
                                RPDO_MAPPING))

    def _read_kind(self, node_id: int, dictionary: Optional[ObjectDictionary], kind: str,
                   communication: int, mapping_index: int) -> Dict[int, PdoMapping]:
        found = {}
        for number in range(1, MAX_PDOS + 1):
            com = communication + number - 1
            subs = (1, 2, 5) if kind == 'tpdo' else (1, 2)
            results = self._numbers(node_id, [(com, sub) for sub in subs], optional={5})
            if results is None:
                break
            cob_entry, transmission_type, *rest = results
            event_timer = rest[0] if rest else 0
            counted = self._numbers(node_id, [(mapping_index + number - 1, 0)])
            if counted is None:
                raise ParametersFailed(f'{kind.upper()} {number} has communication '
                                       f'parameters but no mapping object '
                                       f'0x{mapping_index + number - 1:04X}')
            count = counted[0]
            if count > MAX_ENTRIES:
                raise ParametersFailed(f'{kind.upper()} {number} has {count} mapping '
                                       f'entries: CiA 301 allows {MAX_ENTRIES}')
            mapped = self._numbers(node_id, [(mapping_index + number - 1, sub)
                                             for sub in range(1, count + 1)]) if count \
                else []
            found[number] = parse_mapping(node_id, kind, number, cob_entry,
                                          transmission_type & 0xFF, event_timer, mapped,
                                          dictionary)
        return found

    def _numbers(self, node_id: int, objects: Sequence[Tuple[int, int]],
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
                raise ParametersFailed(f'0x{index:04X}:{sub}: {result.message}')
        return numbers

