"""A bus description file (ros2_canopen's ``bus.yml``) read into frozen dataclasses.

The format is Lely's ``dcfgen`` YAML as ros2_canopen uses it, so a file written for
ros2_canopen describes the same bus here: ``options`` (``dcf_path``), ``master``,
``defaults``, and the devices either under ``nodes:`` (ros2_canopen's ``cogen`` form) or at
the top level beside ``master`` (dcfgen's own form), not both. Every key is checked here for
type and range; what a value means for a device (its object's type, whether it can be
mapped) is checked against the device's EDS/DCF by the caller.

Where ros2_canopen or dcfgen leave a choice, or differ from each other:

- ``defaults`` is merged into every node key by key, and a node's own key wins: a node's
  ``sdo:`` (or ``tpdo:``, ``rpdo:``) list replaces the defaults' one as a whole.
  ros2_canopen's cogen lets the defaults win instead, and loses ``sdo`` given there (its
  issue #257).
- ``@BUS_CONFIG_PATH@`` in a path is the file's folder: ros2_canopen's CMake replaces it by
  the installed copy of that folder. A relative ``options.dcf_path`` and ``software_file``
  are relative to the file's folder; a node's ``dcf`` is relative to its ``dcf_path`` (the
  node's own, else ``options.dcf_path``, else the file's folder), where ros2_canopen's
  drivers open it. The path is made absolute; whether the file exists is the caller's to
  check.
- A key this gateway does not implement is listed in ``BusDescription.unsupported`` by its
  path (``nodes.left_wheel.polling``, ``master.baudrate``; list entries counted from 1, as
  ``nodes.x.sdo[2].foo``), for one warning; none is dropped silently. The keys naming
  ros2_canopen's own classes (``driver`` and ``package`` of the master, ``package`` of a
  node) are taken without a word: the gateway is the master and its own driver.
- Numbers are YAML integers; node ids, identity values, indices, sub-indices, COB-IDs and
  PDO numbers may also be quoted (``"0x6060"``, ``"1000"``), as ros2_canopen's files write
  them. An ``sdo`` value keeps its YAML type (a quoted hex value stays text). A yes/no key
  takes true/false or 1/0. ``master.boot_time`` (dcfgen) and ``master.boot_timeout``
  (ros2_canopen) are one setting here: give one.
- A key given twice in one mapping is an error (PyYAML would keep the last). Top-level keys
  starting with ``.`` hold YAML anchors and are skipped, as dcfgen skips them. ``nodes`` is
  a mapping of names, as cogen reads it (ros2_canopen's configuration page draws a list).
"""

from dataclasses import dataclass
import os
import re
from typing import Dict, FrozenSet, List, Optional, Tuple

import yaml

from ..pdo.mapping import MAX_ENTRIES, MAX_PDOS
from ..protocol import MAX_NODE_ID
from ..text import quoted
from ..values import parse_integer

BUS_CONFIG_PATH = '@BUS_CONFIG_PATH@'
PATH_LIMIT = 120  # characters of a path shown in a message
UNSIGNED16 = 0xFFFF
UNSIGNED32 = 0xFFFFFFFF
MAX_RESTORE_SUBINDEX = 0x7F  # 0x1011: 1 all, 2 communication, 3 application, 4..0x7F vendor
MAX_CAN_ID = 0x7FF  # a PDO's cob_id: an 11-bit CAN-ID (the gateway serves no 29-bit PDO)
# The CAN-IDs CiA 301 restricts: no PDO may use them (a TPDO on 0x000 would be NMT commands).
RESTRICTED_CAN_IDS = ((0x000, 0x000, 'NMT'), (0x001, 0x07F, 'reserved'),
                      (0x101, 0x180, 'reserved'), (0x581, 0x5FF, 'SDO answers'),
                      (0x601, 0x67F, 'SDO requests'), (0x6E0, 0x6FF, 'reserved'),
                      (0x701, 0x77F, 'heartbeats and boot-ups'), (0x780, 0x7FF, 'reserved'))

