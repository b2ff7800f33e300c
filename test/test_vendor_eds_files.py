"""Vendors' EDS and DCF files as they are: simulated, named, and configured from.

The tests write files in the shapes vendors' tools write them (hex and decimal values,
two's-complement negatives, ``$NODEID`` expressions with and without spaces, CompactSubObj
arrays and records, ObjFlags, DOMAINs with and without a value, empty strings, 64-bit types,
a DCF's ParameterValue, an object of a type canopen does not know, entries that share a name)
and meet them as a user does: a simulated device built from the file answers over SDO, the
command line names every object, ``pdo.configure`` writes the file's PDOs into a durand
device, and a file canopen cannot parse stops the node with the file and the line named.
"""

from dataclasses import dataclass
import math
import struct
import subprocess
from typing import List, Optional, Union

from lifecycle_msgs.msg import Transition
import pytest
from test_lifecycle import Managed

from cbcan_ros.core import eds
from cbcan_ros.ros.cli import build_parser, Client, run
from cbcan_ros.simulation.durand.device import DurandDevice

from conftest import new_channel, wait_until
from node_process import executable, START_TIMEOUT

NODE = 11
NO_VALUE = 0x060A0023  # CiA 301: resource not available (an object with no value)
# canopen's SDO server (the simulated device) answers an empty value "no data available"
# rather than with a transfer of no bytes.
NO_DATA = 0x08000024
PROMPT = 10.0

# CiA 301 data types: code, struct format ('' for bytes and strings)
TYPES = {'BOOLEAN': (0x1, '<?'), 'INTEGER8': (0x2, '<b'), 'INTEGER16': (0x3, '<h'),
         'INTEGER32': (0x4, '<i'), 'UNSIGNED8': (0x5, '<B'), 'UNSIGNED16': (0x6, '<H'),
         'UNSIGNED32': (0x7, '<I'), 'REAL32': (0x8, '<f'), 'VISIBLE_STRING': (0x9, ''),
         'DOMAIN': (0xF, ''), 'INTEGER64': (0x15, '<q'), 'UNSIGNED64': (0x1B, '<Q')}


@dataclass
class Entry:
    """One object or sub-index of a generated file, and what a device must answer for it."""

    index: int
    subindex: Optional[int]  # None: a VAR object
    name: str
    type_name: str
    hex_value: Optional[str]  # DefaultValue as a vendor's tool writes it in hex
    decimal_value: Optional[str]  # the same value as other tools write it
    expected: object  # the value (int, float, str, bytes), or a function of the node id
    access: str = 'rw'
    extra: str = ''  # more lines of the section (ObjFlags, ...)
    abort: int = 0  # the abort code a read gets instead of a value

    def answer(self, node_id: int) -> Union[bytes, int]:
        """Return the bytes an SDO read of this entry must return, or its abort code."""
        if self.abort:
            return self.abort
        value = self.expected(node_id) if callable(self.expected) else self.expected
        fmt = TYPES[self.type_name][1]
        if not fmt:
            return value.encode() if isinstance(value, str) else value
        return struct.pack(fmt, value)

    def qualified_name(self, parent: Optional[str]) -> str:
        """Return the name the command line takes: "Object.Entry" for an entry."""
        return f'{parent}.{self.name}' if parent else self.name


NAMES = 'Outputs'  # the array whose entries all share one name


