"""The PDOs of a simulated durand device: the parameters it stores, and TPDO event timers.

durand 0.5.0's TPDOs have no event timer (0x1800+n sub 5): added here, transmitting an
event-driven TPDO every event timer period while it is active. Its PDO parameters survive a
reset; a device restores its stored ones: :class:`PdoConfig` lists those, applied at every
boot. Its TPDOs of transmission type 2..240 send on every SYNC once they have sent on the nth:
mended here (:class:`_SyncHandler`), for every durand device of the process.
"""

from dataclasses import dataclass
from typing import Dict, Optional, Sequence, Tuple

import durand
from durand.datatypes import DatatypeEnum as DT
from durand.object_dictionary import Variable
from durand.services.pdo import tpdo as durand_tpdo

from .scheduler import shared_scheduler

# 4 PDOs each way, the predefined connection set.
PDOS = 4
TPDO_COMMUNICATION = 0x1800
EVENT_TIMER_SUB = 5


class _SyncHandler(durand_tpdo.SyncHandler):
    """durand's SYNC handling of a synchronous TPDO, sending every nth SYNC (type n), not after.

    durand 0.5.0 counts SYNCs without ever starting the count again. Nor is a TPDO sent outside
    OPERATIONAL, where durand's attempt fails (and is swallowed) for want of mapped values.
    """

    def _on_sync(self):
        if self._tpdo._cache is None:
            return  # not active: nothing to send
        if not self._divider:
            super()._on_sync()  # type 0: once after a change, as durand does
            return
        self._counter += 1
        if self._counter >= self._divider:
            self._counter = 0
            self._tpdo.transmit()


# durand makes a TPDO's handler by this module name whenever its transmission type is set.
durand_tpdo.SyncHandler = _SyncHandler


@dataclass(frozen=True)
class PdoConfig:
    """One PDO's parameters as a device stores them (applied at every boot).

    ``kind`` 'tpdo' (the device sends it) or 'rpdo' (it receives it); ``number`` 1..4;
    ``mapping`` the mapped objects (index, subindex), each its full size.
    """

    kind: str
    number: int
    mapping: Tuple[Tuple[int, int], ...]
    transmission_type: int = 255
    event_timer: int = 0  # ms, TPDOs only
    enabled: bool = True


class StoredPdos:
    """The PDO parameters a device stores, and its TPDOs' event timers, on its durand node.

    Call :meth:`install` with each new node, before its first :meth:`apply`.
    """

    def __init__(self, configs: Sequence[PdoConfig]):
        self.configs = tuple(configs)
        self._node: Optional[durand.Node] = None
        self._event_timers: Dict[int, object] = {}

    def install(self, node: durand.Node) -> None:
        """Add the event timer objects (0x1800+n sub 5) to the dictionary of ``node``."""
        self._node = node
        od = node.object_dictionary
        for number in range(1, PDOS + 1):
            index = TPDO_COMMUNICATION + number - 1
            od.lookup(index)[EVENT_TIMER_SUB] = Variable(DT.UNSIGNED16, 'rw', 0,
                                                         name='Event timer')
            od.update_callbacks[(index, EVENT_TIMER_SUB)].add(
                lambda value, number=number: self._set_event_timer(number, value))

    def apply(self) -> None:
        """Write the stored parameters into the node's PDOs (and their event timers)."""
        node = self._node
        for config in self.configs:
            pdo = (node.tpdo if config.kind == 'tpdo' else node.rpdo)[config.number - 1]
            pdo.enable = False
            pdo.mapping = config.mapping
            pdo.transmission_type = config.transmission_type
            if config.kind == 'tpdo':
                node.object_dictionary.write(TPDO_COMMUNICATION + config.number - 1,
                                             EVENT_TIMER_SUB, config.event_timer)
            pdo.enable = config.enabled

    def stop_event_timers(self) -> None:
        """Cancel every event timer (the device goes silent)."""
        for number in list(self._event_timers):
            self._set_event_timer(number, 0)

    def _set_event_timer(self, number: int, milliseconds: int) -> None:
        scheduler = shared_scheduler()
        timer = self._event_timers.pop(number, None)
        if timer is not None:
            scheduler.cancel(timer)
        if milliseconds:
            self._event_timers[number] = scheduler.add(
                milliseconds / 1000, self._event_timer_fired, (number, milliseconds))

    def _event_timer_fired(self, number: int, milliseconds: int) -> None:
        tpdo = self._node.tpdo[number - 1]
        if tpdo._cache is not None and tpdo.transmission_type >= 254:  # active, event-driven
            tpdo.transmit()
        self._event_timers[number] = shared_scheduler().add(
            milliseconds / 1000, self._event_timer_fired, (number, milliseconds))
