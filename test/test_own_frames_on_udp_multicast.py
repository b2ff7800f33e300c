"""On udp_multicast the gateway does not take its own frames back; every other process does.

python-can's udp_multicast bus hands a process every frame it sent (``own_frames.py``), each
an echo that wakes the receive thread for nothing. The gateway opens its bus with a socket of
its own for sending and a kernel filter that drops what that socket sent: the frames still
reach the devices (other processes, other sockets), frames from others still reach the
gateway, also another host's from a port of the same number, and its sends are still bounded
by the kernel's send timeout. Where the filter cannot be had, the bus echoes as before and
``~/from_can_bus`` still leaves the gateway's own frames out.
"""

import errno
import logging
import os
import resource
import socket
import struct
import time

import can
from can.interfaces.udp_multicast.utils import pack_message
import canopen
import pytest
from test_raw_frames import FrameRecorder
from test_send_timeout import kernel_bound

from cbcan_ros.core.bus import BusSupervisor, prompt, SEND_TIMEOUT
from cbcan_ros.core.python_can_gaps import own_frames
from cbcan_ros.core.python_can_gaps.own_frames import drop_own_frames

from conftest import wait_until
from node_process import private_bus

WAIT = 20.0
FRAMES = 50
OWN, OTHER = 0x123, 0x124


@pytest.fixture
def group():
    """Yield a private udp_multicast group and a bus of another 'process' on it."""
    address, port = private_bus()
    other = can.Bus(interface='udp_multicast', channel=address, port=port)
    try:
        yield address, port, other
    finally:
        other.shutdown()


def _supervisor(address, port, opened):
    def open_bus() -> can.BusABC:
        bus = can.Bus(interface='udp_multicast', channel=address, port=port)
        opened.append(drop_own_frames(bus))
        opened.append(bus)
        return bus
    network = canopen.Network()
    return network, BusSupervisor(network, open_bus, f'udp_multicast:{address}')


def test_the_gateway_s_frames_reach_others_and_never_come_back_to_it(group):
    address, port, other = group
    opened = []
    network, supervisor = _supervisor(address, port, opened)
    heard = {OWN: [], OTHER: []}
    for can_id, frames in heard.items():
        network.subscribe(can_id, prompt(
            lambda _id, data, _stamp, frames=frames: frames.append(bytes(data))))
    supervisor.start()
    try:
        wait_until(lambda: supervisor.status.up, WAIT, 'the bus open')
        assert opened[0] is True, 'the filter was not attached'
        for number in range(FRAMES):
            supervisor.send(can.Message(arbitration_id=OWN, is_extended_id=False,
                                        data=[number]))
        received = []
        while len(received) < FRAMES:
            message = other.recv(WAIT)
            assert message is not None, f'{len(received)} of {FRAMES} frames reached the group'
            if message.arbitration_id == OWN:
                received.append(message.data[0])
        assert received == list(range(FRAMES))
        # A frame of another process after them: once it is in, any echo would be too.
        other.send(can.Message(arbitration_id=OTHER, is_extended_id=False, data=[7]))
        wait_until(lambda: heard[OTHER], WAIT, "another process's frame heard")
        assert heard == {OWN: [], OTHER: [b'\x07']}
        assert supervisor.status.frames_received == 1
        assert supervisor.status.frames_sent == FRAMES
        sock = own_frames.sending_socket(opened[1])
        assert sock is not opened[1]._multicast._socket, 'sent on the receiving socket'
        assert sock.gettimeout() is None  # blocking: the kernel bounds the send
        assert kernel_bound(sock) == pytest.approx(SEND_TIMEOUT)
    finally:
        supervisor.stop()


def test_a_socket_that_refuses_the_filter_keeps_its_echoes_with_a_warning(group, monkeypatch,
                                                                          caplog):
    address, port, _ = group
    monkeypatch.setattr(own_frames, 'SO_ATTACH_FILTER', 0xDEAD)  # an option no kernel knows
    bus = can.Bus(interface='udp_multicast', channel=address, port=port)
    try:
        with caplog.at_level(logging.WARNING):
            assert drop_own_frames(bus) is False
        assert 'come back to it as before' in caplog.text
        assert own_frames.sending_socket(bus) is bus._multicast._socket
        bus.send(can.Message(arbitration_id=OWN, is_extended_id=False, data=[1]))
        echo = bus.recv(WAIT)
        assert echo is not None and echo.arbitration_id == OWN
    finally:
        bus.shutdown()