def entries() -> List[Entry]:
    """Return the objects every generated file holds (VARs; records and arrays apart)."""
    return [
        Entry(0x1000, None, 'Device type', 'UNSIGNED32', '0x00020192', '131474', 0x20192,
              'ro'),
        Entry(0x1017, None, 'Producer heartbeat time', 'UNSIGNED16', '0x0000', '0', 0),
        Entry(0x2000, None, 'Torque offset', 'INTEGER16', '0xFFFF', '-1', -1),
        Entry(0x2001, None, 'Small step', 'INTEGER8', '0xFD', '-3', -3),
        Entry(0x2002, None, 'Position limit', 'INTEGER32', '0x88CA6C00', str(-0x77359400),
              -0x77359400),
        Entry(0x2003, None, 'Big counter', 'UNSIGNED64', '0xFFFFFFFFFFFFFFFF',
              str(2 ** 64 - 1), 2 ** 64 - 1),
        Entry(0x2004, None, 'Big offset', 'INTEGER64', '0x8000000000000000', str(-2 ** 63),
              -2 ** 63),
        Entry(0x2005, None, 'Gain', 'REAL32', '1.5', '1.5', 1.5),
        Entry(0x2006, None, 'Empty label', 'VISIBLE_STRING', '', '', '', abort=NO_DATA),
        Entry(0x2007, None, 'Label', 'VISIBLE_STRING', 'Axis 1', 'Axis 1', 'Axis 1'),
        Entry(0x2008, None, 'Log without value', 'DOMAIN', None, None, None, abort=NO_VALUE),
        Entry(0x2009, None, 'Calibration', 'DOMAIN', '0102030405', '0102030405',
              bytes([1, 2, 3, 4, 5])),
        Entry(0x200A, None, 'Flagged', 'UNSIGNED8', '0x2A', '42', 42, extra='ObjFlags=0x1'),
        Entry(0x200B, None, 'Enabled', 'BOOLEAN', '0x1', '1', True),
        Entry(0x2020, None, 'Event counter', 'UNSIGNED32', '0x00000007', '7', 7),
    ]


def members() -> List[tuple]:
    """Return (record or array index, its name, object type, its entries)."""
    identity = [Entry(0x1018, 0, 'Highest sub-index supported', 'UNSIGNED8', '0x4', '4', 4,
                      'ro'),
                Entry(0x1018, 1, 'Vendor-ID', 'UNSIGNED32', '0x00000319', '793', 0x319, 'ro'),
                Entry(0x1018, 2, 'Product code', 'UNSIGNED32', '0x51', '81', 0x51, 'ro'),
                Entry(0x1018, 3, 'Revision number', 'UNSIGNED32', '0x10000', '65536', 0x10000,
                      'ro'),
                Entry(0x1018, 4, 'Serial number', 'UNSIGNED32', '0x7', '7', 7, 'ro')]
    tpdo = [Entry(0x1800, 0, 'Highest sub-index supported', 'UNSIGNED8', '0x2', '2', 2, 'ro'),
            Entry(0x1800, 1, 'COB-ID used by TPDO', 'UNSIGNED32', '$NODEID+0x180',
                  '0x180 + $NODEID', lambda node_id: 0x180 + node_id),
            Entry(0x1800, 2, 'Transmission type', 'UNSIGNED8', '0xFF', '255', 255)]
    mapping = [Entry(0x1A00, 0, 'Number of mapped objects', 'UNSIGNED8', '0x2', '2', 2),
               Entry(0x1A00, 1, 'Mapping entry 1', 'UNSIGNED32', '0x20000010',
                     str(0x20000010), 0x20000010),
               Entry(0x1A00, 2, 'Mapping entry 2', 'UNSIGNED32', '0x20020020',
                     str(0x20020020), 0x20020020)]
    outputs = [Entry(0x6201, 0, 'Number of outputs', 'UNSIGNED8', '0x4', '4', 4, 'ro')]
    outputs += [Entry(0x6201, sub, 'Output', 'UNSIGNED8', f'0x{sub:X}', str(sub), sub)
                for sub in range(1, 5)]
    return [(0x1018, 'Identity object', 0x9, identity), (0x1800, 'TPDO 1', 0x9, tpdo),
            (0x1A00, 'TPDO 1 mapping', 0x9, mapping), (0x6201, NAMES, 0x8, outputs)]


# CompactSubObj objects: (index, name, object type, N, entry type, hex, decimal, value)
COMPACT = [(0x6200, 'Write outputs 8-bit', 0x8, 8, 'UNSIGNED8', '0x0', '0', 0),
           (0x6202, 'Gains', 0x9, 3, 'UNSIGNED16', '0x10', '16', 16)]
