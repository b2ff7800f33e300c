"""cbcan_cli with value types and EDS names, against the installed cbcan_node in its own process.

The node runs simulated devices 2 and 5 (config/simulated_device.eds) on a virtual bus of its
own; node 5 has that EDS as its ``node_5.eds`` parameter, node 2 has none. Most commands run
in this process through one cbcan_cli client (a new client, let alone a new process, takes
1-2 s to find the gateway); one runs the installed executable.
"""

import subprocess
import uuid

import pytest

from cbcan_ros.core.values import decode_value, encode_value
from cbcan_ros.ros.cli import build_parser, Client, run

from conftest import new_channel
from node_process import EDS, executable, NodeProcess, START_TIMEOUT

HEARTBEAT = 'Producer heartbeat time'  # 0x1017, UNSIGNED16 in the EDS


@pytest.fixture(scope='module')
def gateway():
    """Start cbcan_node once for the module; return (its name, the process)."""
    namespace = f'/cli{uuid.uuid4().hex[:8]}'
    process = NodeProcess(['-r', f'__ns:={namespace}',
                           '-p', f'can.channel:={new_channel()}',
                           '-p', 'simulation.devices:=[2, 5]',
                           '-p', 'nodes:=[2, 5]',
                           '-p', f'node_5.eds:={EDS}'])
    yield f'{namespace}/cbcan', process
    process.close()


@pytest.fixture(scope='module')
def client(gateway):
    """Yield one cbcan_cli client of the gateway for the module (each finds it in 1-2 s)."""
    client = Client(gateway[0], START_TIMEOUT)
    yield client
    client.close()


@pytest.fixture
def cli(gateway, client, capsys):
    """Return ``cli(*arguments)``: run a cbcan_cli command; (status, stdout, stderr)."""
    def run_command(*arguments):
        status = run(client, build_parser().parse_args(arguments))
        out, err = capsys.readouterr()
        if 'no gateway at' in err:
            raise AssertionError(f'{err}\ncbcan_node output:\n{gateway[1].output()}')
        return status, out, err
    return run_command


@pytest.mark.parametrize('index, value_type, value_line', [
    ('0x1000', 'u32', 'value: 131474  (u32, 0x00020192)'),
    ('0x1000', 'i32', 'value: 131474  (i32, 0x00020192)'),
    ('0x2010', 'i32', 'value: -889275714  (i32, 0xCAFEBABE)'),
    ('0x2010', 'u32', 'value: 3405691582  (u32, 0xCAFEBABE)'),
    ('0x1001', 'u8', 'value: 0  (u8, 0x00)'),
    ('0x1008', 'str', "value: 'cbcan simulated device'  (str)"),
])
def test_sdo_read_decodes_the_answer_as_the_given_type(cli, index, value_type, value_line):
    status, out, err = cli('sdo-read', '5', index, '--type', value_type)
    assert status == 0, err
    assert value_line in out.splitlines(), out


def test_sdo_read_of_floats_reads_back_what_sdo_write_wrote(cli):
    status, out, err = cli('sdo-write', '5', '0x2002', '0', '-0.1', '--type', 'f32')
    assert status == 0, err
    assert '(CD CC CC BD)' in out, out  # -0.1 as IEEE 754 single, little-endian
    status, out, err = cli('sdo-read', '5', '0x2002', '--type', 'f32')
    assert (status, out.splitlines()[-1]) == (0, 'value: -0.1  (f32)'), out + err


@pytest.mark.parametrize('value_type, size', [('u16', 2), ('u64', 8), ('f64', 8), ('i8', 1)])
def test_a_type_of_another_size_is_an_error_naming_type_and_length(cli, value_type, size):
    status, out, err = cli('sdo-read', '5', '0x1000', '--type', value_type)
    assert status == 1, out + err
    assert f'type {value_type} takes {size} byte' in err and 'the answer has 4' in err, err
    assert out.splitlines() == ['data:  92 01 02 00  (4 bytes)'], out  # the bytes still shown


