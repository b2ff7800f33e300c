"""Bus supervision: the one owner of the python-can bus, its health and its reconnection.

python-can's ``Notifier`` ends its receive thread for good on the first receive error, and
canopen's ``Network`` builds on it, so a single bad frame or a replugged adapter would leave
the gateway deaf while it looks healthy. Here one thread opens the bus, receives, and on any
failure (receive or send error, bus-off, an adapter that disappears, a bus that cannot be
opened) reports the bus down once, closes it and opens it again with backoff until it works.

Frames go to the handlers subscribed through canopen's ``Network.subscribe``, called as
canopen's ``Network.notify`` calls them; not through ``notify`` itself, which also files
every frame's node id in a list (``NodeScanner``) that nothing here reads: a scan of up to
127 entries per frame (see the library gaps). A frame nobody subscribed to (the echo of
each frame sent on udp_multicast, mostly) is dropped at once. The network's ``bus`` is a small
proxy whose ``send`` goes through the supervisor, so a send on a bus that is down fails at
once with :class:`BusDown` instead of reaching a dead driver.

The receive thread takes frames from the driver and stamps each with the host's monotonic
clock as it takes it. An adapter's own timestamp is never used: adapters' clocks are offset
from the host's (by seconds on some) and drift. A frame whose handlers are all marked
:func:`prompt` (they return at once: SDO answers, heartbeats, PDOs, LSS answers) is handed
to canopen by the receive thread itself when nothing is waiting for dispatch, which spares
the frame a wake-up of another thread. Every other frame, and every frame behind it, goes
to the dispatch thread in the order taken. So a frame handler that takes its time (or a
burst of frames) holds up only the dispatch: frames are still taken and stamped as they
come, a frame that was on the bus before a request was sent is stamped before it (and the
SDO client can tell it is not the request's answer), and handlers see the frames in the
order they were received, one at a time.
"""

import contextlib
from dataclasses import dataclass
import logging
import queue
import threading
import time
from typing import Callable, List, Optional

import can

from .python_can_gaps.foreign_datagrams import drop_foreign_datagrams
from .python_can_gaps.send_timeout import kernel_send_timeout

LOGGER = logging.getLogger(__name__)

FIRST_RETRY = 0.1
MAX_RETRY = 5.0
RECEIVE_POLL = 0.1  # how soon the receive thread notices a fault reported by a sender
# A transmit queue that does not drain is a fault, not a hang. On udp_multicast the kernel
# holds this bound, not python-can (send_timeout.py: its per-call timeout costs a poll() before
# every send and every receive on the socket).
SEND_TIMEOUT = 0.2
# Frames taken from the driver but not yet handed to canopen, at the most: more than a
# second of a saturated 1 Mbit/s bus. Beyond it frames are dropped and counted, as a
# driver's full receive buffer drops them, rather than held in memory without bound.
DISPATCH_BACKLOG = 10_000

# SocketCAN's error-frame class bit for bus-off (linux/can/error.h CAN_ERR_BUSOFF).
CAN_ERR_BUSOFF = 0x40


def wall_clock(stamp: float) -> float:
    """Return the wall-clock time (``time.time()``) of a frame's ``stamp``.

    Every frame reaches canopen's subscribers stamped with ``time.monotonic()`` when the
    receive thread took it from the driver; this is that moment on the wall clock, for the
    times shown to people and in ROS messages.
    """
    return time.time() - (time.monotonic() - stamp)


def prompt(handler: Callable) -> Callable:
    """Mark a frame handler that returns at once: no I/O, no waiting beyond a short lock.

    Frames whose handlers are all prompt may be handled by the receive thread itself; a
    handler that is not prompt (or not marked) runs on the dispatch thread, where it cannot
    delay the stamping of later frames. The mark is on the function, so every subscription
    of it is prompt. The marks are looked at just before a frame is handed on: a handler
    subscribed in that very moment may get that one frame from the receive thread.
    """
    handler.prompt_handler = True
    return handler


