"""What a request waiting for a worker thread needs: its queue, its deadline, its one answer.

Shared by the SDO channels (one worker per device) and the LSS master (one worker per bus).
"""

from collections import deque
from concurrent.futures import Future, InvalidStateError
import contextlib
import heapq
import itertools
import logging
import threading
import time
from typing import Callable, List

LOGGER = logging.getLogger(__name__)

# The longest the deadline thread waits at once: a deadline further away than a thread can
# wait (threading.TIMEOUT_MAX, some 292 years) would end it with OverflowError.
LONGEST_WAIT = 3600.0


def answer(future: Future, result) -> None:
    """Resolve ``future`` with ``result`` unless it already has its one answer."""
    with contextlib.suppress(InvalidStateError):
        future.set_result(result)


def resolved(result) -> Future:
    """Return a future that already holds ``result`` (for answers that need no bus)."""
    future: Future = Future()
    future.set_result(result)
    return future


class Deadlines:
    """One thread that answers queued requests whose time ran out before their turn.

    A request answered in time cancels its watch, which drops everything the watch held
    (the request, its future, its answer) at once rather than at its deadline: a gateway
    answering thousands of calls with long timeouts holds only those still waiting.
    """

    # Cancelled watches are left in the heap (removing one from its middle costs a full
    # pass) until they are more than half of it, and at least this many.
    COMPACT_AT = 64

    def __init__(self):
        self._heap: List[list] = []  # [deadline, order, expire or None when cancelled]
        self._cancelled = 0
        self._order = itertools.count()
        self._changed = threading.Condition()
        self._running = True
        self._thread = threading.Thread(target=self._run, name='sdo-deadlines', daemon=True)
        self._thread.start()

    def watch(self, deadline: float, expire: Callable[[], None]) -> list:
        """Call ``expire()`` at ``deadline`` (time.monotonic()); returns a handle to cancel."""
        entry = [deadline, next(self._order), expire]
        with self._changed:
            heapq.heappush(self._heap, entry)
            if self._heap[0] is entry:
                self._changed.notify()
        return entry

    def cancel(self, entry: list) -> None:
        """Forget the watch ``entry`` (and what its ``expire`` holds) without calling it."""
        with self._changed:
            if entry[2] is None:
                return
            entry[2] = None
            self._cancelled += 1
            if self._cancelled >= self.COMPACT_AT and 2 * self._cancelled > len(self._heap):
                self._heap = [kept for kept in self._heap if kept[2] is not None]
                heapq.heapify(self._heap)
                self._cancelled = 0

    def __len__(self) -> int:
        """Return how many watches are held, cancelled ones not yet dropped included."""
        with self._changed:
            return len(self._heap)

    def stop(self) -> None:
        """End the thread; pending deadlines are dropped."""
        with self._changed:
            self._running = False
            self._changed.notify()
        self._thread.join(timeout=1.0)

    def _run(self) -> None:
        with self._changed:
            while self._running:
                now = time.monotonic()
                if self._heap and self._heap[0][0] <= now:
                    entry = heapq.heappop(self._heap)
                    expire, entry[2] = entry[2], None  # fired: a later cancel finds it done
                    if expire is None:
                        self._cancelled -= 1
                        continue
                    self._changed.release()
                    try:
                        expire()
                    except Exception:  # noqa: BLE001 - every later deadline must still fire
                        LOGGER.exception('a request could not be timed out')
                    finally:
                        self._changed.acquire()
                    continue
                self._changed.wait(min(self._heap[0][0] - now, LONGEST_WAIT) if self._heap
                                   else None)


class JobQueue:
    """The requests waiting for one worker thread, in order, until it is closed.

    ``lock`` (a re-entrant condition) guards the queue, and whatever its owner keeps with it.
    """

    def __init__(self):
        self.lock = threading.Condition()
        self._jobs: deque = deque()
        self.closed = None  # once closing: what new requests are answered

    def __len__(self) -> int:
        return len(self._jobs)

    def put(self, job) -> None:
        """Queue ``job`` (the caller holds ``lock`` and checked ``closed``)."""
        with self.lock:
            self._jobs.append(job)
            self.lock.notify()

    def close(self, refusal) -> None:
        """Refuse new requests with ``refusal``; the worker ends once the queue is empty."""
        with self.lock:
            self.closed = refusal
            self.lock.notify()

    def take_all(self) -> list:
        """Remove and return every waiting job."""
        with self.lock:
            jobs = list(self._jobs)
            self._jobs.clear()
        return jobs

    def withdraw(self, job) -> bool:
        """Remove ``job`` if it still waits; return whether it did (else it ran or runs)."""
        with self.lock:
            if job not in self._jobs:
                return False
            self._jobs.remove(job)
            return True

    def next(self, on_take: Callable[[object], None]):
        """Wait for the next job, call ``on_take(job)`` under the lock, return it.

        Returns None once closed with nothing left to run.
        """
        with self.lock:
            while not self._jobs and self.closed is None:
                self.lock.wait()
            if not self._jobs:
                return None
            job = self._jobs.popleft()
            on_take(job)
            return job
