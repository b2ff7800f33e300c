"""The bus as a simulated durand device sees it: python-can, with a receive thread of its own.

durand 0.5.0's ``CANBusNetwork`` drops remote frames (node guarding) and polls with a 1 s
cycle, so closing it waits up to 1 s: :class:`BusNetwork` replaces it.
"""

import logging
import threading
import time
from typing import Callable, Dict, Optional

import can
from durand.network import NetworkABC

LOGGER = logging.getLogger(__name__)

RECEIVE_CYCLE = 0.05


class BusNetwork(NetworkABC):
    """The bus as durand sees it, with a receive thread of our own.

    Frames are handed to durand's subscribers under the scheduler's lock. A ``hook`` set for a
    COB-ID sees the frame first, with durand's subscriber for it (or None). A ``rewrite`` may
    change an outgoing frame. Nothing raised while receiving or handling ends the thread.
    """

    def __init__(self, bus: can.BusABC, lock, on_remote: Callable[[can.Message], None]):
        self._bus = bus
        self._lock = lock
        self._on_remote = on_remote
        self._subscriptions: Dict[int, Callable] = {}
        self.hooks: Dict[int, Callable] = {}
        self.rewrite: Optional[Callable[[int, bytes], bytes]] = None
        self.allowed: Callable[[int], bool] = lambda cob_id: True
        self.muted = True  # nothing leaves while the device is being built or after stop
        self.deaf = False  # nothing is taken in while the device restarts
        self._running = False
        self._thread: Optional[threading.Thread] = None

    def add_subscription(self, cob_id: int, callback) -> None:
        """Deliver frames on ``cob_id`` to ``callback(cob_id, data)``."""
        self._subscriptions[cob_id] = callback

    def remove_subscription(self, cob_id: int) -> None:
        """Stop delivering frames on ``cob_id``."""
        self._subscriptions.pop(cob_id, None)

    def send(self, cob_id: int, msg: bytes) -> None:
        """Send a data frame, unless muted; a bus error is logged, never raised into durand."""
        if self.muted or not self.allowed(cob_id):
            return
        if self.rewrite is not None:
            msg = self.rewrite(cob_id, msg)
        try:
            self._bus.send(can.Message(arbitration_id=cob_id, data=msg, is_extended_id=False))
        except Exception:
            LOGGER.warning('durand device could not send 0x%03X %s', cob_id, bytes(msg).hex(),
                           exc_info=True)

    def start(self) -> None:
        """Start the receive thread."""
        self._running = True
        self._thread = threading.Thread(target=self._receive, name='durand-device-rx',
                                        daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the receive thread and wait for it."""
        self._running = False
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)

    @property
    def receiving(self) -> bool:
        """Return whether the receive thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    def _receive(self) -> None:
        while self._running:
            try:
                message = self._bus.recv(RECEIVE_CYCLE)
            except Exception:
                # python-can's Notifier would end here for good and leave the device deaf.
                LOGGER.warning('durand device: receive failed', exc_info=True)
                time.sleep(RECEIVE_CYCLE)
                continue
            if message is not None and self._running and not self.deaf:
                self._dispatch(message)

    def _dispatch(self, message: can.Message) -> None:
        if message.is_error_frame or message.is_fd or message.is_extended_id:
            return
        cob_id = message.arbitration_id
        try:
            with self._lock:
                if message.is_remote_frame:
                    self._on_remote(message)
                    return
                data = bytes(message.data)
                callback = self._subscriptions.get(cob_id)
                hook = self.hooks.get(cob_id)
                if hook is not None:
                    hook(callback, cob_id, data)
                elif callback is not None:
                    callback(cob_id, data)
        except Exception:
            LOGGER.exception('durand device failed on %r', message)
