"""A python-can bus that injects faults on command, for testing the gateway's bus supervision.

``FaultyBus`` wraps a python-can ``virtual`` bus on the same channel, so frames pass both ways
between it and every other virtual-bus user of that channel (simulated CANopen devices, raw test
buses). Faults are armed per channel through ``FaultController.get(channel)``, from any thread,
also while another thread is blocked in ``recv``:

* ``fail_receive(text)``: every FaultyBus open on the channel at that moment fails in ``recv``
  with ``can.CanOperationError(text)`` (within ``FaultyBus.POLL_PERIOD``, 10 ms, also when a
  ``recv`` is already waiting) and keeps failing, like an unplugged adapter, until that instance
  is shut down or ``clear()`` heals it. A bus opened afterwards works normally.
* ``fail_send(text)``: every ``send`` on the channel raises ``can.CanOperationError(text)``
  (nothing reaches the bus) until ``clear()``; applies to buses opened later too.
  ``fail_send(text, after=n)`` lets ``n`` more frames out first: an adapter pulled midway.
* ``fail_open(text)``: constructing a FaultyBus on the channel raises
  ``can.CanInitializationError(text)`` until ``clear()``.
* ``bus_off()``: every open FaultyBus on the channel receives an error frame as SocketCAN
  delivers one on bus-off (``is_error_frame=True``, ``arbitration_id=CAN_ERR_BUSOFF``).
* ``clear()``: heal everything above (frames already delivered stay delivered).

Counters on the controller: ``open_count`` (successful constructions), ``open_failures``,
``receive_failures`` and ``send_failures`` (exceptions raised), ``sent`` (the frames that went
out through any FaultyBus on the channel, oldest first) and ``buses`` (instances now open). The
counters cover every FaultyBus on the channel, whoever opened it.

Registration: ``register()`` adds the interface name ``faulty`` to python-can (its ``BACKENDS``
table and the ``VALID_INTERFACES`` sets that ``can.Bus`` checks), naming this module by its
``__name__``; python-can then imports it by that name and finds the already-imported module, so
the bus and the test share one controller registry. Call it once per process before
``can.Bus(interface='faulty', channel=...)``. Controllers live in the process that imported the
module: a child process has to import this module and call ``register()`` itself, and its faults
are armed there.
"""

import queue
import threading
import time
from typing import ClassVar, Dict, List, Optional

import can

INTERFACE_NAME = 'faulty'
CAN_ERR_BUSOFF = 0x40  # linux/can/error.h: the controller went bus-off


class FaultController:
    """Faults and counters of one channel; get it with ``FaultController.get(channel)``."""

    _registry: ClassVar[Dict[str, 'FaultController']] = {}
    _registry_lock: ClassVar[threading.Lock] = threading.Lock()

    def __init__(self, channel: str):
        self.channel = channel
        self._lock = threading.Lock()
        self._open_error: Optional[str] = None
        self._send_error: Optional[str] = None
        self._sends_left = 0
        self.closing = None  # an Event: closing a bus waits for it (a driver slow to close)
        self._buses: List['FaultyBus'] = []
        self._sent: List[can.Message] = []
        self.open_count = 0
        self.open_failures = 0
        self.receive_failures = 0
        self.send_failures = 0

    @classmethod
    def get(cls, channel: str) -> 'FaultController':
        """Return the controller of ``channel``, creating it on first use."""
        with cls._registry_lock:
            controller = cls._registry.get(str(channel))
            if controller is None:
                controller = cls._registry[str(channel)] = cls(str(channel))
            return controller

    @classmethod
    def forget(cls, channel: str) -> None:
        """Drop the controller of ``channel`` (faults and counters); open buses keep theirs."""
        with cls._registry_lock:
            cls._registry.pop(str(channel), None)

    def fail_receive(self, error_message: str = 'adapter unplugged') -> int:
        """Make every bus open now fail in recv until shut down; return how many were hit."""
        buses = self.buses
        for bus in buses:
            bus.fail_receive(error_message)
        return len(buses)

    def fail_send(self, error_message: str = 'transmit failed', after: int = 0) -> None:
        """Make every send on the channel raise ``can.CanOperationError`` until ``clear()``.

        ``after``: the number of sends that still succeed before the first fails.
        """
        with self._lock:
            self._send_error = error_message
            self._sends_left = after

    def fail_open(self, error_message: str = 'no such adapter') -> None:
        """Make opening a bus on the channel raise ``can.CanInitializationError``."""
        with self._lock:
            self._open_error = error_message

    def bus_off(self) -> int:
        """Deliver a bus-off error frame to every open bus; return how many got it."""
        buses = self.buses
        for bus in buses:
            bus.inject(can.Message(is_error_frame=True, arbitration_id=CAN_ERR_BUSOFF,
                                   is_extended_id=False, dlc=8, data=bytes(8),
                                   channel=self.channel))
        return len(buses)

    def clear(self) -> None:
        """Heal every fault: open, send, and the receive faults of the open buses."""
        with self._lock:
            self._open_error = None
            self._send_error = None
        for bus in self.buses:
            bus.heal()

    @property
    def sent(self) -> List[can.Message]:
        """Return a copy of the frames sent through the channel's FaultyBuses, oldest first."""
        with self._lock:
            return list(self._sent)

    @property
    def buses(self) -> List['FaultyBus']:
        """Return the FaultyBuses open on the channel now, in the order they were opened."""
        with self._lock:
            return list(self._buses)

    def _check_open(self) -> None:
        with self._lock:
            if self._open_error is not None:
                self.open_failures += 1
                raise can.CanInitializationError(self._open_error)

    def _opened(self, bus: 'FaultyBus') -> None:
        with self._lock:
            self.open_count += 1
            self._buses.append(bus)

    def _closed(self, bus: 'FaultyBus') -> None:
        with self._lock:
            if bus in self._buses:
                self._buses.remove(bus)

    def _check_send(self) -> None:
        with self._lock:
            if self._send_error is not None and self._sends_left:
                self._sends_left -= 1
            elif self._send_error is not None:
                self.send_failures += 1
                raise can.CanOperationError(self._send_error)

    def _record_sent(self, msg: can.Message) -> None:
        with self._lock:
            self._sent.append(msg)

    def _count_receive_failure(self) -> None:
        with self._lock:
            self.receive_failures += 1


