"""A deeper kernel receive buffer for the socket-based CAN interfaces (python-can gap).

python-can opens ``socketcan`` and ``udp_multicast`` sockets with the kernel's default receive
buffer (``net.core.rmem_default``, 208 KiB on most Linux machines). A frame takes over 800
bytes of it (the kernel counts a datagram's whole buffer, not its 16 bytes), so the socket
holds some 250 frames: 50 ms of a bus carrying 5,000 frames/s. A receive thread held up longer (a
busy machine, the interpreter lock) and the kernel drops frames without a word, an SDO
answer among them, which the caller then sees as a timeout. python-can has no option for the
buffer's size, so :func:`deepen_receive_buffer` sets it on the socket it keeps.
"""

import logging
import socket
from typing import Optional

import can

from . import udp_multicast_of

LOGGER = logging.getLogger(__name__)

# What is asked for: seconds of a saturated bus. The kernel caps it at net.core.rmem_max
# (and reports twice what it grants, its bookkeeping included).
RECEIVE_BUFFER = 4 * 1024 * 1024


def _socket_of(bus: can.BusABC) -> Optional[socket.socket]:
    # python-can 4.6.1: SocketcanBus.socket; udp_multicast's receiving socket.
    multicast = udp_multicast_of(bus)
    if multicast is not None:
        return multicast._socket
    found = getattr(bus, 'socket', None)
    return found if isinstance(found, socket.socket) else None


def deepen_receive_buffer(bus: can.BusABC, size: int = RECEIVE_BUFFER) -> None:
    """Ask the kernel for a receive buffer of ``size`` bytes on ``bus``'s socket.

    A bus without a socket of its own (``virtual``, ``slcan``, vendors' drivers, whose
    buffers their drivers size) is left as it is. A kernel that grants less than half of it
    gets one warning naming the setting that limits it.
    """
    sock = _socket_of(bus)
    if sock is None:
        return
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)
        granted = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
    except OSError as error:
        LOGGER.warning('the CAN socket keeps its default receive buffer (%s): frames that '
                       'arrive while the gateway is held up may be lost', error)
        return
    if granted < size:
        LOGGER.warning('the kernel granted a CAN receive buffer of %d KiB of the %d KiB asked '
                       'for (sysctl net.core.rmem_max caps it): a burst of frames while the '
                       'gateway is held up may be lost', granted // 1024, size // 1024)
