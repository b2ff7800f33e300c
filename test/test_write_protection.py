"""Write protection for integrators: read_only and sdo.write_allow, through every path."""

import struct

import pytest
from rclpy.parameter import Parameter

from cbcan_ros.ros.node import CbcanNode

from conftest import frames_before_marker

LOCAL_CONTROL = 0x08000021
FLAG, WRITE = 0xCA0E, 5066
ME3_MULTI_WRITE, END = 0x0006, 0xFFFF


def refused_before_the_bus(gateway, service, **fields):
    bus = gateway.raw_bus()
    try:
        response = gateway.call(service, **fields)
        frames = frames_before_marker(gateway, bus)
    finally:
        bus.shutdown()
    assert frames == [], 'the refused write reached the bus'
    return response


def test_read_only_refuses_writes_and_nmt_but_reads(make_gateway):
    gateway = make_gateway(read_only=True)
    response = refused_before_the_bus(gateway, 'sdo_write', node_id=5, index=0x2002,
                                      subindex=0, data=[1, 2, 3, 4])
    assert (response.success, response.abort_code) == (False, LOCAL_CONTROL)
    assert response.message.startswith('0x08000021 DATA_LOCAL_CONTROL')
    assert 'read_only' in response.message
    assert gateway.device(5).node.sdo[0x2002].raw == 0x12345678
    own = gateway.call('sdo_write', node_id=0, index=0x1017, subindex=0, data=[1, 0])
    assert own.abort_code == LOCAL_CONTROL
    nmt = gateway.call('nmt_command', node_id=5, command=1)
    assert not nmt.success and 'read_only' in nmt.message
    assert nmt.abort_code == LOCAL_CONTROL
    assert gateway.device(5).state == 127, 'the NMT command was not sent'
    assert gateway.call('sdo_read', node_id=5, index=0x2002, subindex=0).success


@pytest.mark.parametrize('node, index, allowed', [
    (2, 0x2000, True), (2, 0x2003, True), (2, 0x2004, False), (3, 0x2000, False),
    (3, 0x1017, True), (5, 0x1017, True), (0, 0x1017, True), (5, 0x2021, False),
])
def test_write_allow_rules(make_gateway, node, index, allowed):
    gateway = make_gateway(sdo__write_allow=['2:0x2000-0x2003', '*:0x1017'])
    data = [1, 0] if index in (0x1017, 0x2001) else [1, 0, 0, 0][:{0x2000: 1}.get(index, 4)]
    if allowed:
        response = gateway.call('sdo_write', node_id=node, index=index, subindex=0,
                                data=data)
        assert response.abort_code != LOCAL_CONTROL, response.message
        return
    response = refused_before_the_bus(gateway, 'sdo_write', node_id=node, index=index,
                                      subindex=0, data=data)
    assert (response.success, response.abort_code) == (False, LOCAL_CONTROL)
    assert f'node {node} index 0x{index:04X}' in response.message
    assert 'sdo.write_allow' in response.message


@pytest.mark.parametrize('rule, says', [
    ('5', "'node:index' or 'node:first-last'"),
    ('x:0x2000', "'node:index'"),
    ('200:0x2000', 'node 200 is out of range'),
    ('5:0x3000-0x2000', 'first <= last'),
    ('5:0x10000', 'within 0x0000..0xFFFF'),
])
def test_bad_write_rule_stops_the_node_with_a_message(rule, says):
    with pytest.raises(ValueError, match='write rule') as error:
        CbcanNode(parameter_overrides=[Parameter('sdo.write_allow', value=[rule]),
                                       Parameter('can.channel', value='unused')])
    assert says in str(error.value) and rule in str(error.value)


def test_mailbox_write_is_refused_with_the_abort_words(make_gateway):
    gateway = make_gateway(sdo__write_allow=['5:0x2001'])
    data = struct.pack('<I', 0xDEADBEEF)
    block = [FLAG, WRITE, 5, 0x2002, 0, 4, *struct.unpack('<2H', data)] + [0] * 62
    response = gateway.call('plc_mailbox', format='cbcan', registers=block)
    registers = list(response.registers)
    assert registers[0] == 4  # R3700: aborted
    assert (registers[6], registers[7]) == (LOCAL_CONTROL & 0xFFFF, LOCAL_CONTROL >> 16)
    assert 'DATA_LOCAL_CONTROL' in response.message
    assert gateway.device(5).node.sdo[0x2002].raw == 0x12345678


def test_mailbox_nmt_command_is_refused_when_read_only(make_gateway):
    gateway = make_gateway(read_only=True)
    block = [FLAG, WRITE, 77, 0x1F82, 5, 0, 1] + [0] * 63
    response = gateway.call('plc_mailbox', format='cbcan', registers=block)
    registers = list(response.registers)
    assert registers[0] == 4
    assert (registers[6], registers[7]) == (LOCAL_CONTROL & 0xFFFF, LOCAL_CONTROL >> 16)
    assert gateway.device(5).state == 127


def test_me3can_multi_write_refuses_only_the_protected_block(make_gateway):
    gateway = make_gateway(sdo__write_allow=['5:0x2001'])
    good = [5, 0x2001, 0, 2, 0x1122, 0, 0, 0]
    bad = [5, 0x2002, 0, 4, 0xBEEF, 0xDEAD, 0, 0]
    block = [ME3_MULTI_WRITE, *good, *bad, END] + [0] * (67 - 18)
    response = gateway.call('plc_mailbox', format='me3can', registers=block)
    registers = list(response.registers)
    assert registers[9:17] == [0x0F05, 0x2002, 0, 0, LOCAL_CONTROL & 0xFFFF,
                               LOCAL_CONTROL >> 16, 0, 0]
    assert gateway.device(5).node.sdo[0x2001].raw == 0x1122
    assert gateway.device(5).node.sdo[0x2002].raw == 0x12345678
