"""What the boot of one device checks and writes, worked out once at start from its files.

A :class:`DevicePlan` holds the identity a device must show (0x1000, 0x1018) and the writes
that configure it, in the order of CiA 302-2: the DCF's ``ParameterValue`` entries, the bus
description's ``sdo`` list (each value typed by the DCF/EDS), the PDO parameters (each PDO
disabled, mapped and enabled again as CiA 301 requires), then the heartbeat producer and
consumer. A value that does not fit its object stops the gateway at start, naming the node
and the key; a boot never meets it.
"""

from dataclasses import dataclass, field
import os
import struct
from typing import Callable, Dict, List, Optional, Sequence, Tuple

from canopen.objectdictionary import datatypes, ObjectDictionary, ODArray, ODRecord, ODVariable

from ..nmt import consumer_entry
from ..pdo.mapping import (
    COB_INVALID,
    MAX_PDOS,
    RPDO_COMMUNICATION,
    RPDO_MAPPING,
    TPDO_COMMUNICATION,
    TPDO_MAPPING,
)
from ..values import data_type_name, parse_integer

DEVICE_TYPE = 0x1000
IDENTITY = 0x1018
STORE = 0x1010
RESTORE = 0x1011
CONSUMER_HEARTBEAT = 0x1016
PRODUCER_HEARTBEAT = 0x1017
CONFIGURATION_DATE = 0x1020
PROGRAM_OBJECTS = range(0x1F50, 0x1F60)  # program download (CiA 302-3): never a DCF write
PDO_OBJECTS = range(0x1400, 0x1C00)      # written by the PDO step, in CiA 301's order
SAVE = int.from_bytes(b'save', 'little')  # 0x1010 and 0x1011 take these words as their value
LOAD = int.from_bytes(b'load', 'little')

# 0x1018 sub-index: the CiA 302-2 error status letter of a device that differs there.
IDENTITY_LETTERS = {1: ('D', 'vendor_id'), 2: ('M', 'product_code'),
                    3: ('N', 'revision_number'), 4: ('O', 'serial_number')}

_INTEGER_TYPES = frozenset(datatypes.INTEGER_TYPES) | {datatypes.BOOLEAN}
_FLOAT_TYPES = frozenset((datatypes.REAL32, datatypes.REAL64))
_STRING_TYPES = frozenset((datatypes.VISIBLE_STRING, datatypes.UNICODE_STRING))
_BYTE_TYPES = frozenset((datatypes.DOMAIN, datatypes.OCTET_STRING))
# The predefined connection set (CiA 301): PDO n of 1..4 of a node.
_PREDEFINED = {'tpdo': 0x180, 'rpdo': 0x200}


DEFAULT_BOOT_TIMEOUT = 2.0  # s
# A heartbeat is awaited for this many producer periods (Lely's default heartbeat multiplier),
# and a device that watches the gateway's heartbeat waits as many of its periods.
HEARTBEAT_PERIODS = 3


@dataclass(frozen=True)
class BootSettings:
    """The boots the gateway runs, built by :func:`boot_settings`."""

    plans: Tuple['DevicePlan', ...] = ()
    boot_timeout: float = DEFAULT_BOOT_TIMEOUT  # s: to answer (0x1000), to boot after a reset
    start_nodes: bool = True   # False: no device is started (the bus description's master)


class PlanError(ValueError):
    """A device's bus description or file asks for what cannot be written."""


@dataclass(frozen=True)
class Write:
    """One SDO write of a boot; ``source`` says where it comes from (in a failure's text)."""

    index: int
    subindex: int
    data: bytes
    source: str