UNKNOWN_TYPE = (0x2030, 'Vendor structure', 0x40)


def section(title: str, lines: List[str]) -> str:
    """Return an EDS section."""
    return '\n'.join([f'[{title}]', *lines, ''])


def variable_lines(entry: Entry, style: str) -> List[str]:
    """Return the lines of one variable's section in ``style`` ('hex', 'decimal' or 'dcf')."""
    lines = [f'ParameterName={entry.name}', 'ObjectType=0x7',
             f'DataType=0x{TYPES[entry.type_name][0]:04X}', f'AccessType={entry.access}',
             'PDOMapping=0']
    value = entry.decimal_value if style == 'decimal' else entry.hex_value
    if value is not None:
        lines.append(f'DefaultValue={value}')
    if entry.extra:
        lines.append(entry.extra)
    return lines


def write_file(path, style: str) -> None:
    """Write a device file of every shape above; ``style`` 'dcf' writes ParameterValues."""
    parts = [section('FileInfo', ['FileName=generated.eds', 'FileVersion=1', 'EDSVersion=4.0']),
             section('DeviceInfo', ['VendorName=Test vendor', 'ProductName=Generated drive',
                                    'NrOfRXPDO=0', 'NrOfTXPDO=1'])]
    if style == 'dcf':
        parts.append(section('DeviceComissioning', [f'NodeID=0x{NODE:X}']))
    objects = [e.index for e in entries()] + [m[0] for m in members()] + \
        [c[0] for c in COMPACT] + [UNKNOWN_TYPE[0]]
    parts.append(section('ManufacturerObjects', [f'SupportedObjects={len(objects)}'] +
                         [f'{n}=0x{index:04X}' for n, index in enumerate(objects, 1)]))
    for entry in entries():
        lines = variable_lines(entry, style)
        if style == 'dcf' and entry.index == 0x2000:
            lines.append('ParameterValue=0xFFFE')  # a DCF's value wins over the default
        parts.append(section(f'{entry.index:04X}', lines))
    for index, name, object_type, subs in members():
        parts.append(section(f'{index:04X}', [f'ParameterName={name}',
                                              f'ObjectType=0x{object_type:X}',
                                              f'SubNumber={len(subs)}']))
        parts += [section(f'{index:04X}sub{e.subindex:X}', variable_lines(e, style))
                  for e in subs]
    for index, name, object_type, count, type_name, hex_value, decimal, _ in COMPACT:
        value = decimal if style == 'decimal' else hex_value
        parts.append(section(f'{index:04X}', [
            f'ParameterName={name}', f'ObjectType=0x{object_type:X}',
            f'DataType=0x{TYPES[type_name][0]:04X}', 'AccessType=rw', 'PDOMapping=0',
            f'CompactSubObj={count}', f'DefaultValue={value}']))
    index, name, data_type = UNKNOWN_TYPE
    parts.append(section(f'{index:04X}', [f'ParameterName={name}', 'ObjectType=0x7',
                                          f'DataType=0x{data_type:04X}', 'AccessType=rw']))
    path.write_text('\n'.join(parts))


def expected_reads():
    """Yield (index, subindex, name the command line takes, answer) of every object."""
    for entry in entries():
        yield entry.index, 0, entry.name, entry
    for index, name, _, subs in members():
        for entry in subs:
            yield index, entry.subindex, f'{name}.{entry.name}', entry


def compact_reads():
    """Yield (index, subindex, expected bytes) of the CompactSubObj objects."""
    for index, _, _, count, type_name, _, _, value in COMPACT:
        yield index, 0, bytes([count])
        for sub in range(1, count + 1):
            yield index, sub, struct.pack(TYPES[type_name][1], value)


STYLES = ['hex', 'decimal', 'dcf']


@pytest.fixture(params=STYLES)
def device_file(request, tmp_path):
    """Write a generated file in each style; return (path, style)."""
    path = tmp_path / ('drive.dcf' if request.param == 'dcf' else 'drive.eds')
    write_file(path, request.param)
    return path, request.param


