"""PDO topics: ``~/node_<id>/rpdo`` (what a device sends) and ``~/node_<id>/tpdo`` (to it).

Named from the gateway's side, as ros2_canopen names them: the gateway receives the device's
TPDOs as its RPDOs and publishes them on ``rpdo``; it transmits what arrives on ``tpdo`` to the
device's RPDOs.

Received frames are published by a thread of their own, not by the bus thread: a publication
(message building, serialization, a DDS write) costs tens of microseconds, at 5,000 frames a
second a quarter of the bus thread, which must keep taking SDO answers and heartbeats on time.
Every frame is queued and the thread publishes each as soon as it has published the ones
before it (no fixed number per tick, unlike ros2_canopen #322).
"""

import logging
import math
import queue
import threading
import time
from typing import Callable, Dict, List, Optional, Sequence, Tuple

from builtin_interfaces.msg import Time
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..core.bus import wall_clock
from ..core.pdo.mapping import EntryValue, MAX_PDOS, PdoMapping, ReceivedPdo
from ..core.pdo.service import PdoService
from ..msg import Pdo, PdoEntry

LOGGER = logging.getLogger(__name__)

# Reliable, so a subscriber on the same host gets every frame, and keep-last, so a slow or
# stalled subscriber never holds the publisher up (it loses the oldest frames instead): 100
# is a second of a 100 Hz PDO. Reliable publishers (ros2 topic pub, rclpy's default) match the
# tpdo subscription; a best-effort publisher does not: commands are not to be lost silently.
PDO_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)

# Frames waiting for the publishing thread; beyond this new ones are dropped (counted).
QUEUE_LIMIT = 100_000
# How often the bus thread asks whether a device's rpdo topic has subscribers: a new
# subscriber gets frames from at most this long after it matched.
SUBSCRIBERS_CHECK = 0.1


def topic(node_id: int, direction: str) -> str:
    """Return the topic of a device's PDOs: direction 'rpdo' (published) or 'tpdo'."""
    return f'~/node_{node_id}/{direction}'


def stamp_of(monotonic: float) -> Time:
    """Return the ROS time of a frame received at ``monotonic`` (``time.monotonic()``)."""
    wall = wall_clock(monotonic)
    whole = math.floor(wall)
    return Time(sec=whole, nanosec=min(int((wall - whole) * 1e9), 999_999_999))


def pdo_message(received: ReceivedPdo, reused: Optional[Pdo] = None) -> Pdo:
    """Return the ``cbcan_ros/msg/Pdo`` of one received frame.

    ``reused``, a message made before for the same mapping, is filled in again: only the
    stamp, the bytes and the values change, and rclpy copies a message when it publishes it.
    On the hot path that halves the cost of building one (its setters check every field).
    """
    message = reused
    if message is None:
        mapping = received.mapping
        message = Pdo(node_id=mapping.node_id, pdo=mapping.number, cob_id=mapping.cob_id,
                      entries=[PdoEntry(index=entry.index, subindex=entry.subindex,
                                        name=entry.name, data_type=entry.data_type,
                                        bits=entry.bits)
                               for entry in mapping.entries])
    message.stamp = stamp_of(received.timestamp)
    message.data = received.data
    for entry, decoded in zip(message.entries, received.entries, strict=True):
        entry.value = decoded.value
        entry.data = decoded.data
    return message


def check_request(node_id: int, pdo: int) -> Optional[str]:
    """Return why a PDO number cannot name an RPDO, or None."""
    if not 1 <= pdo <= MAX_PDOS:
        return f'pdo {pdo} is out of range: allowed 1..{MAX_PDOS}'
    return None


def entry_values(entries: Sequence[PdoEntry]) -> List[EntryValue]:
    """Return the values of a message's entries for :meth:`PdoService.write`."""
    return [EntryValue(entry.index, entry.subindex, entry.value, bytes(entry.data))
            for entry in entries]


class PdoTopics:
    """The rpdo publishers and tpdo subscriptions of every device of ``pdo.nodes``.

    ``on_message(node_id, message)`` gets each message arriving on a tpdo topic (in the
    executor); ``active()`` says whether to publish.
    """

    def __init__(self, node: Node, service: PdoService,
                 on_message: Callable[[int, Pdo], None], active: Callable[[], bool]):
        self._node = node
        self._active = active
        self._publishers = {node_id: node.create_publisher(Pdo, topic(node_id, 'rpdo'),
                                                           PDO_QOS)
                            for node_id in service.node_ids}
        self._subscriptions = [
            node.create_subscription(Pdo, topic(node_id, 'tpdo'),
                                     lambda message, n=node_id: on_message(n, message),
                                     PDO_QOS)
            for node_id in service.node_ids]
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._subscribers: Dict[int, Tuple[float, bool]] = {}  # node: (asked at, any)
        self._closing = False
        self.dropped = 0
        self._thread = threading.Thread(target=self._publish_queued, name='pdo publisher',
                                        daemon=True)
        if self._publishers:
            self._thread.start()
            service.add_listener(self._queue_frame)

    def destroy(self) -> None:
        """End the publishing thread and take the topics away (after the bus is closed)."""
        self._closing = True
        self._queue.put(None)
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        for publisher in self._publishers.values():
            self._node.destroy_publisher(publisher)
        for subscription in self._subscriptions:
            self._node.destroy_subscription(subscription)

    def _queue_frame(self, received: ReceivedPdo) -> None:
        # The bus thread: one put on a queue written in C, no lock of ours. A frame of a topic
        # nobody subscribes to is dropped here rather than waking the publishing thread for
        # nothing (volatile: a later subscriber would never get it), as drives send theirs
        # every few milliseconds whether anyone listens or not.
        if not self._subscribed(received.mapping.node_id):
            return
        if self._queue.qsize() >= QUEUE_LIMIT:
            self.dropped += 1
            return
        self._queue.put(received)

    def _subscribed(self, node_id: int) -> bool:
        """Return whether ``~/node_<id>/rpdo`` has subscribers.

        Asked of rclpy at most every ``SUBSCRIBERS_CHECK``: not a call into rcl for each of
        thousands of frames a second.
        """
        now = time.monotonic()
        known = self._subscribers.get(node_id)
        if known is None or now - known[0] >= SUBSCRIBERS_CHECK:
            known = self._subscribers[node_id] = (
                now, bool(self._publishers[node_id].get_subscription_count()))
        return known[1]

    def _publish_queued(self) -> None:
        failures = set()
        messages: Dict[Tuple[int, int], Tuple[PdoMapping, Pdo]] = {}
        while True:
            received = self._queue.get()
            if received is None or self._closing:
                return
            if not self._active():
                continue
            mapping = received.mapping
            publisher = self._publishers[mapping.node_id]
            try:
                # One message per PDO, filled again for each frame (the thread's own).
                kept = messages.get((mapping.node_id, mapping.number))
                message = pdo_message(received, kept[1] if kept and kept[0] is mapping
                                      else None)
                messages[(mapping.node_id, mapping.number)] = (mapping, message)
                publisher.publish(message)
            except Exception as error:  # noqa: BLE001 - one bad publication, not the rest
                kind = type(error).__name__
                if kind not in failures:
                    failures.add(kind)
                    LOGGER.error('a PDO could not be published (%s: %s); later failures '
                                 'of this kind are not logged', kind, error)
