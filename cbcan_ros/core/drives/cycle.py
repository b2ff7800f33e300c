"""The drives' feedback cycle: one thread, one beat a period, on the host's monotonic clock.

Each beat the drive service reads by SDO what no TPDO brings and watches the command
timeout; then the listeners run (the ROS layer publishes ``~/joint_states``). Beats are due
on absolute deadlines, so lateness never adds up; a beat missed on a loaded machine is
skipped, not caught up in a burst.

While the gateway produces SYNC, the beats follow it: one a SYNC cycle, as soon as every
synchronous TPDO the drives answer that SYNC with is in (``took``); without them, half a
period after the SYNC (or after the moment they came the cycle before). So
``~/joint_states`` carries each cycle's feedback once, early enough for a controller's answer
to reach the drives before the next SYNC. A cycle's TPDOs are told apart by whose they are,
not by when they came: the cycle is complete once every TPDO expected came, and a TPDO that
came already in the cycle begins the next one. So a receiving thread held up past the next
SYNC, taking the rest of one cycle's TPDOs and the next cycle's in one burst, completes each
cycle in turn. What the drives showed when a cycle's last TPDO came is taken then, on the
receiving thread (``snapshot``), and is what that beat tells (``beat_snapshot``): TPDOs of
the next cycle taken before the beat runs do not mix in.
"""

from concurrent.futures import Future
import logging
import threading
import time
from typing import Callable, Hashable, List, Optional, Set

from .objects import FEEDBACK

LOGGER = logging.getLogger(__name__)

# What no TPDO brings is read by SDO this often, and at once after each controlword: every
# feedback cycle would be 250 transfers a second a drive, most of a 500 kbit/s bus for a few.
POLL_PERIOD = 0.1
# The timeout of those reads.
POLL_TIMEOUT = 2.0
# With SYNC, the beat comes this fraction of a period after it when TPDOs are still missing.
LATEST_BEAT = 0.5
# ... and this fraction of a period later when some of the cycle's TPDOs are in.
LATE_TPDOS_WAIT = 0.5


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
    """Call ``tick()``, then every listener, once every ``period`` seconds once started.

    ``sync_point(fraction)``: the next time that fraction of a period after a SYNC, None while
    no SYNC is produced (``SyncProducer.next_point``); the beats then follow the SYNC.
    ``snapshot()``: what the drives show, taken when a cycle's last TPDO is in.
    """

    def __init__(self, period: float, tick: Callable[[], None],
                 sync_point: Callable[[float], Optional[float]] = lambda _fraction: None,
                 snapshot: Callable[[], object] = lambda: None):
        self._period = period
        self._tick = tick
        self._sync_point = sync_point
        self._snapshot = snapshot
        self._listeners: List[Callable[[], None]] = []
        self._stopped = False
        self._wake = threading.Condition()
        self._expected = 0  # synchronous TPDOs a SYNC cycle brings (0: not known)
        self._arrived: Set[Hashable] = set()  # of them, those of the cycle under way
        self._completed = 0  # cycles whose TPDOs all came in
        self._beaten = 0     # the last of them beaten
        self._taken = None   # the snapshot of the cycle completed last
        # The snapshot of the beat running (its cycle's), None for a beat without one.
        self.beat_snapshot = None
        # Whether snapshots are taken: only while a beat's listener reads them.
        self.snapshots = True
        self._thread = threading.Thread(target=self._run, name='drive cycle', daemon=True)

    def add_listener(self, listener: Callable[[], None]) -> None:
        """Call ``listener()`` every beat, after the tick."""
        self._listeners.append(listener)

    def start(self) -> None:
        """Start beating."""
        self._thread.start()

    def stop(self) -> None:
        """Stop beating (a beat in progress finishes)."""
        with self._wake:
            self._stopped = True
            self._wake.notify()

    def expect(self, frames: int) -> None:
        """Take ``frames`` as the synchronous TPDOs each SYNC cycle brings (0: unknown)."""
        with self._wake:
            self._expected = frames

    def took(self, tpdo: Hashable) -> None:
        """Count synchronous TPDO ``tpdo`` (whose it is) in; a cycle's last brings the beat.

        One that came already in the cycle under way begins the next cycle: the cycle before
        lost a TPDO, and its beat came at its deadline.
        """
        with self._wake:
            if tpdo in self._arrived:
                self._arrived.clear()
            self._arrived.add(tpdo)
            complete = 0 < self._expected <= len(self._arrived)
            if complete:
                self._arrived.clear()
        if complete:
            # No lock of this cycle held: the drives' lock is taken.
            taken = self._snapshot() if self.snapshots else None
            with self._wake:
                self._completed += 1
                self._taken = taken
                self._wake.notify()

    def _all_in(self) -> bool:
        return self._completed != self._beaten

    def _run(self) -> None:
        due = time.monotonic()
        failures = set()
        while True:
            with self._wake:
                later = due
                while not self._stopped and not self._all_in():
                    timeout = later - time.monotonic()
                    if timeout <= 0:
                        if later == due and self._expected and self._arrived:
                            # Part of a cycle's TPDOs in (a receive thread held up): half a
                            # period more for the rest, rather than tell drives of two cycles.
                            later = due + self._period * LATE_TPDOS_WAIT
                            continue
                        break
                    self._wake.wait(timeout)
                if self._stopped:
                    return
                all_in = self._all_in()
                self._beaten = self._completed
                self.beat_snapshot = self._taken if all_in else None
            beat_at = time.monotonic()
            for step in [self._tick, *self._listeners]:
                try:
                    step()
                except Exception as error:  # noqa: BLE001 - one failure must not end the cycle
                    kind = type(error).__name__
                    if kind not in failures:  # once per kind: there are 50 beats a second
                        failures.add(kind)
                        LOGGER.error('the drive cycle failed (%s: %s); later failures of '
                                     'this kind are not logged', kind, error)
            due = self._next_due(due, beat_at if all_in else None)

    def _next_due(self, due: float, all_in_at: Optional[float]) -> float:
        """Return when the next beat is due at the latest.

        ``all_in_at``: the beat just made came with the cycle's last TPDO, at that time. The
        next cycle's come a period later, wherever in the cycle the drives answer (SYNCs that
        leave late or early against the schedule): only half a period after that is a beat
        due without them.
        """
        now = time.monotonic()
        if all_in_at is not None:
            return all_in_at + (1 + LATEST_BEAT) * self._period
        following = self._sync_point(LATEST_BEAT)
        if following is not None:
            # The latest point of this cycle, unless the beat ran early in it: then the next.
            return following if following - now > self._period / 2 else \
                following + self._period
        due += self._period
        return due if due >= now else now + self._period