@pytest.mark.parametrize('arguments, what', [
    (('sdo-read', '5', '0x6000'), 'read node 5 object 0x6000:00'),
    (('sdo-write', '2', '0x6000', '0', '3', '--type', 'u8'), 'write node 2 object 0x6000:00')])
def test_an_abort_names_the_node_and_the_object(cli, arguments, what):
    # Once a new user's complaint: "error: SDO abort 0x06020000 NOT_EXIST" named neither.
    status, out, err = cli(*arguments)
    assert status == 1, out + err
    assert err.startswith(f'error: {what}: SDO abort 0x06020000 NOT_EXIST'), err


def test_lifecycle_of_a_plain_gateway_says_it_has_none(cli):
    status, out, err = cli('lifecycle', 'configure')
    assert status == 2, out + err
    assert 'is not a managed node' in err and 'cbcan_lifecycle_node' in err, err


def test_an_eds_name_reads_and_writes_with_the_eds_type(cli):
    status, out, err = cli('sdo-write', '5', HEARTBEAT, '1000')
    assert status == 0, err
    assert out.strip() == ('ok: wrote 2 bytes (E8 03) to node 5 object 0x1017:00 '
                           f'({HEARTBEAT})'), out
    status, out, err = cli('sdo-read', '5', 'producer HEARTBEAT time')  # any case
    assert status == 0, err
    assert out.splitlines() == [f'object: {HEARTBEAT} = 0x1017:00, UNSIGNED16',
                                'data:  E8 03  (2 bytes)',
                                'value: 1000  (u16, 0x03E8)'], out

    status, out, err = cli('sdo-write', '5', HEARTBEAT, '70000')
    assert status == 2, out
    assert "'70000' does not fit u16: allowed 0..65535" in err, err
    status, out, err = cli('sdo-read', '5', '0x1017')
    assert 'data:  E8 03  (2 bytes)' in out, out  # nothing was written

    status, out, err = cli('sdo-write', '5', 'Demo INTEGER32', '-7')
    assert status == 0, err
    status, out, err = cli('sdo-read', '5', 'Demo INTEGER32')
    assert out.splitlines()[-1] == 'value: -7  (i32, 0xFFFFFFF9)', out + err

    status, out, err = cli('sdo-write', '5', 'Demo VISIBLE_STRING', 'from', 'the', 'CLI')
    assert status == 0, err
    status, out, err = cli('sdo-read', '5', 'Demo VISIBLE_STRING')
    assert out.splitlines()[-1] == "value: 'from the CLI'  (str)", out + err


@pytest.mark.parametrize('words', [
    ['Identity object.Product code'],
    ['identity object.product code'],
    ['Identity object', 'Product code'],
    ['Identity object', '2'],
])
def test_record_entries_are_named_like_canopen_names_them(cli, words):
    status, out, err = cli('sdo-read', '5', *words)
    assert status == 0, err
    assert out.splitlines() == ['object: Identity object.Product code = 0x1018:02, UNSIGNED32',
                                'data:  51 00 00 00  (4 bytes)',
                                'value: 81  (u32, 0x00000051)'], out


def test_a_record_without_its_entry_lists_the_entries(cli):
    status, out, err = cli('sdo-read', '5', 'Identity object')
    assert status == 2, out
    assert "2 'Product code'" in err and '"Identity object.ENTRY"' in err, err


def test_an_unknown_name_lists_close_matches(cli):
    status, out, err = cli('sdo-read', '5', 'Producer hartbeat tme')
    assert (status, out) == (2, ''), out
    assert f"no object 'Producer hartbeat tme' in '{EDS}'" in err, err
    assert f"did you mean '{HEARTBEAT}'" in err, err

    status, out, err = cli('sdo-read', '5', 'heartbeat')  # a part of the name
    assert f"did you mean '{HEARTBEAT}'" in err, err

    status, out, err = cli('sdo-write', '5', 'Identity object', 'Serial nmber', '1')
    assert status == 2, out
    assert "has no entry 'Serial nmber'; did you mean 'Serial number'" in err, err