class FaultyBus(can.BusABC):
    """A ``virtual`` bus on ``channel`` whose open, recv and send fail when the test says so.

    Without an armed fault it behaves like ``can.Bus(interface='virtual', channel=channel)``.
    Options other than ``receive_own_messages`` and ``can_filters`` (``bitrate``, ...) are
    accepted and ignored, as a real interface's options would be.
    """

    POLL_PERIOD = 0.01  # seconds: the longest a waiting recv takes to notice a receive fault

    def __init__(self, channel: str, receive_own_messages: bool = False, **kwargs):
        controller = FaultController.get(str(channel))
        controller._check_open()
        self._controller = controller
        self._receive_error: Optional[str] = None
        self._injected: 'queue.SimpleQueue[can.Message]' = queue.SimpleQueue()
        self._inner = can.Bus(interface='virtual', channel=str(channel),
                              receive_own_messages=receive_own_messages)
        self.channel_info = f'faulty bus over virtual channel {channel!r}'
        super().__init__(channel=channel, can_filters=kwargs.get('can_filters'))
        controller._opened(self)

    @property
    def controller(self) -> FaultController:
        """Return the controller of this bus's channel."""
        return self._controller

    def fail_receive(self, error_message: str = 'adapter unplugged') -> None:
        """Make this bus fail in recv from now on, until it is shut down or healed."""
        self._receive_error = error_message

    def heal(self) -> None:
        """Undo ``fail_receive`` on this bus."""
        self._receive_error = None

    def inject(self, msg: can.Message) -> None:
        """Queue ``msg`` to be returned by this bus's recv ahead of the frames on the channel."""
        self._injected.put(msg)

    def _raise_if_failed(self) -> None:
        error = self._receive_error
        if error is not None:
            self._controller._count_receive_failure()
            raise can.CanOperationError(error)

    def _recv_internal(self, timeout: Optional[float]):
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            self._raise_if_failed()
            try:
                return self._injected.get_nowait(), False
            except queue.Empty:
                pass
            wait = self.POLL_PERIOD
            if deadline is not None:
                wait = min(wait, max(0.0, deadline - time.monotonic()))
            msg = self._inner.recv(wait)
            if msg is not None:
                self._raise_if_failed()  # an unplugged adapter loses what was in flight
                return msg, False
            if deadline is not None and time.monotonic() >= deadline:
                return None, False

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        """Send ``msg`` to the channel, or raise ``can.CanOperationError`` if sends fail."""
        self._controller._check_send()
        self._inner.send(msg, timeout)
        self._controller._record_sent(msg)

    def shutdown(self) -> None:
        """Close the bus; a receive fault ends with it (safe to call more than once)."""
        if self._is_shutdown:
            return
        closing = self._controller.closing
        if closing is not None:
            closing.wait()
        super().shutdown()
        self._inner.shutdown()
        self._controller._closed(self)


def register() -> None:
    """Make ``can.Bus(interface='faulty', channel=...)`` create a FaultyBus (idempotent)."""
    register_backend(INTERFACE_NAME, __name__, FaultyBus.__name__)


def register_backend(name: str, module: str, class_name: str) -> None:
    """Make ``can.Bus(interface=name)`` create ``module.class_name`` in this process."""
    import can.interfaces
    import can.util

    can.interfaces.BACKENDS[name] = (module, class_name)
    valid = frozenset(can.interfaces.BACKENDS)
    can.interfaces.VALID_INTERFACES = valid
    can.util.VALID_INTERFACES = valid
    can.VALID_INTERFACES = valid
