"""cbcan_cli pdo-echo and pdo-write against the installed cbcan_node with `make run`'s devices.

The node runs the simulated devices of ``make run`` (canopen LocalNodes with the PDOs of
config/simulated_device.eds: TPDO 1 and 2 every 100 ms while operational, RPDO 1 into their
objects), node 5 with that EDS as ``node_5.eds``, node 2 without.
"""

import contextlib
import io
import uuid

import pytest

from cbcan_ros.ros.cli import build_parser, Client, run

from conftest import new_channel, wait_until
from node_process import EDS, NodeProcess, START_TIMEOUT


@pytest.fixture(scope='module')
def cli_run():
    """Start cbcan_node once; return ``cli(capsys, *arguments) -> (status, out, err)``."""
    namespace = f'/pdocli{uuid.uuid4().hex[:8]}'
    process = NodeProcess(['-r', f'__ns:={namespace}', '-p', f'can.channel:={new_channel()}',
                           '-p', 'simulation.devices:=[2, 5]', '-p', 'nodes:=[2, 5]',
                           '-p', 'pdo.nodes:=[2, 5]', '-p', f'node_5.eds:={EDS}'])
    client = Client(f'{namespace}/cbcan', START_TIMEOUT)

    def mapping_of_5_read() -> bool:
        # A value out of range is refused before anything is sent, by the mapping once read.
        with contextlib.redirect_stdout(io.StringIO()), \
                contextlib.redirect_stderr(io.StringIO()) as err:
            run(client, build_parser().parse_args(['pdo-write', '5', '1',
                                                   'Demo UNSIGNED8=256']))
        return 'not read yet' not in err.getvalue()
    # Tests run in any order on either worker: none may find the mapping still being read.
    wait_until(mapping_of_5_read, START_TIMEOUT, "node 5's PDO mapping read")

    def cli(capsys, *arguments):
        status = run(client, build_parser().parse_args(arguments))
        out, err = capsys.readouterr()
        if 'no gateway at' in err:
            raise AssertionError(f'{err}\ncbcan_node output:\n{process.output()}')
        return status, out, err

    yield cli
    client.close()
    process.close()


def test_pdo_echo_prints_what_an_operational_device_sends_by_its_eds_names(cli_run, capsys):
    for node in ('5', '2'):
        assert cli_run(capsys, 'nmt', node, 'start')[0] == 0
    status, out, err = cli_run(capsys, 'pdo-echo', '5', '--count', '4')
    assert status == 0, err
    lines = out.splitlines()
    assert len(lines) == 4
    assert ('TPDO 1 0x185 [6] 34 12 FE FF FF FF | Demo UNSIGNED16=4660 Demo INTEGER32=-2'
            in lines), lines
    assert 'TPDO 2 0x285 [4] 78 56 34 12 | Demo UNSIGNED32=305419896' in lines, lines
    # Without an EDS: entries by index, unsigned numbers of their mapped length.
    status, out, err = cli_run(capsys, 'pdo-echo', '2', '--count', '4')
    assert ('TPDO 1 0x182 [6] 34 12 FE FF FF FF | 0x2001:0=4660 0x2003:0=4294967294'
            in out.splitlines()), out


def test_pdo_write_by_name_and_index_changes_the_device(cli_run, capsys):
    assert cli_run(capsys, 'nmt', '5', 'start')[0] == 0
    status, out, err = cli_run(capsys, 'pdo-write', '5', '1', 'Demo UNSIGNED8=7',
                               '0x2001:0=300')
    assert (status, out.strip()) == (0, 'ok: RPDO 1 of node 5 sent'), err

    def read(index):
        return cli_run(capsys, 'sdo-read', '5', index, '--type', 'u16' if index == '0x2001'
                       else 'u8')[1]
    wait_until(lambda: 'value: 300 ' in read('0x2001'), 5.0, 'RPDO 1 applied')
    assert 'value: 7 ' in read('0x2000')


@pytest.mark.parametrize('arguments, words', [
    (['5', '1', 'Demo UNSIGNED8=256'], ['0x2000:0', '256', '0..255']),
    (['5', '1', 'No such object=1'], ['no object', 'No such object']),
    (['5', '1', '0x2001=abc'], ['abc', 'not a number']),
    (['5', '1'], ['assignments or --data']),
    (['5', '7', '0x2001=1'], ['no RPDO 7']),
    (['9', '1', '0x2001=1'], ['node_id 9', 'pdo.nodes']),
])
def test_pdo_write_refusals_say_what_is_wrong(cli_run, capsys, arguments, words):
    status, out, err = cli_run(capsys, 'pdo-write', *arguments)
    assert status in (1, 2) and not out
    for word in words:
        assert word in err, err