@dataclass(frozen=True)
class DevicePlan:
    """Everything the boot of one device does, decided at start."""

    node_id: int
    name: str
    device_type: int = 0                  # 0x1000 expected; 0 = not checked
    identity: Tuple[Tuple[int, int], ...] = ()  # (0x1018 sub-index, value expected)
    configuration_date: Optional[Tuple[int, int]] = None  # 0x1020:1 and :2 of the DCF
    writes: Tuple[Write, ...] = ()
    restore: int = 0                      # 0x1011 sub-index to "load"; 0 = none
    store: bool = False                   # 0x1010:1 "save" after a verified configuration
    reset_communication: bool = False     # before a boot the device did not start itself
    heartbeat_check: bool = True          # wait for its heartbeat before starting it (K)
    drive: bool = False                   # safe targets before the start
    start: bool = True
    mandatory: bool = False
    boot: bool = True                     # False: IGNORED, left alone
    pdos: bool = False                    # its PDOs are served: read again after the writes
    software_version: Optional[int] = None  # 0x1F56:1 it must show (software_version)
    software_file: str = ''               # downloaded when it differs (program_download.at_boot)
    checked: Dict[Tuple[int, int], bytes] = field(default_factory=dict)  # read back after

    @property
    def heartbeat_producer(self) -> Optional[int]:
        """Return the heartbeat producer time (ms) the boot writes to 0x1017, None for none."""
        written = [write.data for write in self.writes
                   if (write.index, write.subindex) == (PRODUCER_HEARTBEAT, 0)]
        return int.from_bytes(written[-1][:2], 'little') if written else None

    def loss_time(self, default: float) -> Optional[float]:
        """Return how long (s) the device may be silent before it is lost, None: not watched.

        ``HEARTBEAT_PERIODS`` of the producer time the boot gives it, never less than
        ``default`` (``heartbeat.timeout``, also for a device given none); a producer time 0
        means no heartbeat to watch.
        """
        producer = self.heartbeat_producer
        if producer is None:
            return default
        return max(default, HEARTBEAT_PERIODS * producer / 1000) if producer else None

    @property
    def label(self) -> str:
        """Return how messages name the device: its id and, when it differs, its name."""
        plain = f'node_{self.node_id}'
        return plain if self.name in ('', plain) else f'{self.node_id} ({self.name})'


def _variable(dictionary: Optional[ObjectDictionary], index: int,
              subindex: int) -> Optional[ODVariable]:
    if dictionary is None or index not in dictionary:
        return None
    entry = dictionary[index]
    if isinstance(entry, ODVariable):
        return entry if subindex == 0 else None
    return entry.get(subindex) if subindex in entry.subindices else None


def _variables(dictionary: ObjectDictionary) -> List[ODVariable]:
    found = []
    for entry in dictionary.values():
        if isinstance(entry, (ODRecord, ODArray)):
            found += [entry[sub] for sub in sorted(entry.subindices) if sub != 0]
        else:
            found.append(entry)
    return found


def typed_value(variable: ODVariable, value, folder: str, where: str) -> bytes:
    """Return ``value`` (as a bus description gives it) encoded as ``variable``'s type.

    Integers take YAML numbers and texts such as ``"0x2A"``; REAL32/64 numbers; strings
    text; DOMAIN and OCTET_STRING hex digits, or ``file:PATH`` (relative to ``folder``) for
    the bytes of a file. ``where`` names the entry in a message.
    """
    kind = variable.data_type
    try:
        if kind in _INTEGER_TYPES:
            if isinstance(value, str):
                value = parse_integer(value)
            elif isinstance(value, float) and value.is_integer():
                value = int(value)
            if isinstance(value, bool) or not isinstance(value, int):
                raise PlanError(f'{where}: {value!r} is no integer, as '
                                f'{data_type_name(kind)} needs')
            return variable.encode_raw(value)
        if kind in _FLOAT_TYPES:
            number = float(value)
            return struct.pack('<f' if kind == datatypes.REAL32 else '<d', number)
        if kind in _STRING_TYPES:
            if not isinstance(value, str):
                raise PlanError(f'{where}: {value!r} is no text, as {data_type_name(kind)} '
                                f'needs (quote it)')
            return variable.encode_raw(value)
        if kind in _BYTE_TYPES:
            return _bytes_of(value, folder, where)
    except (ValueError, struct.error, OverflowError, UnicodeError) as error:
        if isinstance(error, PlanError):
            raise
        raise PlanError(f'{where}: {value!r} does not fit {data_type_name(kind)} '
                        f'({error})') from None
    raise PlanError(f'{where}: its data type {data_type_name(kind)} cannot be written')


