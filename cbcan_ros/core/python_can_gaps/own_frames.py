"""The gateway's own frames kept off its receive thread on ``udp_multicast`` (python-can gap).

python-can 4.6.1's ``udp_multicast`` driver sends and receives on one socket, joined to the
group with the kernel's multicast loop on (other processes on the host must get the frames),
so every frame the gateway sends comes back to it, although the driver refuses
``receive_own_messages=True`` as "not yet implemented" and so claims the default, False.
Each of those echoes wakes the receive thread, which takes the interpreter lock from the
sending thread at every frame: in a program download (37,450 frames) or at 250 Hz with 8
drives (9 of every 25 frames are the gateway's) that is work no SocketCAN gateway does, as
SocketCAN does not hand a socket its own frames unless asked.

:func:`drop_own_frames` gives the driver a socket of its own for sending, bound to a port of
the kernel's choosing, and attaches a socket filter (classic BPF) to the receiving socket that
drops every datagram from that socket's address and port: the kernel discards the echoes
before anyone wakes. It counts each as a drop of the receiving socket (``/proc/net/udp``,
``ss``) and as a UDP receive error of the machine (``InErrors``, not ``RcvbufErrors``).
Other processes still receive every frame (they are sent to the group as before; only the
source port differs, which python-can never reads).
"""

import ctypes
import logging
import socket
import struct
import sys
from typing import Optional

import can

from . import udp_multicast_of

LOGGER = logging.getLogger(__name__)

# Linux only: the option (asm-generic/socket.h; x86 and ARM use it) and the fact that a UDP
# socket's filter sees the datagram from its UDP header on, source port first.
SO_ATTACH_FILTER = 26
SUPPORTED = sys.platform.startswith('linux')

# Classic BPF (linux/filter.h): loads of a half-word and a word at an offset from the UDP
# header (negative offsets from SKF_NET_OFF: from the IP header), a jump on equal, a return
# of how many bytes to keep (0: drop).
_BPF_LD_H_ABS, _BPF_LD_W_ABS, _BPF_JEQ_K, _BPF_RET_K = 0x28, 0x20, 0x15, 0x06
_SKF_NET_OFF = (1 << 32) - 0x100000


def sending_socket(bus: can.BusABC) -> Optional[socket.socket]:
    """Return the socket ``bus`` sends on, when it is a ``udp_multicast`` bus; else None."""
    multicast = udp_multicast_of(bus)
    if multicast is None:
        return None
    return getattr(multicast, 'cbcan_send_socket', None) or multicast._socket


def drop_own_frames(bus: can.BusABC) -> bool:
    """Have the kernel drop the frames ``bus`` sends before its receive sees them.

    Return True when done: a ``udp_multicast`` bus on Linux. Any other bus is left as it is
    (False); so is one where the sending socket cannot be made or the filter is refused,
    with a warning: it echoes as before.
    """
    multicast = udp_multicast_of(bus)
    if multicast is None or not SUPPORTED:
        return False
    receiving = multicast._socket
    sender = None
    try:
        sender = socket.socket(receiving.family, socket.SOCK_DGRAM)
        hops = struct.pack('@I', multicast.hop_limit)
        if receiving.family == socket.AF_INET:
            sender.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, hops)
        else:
            sender.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_HOPS, hops)
        # Connected, the socket has its source address fixed now: the filter needs it.
        sender.connect(multicast._send_destination)
        address, port = sender.getsockname()[:2]
        _attach_filter(receiving, socket.inet_pton(receiving.family, address), port)
    except OSError as error:
        if sender is not None:
            sender.close()
        LOGGER.warning('udp_multicast: the frames this node sends could not be kept from its '
                       'own receive (%s); they come back to it as before', error)
        return False
    multicast.cbcan_send_socket = sender
    multicast.send = _sender(sender, multicast._send_destination)
    close = multicast.shutdown

    def shutdown() -> None:
        close()
        sender.close()
    multicast.shutdown = shutdown
    return True


def _attach_filter(receiving: socket.socket, address: bytes, port: int) -> None:
    """Drop, on ``receiving``, the datagrams from ``address`` (packed) and ``port``.

    The address too: another host (a LAN, containers on one bridge) may send from a port of
    the same number.
    """
    # (what to load, the value it must equal): the UDP source port, then each 32-bit word of
    # the IP source address, found from the network header (12 bytes in for IPv4, 8 for 6).
    source = _SKF_NET_OFF + (12 if len(address) == 4 else 8)
    checks = [(_BPF_LD_H_ABS, 0, port)] + [
        (_BPF_LD_W_ABS, source + at, int.from_bytes(address[at:at + 4], 'big'))
        for at in range(0, len(address), 4)]
    program = []
    for number, (load, offset, value) in enumerate(checks):
        # Any word that differs: on to the last instruction, which accepts.
        program += [(load, 0, 0, offset), (_BPF_JEQ_K, 0, 2 * (len(checks) - number) - 1,
                                           value)]
    program += [(_BPF_RET_K, 0, 0, 0), (_BPF_RET_K, 0, 0, 0xFFFFFFFF)]
    code = ctypes.create_string_buffer(b''.join(struct.pack('HBBI', *op) for op in program))
    # The kernel copies the program during setsockopt: ``code`` need not outlive the call.
    receiving.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER,
                         struct.pack('HL', len(program), ctypes.addressof(code)))


def _sender(sock: socket.socket, destination):
    """Return a ``send(data, timeout)`` as python-can's, on ``sock``."""
    def send(data: bytes, timeout: Optional[float] = None) -> None:
        if timeout != sock.gettimeout():
            sock.settimeout(timeout)
        try:
            if sock.sendto(data, destination) < len(data):
                raise TimeoutError()
        except TimeoutError:
            raise can.CanTimeoutError() from None
        except OSError as error:
            raise can.CanOperationError('failed to send via socket') from error
    return send
