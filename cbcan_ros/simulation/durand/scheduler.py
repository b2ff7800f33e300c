"""The durand scheduler every simulated durand device shares, with guards durand 0.5.0 needs.

durand's ``SyncScheduler`` sleeps until the earliest timer it knew of when it went to sleep, so
a timer added meanwhile (another device's shorter heartbeat) fires up to the longest period
late; and cancelling a timer while it fires fails inside durand, which then silently keeps the
old heartbeat. :class:`_Scheduler` wakes on every new timer and fires timers under one lock
that everything driving durand holds.
"""

import logging
import sched
import threading
import time
from typing import Callable, Optional

import durand

LOGGER = logging.getLogger(__name__)


class _Timer:
    """One scheduled callback; the flag lets a cancel win over a firing already under way."""

    def __init__(self, callback: Callable, args: tuple, kwargs: dict):
        self.callback = callback
        self.args = args
        self.kwargs = kwargs
        self.cancelled = False
        self.event: Optional[sched.Event] = None


class _Scheduler(durand.scheduler.SyncScheduler):
    """durand's SyncScheduler, woken by every new timer, firing each timer under ``lock``.

    Everything that drives durand (received frames, device methods) holds ``lock`` too, so a
    timer never fires in the middle of a change to the state it works on, and a cancel comes
    either before a firing (which then does nothing) or after it.
    """

    def __init__(self):
        super().__init__(lock=threading.RLock())
        self._interrupt = threading.Event()
        self._sched = sched.scheduler(time.monotonic, self._delay)

    def add(self, delay: float, callback, args=(), kwargs=None) -> _Timer:
        """Schedule ``callback(*args, **kwargs)`` in ``delay`` seconds; returns its handle."""
        timer = _Timer(callback, tuple(args), dict(kwargs or {}))
        timer.event = super().add(delay, self._fire, (timer,))
        self._interrupt.set()  # the runner may be asleep until a later timer
        return timer

    def cancel(self, entry: _Timer) -> None:
        """Cancel a timer; harmless when it has fired or is firing already."""
        entry.cancelled = True
        try:
            super().cancel(entry.event)
        except ValueError:
            pass  # already off the queue: _fire sees the flag

    def pending(self) -> list:
        """Return the callbacks of the timers still to fire (for tests)."""
        return [event.argument[0].callback for event in self._sched.queue
                if not event.argument[0].cancelled]

    def _delay(self, seconds: float) -> None:
        if seconds > 0:
            self._interrupt.wait(seconds)
            self._interrupt.clear()

    def _fire(self, timer: _Timer) -> None:
        with self.lock:
            if timer.cancelled:
                return
            try:
                timer.callback(*timer.args, **timer.kwargs)
            except Exception:
                # An exception here would end the runner thread and every device's timers.
                LOGGER.exception('durand timer %r failed', timer.callback)


_scheduler_lock = threading.Lock()
_scheduler: Optional[_Scheduler] = None


def shared_scheduler() -> _Scheduler:
    """Return the process-wide durand scheduler, installing and starting it on first use."""
    global _scheduler
    with _scheduler_lock:
        if _scheduler is None:
            scheduler = _Scheduler()
            durand.set_scheduler(scheduler)
            threading.Thread(target=scheduler.run, name='durand-scheduler',
                             daemon=True).start()
            _scheduler = scheduler
        return _scheduler