@pytest.fixture
def simulated(make_gateway, device_file):
    """Return (gateway, path, style): a gateway whose simulated node 11 is the file's device."""
    path, style = device_file
    gateway = make_gateway(simulation__devices=[NODE], simulation__eds=str(path),
                           nodes=[NODE])
    return gateway, path, style


def test_a_simulated_device_answers_every_object_with_the_file_s_value(simulated):
    gateway, _, style = simulated
    wrong = []
    for index, subindex, name, entry in expected_reads():
        answer = gateway.call('sdo_read', node_id=NODE, index=index, subindex=subindex)
        expected = entry.answer(NODE)
        if style == 'dcf' and index == 0x2000:
            expected = struct.pack('<h', -2)
        got = bytes(answer.data) if answer.success else answer.abort_code
        if got != expected:
            wrong.append(f'0x{index:04X}:{subindex} {name}: {got!r}, expected {expected!r} '
                         f'({answer.message})')
    for index, subindex, expected in compact_reads():
        answer = gateway.call('sdo_read', node_id=NODE, index=index, subindex=subindex)
        if not answer.success or bytes(answer.data) != expected:
            wrong.append(f'0x{index:04X}:{subindex} (CompactSubObj): {answer.message} '
                         f'{bytes(answer.data)!r}, expected {expected!r}')
    assert wrong == [], '\n'.join(wrong)


@pytest.fixture
def cli(simulated, capsys):
    """Return ``cli(*arguments)``: a cbcan_cli command in this process; (status, out, err)."""
    gateway, path, _ = simulated
    client = Client('/cbcan', START_TIMEOUT)

    def run_command(*arguments):
        status = run(client, build_parser().parse_args(arguments))
        out, err = capsys.readouterr()
        return status, out, err
    yield run_command
    client.close()


def test_the_command_line_names_every_object_of_the_file(simulated, cli):
    _, path, style = simulated
    wrong = []
    for index, subindex, name, entry in expected_reads():
        if entry.name == 'Output':
            continue  # shared by four entries: named by sub-index (the next test)
        status, out, err = cli('sdo-read', str(NODE), name, '--eds', str(path))
        answer = entry.answer(NODE)
        if isinstance(answer, int):
            if status == 0 or f'SDO abort 0x{answer:08X}' not in err:
                wrong.append(f'{name}: {status} {out}{err}')
        elif status != 0 or f'0x{index:04X}:{subindex:02X}' not in out:
            wrong.append(f'{name}: {status} {out}{err}')
    assert wrong == [], '\n'.join(wrong)


def test_a_name_several_entries_share_is_refused_naming_them(simulated, cli):
    _, path, _ = simulated
    status, out, err = cli('sdo-read', str(NODE), f'{NAMES}.Output', '--eds', str(path))
    assert status != 0 and out == '', out
    assert 'is ambiguous' in err and '0x6201:01..04' in err, err
    status, out, err = cli('sdo-read', str(NODE), NAMES, '3', '--eds', str(path))
    assert status == 0 and '0x6201:03' in out, out + err


def test_negative_hex_defaults_are_read_as_twos_complement(device_file):
    path, style = device_file
    dictionary = eds.load(str(path), NODE)
    assert dictionary[0x2000].default == -1
    assert dictionary[0x2001].default == -3
    assert dictionary[0x2004].default == -2 ** 63
    assert dictionary[0x2003].default == 2 ** 64 - 1  # unsigned: as written
    if style == 'dcf':
        assert dictionary[0x2000].value == -2
    assert dictionary[0x1800][1].default == 0x180 + NODE
    assert dictionary[0x6200][0].default == 8 and dictionary[0x6202][0].default == 3
    assert math.isclose(dictionary[0x2005].default, 1.5)


