"""The drives' feedback cycle: one thread, one beat a period, on the host's monotonic clock.

Each beat the drive service reads by SDO what no TPDO brings and watches the command
timeout; then the listeners run (the ROS layer publishes ``~/joint_states``). Beats are due
on absolute deadlines, so lateness never adds up; a beat missed on a loaded machine is
skipped, not caught up in a burst.
"""

from concurrent.futures import Future
import logging
import threading
import time
from typing import Callable, List

from .objects import FEEDBACK

LOGGER = logging.getLogger(__name__)

# What no TPDO brings is read by SDO this often, and at once after each controlword: every
# feedback cycle would be 250 transfers a second a drive, most of a 500 kbit/s bus for a few.
POLL_PERIOD = 0.1
# The timeout of those reads.
POLL_TIMEOUT = 2.0


def poll(drive, lock, read_feedback: Callable[[object, List[int], float], Future],
         now: bool = False) -> None:
    """Read by SDO what no TPDO brings of a re-read drive: every ``POLL_PERIOD``, or ``now``.

    Feedback that TPDOs bring only since the last read is read once more, at once: a TPDO
    sent before the gateway knew the mapping was not taken, a drive not OPERATIONAL sent
    none, and one sent on change only is not sent again. ``read_feedback(drive, indexes,
    timeout)`` reads and takes them (the drive service's); ``lock`` guards the drive record.
    """
    with lock:
        ready = drive.heard and drive.ready == drive.read_wanted
    if ready:  # a mapping read since its re-read: what its RPDOs also map
        drive.objects.read_held(POLL_TIMEOUT)
    with lock:
        if not drive.heard or drive.ready != drive.read_wanted:
            drive.polled_mapped = set()  # once re-read, all it maps counts as new
            return
        # Keyed by the mapping read: one read again may send the same objects on another
        # COB-ID, and what the drive sent there before the gateway followed was lost.
        reads = drive.objects.mapping_reads()
        mapped = drive.objects.mapped_feedback()
        keyed = {(index, reads) for index in mapped}
        drive.polled_mapped &= keyed  # PRE_OPERATIONAL for a moment, it sent no TPDO
        if drive.polling:
            return
        fresh = {index for index, _ in keyed - drive.polled_mapped}
        if not (now or fresh) and time.monotonic() - drive.polled < POLL_PERIOD:
            return
        drive.polled, drive.polled_mapped = time.monotonic(), keyed
        missing = [index for index in FEEDBACK if index not in mapped or index in fresh]
        if not missing:
            return
        drive.polling = True

    def done(_taken: Future) -> None:
        with lock:
            drive.polling = False

    read_feedback(drive, missing, POLL_TIMEOUT).add_done_callback(done)


class FeedbackCycle:
    """Call ``tick()``, then every listener, once every ``period`` seconds once started."""

    def __init__(self, period: float, tick: Callable[[], None]):
        self._period = period
        self._tick = tick
        self._listeners: List[Callable[[], None]] = []
        self._stopped = threading.Event()
        self._thread = threading.Thread(target=self._run, name='drive cycle', daemon=True)

    def add_listener(self, listener: Callable[[], None]) -> None:
        """Call ``listener()`` every beat, after the tick."""
        self._listeners.append(listener)

    def start(self) -> None:
        """Start beating."""
        self._thread.start()

    def stop(self) -> None:
        """Stop beating (a beat in progress finishes)."""
        self._stopped.set()

    def _run(self) -> None:
        due = time.monotonic()
        failures = set()
        while not self._stopped.is_set():
            for step in [self._tick, *self._listeners]:
                try:
                    step()
                except Exception as error:  # noqa: BLE001 - one failure must not end the cycle
                    kind = type(error).__name__
                    if kind not in failures:  # once per kind: there are 50 beats a second
                        failures.add(kind)
                        LOGGER.error('the drive cycle failed (%s: %s); later failures of '
                                     'this kind are not logged', kind, error)
            due += self._period
            now = time.monotonic()
            if due < now:
                due = now + self._period
            self._stopped.wait(due - now)
