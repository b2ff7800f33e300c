"""A send over udp_multicast is bounded by the kernel, not by python-can's per-call timeout.

python-can's udp_multicast bus applies ``send(timeout=...)`` with ``socket.settimeout()`` on the
socket it also receives on; CPython then calls ``poll()`` before every ``sendto()`` and every
``recvmsg()`` on it, two system calls more for each frame sent and its echo
(``cbcan_ros/core/send_timeout.py``). The gateway's bus supervisor gives the same bound to the
kernel (``SO_SNDTIMEO``) and sends without a timeout, so the socket stays in blocking mode.
"""

import socket
import struct

import can
import canopen
import pytest

from cbcan_ros.core.bus import BusSupervisor, prompt, SEND_TIMEOUT
from cbcan_ros.core.python_can_gaps.send_timeout import kernel_send_timeout

from conftest import wait_until
from node_process import private_bus

WAIT = 20.0
FRAMES = 5
TIMEVAL = struct.Struct('@ll')


def kernel_bound(sock: socket.socket) -> float:
    """Return the send timeout the kernel holds for ``sock``, in seconds."""
    seconds, microseconds = TIMEVAL.unpack(
        sock.getsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, TIMEVAL.size))
    return seconds + microseconds / 1_000_000


def test_the_supervisor_sends_on_udp_multicast_without_putting_its_socket_in_timeout_mode():
    group, port = private_bus()
    opened = []

    def open_bus() -> can.BusABC:
        bus = can.Bus(interface='udp_multicast', channel=group, port=port)
        opened.append(bus)
        return bus

    network = canopen.Network()
    supervisor = BusSupervisor(network, open_bus, f'udp_multicast:{group}')
    echoes = []
    network.subscribe(0x123, prompt(lambda _id, data, _stamp: echoes.append(bytes(data))))
    supervisor.start()
    try:
        wait_until(lambda: supervisor.status.up, WAIT, 'the bus open')
        for number in range(FRAMES):
            supervisor.send(can.Message(arbitration_id=0x123, is_extended_id=False,
                                        data=[number]))
        # udp_multicast hands the frames back: they went out, and came in on the same socket.
        wait_until(lambda: len(echoes) == FRAMES, WAIT, 'the frames sent, heard back')
        assert echoes == [bytes([number]) for number in range(FRAMES)]
        assert supervisor.status.frames_sent == FRAMES
        sock = opened[0]._multicast._socket
        assert sock.gettimeout() is None  # blocking mode: no poll() before sends and receives
        assert kernel_bound(sock) == pytest.approx(SEND_TIMEOUT)
    finally:
        supervisor.stop()


def test_a_bus_without_a_socket_of_its_own_keeps_python_cans_timeout():
    bus = can.Bus(interface='virtual', channel='send-timeout-test')
    try:
        assert kernel_send_timeout(bus, SEND_TIMEOUT) == SEND_TIMEOUT
    finally:
        bus.shutdown()