def test_the_command_line_says_once_which_objects_canopen_cannot_type(simulated):
    _, path, _ = simulated
    result = subprocess.run([executable('cbcan_cli'), '--gateway', '/cbcan', '--wait',
                             str(START_TIMEOUT), 'sdo-read', str(NODE), 'Device type',
                             '--eds', str(path)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    notes = [line for line in result.stderr.splitlines() if line]
    assert len(notes) == 1, result.stderr
    assert str(path) in notes[0] and "'Vendor structure'" in notes[0], notes[0]
    assert 'unknown or unsupported' not in result.stderr


@pytest.mark.parametrize('broken, where, reason', [
    ('[2000]\nParameterName=Twice\n', 'END', "section '2000' already exists"),
    ('[2100]\nParameterName=No type\nObjectType=0x7\nAccessType=rw\n', 'END',
     "'DataType'"),
    ('[2100]\nParameterName=Bad type\nObjectType=0x7\nDataType=zz\nAccessType=rw\n',
     'END', 'invalid literal'),
    ('this line is no section\n', 'START', 'MissingSectionHeaderError'),
], ids=['duplicate section', 'no data type', 'bad data type', 'no section header'])
def test_a_file_canopen_cannot_parse_stops_the_node_naming_file_and_line(
        start_node, tmp_path, broken, where, reason):
    path = tmp_path / 'drive.eds'
    write_file(path, 'hex')
    text = path.read_text()
    text = broken + text if where == 'START' else text + '\n' + broken
    path.write_text(text)
    number = 1 if where == 'START' else len(text.splitlines()) - len(broken.splitlines()) + 1
    node = start_node(['-p', f'can.channel:={new_channel()}', '-p', f'nodes:=[{NODE}]',
                       '-p', f'node_{NODE}.eds:={path}'])
    status = node.wait(START_TIMEOUT)
    output = node.output()
    assert status == 1, output
    assert f"parameter node_{NODE}.eds: '{path}'" in output, output
    assert f'at line {number}:' in output and reason in output, output
    assert 'Traceback' not in output, output


def test_pdo_configure_writes_what_the_file_says_into_a_durand_device(make_gateway, tmp_path):
    path = tmp_path / 'drive.dcf'
    write_file(path, 'dcf')
    text = path.read_text()
    # The DCF's values for TPDO 1: transmission type 254, mapping the durand device's 0x2001
    # (16 bits) and 0x2003 (32 bits), a COB-ID with spaces around $NODEID.
    for default, value in (('0x20000010', '0x20010010'), ('0x20020020', '0x20030020')):
        text = text.replace(f'DefaultValue={default}\n',
                            f'DefaultValue={default}\nParameterValue={value}\n')
    text = text.replace('DefaultValue=0xFF\n', 'DefaultValue=0xFF\nParameterValue=254\n', 1)
    text = text.replace('DefaultValue=$NODEID+0x180',
                        'DefaultValue=$NODEID+0x180\nParameterValue=0x280 + $NODEID')
    path.write_text(text)
    channel = new_channel()
    device = DurandDevice(NODE, channel=channel)
    device.start()
    try:
        gateway = make_gateway(can__channel=channel, simulation__devices=None,
                               pdo__nodes=[NODE], pdo__configure=True, nodes=[NODE],
                               **{f'node_{NODE}__eds': str(path)})
        assert gateway.call('nmt_command', node_id=NODE, command=129).success
        wait_until(lambda: device.value(0x1A00, 0) == b'\x02', PROMPT,
                   "the file's TPDO 1 mapping written")
        wait_until(lambda: device.value(0x1800, 1) == (0x280 + NODE).to_bytes(4, 'little'),
                   PROMPT, 'the COB-ID enabled again')
    finally:
        device.stop()
    assert device.value(0x1A00, 1) == (0x20010010).to_bytes(4, 'little')
    assert device.value(0x1A00, 2) == (0x20030020).to_bytes(4, 'little')
    assert device.value(0x1800, 2) == bytes([254])


def test_the_node_says_once_at_start_which_objects_canopen_cannot_type(start_node, tmp_path):
    path = tmp_path / 'drive.eds'
    write_file(path, 'hex')
    node = start_node(['-p', f'can.channel:={new_channel()}', '-p', f'nodes:=[{NODE}]',
                       '-p', f'node_{NODE}.eds:={path}'])
    wait_until(lambda: 'CANopen gateway on' in node.output(), START_TIMEOUT, 'the node up')
    node.stop()
    output = node.output()
    assert output.count("'Vendor structure'") == 1, output
    assert 'unknown or unsupported' not in output, output


def test_a_latin_1_file_is_read_with_its_names(tmp_path):
    path = tmp_path / 'drive.eds'
    write_file(path, 'hex')
    text = path.read_text().replace('ParameterName=Gain', 'ParameterName=Gain at 20 °C')
    path.write_bytes(text.encode('latin-1'))
    dictionary = eds.load(str(path), NODE)
    assert eds.find(dictionary, 'Gain at 20 °C').index == 0x2005


def test_a_file_canopen_cannot_parse_fails_lifecycle_configure_naming_file_and_line(
        start_node, client_node, tmp_path):
    path = tmp_path / 'drive.eds'
    write_file(path, 'hex')
    text = path.read_text() + '\n[2100]\nParameterName=Bad type\nDataType=zz\nAccessType=rw\n'
    path.write_text(text)
    number = len(text.splitlines()) - 3
    managed = Managed(start_node, client_node, '-p', f'nodes:=[{NODE}]',
                      '-p', f'node_{NODE}.eds:={path}')
    assert not managed.transition(Transition.TRANSITION_CONFIGURE)
    assert managed.state() == 'unconfigured'
    wait_until(lambda: f'at line {number}:' in managed.node.output(), PROMPT,
               f'the file and line in the log:\n{managed.node.output()}')
    output = managed.node.output()
    assert f"parameter node_{NODE}.eds: '{path}'" in output and 'Traceback' not in output, output


HEADER = '\n'.join([section('FileInfo', ['FileName=quirk.eds']),
                    section('DeviceInfo', ['VendorName=Test vendor']),
                    section('1000', ['ParameterName=Device type', 'ObjectType=0x7',
                                     'DataType=0x0007', 'AccessType=ro',
                                     'DefaultValue=0x00020192'])])


def quirk_file(tmp_path, *sections: str, prefix: str = '', name: str = 'quirk.eds'):
    """Write HEADER and ``sections`` (with ``prefix`` before all, e.g. a byte order mark)."""
    path = tmp_path / name
    path.write_text(prefix + HEADER + '\n' + '\n'.join(sections), encoding='utf-8')
    return str(path)


def var(index: int, data_type: int, *lines: str) -> str:
    """Return a VAR section of ``data_type`` with ``lines`` (DefaultValue=...)."""
    return section(f'{index:04x}', [f'ParameterName=Object {index:04X}', 'ObjectType=0x7',
                                    f'DataType=0x{data_type:04X}', 'AccessType=rw', *lines])


def test_files_with_a_byte_order_mark_are_read(tmp_path):
    dictionary = eds.load(quirk_file(tmp_path, prefix='\ufeff'), NODE)
    assert dictionary[0x1000].default == 0x20192


def test_values_canopen_leaves_without_one_are_read_as_written(tmp_path):
    notes = []
    dictionary = eds.load(quirk_file(
        tmp_path, var(0x2000, 0x5, 'DefaultValue=$NODEID'),
        var(0x2001, 0x6, 'DefaultValue=0100'),
        var(0x2002, 0x3, 'DefaultValue=0x10000'), var(0x2003, 0x5, 'DefaultValue=abc')),
        NODE, notes.append)
    assert dictionary[0x2000].default == NODE
    assert dictionary[0x2001].default == 100
    assert dictionary[0x2002].default is None and dictionary[0x2003].default is None
    assert len(notes) == 1, notes
    assert "'Object 2002': DefaultValue '0x10000' does not fit its type" in notes[0], notes
    assert "'Object 2003': DefaultValue 'abc' is not a number" in notes[0], notes


def test_compact_arrays_in_lowercase_sections_and_type_definitions_are_read(tmp_path):
    dictionary = eds.load(quirk_file(
        tmp_path,
        section('60a0', ['ParameterName=Inputs', 'ObjectType=0x8', 'DataType=0x0005',
                         'AccessType=rw', 'DefaultValue=0x0', 'CompactSubObj=4']),
        section('0040', ['ParameterName=Vendor struct', 'ObjectType=0x6', 'SubNumber=2']),
        section('0040sub0', ['ParameterName=Entries', 'ObjectType=0x7', 'DataType=0x0005',
                             'AccessType=ro', 'DefaultValue=1']),
        section('0040sub1', ['ParameterName=Field', 'ObjectType=0x7', 'DataType=0x0006',
                             'AccessType=ro', 'DefaultValue=0x0007'])), NODE)
    assert dictionary[0x60A0][0].default == 4 and 0x0040 not in dictionary


def test_a_dcf_commissioning_value_that_is_no_number_is_ignored_and_said(tmp_path):
    notes = []
    path = quirk_file(tmp_path, section('DeviceComissioning', ['NodeID=0x0B', 'Baudrate=']),
                      name='drive.dcf')
    assert eds.load(path, None, notes.append)[0x1000].default == 0x20192
    assert len(notes) == 1 and 'Baudrate' in notes[0], notes


@pytest.mark.parametrize('compact, reason', [
    ('abc', "CompactSubObj='abc' is not a number"), ('256', 'out of range')])
def test_a_compact_count_that_is_wrong_is_an_error_naming_its_line(tmp_path, compact, reason):
    path = quirk_file(tmp_path, section('6200', [
        'ParameterName=Outputs', 'ObjectType=0x8', 'DataType=0x0005', 'AccessType=rw',
        'DefaultValue=0', f'CompactSubObj={compact}']))
    line = open(path).read().splitlines().index('[6200]') + 1
    with pytest.raises(ValueError, match=f'at line {line}: .*{reason}'):
        eds.load(path, NODE)


def test_a_simulated_device_of_a_file_without_heartbeat_or_pdo_mapping_starts(
        make_gateway, tmp_path):
    path = quirk_file(tmp_path, section('1800', ['ParameterName=TPDO 1', 'ObjectType=0x9',
                                                 'SubNumber=2']),
                      section('1800sub0', ['ParameterName=Entries', 'ObjectType=0x7',
                                           'DataType=0x0005', 'AccessType=ro',
                                           'DefaultValue=1']),
                      section('1800sub1', ['ParameterName=COB-ID', 'ObjectType=0x7',
                                           'DataType=0x0007', 'AccessType=rw',
                                           'DefaultValue=$NODEID+0x180']))
    gateway = make_gateway(simulation__devices=[NODE], simulation__eds=path)
    answer = gateway.call('sdo_read', node_id=NODE, index=0x1000)
    assert answer.success and bytes(answer.data) == bytes([0x92, 0x01, 0x02, 0x00]), answer


def test_a_dcf_s_values_of_a_compact_array_are_answered_by_the_simulated_device(
        make_gateway, tmp_path):
    path = quirk_file(tmp_path, section('6300', [
        'ParameterName=Outputs', 'ObjectType=0x8', 'DataType=0x0002', 'AccessType=rw',
        'DefaultValue=0x0', 'CompactSubObj=3']),
        section('6300Value', ['NrOfEntries=2', '1=0x11', '3=0xFF']), name='drive.dcf')
    gateway = make_gateway(simulation__devices=[NODE], simulation__eds=path)
    answers = [gateway.call('sdo_read', node_id=NODE, index=0x6300, subindex=sub)
               for sub in range(4)]
    assert [bytes(answer.data) for answer in answers] == [b'\x03', b'\x11', b'\x00', b'\xff'], \
        [answer.message for answer in answers]
