"""NMT commands, node states from heartbeats and node guarding, and the latched state topic."""

import struct
import time

import can
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from cbcan_ros.msg import NodeStates

from conftest import wait_until

START, STOP, PRE_OP, RESET_NODE, RESET_COMM = 1, 2, 128, 129, 130


def frames_on(bus: can.BusABC, can_id: int, count: int = 1, timeout: float = 5.0):
    """Return the first ``count`` frames with ``can_id`` seen on ``bus``."""
    found = []
    deadline = time.monotonic() + timeout
    while len(found) < count and time.monotonic() < deadline:
        message = bus.recv(0.1)
        if message is not None and message.arbitration_id == can_id:
            found.append(message)
    assert len(found) == count, f'expected {count} frame(s) on 0x{can_id:03X}, saw {found}'
    return found


def state_of(gateway, node_id: int) -> str:
    return gateway.call('nmt_state', node_id=node_id).state_name


@pytest.mark.parametrize('command, state', [
    (START, 'OPERATIONAL'), (STOP, 'STOPPED'), (PRE_OP, 'PRE_OPERATIONAL')])
def test_command_to_one_node_sends_the_frame_and_only_that_node_changes(gateway, command,
                                                                         state):
    if command == PRE_OP:
        assert gateway.call('nmt_command', node_id=5, command=START).success
        gateway.wait_for_states({5: 'OPERATIONAL'})
    bus = gateway.raw_bus()
    try:
        response = gateway.call('nmt_command', node_id=5, command=command)
        frame, = frames_on(bus, 0x000)
    finally:
        bus.shutdown()
    assert response.success, response.message
    assert list(frame.data) == [command, 5]
    gateway.wait_for_states({5: state, 2: 'PRE_OPERATIONAL', 3: 'PRE_OPERATIONAL'})
    reply = gateway.call('nmt_state', node_id=5)
    assert (reply.success, reply.state_name) == (True, state)
    assert 0.0 <= reply.last_seen_age < 3.0


@pytest.mark.parametrize('command, state', [(START, 'OPERATIONAL'), (STOP, 'STOPPED')])
def test_node_0_addresses_all_nodes(gateway, command, state):
    bus = gateway.raw_bus()
    try:
        assert gateway.call('nmt_command', node_id=0, command=command).success
        frame, = frames_on(bus, 0x000)
    finally:
        bus.shutdown()
    assert list(frame.data) == [command, 0]
    gateway.wait_for_states({2: state, 3: state, 5: state})
    assert [state_of(gateway, n) for n in (2, 3, 5)] == [state] * 3


@pytest.mark.parametrize('command, kept', [(RESET_NODE, False), (RESET_COMM, True)])
def test_reset_boots_the_node_again(gateway, command, kept):
    """A reset node sends a boot-up message and is pre-operational; reset node also clears.

    Reset communication keeps application values (0x2002), reset node restores defaults.
    """
    assert gateway.call('sdo_write', node_id=3, index=0x2002, subindex=0,
                        data=list(struct.pack('<I', 7))).success
    assert gateway.call('nmt_command', node_id=3, command=START).success
    gateway.wait_for_states({3: 'OPERATIONAL'})
    bus = gateway.raw_bus()
    try:
        assert gateway.call('nmt_command', node_id=3, command=command).success
        boot_up, = frames_on(bus, 0x703)
    finally:
        bus.shutdown()
    assert list(boot_up.data) == [0]
    gateway.wait_for_states({3: 'PRE_OPERATIONAL'})
    value = gateway.call('sdo_read', node_id=3, index=0x2002, subindex=0).data
    assert struct.unpack('<I', bytes(value))[0] == (7 if kept else 0x12345678)


@pytest.mark.parametrize('fields, words', [
    (dict(node_id=5, command=3), 'command 3 is not an NMT command'),
    (dict(node_id=5, command=0), 'allowed 1 START, 2 STOP'),
    (dict(node_id=128, command=START), 'node_id 128 is out of range: allowed 0..127'),
])
def test_invalid_command_is_refused_and_nothing_is_sent(gateway, fields, words):
    bus = gateway.raw_bus()
    try:
        response = gateway.call('nmt_command', **fields)
        assert gateway.call('nmt_command', node_id=2, command=START).success  # the marker
        frame, = frames_on(bus, 0x000)
    finally:
        bus.shutdown()
    assert not response.success
    assert words in response.message
    assert list(frame.data) == [START, 2], 'the first NMT frame on the bus is the marker'


