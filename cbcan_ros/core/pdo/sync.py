"""SYNC production (CiA 301, COB-ID 0x80): the gateway's clock for synchronous PDOs.

Where the bus times periodic sends itself (the kernel's broadcast manager on SocketCAN, the
adapter on IXXAT), SYNC goes out with python-can's periodic sending, so its period does not
depend on this process being scheduled; with a counter, the task cycles through the frames
1..overflow. On every other bus python-can would send it from a thread of its own, no better
timed than one of ours, and racing the RPDOs: this module's SYNC thread sends it instead,
with the frames that must go before or after it, so each frame's place relative to the SYNC
is known, not guessed from a time grid (a SYNC late by a busy machine no longer lets a frame
meant for the next cycle in ahead of it).

The task is bound to one opened bus: it is stopped when the bus goes down and started again
on the new bus when it comes back (the counter starts again at 1, as after a device's reset).

Synchronous RPDOs must reach a device after a SYNC to be applied at the following one; the
SYNC thread sends them right after the SYNC it sent, or, when the bus times SYNC itself, a
quarter period after it, on the same monotonic time grid as the periodic task (the kernel's
timer keeps a fixed grid from its start, without drift). The same grid tells a stream of
targets whether a frame sent now is in before the next SYNC (``open_for_rpdos``), and calls
back a quarter period before that SYNC (``before_next_sync``), the last moment a frame is
surely in, to repeat a stream's frame in a cycle its caller left without one.
"""

from collections import deque
import contextlib
from dataclasses import dataclass
import logging
import math
import statistics
import threading
import time
from typing import Callable, Iterator, List, Optional, Tuple

import can

from ..bus import BusDown, BusStatus, BusSupervisor, prompt

LOGGER = logging.getLogger(__name__)

SYNC_COB_ID = 0x80
MAX_COUNTER = 240
# Intervals between SYNCs heard on the bus that the measured period is taken over.
PERIOD_SAMPLES = 200
# SYNCs heard back that the time grid is placed by (their median phase).
GRID_SAMPLES = 15
# Synchronous RPDOs leave this fraction of a period after the SYNC: late enough never to
# overtake it, early enough for the synchronous window of any device. A frame of a stream
# is sent at once unless this fraction or less of the period is left before the next SYNC.
RPDO_OFFSET = 0.25
# The longest the thread's SYNC waits for the frames of one cycle being written (``one_cycle``):
# a command message's few frames, within the SYNC period error devices take.
ONE_CYCLE_WAIT = 0.0005


def sync_frames(counter_overflow: int) -> List[can.Message]:
    """Return the frames of one SYNC cycle: one empty frame, or counters 1..overflow."""
    if not counter_overflow:
        return [can.Message(arbitration_id=SYNC_COB_ID, data=b'', is_extended_id=False)]
    return [can.Message(arbitration_id=SYNC_COB_ID, data=bytes([count]), is_extended_id=False)
            for count in range(1, counter_overflow + 1)]


class _ThreadTask:
    """SYNC sent by the producer's thread on the grid from the task's start (see the module).

    ``sent``: the last grid cycle whose SYNC was sent or skipped (-1: none yet); ``count``:
    SYNCs sent, which picks the counter's frame; ``sent_at``: when the last one went out
    (monotonic; None: none yet); ``sending``: held while the thread sends one;
    ``before_ran``: the grid cycle whose SYNC the callbacks before it last ran for.
    """

    def __init__(self, frames: List[can.Message], sending: threading.Lock):
        self.frames = frames
        self.sent = -1
        self.before_ran = -1
        self.count = 0
        self.sent_at: Optional[float] = None
        self._sending = sending

    def stop(self) -> None:
        """Return once a SYNC on its way out is out; none follows.

        The thread sends only while this is the producer's task.
        """
        with self._sending:
            pass