# The keys implemented at each level; any other goes to BusDescription.unsupported.
TOP_LEVEL_KEYS = frozenset({'options', 'master', 'defaults', 'nodes'})
OPTIONS_KEYS = frozenset({'dcf_path'})
MASTER_KEYS = frozenset({'node_id', 'sync_period', 'heartbeat_producer', 'heartbeat_consumer',
                         'boot_time', 'boot_timeout', 'start_nodes'})
IDENTITY_KEYS = ('vendor_id', 'product_code', 'revision_number', 'serial_number')
SCALE_KEYS = ('scale_pos_to_dev', 'scale_pos_from_dev', 'scale_vel_to_dev',
              'scale_vel_from_dev', 'scale_eff_from_dev', 'offset_pos_to_dev',
              'offset_pos_from_dev')
NODE_FLAGS = ('heartbeat_consumer', 'boot', 'mandatory', 'reset_communication',
              'store_configuration', 'start')  # the yes/no keys
NODE_KEYS = frozenset({'node_id', 'dcf', 'dcf_path', 'driver', 'sdo', 'tpdo', 'rpdo',
                       'heartbeat_producer', 'restore_configuration', 'software_file',
                       'software_version', *IDENTITY_KEYS, *SCALE_KEYS, *NODE_FLAGS})
PDO_KEYS = frozenset({'enabled', 'cob_id', 'transmission', 'transmission_type',
                      'event_timer', 'inhibit_time', 'mapping'})
SDO_KEYS = frozenset({'index', 'sub_index', 'subindex', 'value'})
MAPPED_KEYS = frozenset({'index', 'sub_index', 'subindex'})
# Keys naming ros2_canopen's classes: no configuration meaning here.
MASTER_IGNORED = frozenset({'driver', 'package'})
NODE_IGNORED = frozenset({'package'})

_CMAKE_VARIABLE = re.compile(r'@[A-Za-z_][A-Za-z0-9_]*@')


class DescriptionError(ValueError):
    """A bus description that cannot be used; the message names the file and the key."""


@dataclass(frozen=True)
class SdoWrite:
    """One entry of a node's ``sdo:`` list, as the file gives it."""

    index: int
    subindex: int
    value: object  # int, float or str as YAML gave it (a bool as 0/1); the DCF types it later


@dataclass(frozen=True)
class PdoSetting:
    """One entry of a node's ``tpdo:`` or ``rpdo:`` (keyed by the PDO's number 1..512)."""

    number: int
    enabled: bool = True
    cob_id: Optional[int] = None  # None: 'auto' or not given (the caller picks); else as given
    transmission: Optional[int] = None  # 0..255 (``transmission`` or ``transmission_type``)
    event_timer: Optional[int] = None  # ms
    inhibit_time: Optional[int] = None  # 100 µs units, as CiA 301
    mapping: Tuple[Tuple[int, int], ...] = ()  # (index, subindex) in order; sizes: from the DCF


@dataclass(frozen=True)
class DeviceDescription:
    """One node of the file, the defaults merged in."""

    name: str  # the node's key in the file
    node_id: int  # 1..127
    dcf: str  # absolute path of its EDS/DCF; '' none given
    driver: str  # 'drive' (a ros2_canopen ...Cia402Driver), 'proxy' (...ProxyDriver), '' other
    driver_name: str  # the file's ``driver`` as written
    # The identity (0x1018) the device must show: None not given (the DCF's), 0 not checked.
    vendor_id: Optional[int] = None
    product_code: Optional[int] = None
    revision_number: Optional[int] = None
    serial_number: Optional[int] = None
    sdo: Tuple[SdoWrite, ...] = ()
    tpdo: Tuple[PdoSetting, ...] = ()  # by number
    rpdo: Tuple[PdoSetting, ...] = ()
    heartbeat_producer: Optional[int] = None  # ms, for 0x1017; None not given
    heartbeat_consumer: bool = False  # the device watches the gateway's heartbeat (0x1016)
    boot: bool = True
    mandatory: bool = False
    reset_communication: bool = True
    restore_configuration: int = 0  # the 0x1011 sub-index written before configuring; 0 none
    store_configuration: bool = False  # ours: 0x1010:1 "save" after a verified configuration
    start: bool = True  # ours (dcfgen has only master.start_nodes): NMT start after its boot
    software_file: str = ''  # absolute path of the program image a boot may download; ''
    software_version: Optional[int] = None  # 0x1F56:1 the device must show; None not given
    # The SCALE_KEYS given, in that order, as pairs so the description stays hashable (frozen
    # all through): dict(device.scales) to look one up.
    scales: Tuple[Tuple[str, float], ...] = ()


