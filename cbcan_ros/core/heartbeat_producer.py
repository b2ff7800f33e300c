"""The gateway's own heartbeat (CiA 301 heartbeat producer, COB-ID 0x700 + its node id).

A drive's heartbeat consumer (object 0x1016: a producer's node id and a time) watches a
master's heartbeat, and the drive stops by itself (its 0x6007 abort connection option) when
the heartbeat falls silent: the one protection that still works when the gateway's process
dies or its bus adapter is unplugged. The state byte says what the gateway does: OPERATIONAL
(0x05) while it serves, PRE_OPERATIONAL (0x7F) while a managed node is inactive. Nothing is
sent once it stops.

Beats are due on a grid of absolute deadlines of the host's monotonic clock (start + k x
period): a late wake-up delays that one frame, never the ones after it, so no drift
accumulates; a beat missed altogether (the process had no CPU for a whole period) is
skipped, not sent in a burst afterwards, which a consumer would read as a node that is fine.

A thread of ours sends each beat through the bus supervisor, rather than python-can's
periodic sending as SYNC does: the state byte changes with the lifecycle, and a frame sent
this way passes the supervisor's shutdown gate and counters like every other. While the bus
is down a beat fails at once (``BusDown``) and is counted; the next goes out on the reopened
bus, so the producer pauses and resumes with the bus without listening to it.
"""

from dataclasses import dataclass
import logging
import math
import threading
import time
from typing import Callable, Optional

import can

from .bus import BusDown
from .nmt import HEARTBEAT_COB_BASE, OPERATIONAL, PRE_OPERATIONAL, state_name

LOGGER = logging.getLogger(__name__)


def next_beat(sent: int, start: float, period: float, now: float) -> int:
    """Return the beat to send after beat number ``sent`` went out at ``now``.

    Beat k is due at start + k x period, whenever the others went out. Beats whose
    deadlines ``now`` has passed already are skipped: the next one is the first due after
    ``now``.
    """
    return max(sent + 1, math.floor((now - start) / period) + 1)


@dataclass(frozen=True)
class HeartbeatProducerStatus:
    """What diagnostics show of the gateway's heartbeat."""

    node_id: int    # 0: no heartbeat
    period: float   # seconds
    state: int      # the state byte sent now (OPERATIONAL or PRE_OPERATIONAL)
    sent: int       # frames sent
    failed: int     # beats not sent (the bus was down)

    @property
    def state_name(self) -> str:
        """Return the name of the state sent, e.g. 'OPERATIONAL'."""
        return state_name(self.state)


class HeartbeatProducer:
    """Sends ``[state]`` on 0x700 + ``node_id`` every ``period`` seconds (node id 0: never).

    ``supervisor`` is anything with ``send(can.Message)`` raising on failure: the gateway's
    bus supervisor.
    """

    def __init__(self, supervisor, node_id: int, period: float,
                 clock: Callable[[], float] = time.monotonic):
        self.node_id = node_id
        self.period = period
        self._supervisor = supervisor
        self._clock = clock
        self._lock = threading.Condition()
        self._state = OPERATIONAL
        self._extra = False  # a beat asked for out of turn (beat_now)
        self._closing = False
        self._sent = 0
        self._failed = 0
        self._last_sent = None  # clock() of the last beat that went out
        self._silence_limit = math.inf
        self._silence_told = False  # on_silence was called for the silence going on
        self._on_silence: Callable[[float], None] = lambda _seconds: None
        self._thread = threading.Thread(target=self._run, name='heartbeat-producer',
                                        daemon=True)

    @property
    def producing(self) -> bool:
        """Return whether a heartbeat is configured (beats fail while the bus is down)."""
        return self.node_id > 0

    def set_operational(self, active: bool) -> None:
        """Send OPERATIONAL (True) or PRE_OPERATIONAL (False) from the next beat on."""
        with self._lock:
            self._state = OPERATIONAL if active else PRE_OPERATIONAL

    def beat_now(self) -> None:
        """Send a beat at once, beside those on the grid (if a node id is configured).

        A heartbeat consumer watches from the first beat it hears: a drive just told to watch
        the gateway would otherwise not notice its death until a whole period later.
        """
        with self._lock:
            self._extra = True
            self._lock.notify_all()

    def watch_silence(self, limit: float, on_silence: Callable[[float], None]) -> None:
        """Have ``on_silence(seconds)`` called when a beat is due after more than ``limit``.

        ``limit``: the consumer time of the devices that watch this heartbeat. A gateway held
        up that long (its machine starved, the bus down) finds those devices stopped by
        themselves: called once a silence, before that beat is sent, while
        :meth:`silent_too_long` still says so, so no thread of the gateway can send anything
        meanwhile unchecked.
        """
        with self._lock:
            self._silence_limit, self._on_silence = limit, on_silence

    def silent_too_long(self) -> Optional[float]:
        """Return how long no beat went out, when longer than the limit watched; else None."""
        last = self._last_sent  # a float read whole: no lock, asked for every frame
        if last is None:
            return None
        silent = self._clock() - last
        return silent if silent > self._silence_limit else None

    def start(self) -> None:
        """Start beating at once, if a node id is configured."""
        if not self.producing:
            return
        LOGGER.info('producing a heartbeat as node %d every %g ms', self.node_id,
                    self.period * 1000)
        self._thread.start()

    def stop(self) -> None:
        """Stop for good; when this returns no further beat is sent."""
        with self._lock:
            self._closing = True
            self._lock.notify_all()
        if self._thread.is_alive():
            self._thread.join()

    def status(self) -> HeartbeatProducerStatus:
        """Return the heartbeat's status now."""
        with self._lock:
            return HeartbeatProducerStatus(self.node_id, self.period, self._state, self._sent,
                                           self._failed)

    def _run(self) -> None:
        start = self._clock()
        beat = 0
        failures_logged = set()
        with self._lock:
            while not self._closing:
                wait = start + beat * self.period - self._clock()
                extra, self._extra = self._extra, False
                if wait > 0 and not extra:
                    self._lock.wait(wait)
                    continue
                message = can.Message(arbitration_id=HEARTBEAT_COB_BASE + self.node_id,
                                      data=bytes([self._state]), is_extended_id=False)
                silent = None if self._silence_told else self.silent_too_long()
                self._silence_told |= silent is not None  # once a silence (the bus down)
                on_silence = self._on_silence
                # Sent unlocked, so stop() is never held up by a slow adapter; it joins this
                # thread, so nothing is sent after it returns.
                self._lock.release()
                try:
                    if silent is not None:
                        on_silence(silent)
                    self._supervisor.send(message)
                    self._last_sent, self._silence_told = self._clock(), False
                    sent = True
                except BusDown:  # the supervisor reports the bus down, and reopens it
                    sent = False
                except Exception as error:  # noqa: BLE001 - beating must go on: say it once
                    sent = False
                    kind = type(error).__name__
                    if kind not in failures_logged:
                        failures_logged.add(kind)
                        LOGGER.warning('a heartbeat could not be sent: %r', error)
                finally:
                    self._lock.acquire()
                if sent:
                    self._sent += 1
                else:
                    self._failed += 1
                if wait <= 0:  # an extra beat leaves the grid as it is
                    beat = next_beat(beat, start, self.period, self._clock())
