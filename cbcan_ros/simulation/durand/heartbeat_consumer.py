"""A heartbeat consumer (CiA 301, 0x1016) for a simulated durand device; durand has none.

It watches one producer's heartbeat on the device's own bus (``network.BusNetwork``,
by a hook on 0x700 + producer id) and calls back when the producer has been silent for the
consumer time, with a timer on the shared scheduler: nothing polls.
"""

from typing import Callable, Optional

from ...core import nmt
from .network import BusNetwork
from .scheduler import shared_scheduler


class HeartbeatConsumer:
    """Watches the producer that a 0x1016 entry names; ``on_lost()`` when it falls silent.

    Monitoring starts with the first heartbeat heard, and every heartbeat restarts it; after
    a loss it waits for the next heartbeat. Call everything under the scheduler's lock.
    """

    def __init__(self, on_lost: Callable[[], None]):
        self._on_lost = on_lost
        self._network: Optional[BusNetwork] = None
        self._cob_id: Optional[int] = None
        self._timeout = 0.0
        self._timer = None

    def configure(self, network: BusNetwork, entry: int) -> None:
        """Watch what ``entry`` says: (producer id << 16) | time in ms; 0 in either is off."""
        self.stop()
        producer, milliseconds = (entry >> 16) & 0x7F, entry & 0xFFFF
        if producer and milliseconds:
            self._network, self._cob_id = network, nmt.HEARTBEAT_COB_BASE + producer
            self._timeout = milliseconds / 1000
            network.hooks[self._cob_id] = self._on_heartbeat

    def stop(self) -> None:
        """Stop watching."""
        if self._cob_id is not None:
            self._network.hooks.pop(self._cob_id, None)
            self._network = self._cob_id = None
        if self._timer is not None:
            shared_scheduler().cancel(self._timer)
            self._timer = None

    def _on_heartbeat(self, durand_handler, cob_id: int, data: bytes) -> None:
        scheduler = shared_scheduler()
        if self._timer is not None:
            scheduler.cancel(self._timer)
        self._timer = scheduler.add(self._timeout, self._lost)

    def _lost(self) -> None:
        self._timer = None
        self._on_lost()
