"""A datagram on the ``udp_multicast`` group that holds no frame: dropped, not a dead bus.

python-can 4.6.1's ``udp_multicast`` driver raises ``CanOperationError('could not unpack
received message')`` from ``recv`` for any datagram on the group's port it cannot unpack
(another program on the same group and port, a scan, a python-can of another wire format),
which a receive loop can only take as a failed adapter: one such datagram took the gateway's
bus down and failed the transfers under way, and a few more kept it down. Here the driver
drops such a datagram and tells ``on_skipped``; the bus stays up.
"""

from typing import Callable

import can

from . import udp_multicast_of

# python-can 4.6.1's text for a datagram it could not unpack (udp_multicast/bus.py).
UNDECODABLE = 'could not unpack received message'


def skip_undecodable(bus: can.BusABC, on_skipped: Callable[[], None]) -> bool:
    """Have a ``udp_multicast`` ``bus`` drop datagrams that are no frame, calling ``on_skipped()``.

    Return whether it does (False: any other bus, left as it is).
    """
    if udp_multicast_of(bus) is None:
        return False
    receive = bus._recv_internal

    def recv_internal(timeout):
        try:
            return receive(timeout)
        except can.CanOperationError as error:
            if str(error) != UNDECODABLE or error.__cause__ is None:
                raise  # the socket itself failed: a bus fault
            on_skipped()
            return None, False
    bus._recv_internal = recv_internal
    return True
