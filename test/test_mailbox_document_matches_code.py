"""docs/plc_mailbox_formats.md and cbcan_ros/plc/mailbox.py say the same.

A PLC programmer works from the document's tables alone: every code table (registers, commands,
result and status codes, NMT codes and states, abort codes) is parsed here and compared with the
constants of the mailbox, so that neither can change without the other.
"""

import asyncio
import pathlib
import re

import pytest

from cbcan_ros.core import nmt
from cbcan_ros.core.sdo import abort_codes
from cbcan_ros.core.sdo.request_queue import resolved
from cbcan_ros.core.sdo.requests import SdoResult
from cbcan_ros.plc import mailbox
from cbcan_ros.plc.mailbox import Cbcan, Mailbox, Me3can

ROOT = pathlib.Path(__file__).resolve().parent.parent
DOCUMENT = ROOT / 'docs' / 'plc_mailbox_formats.md'
SOURCE = ROOT / 'cbcan_ros' / 'plc' / 'mailbox.py'


def read_tables(text: str) -> dict:
    """Return {heading: [table, ...]}, each table a list of {header: cell} rows, `` removed."""
    tables: dict = {}
    heading, lines = None, []
    for line in text.splitlines() + ['']:
        if line.startswith('|'):
            lines.append([cell.strip().replace('`', '') for cell in line.strip('|').split('|')])
            continue
        if lines:
            header, rows = lines[0], lines[2:]  # lines[1] is the |---| separator
            rows = [dict(zip(header, row, strict=True)) for row in rows]
            tables.setdefault(heading, []).append(rows)
            lines = []
        if line.startswith('#'):
            heading = line.lstrip('#').strip()
    return tables


TABLES = read_tables(DOCUMENT.read_text(encoding='utf-8'))


def table(heading: str, number: int = 0) -> list:
    """Return the rows of the ``number``-th table under ``heading``."""
    assert heading in TABLES, f'no table under the heading "{heading}" in {DOCUMENT.name}'
    return TABLES[heading][number]


def number(cell: str) -> int:
    """Return a decimal or 0x-hexadecimal cell as an int."""
    return int(cell, 0)


def span(cell: str, prefix: str = '') -> range:
    """Return 'R3706..R3769' or '6..69' (without ``prefix``) as a range; one value too."""
    first, _, last = cell.partition('..')
    first = int(first.removeprefix(prefix))
    return range(first, int((last or str(first)).removeprefix(prefix)) + 1)


def test_summaries_give_the_block_sizes():
    for heading, block_type in (('Format `cbcan`: Fatek FBs-CBCAN, R3700..R3769', Cbcan),
                                ('Format `me3can`: Mitsubishi ME3CAN1-L command interface, '
                                 'Un\\G1000..Un\\G1066', Me3can)):
        [row] = table(heading)
        assert (number(row['words']), row['registers']) == (block_type.LENGTH,
                                                            block_type.REGISTERS)
    [cbcan] = table('Format `cbcan`: Fatek FBs-CBCAN, R3700..R3769')
    assert cbcan['largest object'] == f'{Cbcan.MAX_SIZE} bytes'
    [me3can] = table('Format `me3can`: Mitsubishi ME3CAN1-L command interface, '
                     'Un\\G1000..Un\\G1066')
    assert me3can['largest object'] == (f'single read: {Me3can.SINGLE_MAX_SIZE} bytes; '
                                        f'multi: {Me3can.BLOCK_MAX_SIZE} bytes a block')


@pytest.mark.parametrize('heading, block_type, letter, first, data_words', [
    ('cbcan register layout', Cbcan, 'R', 3700, Cbcan.DATA_WORDS),
    ('me3can single SDO read', Me3can, 'G', 1000, Me3can.SINGLE_DATA_WORDS),
])
def test_register_layout_matches_the_word_positions(heading, block_type, letter, first,
                                                    data_words):
    rows = table(heading)
    covered = []
    for row in rows:
        words = span(row['word'])
        assert span(row['register'], letter) == range(first + words[0], first + words[-1] + 1)
        assert getattr(block_type, row['name']) == words[0], row
        covered += words
    assert covered == list(range(block_type.LENGTH))
    assert len(span(rows[-1]['word'])) == data_words


def test_cbcan_commands_are_the_accepted_ones():
    rows = table('cbcan commands')
    services = {'SDO read': Cbcan.SDO_READ, 'SDO write': Cbcan.SDO_WRITE}
    documented = {}
    for row in rows:
        alias = number(row['also accepted'].split()[0])
        documented[number(row['R3701 (decimal)'])] = services[row['service']]
        documented[alias] = services[row['service']]
    assert documented == mailbox.CBCAN_COMMANDS


def test_cbcan_result_codes_are_the_constants():
    rows = table('cbcan result codes')
    assert {row['name']: number(row['R3700']) for row in rows} == {
        name: getattr(Cbcan, name) for name in ('OK', 'CMD_CODE_ERR', 'NODE_ID_ERR',
                                                'SDO_EXEC_ERR')}


