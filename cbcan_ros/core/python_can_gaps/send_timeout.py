"""The send timeout of python-can's ``udp_multicast`` bus, held by the kernel (python-can gap).

python-can 4.6.1's ``udp_multicast`` driver implements ``send(message, timeout)`` with
``socket.settimeout(timeout)`` on the one socket it both sends and receives on. That puts the
socket into CPython's timeout mode, in which every ``sendto()`` and every ``recvmsg()`` on it
is preceded by a ``poll()``: two more system calls for each frame sent (one before the send,
one before the receive of its echo, which ``udp_multicast`` always hands back), each a release
and a re-take of the interpreter lock between the sending thread and the receive thread. In a
program download of 256 KiB (37,450 frames) that was 75,000 ``poll()`` calls and about a tenth
of the node's CPU time, which the raw python canopen baseline, sending without a timeout, does
not spend (docs/performance.md, Program download).

:func:`kernel_send_timeout` keeps the same bound in the kernel instead (``SO_SNDTIMEO``): a
send that cannot be queued within it fails with ``EAGAIN``, which python-can reports as
``CanOperationError``, a fault of the bus as a timed-out send was before. The socket itself
stays in blocking mode, so sends and receives are one system call each. The bound then also
covers python-can's periodic sends (SYNC), which go without a timeout. Other interfaces keep
python-can's per-call timeout: ``socketcan`` waits for the socket with ``select()`` and leaves
the socket's mode alone, and the others have no socket of their own.
"""

import logging
import socket
import struct
from typing import Optional

import can

from .own_frames import sending_socket

LOGGER = logging.getLogger(__name__)


def kernel_send_timeout(bus: can.BusABC, timeout: float) -> Optional[float]:
    """Bound ``bus``'s sends by ``timeout`` s; return what to pass to its ``send(timeout=)``.

    On a ``udp_multicast`` bus the kernel holds the bound (``SO_SNDTIMEO``) and None is
    returned, so python-can never puts the socket into timeout mode; any other bus (or one
    whose socket refuses the option) gets ``timeout`` back, for python-can to apply per call.
    """
    sock = sending_socket(bus)
    if sock is None:
        return timeout
    seconds = int(timeout)
    bound = struct.pack('@ll', seconds, int(round((timeout - seconds) * 1_000_000)))
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, bound)
    except OSError as error:
        LOGGER.debug('SO_SNDTIMEO refused (%s): python-can bounds each send itself', error)
        return timeout
    return None