def _bytes_of(value, folder: str, where: str) -> bytes:
    if not isinstance(value, str):
        raise PlanError(f'{where}: {value!r}: give hex digits or file:PATH for a DOMAIN')
    if value.startswith('file:'):
        path = os.path.join(folder, os.path.expanduser(value[5:]))
        try:
            with open(path, 'rb') as file:
                return file.read()
        except OSError as error:
            raise PlanError(f'{where}: {path} cannot be read ({error.strerror})') from None
    digits = value.replace(' ', '')
    digits = digits[2:] if digits[:2].lower() == '0x' else digits
    try:
        return bytes.fromhex(digits)
    except ValueError:
        raise PlanError(f'{where}: {value!r} is no hex digits (nor file:PATH)') from None


def _file_value(variable: Optional[ODVariable], default: bool):
    """Return the variable's ParameterValue (with ``default``, else its DefaultValue)."""
    if variable is None:
        return None
    if variable.value is not None:
        return variable.value
    return variable.default if default else None


def dcf_writes(dictionary: ObjectDictionary) -> List[Write]:
    """Return the writes of a DCF's ParameterValue entries, except those of other steps.

    Left to their own step: the PDO parameters, store and restore (commands), 0x1020 (written
    once the configuration is verified) and program download's objects.
    """
    writes = []
    for variable in _variables(dictionary):
        index = variable.index
        if (variable.value is None or not variable.writable or index in PDO_OBJECTS
                or index in (STORE, RESTORE, CONFIGURATION_DATE) or index in PROGRAM_OBJECTS):
            continue
        try:
            data = variable.encode_raw(variable.value)
        except (ValueError, TypeError) as error:
            raise PlanError(f'0x{index:04X}:{variable.subindex} ({variable.name}): its '
                            f'ParameterValue {variable.value!r} cannot be encoded '
                            f'({error})') from None
        writes.append(Write(index, variable.subindex, data, 'DCF'))
    return writes


@dataclass
class _Pdo:
    """One PDO's parameters to write; None: not written."""

    kind: str
    number: int
    cob_entry: Optional[int] = None  # with bit 31 when disabled
    transmission: Optional[int] = None
    inhibit_time: Optional[int] = None
    event_timer: Optional[int] = None
    mapping: Optional[List[int]] = None  # the mapping entries (index << 16 | sub << 8 | bits)


def _indices(kind: str, number: int) -> Tuple[int, int]:
    if kind == 'tpdo':
        return TPDO_COMMUNICATION + number - 1, TPDO_MAPPING + number - 1
    return RPDO_COMMUNICATION + number - 1, RPDO_MAPPING + number - 1


def file_pdos(dictionary: ObjectDictionary, defaults: bool) -> Dict[Tuple[str, int], _Pdo]:
    """Return the PDOs a file configures: with ParameterValues (``defaults``: every one).

    ``defaults`` is ``pdo.configure``'s reading: the file's values, else its defaults.
    """
    found = {}
    for kind in ('rpdo', 'tpdo'):
        for number in range(1, MAX_PDOS + 1):
            com_index, map_index = _indices(kind, number)
            com, mapped = dictionary.get(com_index), dictionary.get(map_index)
            if com is None or mapped is None:
                continue
            variables = [*_variables_of(com), *_variables_of(mapped)]
            if not defaults and all(variable.value is None for variable in variables):
                continue

            def number_of(variable: Optional[ODVariable]) -> Optional[int]:
                value = _file_value(variable, defaults)
                return None if value is None else int(value)

            pdo = _Pdo(kind, number, number_of(_variable(dictionary, com_index, 1)),
                       number_of(_variable(dictionary, com_index, 2)),
                       number_of(_variable(dictionary, com_index, 3)),
                       number_of(_variable(dictionary, com_index, 5)))
            count = number_of(_variable(dictionary, map_index, 0))
            if count is not None:
                pdo.mapping = [number_of(_variable(dictionary, map_index, sub)) or 0
                               for sub in range(1, count + 1)
                               if _variable(dictionary, map_index, sub) is not None]
            if pdo.mapping is not None and pdo.cob_entry is None:
                # CiA 301: a mapping is changed only while the PDO is disabled, and that
                # takes its COB-ID: the file's default when it gives no value of its own.
                default = _file_value(_variable(dictionary, com_index, 1), True)
                pdo.cob_entry = None if default is None else int(default)
            found[kind, number] = pdo
    return found


