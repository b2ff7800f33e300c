"""The PLC register mailbox (formats cbcan and me3can) through the ROS service.

Every rule of docs/plc_mailbox_formats.md is checked here against simulated devices 2, 3 and 5
(write protection in test_write_protection.py, a bus going down in test_bus_faults.py); its code
tables are checked against mailbox.py in test_mailbox_document_matches_code.py. Every answer is
compared register by register with the whole block the PLC would read back.
"""

import asyncio
import struct
import time

import can
import pytest

from cbcan_ros.core.sdo.request_queue import resolved
from cbcan_ros.core.sdo.requests import SdoResult
from cbcan_ros.plc.mailbox import Mailbox

from conftest import wait_until

FLAG = 0xCA0E
READ = 5055
WRITE = 5066
FILL = 0xEEEE  # stale data in the data area: must be overwritten by a read, kept otherwise

ME3_READ = 0x0004
ME3_MULTI_WRITE = 0x0006
ME3_MULTI_READ = 0x0008
END = 0xFFFF

U32_5 = struct.pack('<I', 0x12345678)  # 0x2002 of every simulated device at boot


def words(data: bytes, count: int) -> list:
    """Return ``data`` as ``count`` little-endian words (test's own packing), zero padded."""
    data = bytes(data) + bytes(2 * count - len(data))
    return list(struct.unpack(f'<{count}H', data))


def cbcan(command=READ, node=5, index=0x2002, sub=0, size=4, data=(), flag=FLAG, fill=0):
    """Return a 70-word cbcan block; data words after ``data`` hold ``fill``."""
    data = list(data)
    return [flag, command, node, index, sub, size] + data + [fill] * (64 - len(data))


def changed(block, **registers):
    """Return a copy of a cbcan block with registers changed, e.g. R3700=4."""
    answer = list(block)
    for name, value in registers.items():
        answer[int(name[1:]) - 3700] = value
    return answer


def aborted(block, code):
    """Return the cbcan answer to ``block`` for result 4 with abort ``code``."""
    return changed(block, R3700=4, R3706=code & 0xFFFF, R3707=code >> 16)


def call(gateway, registers, block_format='cbcan'):
    """Call the mailbox service; return (registers, message)."""
    response = gateway.call('plc_mailbox', format=block_format, registers=registers)
    return list(response.registers), response.message


def core_read(gateway, node, index, sub=0) -> bytes:
    """Read an object through the SDO service (not the mailbox)."""
    response = gateway.call('sdo_read', node_id=node, index=index, subindex=sub)
    assert response.success, response.message
    return bytes(response.data)


def nmt_frames(bus, count: int, timeout: float = 5.0) -> list:
    """Collect the data of ``count`` frames on COB-ID 0 (NMT), or fewer after ``timeout``."""
    frames = []
    deadline = time.monotonic() + timeout
    while len(frames) < count and time.monotonic() < deadline:
        message = bus.recv(0.1)
        if message is not None and message.arbitration_id == 0:
            frames.append(list(message.data))
    return frames


def assert_no_nmt_frame_before_marker(gateway, bus):
    """Send a marker NMT command (start node 99) and check it is the first NMT frame."""
    assert gateway.call('nmt_command', node_id=99, command=1).success
    assert nmt_frames(bus, 1) == [[0x01, 99]]


def nmt_state_block(node):
    """Return the cbcan block reading the NMT state of ``node`` (0x300C)."""
    return cbcan(READ, node, 0x300C, 0, 0, fill=FILL)


# ----------------------------------------------------------------------------- cbcan: SDO


def test_u32_reads_back_low_word_first(gateway):
    block = cbcan(READ, 5, 0x2002, 0, 128, fill=FILL)
    registers, message = call(gateway, block)
    assert message == ''
    assert registers[:8] == [0, READ, 5, 0x2002, 0, 4, 0x5678, 0x1234]
    assert registers[8:] == [0] * 62  # nothing stale after the data