def test_a_bus_without_a_multicast_socket_is_left_as_it_is():
    bus = can.Bus(interface='virtual', channel='own-frames-test')
    try:
        assert drop_own_frames(bus) is False
        assert own_frames.sending_socket(bus) is None
    finally:
        bus.shutdown()


def test_the_sending_socket_is_closed_with_the_bus(group):
    address, port, _ = group
    bus = can.Bus(interface='udp_multicast', channel=address, port=port)
    assert drop_own_frames(bus)
    sock = own_frames.sending_socket(bus)
    bus.shutdown()
    assert sock.fileno() == -1
    with pytest.raises(OSError):
        sock.sendto(b'x', (address, port))


def _from_another_host(source: str, source_port: int, group: str, port: int,
                       message: can.Message) -> bytes:
    """Return an IPv4 datagram of ``message`` as another host would send it to the group."""
    payload = pack_message(message)
    udp = struct.pack('!HHHH', source_port, port, 8 + len(payload), 0) + payload
    return struct.pack('!BBHHHBBH4s4s', 0x45, 0, 20 + len(udp), 0, 0, 1, socket.IPPROTO_UDP,
                       0, socket.inet_aton(source), socket.inet_aton(group)) + udp


def test_another_host_sending_from_the_same_port_number_is_heard(group):
    address, port, _ = group
    bus = can.Bus(interface='udp_multicast', channel=address, port=port)
    try:
        raw = socket.socket(socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_RAW)
    except PermissionError:
        bus.shutdown()
        pytest.skip('a raw socket (root or CAP_NET_RAW) is needed to send as another host')
    try:
        assert drop_own_frames(bus)
        own_address, own_port = own_frames.sending_socket(bus).getsockname()[:2]
        for can_id, source in ((0x7F0, '10.20.30.40'), (0x7F1, own_address)):
            raw.sendto(_from_another_host(source, own_port, address, port, can.Message(
                arbitration_id=can_id, is_extended_id=False)), (address, 0))
        bus.send(can.Message(arbitration_id=0x7F2, is_extended_id=False))
        heard = []
        deadline = time.monotonic() + 2.0  # all three come within milliseconds
        while time.monotonic() < deadline:
            message = bus.recv(0.1)
            if message is not None:
                heard.append(message.arbitration_id)
        # Another host's frame from that port number; not one with this socket's address
        # and port, nor the frame this bus sent.
        assert heard == [0x7F0], [hex(can_id) for can_id in heard]
    finally:
        raw.close()
        bus.shutdown()


def test_a_process_out_of_file_descriptors_keeps_the_bus_echoing_with_a_warning(group,
                                                                                caplog):
    address, port, _ = group
    bus = can.Bus(interface='udp_multicast', channel=address, port=port)
    try:
        # The lowest free descriptor as the limit: the sending socket is the one too many.
        free = os.dup(0)
        os.close(free)
        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        resource.setrlimit(resource.RLIMIT_NOFILE, (free, hard))
        try:
            with caplog.at_level(logging.WARNING):
                dropped = drop_own_frames(bus)
        finally:
            resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
        assert dropped is False
        assert os.strerror(errno.EMFILE) in caplog.text, caplog.text
        bus.send(can.Message(arbitration_id=OWN, is_extended_id=False, data=[2]))
        echo = bus.recv(WAIT)
        assert echo is not None and echo.arbitration_id == OWN
    finally:
        bus.shutdown()


def test_where_the_filter_is_refused_from_can_bus_still_leaves_the_gateway_s_frames_out(
        make_gateway, monkeypatch, group):
    address, port, other = group
    monkeypatch.setattr(own_frames, 'SO_ATTACH_FILTER', 0xDEAD)  # an option no kernel knows
    harness = make_gateway(can__interface='udp_multicast', can__channel=address,
                           can__options=[f'port={port}'], simulation__devices=None,
                           heartbeat__node_id=100, heartbeat__period=0.05, sync__period=0.05,
                           raw__filters=['0:0'])
    recorder = FrameRecorder(harness.client_node, '/cbcan/from_can_bus')
    wait_until(lambda: harness.node.gateway.bus_status.frames_received > 20, WAIT,
               "the gateway's heartbeats and SYNCs coming back to it")
    # Another process's frame, published: everything before it has been through the bridge.
    other.send(can.Message(arbitration_id=OTHER, is_extended_id=False, data=[9]))
    wait_until(lambda: any(frame.id == OTHER for frame in recorder.frames), WAIT,
               "another process's frame on from_can_bus")
    assert [frame.id for frame in recorder.frames] == [OTHER]