@dataclass(frozen=True)
class MasterDescription:
    """The ``master:`` section: the gateway itself."""

    node_id: int = 0  # the gateway's node id (its heartbeat); 0 not given
    sync_period: int = 0  # µs; 0 none
    heartbeat_producer: int = 0  # ms
    boot_timeout: int = 0  # ms, ``boot_timeout`` (ros2_canopen) or ``boot_time`` (Lely)
    start_nodes: bool = True
    heartbeat_consumer: bool = True  # Lely's default; what it means is the caller's choice
    given: FrozenSet[str] = frozenset()  # the fields above the file gave, by field name


@dataclass(frozen=True)
class BusDescription:
    """A whole bus description file."""

    path: str  # as given to load() or parse()
    master: MasterDescription
    devices: Tuple[DeviceDescription, ...]  # by node id
    unsupported: Tuple[str, ...] = ()  # the paths of the keys given but not implemented


def load(path: str) -> BusDescription:
    """Read the bus description file at ``path``; raise :class:`DescriptionError`."""
    try:
        with open(path, encoding='utf-8') as file:
            text = file.read()
    except OSError as error:
        raise DescriptionError(f'{quoted(path, PATH_LIMIT)} cannot be read: '
                               f'{error.strerror}') from None
    except UnicodeDecodeError:
        raise DescriptionError(f'{quoted(path, PATH_LIMIT)} is not UTF-8 text') from None
    return parse(text, path)


def parse(text: str, path: str) -> BusDescription:
    """Read a bus description from ``text``; raise :class:`DescriptionError`.

    ``path`` names the file in messages, and its folder is the one relative paths and
    ``@BUS_CONFIG_PATH@`` stand for.
    """
    reader = _Reader(path)
    try:
        root = yaml.load(text, Loader=_UniqueKeyLoader)
    except yaml.YAMLError as error:
        mark = getattr(error, 'problem_mark', None)
        where = f' (line {mark.line + 1}, column {mark.column + 1})' if mark else ''
        raise DescriptionError(f'{reader.shown}: not valid YAML: '
                               f'{getattr(error, "problem", None) or error}{where}') from None
    if not isinstance(root, dict):
        raise DescriptionError(f'{reader.shown}: {reader.describe(root)}: allowed a mapping '
                               f'of options, master, defaults and nodes')
    options = reader.keyed('options', root.get('options'))
    reader.note_unknown(options, OPTIONS_KEYS)
    dcf_folder = reader.folder
    if 'dcf_path' in options:
        dcf_folder = reader.location(*options['dcf_path'], reader.folder)
    master = _master(reader, reader.keyed('master', root.get('master')))
    defaults = reader.keyed('defaults', root.get('defaults'))
    reader.note_unknown(defaults, NODE_KEYS, NODE_IGNORED)
    by_id: Dict[int, DeviceDescription] = {}
    for name, where, own in _nodes(reader, root):
        reader.note_unknown(own, NODE_KEYS, NODE_IGNORED)
        device = _device(reader, name, where, {**defaults, **own}, dcf_folder)
        if device.node_id in by_id:
            raise reader.fail(f'{where}.node_id', f'{device.node_id} is also the node_id of '
                              f'{by_id[device.node_id].name}: each node needs its own')
        by_id[device.node_id] = device
    return BusDescription(path, master, tuple(by_id[key] for key in sorted(by_id)),
                          tuple(reader.unsupported))


# The keys of a mapping of the file, each with its path in messages and its value.
_Keyed = Dict[object, Tuple[str, object]]


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, except that a key given twice in a mapping is an error."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == 'tag:yaml.org,2002:merge':
                continue  # '<<: *anchor': the node's own keys override the merged ones
            key = self.construct_object(key_node, deep=True)
            try:
                if key in seen:
                    raise yaml.constructor.ConstructorError(
                        None, None, f'{quoted(key)} is given twice', key_node.start_mark)
                seen.add(key)
            except TypeError:
                pass  # an unhashable key: PyYAML names it below
        return super().construct_mapping(node, deep)