@dataclass(frozen=True)
class SyncStatus:
    """What diagnostics show of SYNC."""

    period: float                       # configured, seconds (0: not produced)
    counter_overflow: int
    running: bool                       # the periodic task is on the bus now
    starts: int                         # times it was started (1 + reopens of the bus)
    heard: int                          # SYNC frames received (an echo of ours, or another's)
    # Median interval between the SYNCs the gateway's thread sent (where it sends them), else
    # between those heard, seconds: the cycle the devices mostly see, which SYNCs skipped on
    # a busy host do not move (they show in the largest error and in ``skipped``).
    measured_period: Optional[float]
    measured_jitter: Optional[float]    # largest deviation of an interval from the period
    skipped: int                        # cycles of the thread's grid that got no SYNC


class SyncProducer:
    """Produces SYNC every ``period`` seconds while the bus is up (``period`` 0: never)."""

    def __init__(self, supervisor: BusSupervisor, network, period: float,
                 counter_overflow: int = 0):
        self.period = period
        self.counter_overflow = counter_overflow
        self._supervisor = supervisor
        self._network = network
        # A plain RLock for the sections entered for every frame sent (``open_for_rpdos``);
        # ``_changed`` waits on it.
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        # Held while the thread sends a SYNC: a task that ends waits for it, so none follows.
        self._sending = threading.Lock()
        # Held while frames that must reach the devices between the same two SYNCs go out
        # (``between_two_syncs``); taken before any other lock of this producer.
        self._burst = threading.Lock()
        self._held_back: Callable[[], Optional[str]] = lambda: None
        self._task = None
        self._task_start = 0.0
        self._grid_start = 0.0
        # Phases (seconds after a point of the task's start grid) of the SYNCs heard back.
        self._phases: deque = deque(maxlen=GRID_SAMPLES)
        self._starts = 0
        self._closing = False
        self._after_sync: List[Callable[[], None]] = []
        self._before_sync: List[Callable[[], None]] = []
        self._heard = 0
        self._skipped = 0
        self._last_heard: Optional[float] = None
        self._intervals: deque = deque(maxlen=PERIOD_SAMPLES)
        self._thread = threading.Thread(target=self._run, name='sync', daemon=True)
        # Each thread's decision within ``one_cycle`` (None outside), and how many threads
        # within it are writing frames that go before the next SYNC.
        self._one_cycle = threading.local()
        self._cycle_writers = 0
        self._sync_held = False  # the thread's SYNC waits for them

    @property
    def producing(self) -> bool:
        """Return whether SYNC is configured (it may still be paused while the bus is down)."""
        return self.period > 0

    def start(self) -> None:
        """Follow the bus: produce while it is up. Call before the bus is started."""
        self._network.subscribe(SYNC_COB_ID, self._on_sync_heard)
        if not self.producing:
            return
        self._supervisor.add_listener(self._on_bus_change)
        self._thread.start()

    def stop(self) -> None:
        """Stop producing for good; callbacks still waiting for a SYNC are dropped."""
        with self._lock:
            self._closing = True
            waiting = self._stop_task()
            self._changed.notify_all()
        _run_all(waiting)
        self._network.unsubscribe(SYNC_COB_ID, self._on_sync_heard)
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)

    def after_next_sync(self, callback: Callable[[], None]) -> bool:
        """Call ``callback()`` right after the next SYNC; False when no SYNC is coming now."""
        with self._lock:
            if self._task is None or self._closing:
                return False
            self._after_sync.append(callback)
            self._changed.notify_all()
            return True

    def before_next_sync(self, callback: Callable[[], None]) -> bool:
        """Call ``callback()`` a quarter period before the next SYNC; False when none comes."""
        with self._lock:
            if self._task is None or self._closing:
                return False
            self._before_sync.append(callback)
            self._changed.notify_all()
            return True

    def hold_while(self, why: Callable[[], Optional[str]]) -> None:
        """Send no SYNC (this thread's) while ``why()`` says why not: those cycles are skipped.

        A SYNC applies the synchronous RPDO frames the devices hold: after the gateway was
        held up, the ones from before it, until the gateway has sent what replaces them.
        """
        self._held_back = why

    def between_two_syncs(self) -> threading.Lock:
        """Return a lock whose holder's frames no SYNC of this thread splits.

        A stop sent again in several synchronous RPDOs at once: a SYNC between two of them
        would apply the one not sent yet, with the controlword that ran the drive, after the
        stop. The thread's SYNC waits while it is held (a few frames). python-can's and the
        kernel's periodic tasks cannot be held: there the frames' order is all that helps.
        """
        return self._burst

    @contextlib.contextmanager
    def one_cycle(self) -> Iterator[None]:
        """Have the synchronous frames written within reach the devices in one SYNC cycle.

        The targets of one command message for several drives: whether a stream's frame goes
        at once or waits for the SYNC (``open_for_rpdos``) is decided once, on entry, for all
        of them, not frame by frame as the cut-off passes; and while the ones going at once
        are written, this thread's SYNC waits for them (``ONE_CYCLE_WAIT`` at most), so it
        does not come between two of them.
        """
        if getattr(self._one_cycle, 'open', None) is not None:
            yield  # within one already: its decision holds
            return
        with self._lock:
            open_now = self.open_for_rpdos()
            self._cycle_writers += open_now
        self._one_cycle.open = open_now
        try:
            yield
        finally:
            self._one_cycle.open = None
            if open_now:
                with self._lock:
                    self._cycle_writers -= 1
                    if self._sync_held:  # most messages end long before their SYNC
                        self._changed.notify_all()

    def open_for_rpdos(self) -> bool:
        """Return whether a synchronous RPDO sent now is applied at the next SYNC.

        True from a SYNC until a quarter period before the next one, while SYNC is produced.
        When this thread sends SYNC, from the moment the cycle's SYNC went out, however late:
        a frame sent before it would be applied by it, a cycle early, and leave the cycle
        after it without a frame. Within ``one_cycle``, what it was on entry.
        """
        decided = getattr(self._one_cycle, 'open', None)
        if decided is not None:
            return decided
        with self._lock:
            task = self._task
            if task is None:
                return False
            cycles = (time.monotonic() - self._grid_start) / self.period
            if isinstance(task, _ThreadTask) and task.sent < math.floor(cycles):
                return False
        return cycles % 1 < 1 - RPDO_OFFSET

    def next_point(self, fraction: float) -> Optional[float]:
        """Return the next monotonic time ``fraction`` of a period after a SYNC, or None.

        None while no SYNC is produced (the bus is down, or SYNC is not configured).
        """
        with self._lock:
            if self._task is None:
                return None
            return self._next_point(fraction, time.monotonic())

    def _next_point(self, fraction: float, now: float) -> float:
        cycle = math.floor((now - self._grid_start) / self.period - fraction) + 1
        return self._grid_start + (cycle + fraction) * self.period

    def status(self) -> SyncStatus:
        """Return the SYNC status now."""
        with self._lock:
            intervals = list(self._intervals)
            running = self._task is not None
            starts, heard, skipped = self._starts, self._heard, self._skipped
        measured = statistics.median(intervals) if intervals else None
        jitter = (max(abs(interval - self.period) for interval in intervals)
                  if intervals and self.period else None)
        return SyncStatus(self.period, self.counter_overflow, running, starts, heard,
                          measured, jitter, skipped)

    def _on_bus_change(self, status: BusStatus) -> None:
        with self._lock:
            waiting = self._stop_task()
            started = status.up and not self._closing and self._start_task()
        _run_all(waiting)
        if not started:
            return
        LOGGER.info('producing SYNC every %g ms%s', self.period * 1000,
                    f' with a counter to {self.counter_overflow}' if self.counter_overflow
                    else '')

    def _start_task(self) -> bool:
        # Taken before: python-can's thread and the kernel's broadcast manager send the first
        # SYNC as they start, so each SYNC goes out just after its grid point, never before.
        grid_start = time.monotonic()
        frames = sync_frames(self.counter_overflow)
        try:
            self._task = (self._supervisor.send_periodic(frames, self.period)
                          if self._supervisor.times_periodic_sends()
                          else _ThreadTask(frames, self._sending))
        except BusDown as error:
            LOGGER.warning('SYNC could not be started: %s', error)
            return False
        self._changed.notify_all()  # the thread's SYNC is due at once
        self._task_start = self._grid_start = grid_start
        self._phases.clear()
        # The gap since a SYNC heard before (a bus down meanwhile) is no period of SYNC.
        self._last_heard = None
        self._starts += 1
        return True

    def _stop_task(self) -> List[Callable[[], None]]:
        """Stop the task; return the callbacks that waited for its SYNC (run them unlocked)."""
        task, self._task = self._task, None
        if task is not None:
            try:
                task.stop()
            except Exception as error:  # noqa: BLE001 - a dead adapter may fail to stop it
                LOGGER.debug('stopping the SYNC task raised %r', error)
        # Whatever waited for a SYNC of this task is answered by its own caller's checks.
        waiting, self._after_sync = self._after_sync, []
        waiting, self._before_sync = waiting + self._before_sync, []
        return waiting

    def _run(self) -> None:
        """Send SYNC (a ``_ThreadTask``) and run the callbacks before and after it, on time."""
        never = math.inf
        while True:
            with self._lock:
                while not self._closing and not (self._task is not None and (
                        isinstance(self._task, _ThreadTask) or self._after_sync
                        or self._before_sync)):
                    self._changed.wait()
                if self._closing:
                    return
                task, now = self._task, time.monotonic()
                if isinstance(task, _ThreadTask):
                    sync = self._grid_start + (task.sent + 1) * self.period
                    after = never  # run right after the SYNC sent
                    # Before this SYNC however late the thread is: a stream's repeat that
                    # missed its point still reaches the devices in its cycle, where waiting
                    # for the next point left the cycle without a frame. Once run for this
                    # SYNC, the callbacks added since are the next one's.
                    before = sync + ((task.before_ran == task.sent + 1)
                                     - RPDO_OFFSET) * self.period
                else:
                    sync = never
                    after = self._next_point(RPDO_OFFSET, now) if self._after_sync else never
                    before = self._next_point(1 - RPDO_OFFSET, now)
                before = before if self._before_sync else never
                due = min(sync, after, before)
                self._changed.wait(max(due - now, 0.0))
                if time.monotonic() < due or self._task is not task:
                    continue
                if sync == due and not self._frames_of_the_cycle_written(due + ONE_CYCLE_WAIT,
                                                                         task):
                    continue
                callbacks = []
                if after == due:
                    callbacks, self._after_sync = self._after_sync, []
                if before == due:
                    callbacks, self._before_sync = callbacks + self._before_sync, []
                    if isinstance(task, _ThreadTask):
                        task.before_ran = task.sent + 1
            if sync == due:
                cycle, sent_at, refused = self._send_sync(task)
                with self._lock:  # a frame held back until now goes out right after it
                    if self._task is task:
                        if refused:  # the gap to the next SYNC is the outage, no period
                            task.sent_at = None
                        else:  # cycles passed without a SYNC: the thread was late
                            self._skipped += cycle - task.sent - (sent_at is not None)
                        task.sent = cycle
                        # Not after a SYNC skipped: a frame would reach the device with the
                        # ones of the cycle before, which the time grid takes as applied.
                        if sent_at is not None:
                            self._note_sent(task, sent_at)
                            callbacks, self._after_sync = callbacks + self._after_sync, []
            _run_all(callbacks)

    def _frames_of_the_cycle_written(self, until: float, task: _ThreadTask) -> bool:
        """Wait until ``one_cycle``'s frames before this SYNC are out, or ``until`` (lock held).

        Return False when the task ended or shutdown began meanwhile.
        """
        while self._cycle_writers and self._task is task and not self._closing:
            left = until - time.monotonic()
            if left <= 0:
                break
            self._sync_held = True
            self._changed.wait(left)
            self._sync_held = False
        return self._task is task and not self._closing

    def _note_sent(self, task: _ThreadTask, stamp: float) -> None:
        """Measure the period between the thread's SYNCs (lock held).

        Sent, not heard: most adapters do not hand a process its own frames, and the host's
        clock when each went out is what the devices' cycle follows.
        """
        if task.sent_at is not None:
            self._intervals.append(stamp - task.sent_at)
        task.sent_at = stamp

    def _send_sync(self, task: _ThreadTask) -> Tuple[int, Optional[float], bool]:
        """Send the SYNC of the grid cycle due now.

        Return the cycle, when it went out (None: not sent) and whether the bus refused it
        (down, though its thread may not have seen it yet): no lateness of the thread.

        One later than half a period is skipped rather than sent late: after a stall, SYNCs
        sent back to back would give the devices cycles of no length, and the next one on
        the grid comes soon.
        """
        with self._burst, self._sending:  # where the grid is once frames held apart are out
            cycles = (time.monotonic() - self._grid_start) / self.period
            cycle = math.floor(cycles)
            send = cycles - cycle <= 0.5 and not self._held_back()
            if send and self._task is task:  # not when the bus went down or shutdown began
                try:
                    self._supervisor.send(task.frames[task.count % len(task.frames)])
                    task.count += 1
                    return cycle, time.monotonic(), False
                except BusDown:
                    return cycle, None, True  # the bus thread reports it; this task ends then
        return cycle, None, False

    @prompt
    def _on_sync_heard(self, _can_id: int, _data: bytearray, timestamp: float) -> None:
        with self._lock:
            self._heard += 1
            previous, self._last_heard = self._last_heard, timestamp
            if isinstance(self._task, _ThreadTask):
                return  # its period is measured where it sends (_note_sent)
            if previous is not None:
                self._intervals.append(timestamp - previous)
            if self._task is not None:
                self._follow_heard(timestamp, previous)

    def _follow_heard(self, stamp: float, previous: Optional[float]) -> None:
        """Place the grid on the SYNCs heard back: their median phase (lock held).

        python-can's thread starts its own grid when it first runs, which on a busy machine
        is milliseconds after the task was started: every SYNC then leaves that much after
        its grid point, and a stream's frame timed on the grid could race it. A SYNC is
        heard after a delay of its own: the median of the last ones is where the cycle's
        SYNC is, and one heard late by a stall (even by more than half a period, which
        reads as early) does not move it. Adapters that do not echo their own frames leave
        the grid where the task was started.

        Only a SYNC heard about a period after the one before places it (the first of the
        task aside): after a stall python-can's thread sends the SYNCs it missed back to
        back, and a receiving thread held up takes those it missed at once; such a burst,
        eight or more, would outnumber the SYNCs on the grid among the last 15. Nor does a
        SYNC of another producer less than half a period after one of ours.
        """
        period = self.period
        if self._phases and (previous is None
                             or not period / 2 < stamp - previous < period * 3 / 2):
            return
        self._phases.append((stamp - self._task_start) % period)
        reference = (self._phases[0] if len(self._phases) == 1
                     else (self._grid_start - self._task_start) % period)
        # Each phase as the nearest one to the grid's, so the median does not wrap.
        phases = sorted(reference + (phase - reference + period / 2) % period - period / 2
                        for phase in self._phases)
        self._grid_start = self._task_start + phases[len(phases) // 2]

def _run_all(callbacks: List[Callable[[], None]]) -> None:
    for callback in callbacks:
        try:
            callback()
        except Exception:  # noqa: BLE001 - one failing callback must not stop the others
            LOGGER.exception('a callback after SYNC failed')