def slcan_bitrates() -> List[int]:
    """Return the bit rates python-can's slcan driver can set (its table of S commands).

    python-can keeps the table private (``slcanBus._BITRATES``) and fails every open with
    another rate, so the parameter checks ask here rather than let the bus reopen for ever.
    """
    from can.interfaces.slcan import slcanBus
    return sorted(slcanBus._BITRATES)


class BusDown(Exception):
    """The CAN bus is not usable now; the message says why."""


@dataclass(frozen=True)
class BusStatus:
    """What callers and diagnostics see of the bus."""

    up: bool
    reason: str           # why it is down ('' while up)
    reopen_count: int     # successful reopens after a fault (the first open is not counted)
    frames_received: int
    frames_sent: int
    error_frames: int
    frames_dropped: int = 0  # received while DISPATCH_BACKLOG frames waited for canopen
    datagrams_dropped: int = 0  # udp_multicast: no frame of this bus (``foreign_datagrams``)


class _SupervisedBus:
    """Stands in for the python-can bus inside canopen's Network.

    Sends go through the supervisor, which knows whether there is a bus to send on.
    """

    def __init__(self, supervisor: 'BusSupervisor'):
        self._supervisor = supervisor
        # canopen calls send(message) for every frame it sends: the supervisor's, directly.
        self.send: Callable[[can.Message], None] = supervisor.send

    @property
    def channel_info(self) -> str:
        return self._supervisor.description