@pytest.mark.parametrize('command, node, index, sub, size, data', [
    (READ, 5, 0x2000, 0, 128, b'\x12'),
    (READ, 5, 0x2001, 0, 2, struct.pack('<H', 0x1234)),
    (READ, 5, 0x2003, 0, 4, struct.pack('<i', -2)),
    (READ, 2, 0x1000, 0, 4, struct.pack('<I', 0x00020192)),
    (READ, 3, 0x1008, 0, 128, b'cbcan simulated device'),
    (READ, 2, 0x2021, 0, 18, b'hello from the bus'),  # exactly R3705 bytes
    (0x5055, 5, 0x2002, 0, 4, U32_5),  # the hexadecimal alias
    (READ, 0, 0x1018, 2, 4, struct.pack('<I', 0xCBCA)),  # the gateway's own dictionary
    (READ, 0, 0x1008, 0, 128, b'cbcan_ros gateway'),
    (READ, 0, 0x1017, 0, 2, b'\x00\x00'),
])
def test_cbcan_read(gateway, command, node, index, sub, size, data):
    block = cbcan(command, node, index, sub, size, fill=FILL)
    registers, message = call(gateway, block)
    assert message == ''
    assert registers == [0, command, node, index, sub, len(data)] + words(data, 64)


@pytest.mark.parametrize('command, node, index, data', [
    (WRITE, 5, 0x2000, b'\x7f'),
    (WRITE, 5, 0x2001, struct.pack('<H', 0xBEEF)),
    (WRITE, 5, 0x2002, struct.pack('<I', 0xCAFEF00D)),
    (0x5066, 3, 0x2002, struct.pack('<I', 0x0BADCAFE)),  # the hexadecimal alias
    (WRITE, 5, 0x2003, struct.pack('<i', -123456)),
    (WRITE, 2, 0x2021, b'odd 5'),  # odd length: the high byte of the last word is unused
    (WRITE, 5, 0x2020, bytes(range(100, 228))),  # 128 bytes, the most a block carries
    (WRITE, 0, 0x1017, struct.pack('<H', 500)),  # the gateway's own dictionary
])
def test_cbcan_write_then_read_back(gateway, command, node, index, data):
    block = cbcan(command, node, index, 0, len(data), words(data, 64))
    if len(data) % 2:
        block[6 + len(data) // 2] |= 0xAB00  # a byte beyond R3705 must not be written
    registers, message = call(gateway, block)
    assert message == ''
    assert registers == changed(block, R3700=0)
    assert core_read(gateway, node, index) == data
    registers, message = call(gateway, cbcan(READ, node, index, 0, 128, fill=FILL))
    assert message == ''
    assert registers[5:] == [len(data)] + words(data, 64)


def test_empty_format_is_cbcan(gateway):
    registers, message = call(gateway, cbcan(READ, 5, 0x2002, 0, 4), block_format='')
    assert message == ''
    assert registers[:8] == [0, READ, 5, 0x2002, 0, 4, 0x5678, 0x1234]


@pytest.mark.parametrize('block, answer, says', [
    # R3700 not the execute flag: nothing runs, the block comes back unchanged
    (cbcan(flag=0), 'unchanged', 'execute flag'),
    (cbcan(flag=0xCA0F), 'unchanged', 'execute flag'),
    (cbcan(flag=4), 'unchanged', 'execute flag'),
    # R3701 not a command: result 1
    (cbcan(command=1234), dict(R3700=1), '5055'),
    (cbcan(command=5056), dict(R3700=1), '5055'),
    (cbcan(command=0x1F82, index=0x1F82), dict(R3700=1), '5066'),
    # node id above 127: result 2
    (cbcan(node=128), dict(R3700=2), 'R3702'),
    (cbcan(WRITE, node=0xFFFF, data=[1, 2]), dict(R3700=2), 'R3702'),
    # R3705 of 0 or above 128: ABORT_SYS_LENGTH
    (cbcan(size=0), 0x06040047, 'R3705'),
    (cbcan(size=129), 0x06040047, 'R3705'),
    (cbcan(WRITE, size=0, data=[1, 2]), 0x06040047, 'R3705'),
    (cbcan(WRITE, size=200, data=[1, 2]), 0x06040047, 'R3705'),
    # sub-index above 255
    (cbcan(sub=256), 0x06090011, 'R3704'),
    # object longer than R3705: ABORT_READ_LENGTH, nothing partial
    (cbcan(size=2, fill=FILL), 0x05040005, 'OUT_OF_MEMORY'),
    (cbcan(size=3, fill=FILL), 0x05040005, 'OUT_OF_MEMORY'),
    (cbcan(index=0x2020, size=128, fill=FILL), 0x05040005, 'OUT_OF_MEMORY'),
    (cbcan(index=0x1008, size=21, fill=FILL), 0x05040005, 'OUT_OF_MEMORY'),
    (cbcan(node=0, index=0x1008, size=16, fill=FILL), 0x05040005, 'OUT_OF_MEMORY'),
    # SDO aborts from the device, and from the gateway's own dictionary
    (cbcan(index=0x6000, fill=FILL), 0x06020000, 'NOT_EXIST'),
    (cbcan(index=0x1018, sub=9, fill=FILL), 0x06090011, 'SUBINDEX_NOT_EXIST'),
    (cbcan(index=0x2011, fill=FILL), 0x06010001, 'WRITE_ONLY'),
    (cbcan(WRITE, index=0x2010, data=[1, 2]), 0x06010002, 'READ_ONLY'),
    (cbcan(WRITE, index=0x2002, size=2, data=[1]), 0x06070010, 'TYPE_MISMATCH'),
    (cbcan(node=0, index=0x6000), 0x06020000, 'NOT_EXIST'),
    (cbcan(WRITE, node=0, index=0x1018, sub=2, data=[1, 2]), 0x06010002, 'READ_ONLY'),
    # an SDO read of 0x1F82 and an SDO write to 0x300C are SDOs of the node, not NMT services
    (cbcan(index=0x1F82, sub=128, fill=FILL), 0x06020000, 'NOT_EXIST'),
    (cbcan(WRITE, index=0x300C, data=[1, 2]), 0x06020000, 'NOT_EXIST'),
    # no answer: ABORT_TIME_OUT
    (cbcan(node=9, fill=FILL), 0x05040000, 'TIMEOUT'),
    (cbcan(WRITE, node=9, data=[1, 2]), 0x05040000, 'TIMEOUT'),
    # NMT command (0x1F82): sub-index 0 or above 128 -> result 2; unknown command -> abort
    (cbcan(WRITE, 5, 0x1F82, 0, 0, [1]), dict(R3700=2), 'R3704'),
    (cbcan(WRITE, 5, 0x1F82, 129, 0, [1]), dict(R3700=2), 'R3704'),
    (cbcan(WRITE, 5, 0x1F82, 255, 0, [1]), dict(R3700=2), 'R3704'),
    (cbcan(WRITE, 5, 0x1F82, 300, 0, [1]), dict(R3700=2), 'R3704'),
    (cbcan(WRITE, 5, 0x1F82, 5, 0, [3]), 0x06090030, 'R3706'),
    (cbcan(WRITE, 5, 0x1F82, 5, 0, [0]), 0x06090030, 'R3706'),
    (cbcan(WRITE, 5, 0x1F82, 128, 0, [131]), 0x06090030, 'R3706'),
    (cbcan(WRITE, 5, 0x1F82, 128, 0, [0x0101]), 0x06090030, 'R3706'),
    # NMT state (0x300C): node 0 or above 127 -> result 2; sub-index other than 0
    (cbcan(READ, 0, 0x300C, 0, 0), dict(R3700=2), 'R3702'),
    (cbcan(READ, 128, 0x300C, 0, 0), dict(R3700=2), 'R3702'),
    (cbcan(READ, 5, 0x300C, 1, 0, fill=FILL), 0x06090011, 'R3704'),
])
def test_cbcan_errors(gateway, block, answer, says):
    bus = gateway.raw_bus()
    try:
        registers, message = call(gateway, block)
        if answer == 'unchanged':
            expected = block
        elif isinstance(answer, dict):
            expected = changed(block, **answer)
        else:
            expected = aborted(block, answer)
        assert registers == expected
        assert says in message
        assert_no_nmt_frame_before_marker(gateway, bus)
    finally:
        bus.shutdown()


def test_failed_write_leaves_the_object_unchanged(gateway):
    block = cbcan(WRITE, 5, 0x2002, 0, 2, [0xAAAA])
    registers, message = call(gateway, block)
    assert registers == aborted(block, 0x06070010)
    assert core_read(gateway, 5, 0x2002) == U32_5


# ----------------------------------------------------------------------------- cbcan: NMT

NMT_PAIRS = [(5, 0x01), (1, 0x01), (4, 0x02), (2, 0x02), (127, 0x80), (128, 0x80),
             (6, 0x81), (129, 0x81), (7, 0x82), (130, 0x82)]


@pytest.mark.parametrize('target, wire_node', [(5, 5), (127, 127), (128, 0)])
@pytest.mark.parametrize('code, wire_command', NMT_PAIRS)
def test_nmt_command_sends_the_cia301_frame(gateway, code, wire_command, target, wire_node):
    bus = gateway.raw_bus()
    try:
        block = cbcan(WRITE, 77, 0x1F82, target, 0, [code])  # R3702 is ignored
        registers, message = call(gateway, block)
        assert message == ''
        assert registers == changed(block, R3700=0)
        assert nmt_frames(bus, 1) == [[wire_command, wire_node]]
    finally:
        bus.shutdown()


def test_fatek_worked_example_starts_all_nodes(gateway):
    gateway.wait_for_states({2: 'PRE_OPERATIONAL', 3: 'PRE_OPERATIONAL',
                             5: 'PRE_OPERATIONAL'})
    bus = gateway.raw_bus()
    try:
        block = [0] * 70
        block[1], block[3], block[4], block[6] = 5066, 0x1F82, 128, 5
        block[0] = 0xCA0E
        registers, message = call(gateway, block)
        assert message == ''
        assert registers == [0, 5066, 0, 0x1F82, 128, 0, 5] + [0] * 63
        assert nmt_frames(bus, 1) == [[0x01, 0x00]]
    finally:
        bus.shutdown()
    gateway.wait_for_states({2: 'OPERATIONAL', 3: 'OPERATIONAL', 5: 'OPERATIONAL'})
    assert [gateway.device(n).state for n in (2, 3, 5)] == [5, 5, 5]


@pytest.mark.parametrize('code, name, value', [
    (5, 'OPERATIONAL', 5), (1, 'OPERATIONAL', 5),
    (4, 'STOPPED', 4), (2, 'STOPPED', 4),
    (127, 'PRE_OPERATIONAL', 127), (128, 'PRE_OPERATIONAL', 127),
])
def test_nmt_state_after_a_command(gateway, code, name, value):
    gateway.wait_for_states({5: 'PRE_OPERATIONAL', 3: 'PRE_OPERATIONAL'})
    registers, message = call(gateway, cbcan(WRITE, 0, 0x1F82, 5, 0, [code]))
    assert (registers[0], message) == (0, '')
    gateway.wait_for_states({5: name})
    block = nmt_state_block(5)
    registers, message = call(gateway, block)
    assert message == ''
    assert registers == [0, READ, 5, 0x300C, 0, 2, value] + [0] * 63
    registers, _ = call(gateway, nmt_state_block(3))  # the others are untouched
    assert registers[6] == 127


def test_nmt_state_of_a_booted_device_is_pre_operational(gateway):
    gateway.wait_for_states({2: 'PRE_OPERATIONAL'})
    registers, message = call(gateway, nmt_state_block(2))
    assert message == ''
    assert registers == [0, READ, 2, 0x300C, 0, 2, 127] + [0] * 63


def test_nmt_state_of_a_never_seen_node_is_not_detected(gateway):
    registers, message = call(gateway, nmt_state_block(9))
    assert message == ''
    assert registers == [0, READ, 9, 0x300C, 0, 2, 6] + [0] * 63


@pytest.mark.parametrize('node, reported, answered', [
    (20, 0, 127),  # seen only booting: after its boot-up message a node is pre-operational
    (21, 0x42, 0x42),  # a state byte CiA 301 does not define is passed on as it is
])
def test_nmt_state_is_the_state_the_node_reported(gateway, node, reported, answered):
    bus = gateway.raw_bus()
    try:
        bus.send(can.Message(arbitration_id=0x700 + node, data=[reported],
                             is_extended_id=False))
        wait_until(lambda: gateway.node.gateway.monitor.status(node).last_seen is not None,
                   5.0, f'the heartbeat of node {node}')
        assert gateway.node.gateway.monitor.status(node).state == reported
        registers, message = call(gateway, nmt_state_block(node))
        assert message == ''
        assert registers == [0, READ, node, 0x300C, 0, 2, answered] + [0] * 63
    finally:
        bus.shutdown()


def test_nmt_state_ignores_r3705(gateway):
    gateway.wait_for_states({5: 'PRE_OPERATIONAL'})
    block = cbcan(0x5055, 5, 0x300C, 0, 1000)
    registers, message = call(gateway, block)
    assert message == ''
    assert registers == [0, 0x5055, 5, 0x300C, 0, 2, 127] + [0] * 63


# ----------------------------------------------------------------------------- me3can


def me3(command, *words_, fill=0):
    """Return a 67-word me3can block: G1000 = command, then ``words_``, then ``fill``."""
    return [command] + list(words_) + [fill] * (66 - len(words_))


def me3_blocks(command, blocks, fill=0):
    """Return a multi block from up to 8 (node, index, sub, length, data bytes) tuples."""
    block = [command]
    for node, index, sub, length, data in blocks:
        block += [node, index, sub, length] + words(data, 4)
    return block + [fill] * (67 - len(block))


@pytest.mark.parametrize('node, index, sub, data', [
    (5, 0x2002, 0, U32_5),
    (5, 0x2000, 0, b'\x12'),
    (3, 0x1008, 0, b'cbcan simulated device'),
    (2, 0x2021, 0, b'hello from the bus'),
    (0, 0x1018, 2, struct.pack('<I', 0xCBCA)),
])
def test_me3can_single_read(gateway, node, index, sub, data):
    registers, message = call(gateway, me3(ME3_READ, node, index, sub, fill=FILL), 'me3can')
    assert message == ''
    assert registers == [0x0005, node, index, sub, len(data)] + words(data, 62)


def test_me3can_single_read_ignores_the_reserved_high_byte(gateway):
    registers, message = call(gateway, me3(ME3_READ, 0, 0x1018, 0x5A02), 'me3can')
    assert message == ''
    assert registers == [0x0005, 0, 0x1018, 2, 4, 0xCBCA] + [0] * 61


def test_me3can_single_read_takes_124_bytes_but_not_125(gateway):
    for size, answer in ((124, 0x0005), (125, 0x000F)):
        data = bytes(range(7, 7 + size))
        written = gateway.call('sdo_write', node_id=5, index=0x2020, subindex=0,
                               data=list(data))
        assert written.success, written.message
        block = me3(ME3_READ, 5, 0x2020, 0, fill=FILL)
        registers, message = call(gateway, block, 'me3can')
        if answer == 0x0005:
            assert message == ''
            assert registers == [0x0005, 5, 0x2020, 0, 124] + words(data, 62)
        else:
            assert registers == [0x000F] + block[1:]
            assert 'OUT_OF_MEMORY' in message


@pytest.mark.parametrize('node, index, sub, says', [
    (5, 0x2020, 0, 'OUT_OF_MEMORY'),  # 200 bytes at boot
    (5, 0x6000, 0, 'NOT_EXIST'),
    (5, 0x2011, 0, 'WRITE_ONLY'),
    (9, 0x1000, 0, 'TIMEOUT'),
    (0, 0x6000, 0, 'NOT_EXIST'),
    (128, 0x1000, 0, 'G1001'),
    (0xFFFF, 0x1000, 0, 'G1001'),
])
def test_me3can_single_read_errors(gateway, node, index, sub, says):
    block = me3(ME3_READ, node, index, sub, 0x1234, fill=FILL)
    registers, message = call(gateway, block, 'me3can')
    assert registers == [0x000F] + block[1:]
    assert says in message


MULTI_READS = [
    (5, 0x2002, 0, U32_5),
    (0, 0x1018, 2, struct.pack('<I', 0xCBCA)),
    (3, 0x2000, 0, b'\x12'),
    (2, 0x2001, 0, struct.pack('<H', 0x1234)),
    (5, 0x2003, 0, struct.pack('<i', -2)),
    (3, 0x1000, 0, struct.pack('<I', 0x00020192)),
    (2, 0x1017, 0, struct.pack('<H', 200)),
    (0, 0x1017, 0, b'\x00\x00'),
]


@pytest.mark.parametrize('count', [1, 3, 7, 8])
def test_me3can_multi_read(gateway, count):
    request = [(node, index, sub, 0x3333, b'\xee' * 8)
               for node, index, sub, _ in MULTI_READS[:count]]
    block = me3_blocks(ME3_MULTI_READ, request, fill=0x7777)
    if count < 8:
        block[1 + 8 * count] = END  # blocks after the end stay as they are
    registers, message = call(gateway, block, 'me3can')
    assert message == ''
    expected = me3_blocks(0x0009, [(node, index, sub, len(data), data)
                                   for node, index, sub, data in MULTI_READS[:count]])
    expected[1 + 8 * count:] = block[1 + 8 * count:]
    assert registers == expected


def test_me3can_multi_read_with_failed_blocks(gateway):
    request = [(5, 0x2002, 0, 0, b''), (5, 0x6000, 0, 0, b'\xee' * 8),
               (9, 0x1000, 0, 0, b''), (3, 0x1008, 0, 0, b''), (2, 0x2001, 0, 0, b'')]
    block = me3_blocks(ME3_MULTI_READ, request)
    block[1 + 8 * 5] = END
    registers, message = call(gateway, block, 'me3can')
    assert registers[0] == 0x00F9
    assert registers[1:9] == [5, 0x2002, 0, 4, 0x5678, 0x1234, 0, 0]
    assert registers[9:17] == [0x0F05, 0x6000, 0, 0, 0x0000, 0x0602, 0, 0]
    assert registers[17:25] == [0x0F09, 0x1000, 0, 0, 0x0000, 0x0504, 0, 0]
    assert registers[25:33] == [0x0F03, 0x1008, 0, 0, 0x0005, 0x0504, 0, 0]  # 22 bytes > 8
    assert registers[33:41] == [2, 0x2001, 0, 2, 0x1234, 0, 0, 0]
    assert registers[41:] == block[41:]
    for says in ('block 2', 'NOT_EXIST', 'block 3', 'TIMEOUT', 'block 4', 'OUT_OF_MEMORY'):
        assert says in message


def test_me3can_multi_write(gateway):
    request = [(5, 0x2002, 0, 4, struct.pack('<I', 0xDEADBEEF)),
               (2, 0x2001, 0x0100, 2, struct.pack('<H', 0xBEEF)),  # reserved high byte
               (0, 0x1017, 0, 2, struct.pack('<H', 1234)),
               (3, 0x2021, 0, 7, b'seven!!\xab')]  # 8th byte beyond the length
    block = me3_blocks(ME3_MULTI_WRITE, request, fill=0x4444)
    block[1 + 8 * 4] = END
    registers, message = call(gateway, block, 'me3can')
    assert message == ''
    assert registers == [0x0007] + block[1:]
    assert core_read(gateway, 5, 0x2002) == struct.pack('<I', 0xDEADBEEF)
    assert core_read(gateway, 2, 0x2001) == struct.pack('<H', 0xBEEF)
    assert core_read(gateway, 0, 0x1017) == struct.pack('<H', 1234)
    assert core_read(gateway, 3, 0x2021) == b'seven!!'
    registers, message = call(gateway, me3(ME3_READ, 5, 0x2002, 0), 'me3can')
    assert registers[:7] == [0x0005, 5, 0x2002, 0, 4, 0xBEEF, 0xDEAD]


def test_me3can_multi_write_with_a_failed_block(gateway):
    request = [(5, 0x2010, 0, 4, b'\x01\x02\x03\x04'), (5, 0x2001, 0, 2, b'\x22\x11'),
               (9, 0x2001, 0, 2, b'\x22\x11')]
    block = me3_blocks(ME3_MULTI_WRITE, request)
    block[1 + 8 * 3] = END
    registers, message = call(gateway, block, 'me3can')
    assert registers[0] == 0x00F7
    assert registers[1:9] == [0x0F05, 0x2010, 0, 0, 0x0002, 0x0601, 0, 0]
    assert registers[9:17] == block[9:17]
    assert registers[17:25] == [0x0F09, 0x2001, 0, 0, 0x0000, 0x0504, 0, 0]
    assert registers[25:] == block[25:]
    assert 'READ_ONLY' in message and 'TIMEOUT' in message
    assert core_read(gateway, 5, 0x2001) == b'\x22\x11'  # the good block was written


@pytest.mark.parametrize('command, blocks, says', [
    (ME3_MULTI_READ, [(5, 0x2002, 0, 0, b''), (300, 0x2002, 0, 0, b'')], 'block 2'),
    (ME3_MULTI_WRITE, [(5, 0x2002, 0, 4, b'\1\2\3\4'), (128, 0x2002, 0, 4, b'')], 'block 2'),
    (ME3_MULTI_WRITE, [(5, 0x2002, 0, 4, b'\1\2\3\4'), (5, 0x2001, 0, 0, b'')], 'G1012'),
    (ME3_MULTI_WRITE, [(5, 0x2002, 0, 9, b'\1\2\3\4')], 'G1004'),
    (ME3_MULTI_WRITE, [(5, 0x2002, 0, 0xFFFF, b'\1\2\3\4')], 'G1004'),
    (ME3_MULTI_READ, [], 'empty'),
    (ME3_MULTI_WRITE, [], 'empty'),
])
def test_me3can_malformed_multi_request_runs_nothing(gateway, command, blocks, says):
    block = me3_blocks(command, blocks)
    block[1 + 8 * len(blocks)] = END
    registers, message = call(gateway, block, 'me3can')
    assert registers == [0x000F] + block[1:]
    assert says in message
    assert core_read(gateway, 5, 0x2002) == U32_5  # block 1 was not executed


@pytest.mark.parametrize('command', [0x0000, 0x0001, 0x0002, 0x0005, 0x0007, 0x0009,
                                     0x000F, 0x00F7, 0x4004, 0xFFFF])
def test_me3can_unknown_command_changes_nothing_else(gateway, command):
    block = me3(command, 5, 0x2002, 0, 4, 0x1111, 0x2222, fill=FILL)
    registers, message = call(gateway, block, 'me3can')
    assert registers == [0x000F] + block[1:]
    assert f'0x{command:04X}' in message


# ----------------------------------------------------------------------------- block shape


@pytest.mark.parametrize('block_format, length, says', [
    ('cbcan', 69, '70'), ('cbcan', 71, '70'), ('', 0, '70'), ('cbcan', 67, '70'),
    ('me3can', 66, '67'), ('me3can', 70, '67'), ('me3can', 1, '67'),
    ('fatek', 70, 'me3can'), ('CBCAN', 70, 'cbcan'), ('me3can ', 67, 'cbcan'),
])
def test_wrong_length_or_unknown_format_changes_nothing(gateway, block_format, length, says):
    block = ([FLAG, READ, 5, 0x2002, 0, 4] + [FILL] * 70)[:length]
    registers, message = call(gateway, block, block_format)
    assert registers == block
    assert says in message


def run_mailbox(gateway_core, block_format, registers):
    """Execute a block through the Python API (no ROS), as a non-ROS user would."""
    mailbox = Mailbox(gateway_core, lambda future: asyncio.wrap_future(future))
    return asyncio.run(mailbox.execute(block_format, registers))


@pytest.mark.parametrize('block_format, registers', [
    ('cbcan', cbcan(data=[70000])),
    ('cbcan', cbcan(node=-1)),
    ('cbcan', cbcan(size=1.5)),
    ('me3can', me3(ME3_READ, 5, 0x2002, -4)),
    ('me3can', me3(ME3_READ, 5, None)),
])
def test_python_api_refuses_values_that_are_not_words(gateway, block_format, registers):
    answer, message = run_mailbox(gateway.node.gateway, block_format, list(registers))
    assert answer == registers
    assert '0..65535' in message


def test_python_api_executes_blocks(gateway):
    answer, message = run_mailbox(gateway.node.gateway, 'cbcan', tuple(cbcan()))
    assert message == ''
    assert answer[:8] == [0, READ, 5, 0x2002, 0, 4, 0x5678, 0x1234]


class _BrokenGateway:
    """A core whose SDO calls fail unexpectedly, or resolve to a refusal without a code."""

    def __init__(self, raise_error: bool):
        self._raise = raise_error

    def sdo_read(self, *args, **kwargs):
        if self._raise:
            raise RuntimeError('the core broke')
        return resolved(SdoResult.failed('refused before the bus'))

    sdo_write = sdo_read


@pytest.mark.parametrize('raise_error, says', [(True, 'the core broke'),
                                               (False, 'refused before the bus')])
@pytest.mark.parametrize('command', [READ, WRITE])
def test_unexpected_failure_is_an_error_answer_cbcan(raise_error, says, command):
    block = cbcan(command, data=[1, 2])
    answer, message = run_mailbox(_BrokenGateway(raise_error), 'cbcan', block)
    assert answer == aborted(block, 0x08000000)
    assert says in message


@pytest.mark.parametrize('raise_error, says', [(True, 'the core broke'),
                                               (False, 'refused before the bus')])
def test_unexpected_failure_is_an_error_answer_me3can(raise_error, says):
    block = me3(ME3_READ, 5, 0x2002, 0)
    answer, message = run_mailbox(_BrokenGateway(raise_error), 'me3can', block)
    assert answer == [0x000F] + block[1:]
    assert says in message