def test_cbcan_nmt_objects_are_the_constants():
    command = table(f'NMT command: SDO write to 0x{Cbcan.NMT_COMMAND_INDEX:04X}')
    [target] = [row for row in command if row['register'] == 'R3704']
    assert f'or {Cbcan.ALL_NODES} for all nodes' in target['the PLC writes']
    state = table(f'NMT state: SDO read of 0x{Cbcan.NMT_STATE_INDEX:04X}')
    [size] = [row for row in state if row['register'] == 'R3705']
    assert number(size['the gateway answers']) == Cbcan.NMT_STATE_SIZE


def test_cbcan_nmt_command_codes_map_to_the_cia301_specifiers():
    documented = {}
    for row in table('cbcan NMT command codes'):
        specifier = getattr(nmt, row['command'])
        assert number(row['also accepted (CiA 301)']) == specifier
        assert row['frame on COB-ID 0 for node 5'] == f'{specifier:02X} 05'
        documented[number(row['Fatek code'])] = specifier
        documented[specifier] = specifier
    assert documented == mailbox.CBCAN_NMT_COMMANDS


def test_cbcan_nmt_state_values_are_the_states():
    rows = table('cbcan NMT state values')
    assert {row['name']: number(row['R3706']) for row in rows} == {
        name: getattr(nmt, name) for name in ('STOPPED', 'PRE_OPERATIONAL', 'OPERATIONAL',
                                              'NOT_DETECTED')}


ME3CAN_CODES = ('SDO_READ', 'SDO_READ_OK', 'MULTI_WRITE', 'MULTI_WRITE_OK',
                'MULTI_WRITE_BLOCK_ERROR', 'MULTI_READ', 'MULTI_READ_OK',
                'MULTI_READ_BLOCK_ERROR', 'ERROR')


def test_me3can_codes_are_the_constants():
    commands, answers = TABLES['me3can command and status codes']
    documented = {row['name']: number(row['G1000 request']) for row in commands}
    documented.update({row['name']: number(row['G1000 answer']) for row in answers})
    assert documented == {name: getattr(Me3can, name) for name in ME3CAN_CODES}


class _Core:
    """A core whose every SDO succeeds with two bytes, or aborts with 0x06020000."""

    def __init__(self, succeed: bool):
        self._result = SdoResult.ok(b'\x01\x02') if succeed else SdoResult.aborted(0x06020000)

    def sdo_read(self, *args, **kwargs):
        return resolved(self._result)

    sdo_write = sdo_read


def me3can_status(command: int, succeed: bool) -> int:
    """Return G1000 after ``command`` with one block (node 5, 0x2002:0, 2 bytes)."""
    block = [command, 5, 0x2002, 0, 2, 0x0201, 0, 0, 0, Me3can.END_OF_LIST] + [0] * 57
    answer, _ = asyncio.run(Mailbox(_Core(succeed), asyncio.wrap_future).execute('me3can',
                                                                                  block))
    return answer[0]


@pytest.mark.parametrize('row', table('me3can command and status codes'),
                         ids=lambda row: row['name'])
def test_me3can_commands_answer_the_documented_status(row):
    command = number(row['G1000 request'])
    assert me3can_status(command, True) == number(row['G1000 when everything succeeded'])
    failed = row['G1000 when a block failed'] or row['G1000 on error']
    assert me3can_status(command, False) == number(failed)


def test_me3can_block_layout_matches_the_constants():
    layout = table('me3can block layout')
    assert [span(row['word in block']) for row in layout][-1] == range(
        4, 4 + Me3can.BLOCK_DATA_WORDS)
    assert f'0x{Me3can.END_OF_LIST:04X} to end the list' in layout[0]['the PLC writes']
    assert layout[0]['the gateway answers: failure'] == f'0x{Me3can.FAILED_NODE:04X} + node id'
    assert f'1..{Me3can.BLOCK_MAX_SIZE} bytes' in layout[3]['the PLC writes']
    rows = table('me3can block registers')
    assert [number(row['block']) for row in rows] == list(range(1, Me3can.BLOCKS + 1))
    for row in rows:
        first = 1000 + Me3can.FIRST_BLOCK + (number(row['block']) - 1) * Me3can.BLOCK_WORDS
        fields = [row[name] for name in ('node', 'index', 'sub-index', 'length')]
        assert fields == [f'G{first + offset}' for offset in range(4)]
        assert span(row['data'], 'G') == range(first + 4, first + 4 + Me3can.BLOCK_DATA_WORDS)


def test_abort_code_table_names_every_code_the_mailbox_produces():
    rows = table('Abort codes the gateway produces')
    documented = {number(row['code']): row['name'] for row in rows}
    assert documented == {code: abort_codes.NAMES[code] for code in documented}
    used = {getattr(abort_codes, name) for name in
            re.findall(r'abort_codes\.([A-Z_]+)', SOURCE.read_text(encoding='utf-8'))}
    # and those the core answers for the mailbox: timeout, too long, busy, write protection
    used |= {abort_codes.TIMEOUT, abort_codes.OUT_OF_MEMORY, abort_codes.NO_RESOURCE,
             abort_codes.LOCAL_CONTROL}
    assert used == set(documented)
