"""canopen 2.4.1's ``EmcyConsumer``, decoding one device's EMCY frames for the gateway.

``EmcyConsumer`` keeps every EMCY it ever received in two lists (memory grows on a
long-running robot), and a frame shorter than 8 bytes raises ``struct.error`` into the receive
thread: :class:`EmcyDecoder` keeps the latest only and says "malformed".
"""

import struct
from typing import Tuple

from canopen.emcy import EmcyConsumer, EmcyError


class MalformedEmcy(Exception):
    """A frame on an EMCY COB-ID that is not an EMCY (CiA 301: 8 bytes)."""


class EmcyDecoder:
    """canopen's ``EmcyConsumer`` for one device, keeping only what is still needed."""

    def __init__(self):
        self._consumer = EmcyConsumer()

    def decode(self, can_id: int, data: bytes, timestamp: float) -> Tuple[EmcyError, bool]:
        """Decode one frame; return the EMCY and whether it is an active error.

        Raises :class:`MalformedEmcy` for a frame shorter than an EMCY.
        """
        consumer = self._consumer
        try:
            consumer.on_emcy(can_id, data, timestamp)
        except struct.error:
            raise MalformedEmcy(f'{len(data)} bytes') from None
        with consumer.emcy_received:
            error = consumer.log[-1]
            # An error reset has emptied the consumer's active list; any other EMCY is on it.
            is_active = bool(consumer.active) and consumer.active[-1] is error
            del consumer.log[:]
            del consumer.active[:-1]
        return error, is_active