class _Reader:
    """Checks each value against what its key allows; collects the keys not implemented.

    Every check takes the value's path in messages first, then the value.
    """

    def __init__(self, path: str):
        self.shown = quoted(path, PATH_LIMIT)
        self.folder = os.path.dirname(os.path.abspath(path))
        self.unsupported: List[str] = []

    def fail(self, path: str, problem: str) -> DescriptionError:
        return DescriptionError(f'{self.shown}: {path}: {problem}')

    def note_unknown(self, given: _Keyed, known: FrozenSet[str],
                     ignored: FrozenSet[str] = frozenset()) -> None:
        for key, (path, _) in given.items():
            if key not in known and key not in ignored and path not in self.unsupported:
                self.unsupported.append(path)  # a key of the defaults is listed once

    @staticmethod
    def describe(value) -> str:
        if value is None:
            return 'nothing (null)'
        kinds = ((bool, 'a boolean'), (int, 'an integer'), (float, 'a number'),
                 (str, 'text'), (list, 'a list'), (dict, 'a mapping'))
        kind = next((name for type_, name in kinds if isinstance(value, type_)), 'a value')
        return f'{quoted(value)} is {kind}' if isinstance(value, (bool, int, float, str)) \
            else kind

    def keyed(self, path: str, value) -> _Keyed:
        if value is None:
            return {}
        if not isinstance(value, dict):
            raise self.fail(path, f'{self.describe(value)}: allowed a mapping of keys')
        return {key: (f'{path}.{key}', item) for key, item in value.items()}

    def entries(self, path: str, value) -> List[Tuple[str, object]]:
        if value is None:
            return []
        if not isinstance(value, list):
            raise self.fail(path, f'{self.describe(value)}: allowed a list (- entries)')
        return [(f'{path}[{position}]', item) for position, item in enumerate(value, 1)]

    def integer(self, path: str, value, low: int, high: int, text: bool = False,
                unit: str = '') -> int:
        shown_high = f'0x{high:X}' if text and high >= 0x1000 else str(high)
        allowed = f'allowed an integer {low}..{shown_high}{unit}'
        if text:
            allowed += ' (or its text, as "0x1A")'
        if isinstance(value, str) and text:
            try:
                number = parse_integer(value.strip())
            except ValueError:
                raise self.fail(path, f'{quoted(value)} is not a number: {allowed}') from None
        elif isinstance(value, int) and not isinstance(value, bool):
            number = value
        else:
            raise self.fail(path, f'{self.describe(value)}: {allowed}')
        if not low <= number <= high:
            raise self.fail(path, f'{number} is out of range: {allowed}')
        return number

    def flag(self, path: str, value) -> bool:
        if isinstance(value, bool) or isinstance(value, int) and value in (0, 1):
            return bool(value)
        raise self.fail(path, f'{self.describe(value)}: allowed true or false')

    def location(self, path: str, value, base: str) -> str:
        if not isinstance(value, str):
            raise self.fail(path, f'{self.describe(value)}: allowed a path')
        resolved = value.replace(BUS_CONFIG_PATH, self.folder)
        unknown = _CMAKE_VARIABLE.search(resolved)
        if unknown:
            raise self.fail(path, f'{quoted(value, PATH_LIMIT)} names {unknown.group()}: only '
                            f"{BUS_CONFIG_PATH} (the file's folder) is known here")
        return os.path.normpath(os.path.join(base, resolved))


def _nodes(reader: _Reader, root: dict) -> List[Tuple[str, str, _Keyed]]:
    """Return each node as (name, its path in messages, its own keys)."""
    stray = [key for key in root if key not in TOP_LEVEL_KEYS and not _hidden(key)]
    if 'nodes' in root:
        if stray:
            raise reader.fail(str(stray[0]), "a node at the top level beside 'nodes:': give "
                              "every node under nodes (ros2_canopen's cogen drops it)")
        found = [(name, where, node)
                 for name, (where, node) in reader.keyed('nodes', root['nodes']).items()
                 if not _hidden(name)]
    else:
        found = [(name, str(name), root[name]) for name in stray]
    for name, where, _ in found:
        if not isinstance(name, str):
            raise reader.fail(where, f'{reader.describe(name)}: a node is named by text')
    return [(name, where, reader.keyed(where, node)) for name, where, node in found]


