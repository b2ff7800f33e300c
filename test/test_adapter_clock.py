"""Answers, heartbeat ages and node states never depend on the CAN adapter's clock.

Adapters stamp received frames with a clock of their own, offset from the host's by up to
seconds and drifting. The gateway decides only on the host's monotonic clock, taken when its
receive thread takes a frame from the driver. These tests give the gateway a bus whose frames
carry such a clock (``adapter_clock_bus``): in this process, against a durand device (a
CANopen stack independent of the gateway's), and through the installed node.
"""

import os
import struct
import uuid

import adapter_clock_bus
import pytest

from cbcan_ros.core.gateway import Gateway, GatewayConfig
from cbcan_ros.msg import NodeStates
from cbcan_ros.ros.interface import NODE_STATES_QOS
from cbcan_ros.simulation.durand.dictionary import DOMAIN_DEFAULT, DOMAIN_INDEX
from cbcan_ros.srv import NmtState, SdoRead, SdoWrite

from conftest import new_channel, wait_until
from node_process import call, private_bus, service_client

NODE = 7
ROUNDS = 20
CALL_TIMEOUT = 5.0  # far above a prompt answer: only a dropped answer runs into it
HEARTBEAT_AGE = 1.0  # the device beats every 0.2 s

CLOCKS = ['offset:-5', 'offset:-0.8', 'offset:-0.05', 'offset:1', 'offset:5',
          'drift:-0.5', 'drift:0.5', 'zero', 'boot']

adapter_clock_bus.register()


@pytest.mark.parametrize('adapter_clock', CLOCKS)
def test_every_answer_and_heartbeat_arrives_whatever_the_adapter_clock(start_durand,
                                                                       adapter_clock):
    channel = new_channel()
    start_durand(NODE, channel=channel)
    gateway = Gateway(GatewayConfig(interface=adapter_clock_bus.INTERFACE_NAME,
                                    channel=channel, bus_options={'clock': adapter_clock},
                                    expected_nodes=(NODE,)))
    gateway.start()
    try:
        for round_ in range(ROUNDS):
            value = struct.pack('<I', 0x01020304 * round_ & 0xFFFFFFFF)
            written = gateway.sdo_write(NODE, 0x2002, 0, value, CALL_TIMEOUT).result()
            assert written.success, (round_, written.message)
            read = gateway.sdo_read(NODE, 0x2002, 0, timeout=CALL_TIMEOUT).result()
            assert read.success, (round_, read.message)
            assert read.data == value
        segmented = gateway.sdo_read(NODE, DOMAIN_INDEX, 0, timeout=CALL_TIMEOUT).result()
        assert segmented.success and segmented.data == DOMAIN_DEFAULT, segmented.message
        wait_until(lambda: _fresh(gateway.monitor.status(NODE)), 10.0,
                   f'a fresh heartbeat of node {NODE} (last: {gateway.monitor.status(NODE)})')
    finally:
        gateway.stop()


def _fresh(status) -> bool:
    return (status.state_name == 'PRE_OPERATIONAL' and status.last_seen_age is not None
            and 0.0 <= status.last_seen_age < HEARTBEAT_AGE)


@pytest.mark.parametrize('adapter_clock', ['offset:-5', 'boot'])
def test_the_installed_node_answers_whatever_the_adapter_clock(start_node, client_node,
                                                               start_durand, monkeypatch,
                                                               tmp_path, adapter_clock):
    """The adapter bus is a python-can plugin, found as the node would find a vendor's."""
    group, port = private_bus()
    start_durand(NODE, interface='udp_multicast', channel=group, bus_options={'port': port})
    monkeypatch.setenv('PYTHONPATH', adapter_clock_bus.plugin_path(tmp_path) + ':' +
                       os.environ.get('PYTHONPATH', ''))
    namespace = f'/clock{uuid.uuid4().hex[:8]}'
    gateway = start_node(['-r', f'__ns:={namespace}',
                          '-p', f'can.interface:={adapter_clock_bus.INTERFACE_NAME}',
                          '-p', f'can.channel:={group}',
                          '-p', f'can.options:=["clock={adapter_clock}", '
                                f'"inner_interface=udp_multicast"]',
                          '-p', f'nodes:=[{NODE}]'], port)
    states = []
    client_node.create_subscription(NodeStates, f'{namespace}/cbcan/node_states',
                                    states.append, NODE_STATES_QOS)
    sdo_read = service_client(client_node, SdoRead, f'{namespace}/cbcan/sdo_read', gateway)
    sdo_write = service_client(client_node, SdoWrite, f'{namespace}/cbcan/sdo_write', gateway)
    nmt_state = service_client(client_node, NmtState, f'{namespace}/cbcan/nmt_state', gateway)
    for round_ in range(ROUNDS):
        value = list(struct.pack('<I', 0x0A0B0C0D + round_))
        written = call(sdo_write, SdoWrite.Request(node_id=NODE, index=0x2002, data=value,
                                                   timeout=CALL_TIMEOUT), 'write', gateway)
        assert written.success, (round_, written.message)
        read = call(sdo_read, SdoRead.Request(node_id=NODE, index=0x2002,
                                              timeout=CALL_TIMEOUT), 'read', gateway)
        assert read.success and list(read.data) == value, (round_, read.message)

    def fresh_state():
        answer = call(nmt_state, NmtState.Request(node_id=NODE), 'nmt_state', gateway)
        return (answer.state_name == 'PRE_OPERATIONAL'
                and 0.0 <= answer.last_seen_age < HEARTBEAT_AGE)
    wait_until(fresh_state, 10.0, f'a fresh heartbeat of node {NODE} in nmt_state')
    wait_until(lambda: any(n.node_id == NODE and n.state_name == 'PRE_OPERATIONAL'
                           for n in states[-1].nodes) if states else False,
               10.0, f'node {NODE} PRE_OPERATIONAL on node_states')
