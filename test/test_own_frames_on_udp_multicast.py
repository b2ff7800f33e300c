"""On udp_multicast the gateway does not take its own frames back; every other process does.

python-can's udp_multicast bus hands a process every frame it sent (``own_frames.py``), each
an echo that wakes the receive thread for nothing. The gateway opens its bus with a socket of
its own for sending and a kernel filter that drops what that socket sent: the frames still
reach the devices (other processes, other sockets), frames from others still reach the
gateway, and its sends are still bounded by the kernel's send timeout.
"""

import logging

import can
import canopen
import pytest
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
