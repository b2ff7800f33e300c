"""What a ``udp_multicast`` group carries that is no frame of this bus: dropped, counted.

python-can 4.6.1's ``udp_multicast`` driver takes whatever another program sends to the
group's port:

- a datagram it cannot unpack makes ``recv`` raise ``CanOperationError('could not unpack
  received message')``, which a receive loop can only take as a failed adapter (one took the
  gateway's bus down and failed the transfers under way, a few more kept it down);
- a datagram it does unpack is a ``Message`` whatever its field types: msgpack carries floats
  (its check lets an arbitration id of 0.5 through, and a dlc of 1.0 or True), and ``data``
  of any type is made bytes (an int 1 becomes one zero byte, a boot-up; a list ``[5]`` an
  OPERATIONAL heartbeat), which no CANopen code expects (one ended the gateway's receive
  thread: the bus looked up and was deaf);
- a CAN FD frame is taken (the driver opens for FD unless told not to), though CANopen here
  runs on classic CAN;
- an error frame is another program's (no adapter reports to a group), yet a bus-off one
  would take the gateway's bus down.

Here the bus receives through :func:`drop_foreign_datagrams`' own ``_recv_internal``: it
unpacks each datagram as python-can does, checks the field types before python-can converts
them, and drops all of the above, telling ``on_dropped()``; the bus stays up.
"""

from typing import Callable, Optional

import can
import msgpack

from . import udp_multicast_of


def drop_foreign_datagrams(bus: can.BusABC, on_dropped: Callable[[], None]) -> bool:
    """Have a ``udp_multicast`` ``bus`` drop what is no frame of it, calling ``on_dropped()``.

    Return whether it does (False: any other bus, left as it is).
    """
    multicast = udp_multicast_of(bus)
    if multicast is None:
        return False
    receive = multicast.recv  # raises CanOperationError when the socket fails: a bus fault

    def recv_internal(timeout):
        received = receive(timeout)
        if not received:
            return None, False
        datagram, _sender, stamp = received
        message = _frame_of_this_bus(datagram, stamp)
        if message is None:
            on_dropped()
            return None, False
        return message, False
    bus._recv_internal = recv_internal
    return True


def _frame_of_this_bus(datagram: bytes, stamp: float) -> Optional[can.Message]:
    """Return the classic CAN frame ``datagram`` carries (received at ``stamp``), else None.

    The datagram as python-can's ``pack_message`` makes it: a msgpack map of ``Message``'s
    fields, ``data`` as msgpack bin.
    """
    try:
        fields = msgpack.unpackb(datagram, raw=False)
    except Exception:  # noqa: BLE001 - whatever fails to unpack is no frame
        return None
    if type(fields) is not dict or not _typed_as_a_frame(fields):
        return None
    fields['timestamp'] = stamp  # the kernel's receive time, as the driver's replace does
    try:
        message = can.Message(check=True, **fields)
    except (TypeError, ValueError):  # a field Message does not have, or values it refuses
        return None
    can_id = message.arbitration_id
    if (message.is_fd or message.is_error_frame
            or not 0 <= can_id < (0x20000000 if message.is_extended_id else 0x800)):
        return None
    return message


def _typed_as_a_frame(fields: dict) -> bool:
    """Return whether the fields a datagram names have the types of a frame's.

    Each field absent takes ``Message``'s default. Written out, not looped over names: this
    runs for every received frame.
    """
    get = fields.get
    dlc = get('dlc')
    return (type(get('arbitration_id', 0)) is int and type(get('data', b'')) is bytes
            and (dlc is None or type(dlc) is int)
            and type(get('is_extended_id', True)) is bool
            and type(get('is_remote_frame', False)) is bool
            and type(get('is_error_frame', False)) is bool
            and type(get('is_fd', False)) is bool
            and type(get('bitrate_switch', False)) is bool
            and type(get('error_state_indicator', False)) is bool
            and type(get('is_rx', True)) is bool)