def _variables_of(entry) -> List[ODVariable]:
    if isinstance(entry, (ODRecord, ODArray)):
        return [entry[sub] for sub in entry.subindices]
    return [entry]


def described_pdo(setting, kind: str, node_id: int, dictionary: Optional[ObjectDictionary],
                  where: str, pdo: Optional[_Pdo]) -> _Pdo:
    """Return a PDO of the file (``pdo``, or a new one) with the bus description's keys."""
    pdo = pdo or _Pdo(kind, setting.number)
    if setting.cob_id is not None:
        cob = setting.cob_id
    elif pdo.cob_entry is not None:
        cob = pdo.cob_entry & ~COB_INVALID
    elif setting.number <= 4:
        cob = _PREDEFINED[kind] + 0x100 * (setting.number - 1) + node_id
    elif setting.enabled:
        raise PlanError(f'{where}.cob_id: {kind.upper()} {setting.number} is not in the '
                        f'predefined connection set (1..4): give its cob_id')
    else:
        cob = 0
    pdo.cob_entry = cob if setting.enabled else cob | COB_INVALID
    for key in ('transmission', 'inhibit_time', 'event_timer'):
        if getattr(setting, key) is not None:
            setattr(pdo, key, getattr(setting, key))
    if setting.mapping:
        pdo.mapping = []
        for position, (index, subindex) in enumerate(setting.mapping, 1):
            variable = _variable(dictionary, index, subindex)
            if variable is None or variable.data_type not in ODVariable.STRUCT_TYPES:
                raise PlanError(f'{where}.mapping[{position}]: 0x{index:04X}:{subindex} is '
                                f'not an object of fixed size in the DCF/EDS, so its size '
                                f'in the PDO is unknown')
            bits = (1 if variable.data_type == datatypes.BOOLEAN
                    else 8 * ODVariable.STRUCT_TYPES[variable.data_type].size)
            pdo.mapping.append(index << 16 | subindex << 8 | bits)
        if sum(entry & 0xFF for entry in pdo.mapping) > 64:
            raise PlanError(f'{where}.mapping: maps more than 64 bits (8 bytes)')
    return pdo


def pdo_writes(pdo: _Pdo) -> List[Write]:
    """Return the writes that put one PDO onto a device, in the order CiA 301 requires.

    Disabled first (bit 31 of its COB-ID), mapping count 0, the entries, the count, then
    enabled: a device refuses a mapping changed while the PDO is valid.
    """
    com_index, map_index = _indices(pdo.kind, pdo.number)
    source = f'{pdo.kind.upper()} {pdo.number}'

    def write(index: int, subindex: int, value: int, size: int) -> Write:
        return Write(index, subindex, (value & ((1 << 8 * size) - 1)).to_bytes(size, 'little'),
                     source)

    writes = []
    if pdo.cob_entry is not None:
        writes.append(write(com_index, 1, pdo.cob_entry | COB_INVALID, 4))
    for subindex, value, size in ((2, pdo.transmission, 1), (3, pdo.inhibit_time, 2),
                                  (5, pdo.event_timer, 2)):
        if value is not None:
            writes.append(write(com_index, subindex, value, size))
    if pdo.mapping is not None:
        writes.append(write(map_index, 0, 0, 1))
        writes += [write(map_index, sub, entry, 4) for sub, entry in enumerate(pdo.mapping, 1)]
        writes.append(write(map_index, 0, len(pdo.mapping), 1))
    if pdo.cob_entry is not None and not pdo.cob_entry & COB_INVALID:
        writes.append(write(com_index, 1, pdo.cob_entry, 4))
    return writes


def checked_values(writes: Sequence[Write]) -> Dict[Tuple[int, int], bytes]:
    """Return what each written object must read back: the last value written to it."""
    return {(write.index, write.subindex): write.data for write in writes}


