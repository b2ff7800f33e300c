"""Raw CAN frames as ROS: ``~/from_can_bus``, ``~/to_can_bus`` and ``~/send_frames``.

The topics carry ``can_msgs/msg/Frame`` under the names ros2_socketcan gives them, so its
tools and the programs written for it work with the gateway's bus (remapped where they
expect other names). can_msgs is imported only when the topics are asked for, so the
gateway runs without it otherwise (the parameters refuse to start without it, saying so).

Received frames are published by a thread of their own, as the PDOs are (``pdo.py``): the
bus receive thread only queues each frame that passed ``raw.filters``, and the thread
publishes them in that order, each stamped with the host's time at which the bus thread took
it from the adapter.
"""

import logging
import math
import queue
import threading
from typing import Callable, Optional

from builtin_interfaces.msg import Time
import can
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..core.bus import wall_clock
from ..core.raw.frames import Frame, RawFrames, Refusal
from ..srv import SendFrames
from .pdo import QUEUE_LIMIT

LOGGER = logging.getLogger(__name__)

# Reliable, as ros2_socketcan's publisher and subscription (depth 500 there): a subscriber on
# the same host gets every frame. Keep-last, deeper than ros2_socketcan's: a subscriber that
# stalls loses the oldest frames rather than holding the publisher up, and this is a fifth
# of a second of a saturated 1 Mbit/s bus.
RAW_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)

FROM_BUS = '~/from_can_bus'
TO_BUS = '~/to_can_bus'

PADDING = bytes(8)


def frame_of(message) -> Frame:
    """Return the core's frame of a ``can_msgs/msg/Frame`` or ``cbcan_ros/msg/CanFrame``."""
    return Frame(can_id=message.id, data=bytes(message.data), dlc=message.dlc,
                 is_extended=message.is_extended, is_rtr=message.is_rtr,
                 is_error=message.is_error)


def fill_frame(out, message: can.Message, wall: float) -> None:
    """Write a received python-can frame, taken at ``wall`` (``time.time()``), into ``out``."""
    whole = math.floor(wall)
    out.header.stamp = Time(sec=whole, nanosec=min(int((wall - whole) * 1e9), 999_999_999))
    out.id = message.arbitration_id
    out.is_rtr = message.is_remote_frame
    out.is_extended = message.is_extended_id
    out.is_error = message.is_error_frame
    out.dlc = message.dlc
    # A fixed uint8[8]: rclpy takes a list of ints (bytes it would read as one number).
    out.data = list((bytes(message.data) + PADDING)[:8])


class RawFrameTopics:
    """The raw bridge of one gateway node.

    ``inactive()`` returns why nothing may be sent or published now (a managed node that is
    not active), or None. ``service`` is the rclpy service of ``~/send_frames``, answered in
    its callback; the owner drains and destroys it with its other services.
    """

    def __init__(self, node: Node, raw: RawFrames, inactive: Callable[[], Optional[str]],
                 frame_id: str, **service_options):
        self._node = node
        self._raw = raw
        self._inactive = inactive
        self._frame_id = frame_id
        self.service = node.create_service(SendFrames, '~/send_frames', self._on_send_frames,
                                           **service_options)
        self._publisher = None
        self._subscription = None
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._closing = False
        self._thread = threading.Thread(target=self._publish_queued, name='raw publisher',
                                        daemon=True)
        sending = not raw.settings.send_allow.empty
        if not raw.receiving and not sending:
            return  # no topics: can_msgs is not needed
        from can_msgs.msg import Frame as FrameMessage  # checked by the parameters
        self._message_type = FrameMessage
        if raw.receiving:
            self._publisher = node.create_publisher(FrameMessage, FROM_BUS, RAW_QOS)
            self._thread.start()
            raw.add_listener(self._queue_frame)
        if sending:
            self._subscription = node.create_subscription(FrameMessage, TO_BUS,
                                                          self._on_to_bus, RAW_QOS)

    def destroy(self) -> None:
        """End the publishing thread and take the topics away (after the bus is closed)."""
        self._closing = True
        self._queue.put(None)
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        if self._publisher is not None:
            self._node.destroy_publisher(self._publisher)
        if self._subscription is not None:
            self._node.destroy_subscription(self._subscription)

    def _on_send_frames(self, request, response):
        try:
            refusal = self._inactive()
            if refusal:
                response.success, response.sent, response.message = False, 0, refusal
                return response
            result = self._raw.send([frame_of(frame) for frame in request.frames])
            response.success, response.sent, response.message = (result.success, result.sent,
                                                                  result.message)
        except Exception as error:  # noqa: BLE001 - it would end the node's executor
            response.success = False
            response.message = f'internal error of the gateway: {type(error).__name__}: ' \
                               f'{error}'[:300]
        return response

    def _on_to_bus(self, message) -> None:
        """Send what arrived on ~/to_can_bus; a refusal is logged once per kind and counted."""
        refusal = self._inactive()
        try:
            refused = (Refusal('inactive', refusal) if refusal
                       else self._raw.send_one(frame_of(message)))
        except Exception as error:  # noqa: BLE001 - it would end the node's executor
            refused = Refusal('internal error', f'internal error of the gateway: '
                                                f'{type(error).__name__}: {error}')
        if refused is not None:
            self._raw.refuse(f'{TO_BUS[2:]}: frame not sent', refused)

    def _queue_frame(self, message: can.Message, stamp: float) -> None:
        # The bus receive thread: one put on a queue written in C, no lock of ours. A frame
        # received while the node is inactive is never published, even after activation, and
        # one nobody subscribes to is dropped here rather than waking the publishing thread
        # (volatile: a later subscriber would never get it), as the PDO topics do.
        if self._inactive() or not self._publisher.get_subscription_count():
            return
        if self._queue.qsize() >= QUEUE_LIMIT:
            self._raw.lost()
            return
        self._queue.put((message, stamp))

    def _publish_queued(self) -> None:
        failures = set()
        out = self._message_type()  # filled again for each frame: rclpy copies on publish
        out.header.frame_id = self._frame_id
        publisher = self._publisher
        latest = 0.0
        while True:
            item = self._queue.get()
            if item is None or self._closing:
                return
            message, stamp = item
            # The wall clock of a monotonic stamp is read anew for each frame; the two clocks
            # are read a moment apart, which would put a frame microseconds before the one
            # received before it: stamps keep bus order.
            latest = max(wall_clock(stamp), latest)
            try:
                fill_frame(out, message, latest)
                publisher.publish(out)
            except Exception as error:  # noqa: BLE001 - one bad publication, not the rest
                kind = type(error).__name__
                if kind not in failures:
                    failures.add(kind)
                    LOGGER.error('a raw frame could not be published (%s: %s); later '
                                 'failures of this kind are not logged', kind, error)