def test_state_of_an_invalid_node_id_is_refused(gateway):
    for node_id in (0, 128):
        reply = gateway.call('nmt_state', node_id=node_id)
        assert not reply.success
        assert f'node_id {node_id} is out of range: allowed 1..127' in reply.message


def test_never_seen_node_is_not_detected(make_gateway):
    gateway = make_gateway(nodes=[42])
    reply = gateway.call('nmt_state', node_id=42)
    assert (reply.success, reply.state, reply.state_name) == (True, 6, 'NOT_DETECTED')
    assert reply.last_seen_age == -1.0
    gateway.wait_for_states({42: 'NOT_DETECTED', 2: 'PRE_OPERATIONAL'})
    unknown = gateway.call('nmt_state', node_id=77)
    assert (unknown.success, unknown.state_name, unknown.last_seen_age) == (
        True, 'NOT_DETECTED', -1.0)


def test_silent_node_becomes_not_detected_and_comes_back(make_gateway):
    gateway = make_gateway(heartbeat__timeout=0.5)
    gateway.wait_for_states({5: 'PRE_OPERATIONAL'})
    # Producer heartbeat time 0 switches the device's heartbeat off (CiA 301).
    assert gateway.call('sdo_write', node_id=5, index=0x1017, subindex=0, data=[0, 0]).success
    gateway.wait_for_states({5: 'NOT_DETECTED', 2: 'PRE_OPERATIONAL'})
    reply = gateway.call('nmt_state', node_id=5)
    assert reply.state_name == 'NOT_DETECTED'
    assert reply.last_seen_age >= 0.5, 'the age still tells when the node last spoke'
    assert gateway.call('sdo_write', node_id=5, index=0x1017, subindex=0,
                        data=[100, 0]).success
    gateway.wait_for_states({5: 'PRE_OPERATIONAL'})


def test_topic_lists_every_known_node_sorted_with_last_seen(make_gateway):
    gateway = make_gateway(nodes=[9, 1])
    gateway.wait_for_states({1: 'NOT_DETECTED', 2: 'PRE_OPERATIONAL', 3: 'PRE_OPERATIONAL',
                             5: 'PRE_OPERATIONAL', 9: 'NOT_DETECTED'})
    message = gateway.states[-1]
    assert [n.node_id for n in message.nodes] == [1, 2, 3, 5, 9]
    seen = {n.node_id: n.last_seen.sec for n in message.nodes}
    assert seen[1] == 0 and seen[9] == 0
    assert abs(seen[2] - time.time()) < 60


def test_late_subscriber_gets_the_current_picture_at_once(make_gateway):
    gateway = make_gateway(state_publish_period=3600.0)
    assert gateway.call('nmt_command', node_id=2, command=START).success
    gateway.wait_for_states({2: 'OPERATIONAL'})
    received = []
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
    gateway.client_node.create_subscription(NodeStates, '/cbcan/node_states',
                                            received.append, qos)
    wait_until(lambda: received, 10.0, 'the latched node states')
    assert {n.node_id: n.state_name for n in received[0].nodes}[2] == 'OPERATIONAL'


def test_node_guarding_tracks_a_node_without_heartbeat(make_gateway):
    gateway = make_gateway(node_guarding=[3], node_guarding_period=0.1,
                           heartbeat__timeout=0.5)
    assert gateway.call('sdo_write', node_id=3, index=0x1017, subindex=0, data=[0, 0]).success
    bus = gateway.raw_bus()
    try:
        request, = frames_on(bus, 0x703)
        while not request.is_remote_frame:
            request, = frames_on(bus, 0x703)
    finally:
        bus.shutdown()
    assert gateway.call('nmt_command', node_id=3, command=START).success
    gateway.wait_for_states({3: 'OPERATIONAL'})
    # Node 5 is not guarded: without heartbeat it times out, while guarded 3 stays known.
    assert gateway.call('sdo_write', node_id=5, index=0x1017, subindex=0, data=[0, 0]).success
    gateway.wait_for_states({5: 'NOT_DETECTED', 3: 'OPERATIONAL'})
