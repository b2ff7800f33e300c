"""What the gateway adds to python-can 4.6.1's socket drivers, in one place.

python-can opens the bus; where its ``udp_multicast`` and ``socketcan`` drivers fall short for
a gateway (frames lost without a word, a system call more per frame, its own frames handed
back), the socket the driver keeps is adjusted here and nowhere else, one module per gap.
Each is listed in docs/library_gaps.md; the bus supervisor (``core/bus.py``) covers the
others (``Notifier``, ``slcan``, adapters' clocks).

- :mod:`.receive_buffer`: a receive buffer deep enough for a thread held up (both drivers).
- :mod:`.send_timeout`: the send timeout held by the kernel (``udp_multicast``).
- :mod:`.own_frames`: the gateway's own frames dropped by the kernel (``udp_multicast``).
- :mod:`.foreign_datagrams`: what a group carries that is no frame of this bus (a datagram that
  does not unpack, a malformed frame, another program's error frame) dropped, not taken as
  a dead bus (``udp_multicast``).
"""

import socket

import can


def udp_multicast_of(bus: can.BusABC):
    """Return the driver object of a ``udp_multicast`` ``bus`` that keeps its socket, or None.

    python-can 4.6.1: ``UdpMulticastBus._multicast``, a ``GeneralPurposeUdpMulticastBus``
    whose ``_socket`` sends and receives (private both: this is the one place that reads them).
    """
    multicast = getattr(bus, '_multicast', None)
    return multicast if isinstance(getattr(multicast, '_socket', None), socket.socket) else None
