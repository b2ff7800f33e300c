"""What a ``udp_multicast`` group carries that is no frame of this bus: dropped, counted.

python-can 4.6.1's ``udp_multicast`` driver takes whatever another program sends to the
group's port:

- a datagram it cannot unpack makes ``recv`` raise ``CanOperationError('could not unpack
  received message')``, which a receive loop can only take as a failed adapter (one took the
  gateway's bus down and failed the transfers under way, a few more kept it down);
- a datagram it does unpack is a ``Message`` whatever its field types (msgpack carries
  floats, and its check lets an arbitration id of 0.5 through), which no CANopen code expects
  (one ended the gateway's receive thread: the bus looked up and was deaf);
- an error frame is another program's (no adapter reports to a group), yet a bus-off one
  would take the gateway's bus down.

Here the driver drops all three and tells ``on_dropped()``; the bus stays up.
"""

from typing import Callable

import can

from . import udp_multicast_of

# python-can 4.6.1's text for a datagram it could not unpack (udp_multicast/bus.py).
UNDECODABLE = 'could not unpack received message'


def drop_foreign_datagrams(bus: can.BusABC, on_dropped: Callable[[], None]) -> bool:
    """Have a ``udp_multicast`` ``bus`` drop what is no frame of it, calling ``on_dropped()``.

    Return whether it does (False: any other bus, left as it is).
    """
    if udp_multicast_of(bus) is None:
        return False
    receive = bus._recv_internal

    def recv_internal(timeout):
        try:
            message, filtered = receive(timeout)
        except can.CanOperationError as error:
            if str(error) != UNDECODABLE or error.__cause__ is None:
                raise  # the socket itself failed: a bus fault
            on_dropped()
            return None, False
        if message is not None and not _is_frame_of_this_bus(message):
            on_dropped()
            return None, False
        return message, filtered
    bus._recv_internal = recv_internal
    return True


def _is_frame_of_this_bus(message: can.Message) -> bool:
    """Return whether ``message`` is a well-formed CAN frame, not another bus's error frame."""
    # Every received frame passes here: the flags are checked one by one, not in a loop
    # over their names, which took three times as long.
    can_id, data, extended, fd = (message.arbitration_id, message.data, message.is_extended_id,
                                  message.is_fd)
    return (type(extended) is bool and type(fd) is bool
            and message.is_error_frame is False
            and type(message.is_remote_frame) is bool and type(message.bitrate_switch) is bool
            and type(message.error_state_indicator) is bool and type(message.is_rx) is bool
            and type(can_id) is int and 0 <= can_id < (0x20000000 if extended else 0x800)
            and isinstance(data, (bytes, bytearray))
            and len(data) <= (64 if fd else 8))