def _hidden(key) -> bool:
    return isinstance(key, str) and key.startswith('.')


def _master(reader: _Reader, given: _Keyed) -> MasterDescription:
    reader.note_unknown(given, MASTER_KEYS, MASTER_IGNORED)
    if 'boot_time' in given and 'boot_timeout' in given:
        raise reader.fail('master.boot_time', 'master.boot_timeout is given too: they are one '
                          'setting here (the time a device has to boot), give one')
    fields = {}
    if 'node_id' in given:
        fields['node_id'] = reader.integer(*given['node_id'], 1, MAX_NODE_ID, text=True)
    if 'sync_period' in given:
        fields['sync_period'] = reader.integer(*given['sync_period'], 0, UNSIGNED32,
                                               unit=' µs')
    if 'heartbeat_producer' in given:
        fields['heartbeat_producer'] = reader.integer(*given['heartbeat_producer'], 0,
                                                      UNSIGNED16, unit=' ms')
    for key in ('boot_timeout', 'boot_time'):
        if key in given:
            fields['boot_timeout'] = reader.integer(*given[key], 0, UNSIGNED32, unit=' ms')
    for key in ('start_nodes', 'heartbeat_consumer'):
        if key in given:
            fields[key] = reader.flag(*given[key])
    return MasterDescription(**fields, given=frozenset(fields))


def _device(reader: _Reader, name: str, where: str, given: _Keyed,
            dcf_folder: str) -> DeviceDescription:
    """Return the node ``name``, ``given`` its keys (the defaults' and, winning, its own)."""
    if 'node_id' not in given:
        raise reader.fail(where, f'no node_id: allowed 1..{MAX_NODE_ID}')
    fields = {'name': name,
              'node_id': reader.integer(*given['node_id'], 1, MAX_NODE_ID, text=True)}
    if 'dcf_path' in given:
        dcf_folder = reader.location(*given['dcf_path'], reader.folder)
    path, dcf = given.get('dcf', ('', ''))
    fields['dcf'] = reader.location(path, dcf, dcf_folder) if dcf != '' else ''
    path, driver_name = given.get('driver', ('', ''))
    if not isinstance(driver_name, str):
        raise reader.fail(path, f'{reader.describe(driver_name)}: allowed a class name, as '
                          f'"ros2_canopen::Cia402Driver"')
    fields['driver_name'] = driver_name
    fields['driver'] = ('drive' if driver_name.endswith('Cia402Driver') else
                        'proxy' if driver_name.endswith('ProxyDriver') else '')
    for key in IDENTITY_KEYS:
        if key in given:
            fields[key] = reader.integer(*given[key], 0, UNSIGNED32, text=True)
    if 'sdo' in given:
        fields['sdo'] = _sdo_writes(reader, *given['sdo'])
    for kind in ('tpdo', 'rpdo'):
        if kind in given:
            fields[kind] = _pdo_settings(reader, *given[kind])
    if 'heartbeat_producer' in given:
        fields['heartbeat_producer'] = reader.integer(*given['heartbeat_producer'], 0,
                                                      UNSIGNED16, unit=' ms')
    for key in NODE_FLAGS:
        if key in given:
            fields[key] = reader.flag(*given[key])
    if 'restore_configuration' in given:
        path, restore = given['restore_configuration']
        fields['restore_configuration'] = int(restore) if isinstance(restore, bool) else \
            reader.integer(path, restore, 0, MAX_RESTORE_SUBINDEX)
    fields['scales'] = tuple((key, _scale(reader, *given[key]))
                             for key in SCALE_KEYS if key in given)
    if 'software_version' in given:
        # 0 is no software id (no valid program): a boot could never match it, and it would
        # download software_file again at every boot without checking what it got.
        fields['software_version'] = reader.integer(*given['software_version'], 1,
                                                    UNSIGNED32, text=True)
    if 'software_file' in given:
        fields['software_file'] = reader.location(*given['software_file'], reader.folder)
        if 'software_version' not in given:
            raise reader.fail(f'{where}.software_file', 'no software_version beside it: give '
                              'the software id (0x1F56:1) the file holds, so that a boot '
                              'knows when to download it')
    return DeviceDescription(**fields)