class BusSupervisor:
    """Opens, watches and reopens the bus of a canopen ``Network``.

    ``open_bus`` creates a new python-can bus each time it is called. Listeners get
    ``(status)`` after every change between up and down, from the supervisor's thread.
    """

    def __init__(self, network, open_bus: Callable[[], can.BusABC], description: str):
        self.description = description
        self._network = network
        self._open_bus = open_bus
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._bus: Optional[can.BusABC] = None
        self._send_timeout: Optional[float] = SEND_TIMEOUT  # what the open bus's send() gets
        self._up = False
        self._reason = 'not opened yet'
        self._opened_before = False
        self._down_logged = False
        self._told_up = False  # what the listeners were told last
        self._first_attempt = threading.Event()
        self._fault: Optional[str] = None
        self._stopping = False
        self._send_gate: Optional[Callable[[can.Message], bool]] = None
        self._gate_reason = ''
        self._reopen_count = 0
        self._received = 0
        self._queued = 0      # frames given to the dispatch thread
        self._dispatched = 0  # of those, frames whose handlers have returned
        self._dropped = 0
        self._sent = 0
        self._error_frames = 0
        self._datagrams_dropped = 0
        self._listener_errors = set()
        self._listeners: List[Callable[[BusStatus], None]] = []
        self._frame_watcher: Optional[Callable[[can.Message, float], None]] = None
        self._on_sent: Optional[Callable[[can.Message], None]] = None
        self._frames: queue.SimpleQueue = queue.SimpleQueue()  # (id, data, stamp) or None
        self._thread = threading.Thread(target=self._run, name='can-bus', daemon=True)
        self._dispatcher = threading.Thread(target=self._dispatch, name='can-dispatch',
                                            daemon=True)
        network.bus = _SupervisedBus(self)

    def add_listener(self, listener: Callable[[BusStatus], None]) -> None:
        """Call ``listener(status)`` whenever the bus goes down or comes back up."""
        self._listeners.append(listener)

    def watch_frames(self, watcher: Callable[[can.Message, float], None],
                     on_sent: Optional[Callable[[can.Message], None]] = None) -> None:
        """Call ``watcher(message, stamp)`` for every frame taken, before anything else sees it.

        Every frame: data, remote, extended and error frames, from the receive thread, so
        ``watcher`` must return at once. ``on_sent(message)``, if given, is told of every frame
        about to go out through the bus, python-can's periodic ones (SYNC) included, so frames
        that come back on a bus that echoes can be told apart. Call before :meth:`start`.
        """
        self._frame_watcher = watcher
        self._on_sent = on_sent

    @property
    def down_reason(self) -> Optional[str]:
        """Return why the bus is down, None while it is up (checked for every request)."""
        with self._lock:
            return None if self._up else self._reason

    @property
    def status(self) -> BusStatus:
        """Return the bus state now."""
        with self._lock:
            return BusStatus(self._up, '' if self._up else self._reason, self._reopen_count,
                             self._received, self._sent, self._error_frames, self._dropped,
                             self._datagrams_dropped)

    def start(self) -> None:
        """Open the bus (at once if possible) and keep it open from a thread of its own.

        A bus that cannot be opened now is no error: it is retried in the background and
        the status says why it is down meanwhile.
        """
        self._dispatcher.start()
        self._thread.start()
        self._first_attempt.wait(MAX_RETRY)

    def restrict_sending(self, allowed: Callable[[can.Message], bool], reason: str) -> None:
        """From now on send only frames for which ``allowed(frame)`` holds; others fail."""
        with self._lock:
            self._send_gate = allowed
            self._gate_reason = reason

    def stop(self) -> None:
        """Close the bus and end the supervisor's thread."""
        with self._lock:
            self._stopping = True
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self._frames.put(None)
        if self._dispatcher.is_alive():
            self._dispatcher.join(timeout=2.0)

    def send(self, message: can.Message) -> None:
        """Send ``message``; raise :class:`BusDown` when there is no usable bus.

        A failed send is a fault of the bus: it is reported down and reopened.
        """
        # One locked section per frame (this runs for every segment of a program image): the
        # frame is counted as it is handed over, and taken back if the driver refuses it.
        with self._lock:
            if self._send_gate is not None and not self._send_gate(message):
                raise BusDown(self._gate_reason)
            bus = self._bus
            if bus is None or not self._up:
                raise BusDown(f'the CAN bus is down: {self._reason}')
            timeout = self._send_timeout
            self._sent += 1
        try:
            bus.send(message, timeout=timeout)
        except Exception as error:  # noqa: BLE001 - any driver failure is a bus fault
            with self._lock:
                self._sent -= 1
            reason = f'sending failed: {error}'
            self._report_fault(bus, reason)
            raise BusDown(f'the CAN bus is down: {reason}') from error

    def times_periodic_sends(self) -> bool:
        """Return whether the bus open now times periodic sends itself, without a thread.

        SocketCAN's bus hands them to the kernel's broadcast manager, IXXAT's to the adapter;
        on every other python-can bus ``send_periodic`` starts a Python thread, which needs
        the interpreter lock at every send like any thread of this process.
        """
        with self._lock:
            bus = self._bus
        return bus is not None and (type(bus)._send_periodic_internal
                                    is not can.BusABC._send_periodic_internal)

    def send_periodic(self, messages: List[can.Message], period: float):
        """Start python-can's periodic sending of ``messages`` (in turn) on the bus open now.

        Returns the python-can task; raise :class:`BusDown` when there is no usable bus. The
        task is bound to this bus: the caller stops it when the bus goes down and starts a
        new one when it is back (closing the bus stops it too).
        """
        with self._lock:
            if self._send_gate is not None and not all(map(self._send_gate, messages)):
                raise BusDown(self._gate_reason)
            bus = self._bus
            if bus is None or not self._up:
                raise BusDown(f'the CAN bus is down: {self._reason}')
            try:
                return bus.send_periodic(messages, period)
            except Exception as error:  # noqa: BLE001 - any driver failure is a bus fault
                raise BusDown(f'periodic sending failed: {error}') from error

    def _report_fault(self, bus: can.BusABC, reason: str) -> None:
        """Take a failed send as a fault of ``bus``: sends fail at once from now on.

        The bus thread closes it and tells the listeners, not the sending thread: that may
        hold its caller's locks (canopen's send lock, a PDO frame lock), which a listener
        sending a frame (SYNC's waiting RPDOs) would wait for forever.
        """
        with self._lock:
            if self._bus is not bus or not self._up:
                return
            self._fault = reason
            self._up = False
            self._reason = reason

    def _run(self) -> None:
        retry = FIRST_RETRY
        while not self._wake.is_set():
            try:
                bus = self._open_bus()
            except Exception as error:  # noqa: BLE001 - any driver failure: try again later
                self._going_down(f'cannot open the bus: {error}')
                self._first_attempt.set()
                self._wake.wait(retry)
                retry = min(retry * 2, MAX_RETRY)
                continue
            opened = time.monotonic()
            send_timeout = kernel_send_timeout(bus, SEND_TIMEOUT)
            drop_foreign_datagrams(bus, self._dropped_datagram)
            self._note_sends(bus)
            self._coming_up(bus, send_timeout)
            reason = self._receive(bus)
            if reason is None:
                self._close(bus)
                LOGGER.info('CAN bus %s is closed', self.description)
                return
            # Told before closing: a driver may take long to close a dead adapter, and the
            # callers waiting on the bus are answered meanwhile.
            self._going_down(reason)
            self._close(bus)
            if time.monotonic() - opened >= MAX_RETRY:
                retry = FIRST_RETRY  # it worked for a while: this is a new fault
            self._wake.wait(retry)
            retry = min(retry * 2, MAX_RETRY)

    def _receive(self, bus: can.BusABC) -> Optional[str]:
        """Take frames from the driver until a fault (returned as its reason) or stop (None)."""
        # The hot path: flags are read and this thread's own counters bumped without the
        # lock (one writer; reading an attribute is atomic), so a frame costs no lock.
        frames = self._frames
        subscribers = self._network.subscribers
        watcher = self._frame_watcher
        receive, monotonic = bus.recv, time.monotonic
        while True:
            if self._stopping:
                return None
            if self._fault is not None:
                return self._fault
            try:
                message = receive(RECEIVE_POLL)
            except Exception as error:  # noqa: BLE001 - any driver failure is a bus fault
                return f'receiving failed: {error}'
            if message is None:
                continue
            try:  # no frame, however odd, may end this thread: the bus would be deaf
                stamp = monotonic()
                if watcher is not None:
                    try:
                        watcher(message, stamp)
                    except Exception as error:  # noqa: BLE001 - it must not deafen CANopen
                        self._handler_failed(error)
                if message.is_error_frame:
                    self._error_frames += 1
                    if message.arbitration_id & CAN_ERR_BUSOFF:
                        return 'the adapter reported bus-off'
                    continue
                # CANopen (CiA 301) uses 11-bit identifiers: extended frames are not for us.
                if message.is_remote_frame or message.is_extended_id:
                    continue
                # Each counter has one writer (_dispatched the dispatch thread, the others this
                # thread): no lock. Frames are waiting while the dispatch thread has not returned
                # from all it was given.
                backlog = self._queued - self._dispatched
                if backlog >= DISPATCH_BACKLOG:
                    self._dropped += 1
                    if self._dropped == 1:
                        LOGGER.error('CAN bus %s: frames arrive faster than they can be handled; '
                                     'frames beyond a backlog of %d are dropped (counted in the '
                                     'bus status)', self.description, DISPATCH_BACKLOG)
                    continue
                self._received += 1
                frame_id = message.arbitration_id
                handlers = subscribers.get(frame_id)
                if not handlers:
                    continue  # nobody listens (an echo of ours, another master's frames)
                waiting = backlog != 0
                if not waiting:  # (a loop, not all(): this runs for every frame)
                    for handler in handlers:
                        if not getattr(handler, 'prompt_handler', False):
                            waiting = True
                            break
                data = message.data
                if waiting:
                    self._queued += 1
                    frames.put((frame_id, data, stamp))
                    continue
                for handler in handlers:
                    try:
                        handler(frame_id, data, stamp)
                    except Exception as error:  # noqa: BLE001 - one must not deafen the rest
                        self._handler_failed(error)
            except Exception as error:  # noqa: BLE001
                self._handler_failed(error, 'taking a received frame')

    def _note_sends(self, bus: can.BusABC) -> None:
        """Have every frame sent through ``bus`` told to ``on_sent`` (see watch_frames)."""
        on_sent = self._on_sent
        if on_sent is None:
            return
        send = bus.send

        # On the instance: python-can's periodic tasks send through bus.send as well. Told
        # before it goes: an echo may come back before send returns.
        def send_noted(message: can.Message, timeout: Optional[float] = None) -> None:
            on_sent(message)
            send(message, timeout)

        bus.send = send_noted

    def _dispatch(self) -> None:
        """Hand the queued frames to canopen's subscribers, in the order they were taken."""
        frames = self._frames
        subscribers = self._network.subscribers
        while True:
            frame = frames.get()
            if frame is None:
                return
            # Those subscribed now: one may have unsubscribed since the frame came.
            for handler in subscribers.get(frame[0], ()):
                try:
                    handler(*frame)
                except Exception as error:  # noqa: BLE001 - one must not deafen the rest
                    self._handler_failed(error)
            self._dispatched += 1

    def _dropped_datagram(self) -> None:
        # On the bus thread, the counter's one writer (as the other receive counters).
        self._datagrams_dropped += 1
        if self._datagrams_dropped == 1:
            LOGGER.warning('CAN bus %s: a datagram on the udp_multicast group held no CAN frame '
                           'of this bus (another program on the same group and port?); it '
                           'was dropped, and later ones are counted in the bus status, not '
                           'logged', self.description)

    def _handler_failed(self, error: Exception, what: str = 'a frame handler') -> None:
        kind = (what, type(error).__name__)
        if kind not in self._listener_errors:
            self._listener_errors.add(kind)
            LOGGER.exception('%s failed (%s); the bus goes on', what, kind[1])

    def _coming_up(self, bus: can.BusABC, send_timeout: Optional[float]) -> None:
        with self._lock:
            reopened = self._opened_before
            if reopened:
                self._reopen_count += 1
            self._opened_before = True
            self._down_logged = False
            self._bus = bus
            self._send_timeout = send_timeout
            self._up = True
            self._told_up = True
            self._fault = None
            self._reason = ''
        if reopened:
            LOGGER.warning('CAN bus %s is up again', self.description)
        else:
            LOGGER.info('CAN bus %s is open', self.description)
        self._first_attempt.set()
        self._notify()

    def _going_down(self, reason: str) -> None:
        with self._lock:
            if self._stopping:
                return
            changed = self._told_up or self._reason != reason
            self._told_up = False
            log = not self._down_logged
            self._down_logged = True
            self._up = False
            self._reason = reason
        if log:
            LOGGER.error('CAN bus %s is down: %s; reopening until it works', self.description,
                         reason)
        if changed:
            self._notify()

    def _close(self, bus: can.BusABC) -> None:
        with self._lock:
            self._bus = None
            self._up = False
        try:
            bus.shutdown()
        except Exception as error:  # noqa: BLE001 - a dead adapter may fail to close too
            LOGGER.debug('closing the failed bus raised %r', error)
            # python-can's slcan driver writes to the (gone) port before closing it, so a
            # failed shutdown leaves the serial port open: close it, or every replug leaks one.
            port = getattr(bus, 'serialPortOrig', None)
            if port is not None:
                with contextlib.suppress(Exception):
                    port.close()

    def _notify(self) -> None:
        # Called on the bus thread: a listener that raised would end it, and the bus would
        # never be reopened.
        status = self.status
        for listener in self._listeners:
            try:
                listener(status)
            except Exception as error:  # noqa: BLE001 - one listener must not deafen the rest
                self._handler_failed(error, 'a bus status listener')