def heartbeat_writes(producer_ms: Optional[int], consumer: bool, master_id: int,
                     consumer_ms: int, where: str) -> List[Write]:
    """Return the writes of the heartbeat producer (0x1017) and consumer (0x1016:1) times.

    The consumer watches the gateway's heartbeat (node ``master_id``) for ``consumer_ms``.
    """
    writes = []
    if producer_ms is not None:
        if not 0 <= producer_ms <= 0xFFFF:
            raise PlanError(f'{where}.heartbeat_producer: {producer_ms} ms is out of range: '
                            f'0..65535')
        writes.append(Write(PRODUCER_HEARTBEAT, 0, producer_ms.to_bytes(2, 'little'),
                            'heartbeat_producer'))
    if consumer:
        if not master_id:
            raise PlanError(f'{where}.heartbeat_consumer: the gateway has no heartbeat to '
                            f'watch: give master.node_id or the parameter heartbeat.node_id')
        entry = consumer_entry(master_id, consumer_ms)
        writes.append(Write(CONSUMER_HEARTBEAT, 1, entry.to_bytes(4, 'little'),
                            'heartbeat_consumer'))
    return writes


def expected_identity(description, dictionary: Optional[ObjectDictionary]
                      ) -> Tuple[int, Tuple[Tuple[int, int], ...]]:
    """Return the device type and the 0x1018 entries (sub-index, value) a device must show.

    A value of the bus description wins; without it the DCF's: its ParameterValue, or for
    the device type, vendor and product code its DefaultValue (an EDS describes a product,
    not one device: its revision and serial number defaults are rarely the device's). 0: not
    checked.
    """
    device_type = _file_value(_variable(dictionary, DEVICE_TYPE, 0), True) or 0
    identity = []
    for subindex, (_, key) in IDENTITY_LETTERS.items():
        given = getattr(description, key)
        if given is None:
            given = _file_value(_variable(dictionary, IDENTITY, subindex), subindex <= 2)
        if given:
            identity.append((subindex, int(given)))
    return int(device_type), tuple(identity)


def configuration_date(dictionary: Optional[ObjectDictionary]) -> Optional[Tuple[int, int]]:
    """Return the DCF's 0x1020 (configuration date, time) when it gives both, else None."""
    date = _file_value(_variable(dictionary, CONFIGURATION_DATE, 1), False)
    time_of_day = _file_value(_variable(dictionary, CONFIGURATION_DATE, 2), False)
    if date is None or time_of_day is None:
        return None
    return int(date), int(time_of_day)


def device_plan(description, dictionary: Optional[ObjectDictionary], folder: str,
                master_id: int, consumer_ms: int, drive: bool, pdos: bool,
                watches: bool = False) -> DevicePlan:
    """Return the boot of a device of a bus description; raise :class:`PlanError`.

    ``folder`` is the bus description's (``file:`` values are read from there),
    ``master_id`` the gateway's heartbeat node id, ``consumer_ms`` the time a device that
    watches it (``heartbeat_consumer``) waits, ``drive`` whether it is run as a drive,
    ``pdos`` whether its PDOs are served, ``watches`` whether it watches the gateway's
    heartbeat though the file does not say so (a drive, unless the drives run on when the
    gateway dies).
    """
    where = f'nodes.{description.name}'
    writes = dcf_writes(dictionary) if dictionary is not None else []
    for position, entry in enumerate(description.sdo, 1):
        place = f'{where}.sdo[{position}] (0x{entry.index:04X}:{entry.subindex})'
        variable = _variable(dictionary, entry.index, entry.subindex)
        if variable is None:
            raise PlanError(f'{place}: the object is not in the DCF/EDS '
                            f'({description.dcf or "none given"}), so its type is unknown')
        writes.append(Write(entry.index, entry.subindex,
                            typed_value(variable, entry.value, folder, place), 'sdo'))
    pdos_of_file = file_pdos(dictionary, False) if dictionary is not None else {}
    for kind, settings in (('rpdo', description.rpdo), ('tpdo', description.tpdo)):
        for setting in settings:
            key = (kind, setting.number)
            pdos_of_file[key] = described_pdo(setting, kind, description.node_id, dictionary,
                                              f'{where}.{kind}.{setting.number}',
                                              pdos_of_file.get(key))
    for key in sorted(pdos_of_file):
        writes += pdo_writes(pdos_of_file[key])
    writes += heartbeat_writes(description.heartbeat_producer,
                               description.heartbeat_consumer or watches, master_id,
                               consumer_ms, where)
    device_type, identity = expected_identity(description, dictionary)
    restore = int(description.restore_configuration)
    return DevicePlan(
        node_id=description.node_id, name=description.name, device_type=device_type,
        identity=identity, configuration_date=configuration_date(dictionary),
        writes=tuple(writes), restore=restore, store=description.store_configuration,
        reset_communication=description.reset_communication, drive=drive,
        start=description.start, mandatory=description.mandatory, boot=description.boot,
        pdos=pdos, checked=checked_values(writes),
        software_version=description.software_version,
        software_file=_software_file(description.software_file, where))