def _scale(reader: _Reader, path: str, value) -> float:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    raise reader.fail(path, f'{reader.describe(value)}: allowed a number')


def _address(reader: _Reader, where: str, entry: _Keyed) -> Tuple[int, int]:
    """Return an entry's (index, subindex); ``sub_index`` (ros2_canopen) or ``subindex``."""
    if 'index' not in entry:
        raise reader.fail(where, 'no index: allowed an object index 0x0001..0xFFFF')
    if 'sub_index' in entry and 'subindex' in entry:
        raise reader.fail(f'{where}.subindex', 'sub_index is given too: give one')
    subindex = entry.get('subindex') or entry.get('sub_index') or (f'{where}.sub_index', 0)
    return (reader.integer(*entry['index'], 1, UNSIGNED16, text=True),
            reader.integer(*subindex, 0, 0xFF, text=True))


def _sdo_writes(reader: _Reader, path: str, value) -> Tuple[SdoWrite, ...]:
    writes = []
    for where, entry in reader.entries(path, value):
        entry = reader.keyed(where, entry)
        reader.note_unknown(entry, SDO_KEYS)
        index, subindex = _address(reader, where, entry)
        if 'value' not in entry:
            raise reader.fail(where, 'no value: allowed a number or text')
        value_path, written = entry['value']
        if isinstance(written, bool):
            written = int(written)
        elif not isinstance(written, (int, float, str)):
            raise reader.fail(value_path, f'{reader.describe(written)}: allowed a number or '
                              f'text')
        writes.append(SdoWrite(index, subindex, written))
    return tuple(writes)


def _pdo_settings(reader: _Reader, path: str, value) -> Tuple[PdoSetting, ...]:
    settings: Dict[int, PdoSetting] = {}
    for number_key, (where, entry) in reader.keyed(path, value).items():
        number = reader.integer(where, number_key, 1, MAX_PDOS, text=True)
        if number in settings:
            raise reader.fail(where, f'PDO {number} is given twice')
        entry = reader.keyed(where, entry)
        reader.note_unknown(entry, PDO_KEYS)
        if 'transmission' in entry and 'transmission_type' in entry:
            raise reader.fail(f'{where}.transmission_type', 'transmission is given too: '
                              'give one')
        fields = {}
        if 'enabled' in entry:
            fields['enabled'] = reader.flag(*entry['enabled'])
        if 'cob_id' in entry and entry['cob_id'][1] != 'auto':
            cob_id = reader.integer(*entry['cob_id'], 0, MAX_CAN_ID, text=True,
                                    unit=' (an 11-bit CAN-ID)')
            restricted = next((what for low, high, what in RESTRICTED_CAN_IDS
                               if low <= cob_id <= high), None)
            if restricted:
                raise reader.fail(entry['cob_id'][0], f'0x{cob_id:03X} is a CAN-ID CiA 301 '
                                  f'restricts ({restricted}): give another')
            fields['cob_id'] = cob_id
        for key in ('transmission', 'transmission_type'):
            if key in entry:
                fields['transmission'] = reader.integer(*entry[key], 0, 0xFF)
        for key, unit in (('event_timer', ' ms'), ('inhibit_time', ' x 100 µs')):
            if key in entry:
                fields[key] = reader.integer(*entry[key], 0, UNSIGNED16, unit=unit)
        if 'mapping' in entry:
            mapped = reader.entries(*entry['mapping'])
            if len(mapped) > MAX_ENTRIES:
                raise reader.fail(entry['mapping'][0], f'{len(mapped)} entries: CiA 301 '
                                  f'allows {MAX_ENTRIES}')
            addresses = []
            for item_where, item in mapped:
                item = reader.keyed(item_where, item)
                reader.note_unknown(item, MAPPED_KEYS)
                addresses.append(_address(reader, item_where, item))
            fields['mapping'] = tuple(addresses)
        settings[number] = PdoSetting(number, **fields)
    return tuple(settings[number] for number in sorted(settings))
