"""The dictionary of a simulated durand device: the objects of ``config/simulated_device.eds``.

Built into a durand node in place of the few objects durand puts there itself; a boot restores
the defaults from it.
"""

from typing import Container, Dict, Sequence

from durand.datatypes import DatatypeEnum as DT
from durand.object_dictionary import ObjectDictionary, Record, Variable
from durand.services.sdo.server import SDODomainAbort

SLOW_INDEX = 0x2200
DOMAIN_INDEX = 0x2020
DOMAIN_MAX_SIZE = 65536
DOMAIN_DEFAULT = bytes(range(200))
HEARTBEAT_INDEX = 0x1017
HEARTBEAT_DEFAULT = 200  # ms, as config/simulated_device.eds
IDENTITY_INDEX = 0x1018
IDENTITY = (0x0, 0x51, 0x10000, 0x0)  # 0x1018:1..4 as config/simulated_device.eds
STORE_INDEX = 0x1010
RESTORE_INDEX = 0x1011
CONFIGURATION_DATE_INDEX = 0x1020
SAVES_ON_COMMAND = 1  # what 0x1010:1 and 0x1011:1 read (CiA 301: saves/restores on command)

ABORT_LENGTH_TOO_HIGH = 0x06070012

# (index, subindex, datatype, access, default, name), as config/simulated_device.eds.
OBJECTS = (
    (0x1000, 0, DT.UNSIGNED32, 'ro', 0x00020192, 'Device type'),
    (0x1001, 0, DT.UNSIGNED8, 'ro', 0, 'Error register'),
    (0x1008, 0, DT.VISIBLE_STRING, 'const', b'cbcan simulated device',
     'Manufacturer device name'),
    (0x100A, 0, DT.VISIBLE_STRING, 'const', b'1.0', 'Manufacturer software version'),
    (STORE_INDEX, 1, DT.UNSIGNED32, 'rw', SAVES_ON_COMMAND, 'Save all parameters'),
    (RESTORE_INDEX, 1, DT.UNSIGNED32, 'rw', SAVES_ON_COMMAND,
     'Restore all default parameters'),
    (HEARTBEAT_INDEX, 0, DT.UNSIGNED16, 'rw', HEARTBEAT_DEFAULT, 'Producer heartbeat time'),
    (0x1018, 1, DT.UNSIGNED32, 'ro', 0x0, 'Vendor-ID'),
    (0x1018, 2, DT.UNSIGNED32, 'ro', 0x51, 'Product code'),
    (0x1018, 3, DT.UNSIGNED32, 'ro', 0x10000, 'Revision number'),
    (0x1018, 4, DT.UNSIGNED32, 'ro', 0x0, 'Serial number'),
    (CONFIGURATION_DATE_INDEX, 1, DT.UNSIGNED32, 'rw', 0, 'Configuration date'),
    (CONFIGURATION_DATE_INDEX, 2, DT.UNSIGNED32, 'rw', 0, 'Configuration time'),
    (0x2000, 0, DT.UNSIGNED8, 'rw', 0x12, 'Demo UNSIGNED8'),
    (0x2001, 0, DT.UNSIGNED16, 'rw', 0x1234, 'Demo UNSIGNED16'),
    (0x2002, 0, DT.UNSIGNED32, 'rw', 0x12345678, 'Demo UNSIGNED32'),
    (0x2003, 0, DT.INTEGER32, 'rw', -2, 'Demo INTEGER32'),
    (0x2010, 0, DT.UNSIGNED32, 'ro', 0xCAFEBABE, 'Demo read-only UNSIGNED32'),
    (0x2011, 0, DT.UNSIGNED32, 'wo', 0, 'Demo write-only UNSIGNED32'),
    (DOMAIN_INDEX, 0, DT.DOMAIN, 'rw', DOMAIN_DEFAULT, 'Demo DOMAIN (large data)'),
    (0x2021, 0, DT.VISIBLE_STRING, 'rw', b'hello from the bus', 'Demo VISIBLE_STRING'),
    (SLOW_INDEX, 0, DT.UNSIGNED32, 'ro', 0x51057, 'Slow value (answers after a delay)'),
)

RECORD_NAMES = {0x1018: 'Identity object', STORE_INDEX: 'Store parameters',
                RESTORE_INDEX: 'Restore default parameters',
                CONFIGURATION_DATE_INDEX: 'Verify configuration'}


def add_objects(od: ObjectDictionary, identity: Sequence[int]) -> None:
    """Put the objects into ``od`` (durand's own 0x1000/0x1008/0x1017/0x1018 are replaced).

    ``identity``: 0x1018:1..4 (vendor, product, revision, serial).
    """
    records: Dict[int, Record] = {}
    for index, subindex, datatype, access, default, name in OBJECTS:
        if index == IDENTITY_INDEX:
            default = identity[subindex - 1]
        variable = Variable(datatype, access, default, name=name)
        if subindex:
            records.setdefault(index, Record(name=RECORD_NAMES[index]))[subindex] = variable
        else:
            od[index] = variable
    for index, record in records.items():
        od[index] = record
    od.validate_callbacks[(DOMAIN_INDEX, 0)].add(_check_domain_size)


def restore_defaults(od: ObjectDictionary, clear: range, keep: Container[int]) -> None:
    """Return the objects in ``clear`` to their defaults, all but those of ``keep``."""
    for index, obj in od:
        if index not in clear or index in keep:
            continue
        for subindex, variable in ([(0, obj)] if isinstance(obj, Variable) else list(obj)):
            if od.has_value(index, subindex):
                od.write(index, subindex, _default_of(variable))


def _check_domain_size(value: bytes) -> None:
    if len(value) > DOMAIN_MAX_SIZE:
        raise SDODomainAbort(ABORT_LENGTH_TOO_HIGH, (DOMAIN_INDEX, 0))


def _default_of(variable: Variable):
    if variable.value is not None:
        return variable.value
    return b'' if variable.size is None else 0