def _software_file(path: str, where: str) -> str:
    """Return ``path`` once it is known to be a readable file ('' stays '')."""
    if path and not os.access(path, os.R_OK) or path and not os.path.isfile(path):
        raise PlanError(f'{where}.software_file: {path} is not a readable file')
    return path


def pdo_configure_plan(node_id: int, dictionary: ObjectDictionary, master_id: int = 0,
                       consumer_ms: int = 0) -> DevicePlan:
    """Return the boot ``pdo.configure`` asks for: the file's PDO parameters.

    No identity checked, no reset, no start: what the parameter always did, as a boot. With
    ``consumer_ms`` (a drive that watches the gateway) its heartbeat consumer is written too.
    """
    writes = []
    for key in sorted(pdos := file_pdos(dictionary, True)):
        writes += pdo_writes(pdos[key])
    writes += heartbeat_writes(None, bool(consumer_ms), master_id, consumer_ms,
                               f'node_{node_id}')
    return DevicePlan(node_id=node_id, name=f'node_{node_id}', writes=tuple(writes),
                      heartbeat_check=False, start=False, pdos=True,
                      checked=checked_values(writes))


def boot_settings(description, pdo_configure: Sequence[int],
                  dictionaries: Dict[int, ObjectDictionary], master_id: int,
                  consumer_ms: Callable[[int], int], drives: Sequence[int],
                  pdo_nodes: Sequence[int], watching: Sequence[int] = ()) -> BootSettings:
    """Return the boots of the bus description's devices and of ``pdo.configure``'s.

    ``pdo_configure``: the devices whose file's PDO parameters are written at each boot
    (those the bus description names boot by it instead); ``consumer_ms(node_id)``: the
    heartbeat consumer time of a device that watches the gateway; ``watching``: the drives
    that watch it (``drives.consumer_time``), whose consumer a boot writes before their
    start. Raises PlanError naming the node and the key of a value that cannot be written.
    """
    plans = []
    described = set()
    if description is not None:
        folder = os.path.dirname(os.path.abspath(description.path))
        for device in description.devices:
            node_id = device.node_id
            described.add(node_id)
            try:
                plans.append(device_plan(device, dictionaries.get(node_id), folder, master_id,
                                         consumer_ms(node_id), node_id in drives,
                                         node_id in pdo_nodes, node_id in watching))
            except PlanError as error:
                raise PlanError(f'bus description {description.path}: {error}') from None
    plans += [pdo_configure_plan(node_id, dictionaries[node_id], master_id,
                                 consumer_ms(node_id) if node_id in watching else 0)
              for node_id in pdo_configure
              if node_id not in described and node_id in dictionaries]
    master = description.master if description is not None else None
    return BootSettings(
        plans=tuple(sorted(plans, key=lambda plan: plan.node_id)),
        boot_timeout=(master.boot_timeout / 1000 if master and master.boot_timeout
                      else DEFAULT_BOOT_TIMEOUT),
        start_nodes=master.start_nodes if master else True)