def test_long_input_is_not_echoed_back(cli):
    status, out, err = cli('sdo-read', '5', 'Demo ' * 20_000)
    assert status == 2 and 'no object' in err, err
    assert len(err) < 500, f'{len(err)} characters of error'
    status, out, err = cli('sdo-write', '5', HEARTBEAT, '9' * 100_000)
    assert status == 2 and 'is too long for a number (100000 characters)' in err, err
    assert len(err) < 500, f'{len(err)} characters of error'


def test_the_eds_option_names_objects_of_a_node_without_eds_parameter(cli):
    status, out, err = cli('sdo-read', '2', 'Demo UNSIGNED16')
    assert status == 2, out
    assert 'parameter node_2.eds is empty' in err and '--eds FILE' in err, err

    status, out, err = cli('sdo-read', '2', 'Demo UNSIGNED16', '--eds', EDS)
    assert status == 0, err
    assert out.splitlines()[-1] == 'value: 4660  (u16, 0x1234)', out

    status, out, err = cli('sdo-read', '2', 'Demo UNSIGNED16', '--eds', '/nonexistent/x.eds')
    assert status == 2, out
    assert "--eds '/nonexistent/x.eds': no such file" in err, err

    status, out, err = cli('sdo-read', '7', 'Demo UNSIGNED16')  # not in nodes: no parameter
    assert status == 2, out
    assert 'has no parameter node_7.eds' in err, err


def test_the_installed_cli_reads_by_eds_name(gateway):
    name, process = gateway
    cli = subprocess.run([executable('cbcan_cli'), '--gateway', name,
                          '--wait', str(START_TIMEOUT), 'sdo-read', '5', 'Demo UNSIGNED8'],
                         capture_output=True, text=True, timeout=START_TIMEOUT + 30)
    assert cli.returncode == 0, cli.stdout + cli.stderr + process.output()
    assert cli.stdout.splitlines()[-1] == 'value: 18  (u8, 0x12)', cli.stdout


@pytest.mark.parametrize('content, reason', [
    (None, 'no such file'),
    ('hello\n', 'is not an EDS or DCF file canopen can read'),
    ('', 'defines no objects'),
])
def test_a_bad_eds_parameter_stops_the_node_naming_parameter_and_file(
        start_node, tmp_path, content, reason):
    path = tmp_path / 'device.eds'
    if content is not None:
        path.write_text(content)
    node = start_node(['-p', f'can.channel:={new_channel()}', '-p', 'node_guarding:=[9]',
                       '-p', f'node_9.eds:={path}'])
    status = node.wait(START_TIMEOUT)
    output = node.output()
    assert status == 1, output
    assert f"parameter node_9.eds: '{path}'" in output and reason in output, output
    assert 'Traceback' not in output, output


@pytest.mark.parametrize('value_type, word, value', [
    ('u8', '255', 255), ('i8', '-128', -128), ('u24', '0xFFFFFF', 0xFFFFFF),
    ('i16', '-0x8000', -0x8000), ('u64', str(2**64 - 1), 2**64 - 1),
    ('i64', str(-2**63), -2**63), ('f32', '0.1', 0.1), ('f64', '-2.5e-300', -2.5e-300),
    ('str', 'grüße', 'grüße'), ('hex', '0a 0B', b'\x0a\x0b'),
])
def test_every_value_type_decodes_what_it_encodes(value_type, word, value):
    assert decode_value(encode_value([word], value_type), value_type) == value


@pytest.mark.parametrize('value_type, word, message', [
    ('u8', '256', 'allowed 0..255'),
    ('i64', str(2**63), f'allowed {-2**63}..{2**63 - 1}'),
    ('f32', '1e39', 'does not fit f32'),
    ('f64', 'one', 'is not a number'),
    ('hex', '0x12', 'type hex takes the bytes as on the bus'),
])
def test_a_value_that_does_not_fit_its_type_is_refused(value_type, word, message):
    with pytest.raises(ValueError, match=message):
        encode_value([word], value_type)
