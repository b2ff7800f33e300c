"""SDO transfers: request checks, the transfer functions and one bounded queue per device.

Every transfer runs on the worker thread of its device, so requests to one device are
serialized (a device has one SDO server channel) while different devices run in parallel.
Callers get a ``concurrent.futures.Future`` that always resolves to exactly one
:class:`SdoResult`, within the request's timeout: every failure of the canopen library,
expected or not, becomes an honest error answer here, and so do a full queue, a lost bus
and shutdown.
"""

from collections import deque
from concurrent.futures import Future, InvalidStateError
import contextlib
from dataclasses import dataclass
import heapq
import itertools
import logging
import math
import statistics
import threading
import time
from typing import Callable, List, Optional, Sequence

from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from . import abort_codes
from .bus import BusDown
from .canopen_gaps import (
    close_without_frames,
    DownloadStream,
    StrictSdoClient,
    TransferAborted,
    TransferCancelled,
    upload_finished,
)

LOGGER = logging.getLogger(__name__)

MAX_NODE_ID = 127
MAX_TIMEOUT = 60.0

# The p50 latency of a device is taken over its last this many successful accesses: a
# bounded sample, so a long-running gateway holds a few kilobytes per device, not a history.
LATENCY_SAMPLES = 1000


@dataclass(frozen=True)
class SdoResult:
    """The one answer every SDO request gets."""

    success: bool
    abort_code: int = 0
    message: str = ''
    data: bytes = b''

    @classmethod
    def ok(cls, data: bytes = b'') -> 'SdoResult':
        """Return a successful result carrying ``data``."""
        return cls(True, data=bytes(data))

    @classmethod
    def aborted(cls, code: int, detail: str = '') -> 'SdoResult':
        """Return a failed result for abort ``code``, with an optional detail appended."""
        message = abort_codes.describe(code)
        if detail:
            message = f'{message} ({detail})'
        return cls(False, abort_code=code, message=message)

    @classmethod
    def failed(cls, message: str, code: int = 0) -> 'SdoResult':
        """Return a failed result that no device abort explains (refused, bus down, ...)."""
        return cls(False, abort_code=code, message=message)


def check_node_id(node_id: int, allowed: str = "0..127 (0 = the gateway's own dictionary)",
                  lowest: int = 0) -> Optional[str]:
    """Return why ``node_id`` is not allowed, or None."""
    if not lowest <= node_id <= MAX_NODE_ID:
        return f'node_id {node_id} is out of range: allowed {allowed}'
    return None


@dataclass(frozen=True)
class Access:
    """One SDO access: a read (upload) or a write (download) of ``index:subindex``."""

    node_id: int
    index: int
    subindex: int
    write: bool = False
    data: bytes = b''
    max_size: int = 0  # reads: largest answer accepted, bytes; 0 = no limit

    def problem(self) -> Optional[str]:
        """Return why this access is not valid, or None; checked before anything is sent."""
        problem = check_node_id(self.node_id)
        if problem:
            return problem
        if not 0 <= self.index <= 0xFFFF:
            return f'index {self.index} is out of range: allowed 0x0000..0xFFFF'
        if not 0 <= self.subindex <= 0xFF:
            return f'subindex {self.subindex} is out of range: allowed 0..255'
        if self.write and not self.data:
            return 'data is empty: write at least 1 byte'
        if not self.write and not 0 <= self.max_size <= 0xFFFFFFFF:
            return (f'max_size {self.max_size} is out of range: allowed 0 (no limit) to '
                    f'4294967295')
        return None


def check_timeout(timeout: float) -> Optional[str]:
    """Return why a request's timeout is not valid, or None."""
    if math.isnan(timeout) or not 0.0 <= timeout <= MAX_TIMEOUT:
        return (f'timeout {timeout} s is out of range: allowed 0 (use the sdo.timeout '
                f'parameter) up to {MAX_TIMEOUT:g} s')
    return None


class ObjectTooLarge(Exception):
    """The object is larger than the caller accepts (``max_size``)."""


def check_size(size: int, max_size: int) -> None:
    """Raise :class:`ObjectTooLarge` when ``size`` bytes exceed a non-zero ``max_size``."""
    if max_size and size > max_size:
        raise ObjectTooLarge(f'the object holds {size} bytes, max_size is {max_size}')


def _write_all(stream, data: bytes) -> None:
    # A raw canopen stream takes at most 7 bytes per write() (one segment): loop.
    view = memoryview(data)
    position = 0
    while position < len(data):
        position += stream.write(view[position:position + 7])


def _close_after_failure(client: StrictSdoClient, stream) -> None:
    # The transfer ends with an abort (if the device heard of it); the stream is then marked
    # closed without canopen's closing frames and log lines, now and at garbage collection.
    client.abort(abort_codes.GENERAL_ERROR)
    close_without_frames(stream)


def upload(client: StrictSdoClient, index: int, subindex: int, max_size: int,
           block: bool) -> bytes:
    """Read an object, refusing more than ``max_size`` bytes (0 = no limit).

    The size a device announces is checked before any segment is fetched, so an oversized
    object costs one round trip (aborted with 0x05040005); the bytes that arrive must then
    match the announced size (0x06070012 too many, 0x06070013 too few).
    """
    stream = client.open(index, subindex, 'rb', buffering=0, block_transfer=block)
    try:
        data = _read_all(client, stream, max_size)
    except BaseException:
        _close_after_failure(client, stream)
        raise
    stream.close()
    return data


def _read_all(client: StrictSdoClient, stream, max_size: int) -> bytes:
    expedited = getattr(stream, 'exp_data', None) is not None
    announced = stream.size
    parts = []
    received = 0
    try:
        if announced is not None:
            check_size(announced, max_size)
        while True:
            part = stream.read(7)
            # A segment may carry no data and still say more follow (c = 0): only the
            # stream's own end ends the upload.
            if not part and upload_finished(stream):
                break
            parts.append(part)
            received += len(part)
            check_size(received, max_size)
            if announced is not None and received > announced:
                raise client.fail(abort_codes.DATA_TOO_LONG,
                                  f'the device announced {announced} bytes and sent more')
    except ObjectTooLarge as error:
        raise client.fail(abort_codes.OUT_OF_MEMORY, str(error), on_bus=not expedited) \
            from None
    if announced is not None and received != announced:
        raise client.fail(abort_codes.DATA_TOO_SHORT,
                          f'the device announced {announced} bytes and sent {received}')
    return b''.join(parts)


def download(client: StrictSdoClient, index: int, subindex: int, data: bytes,
             block: bool) -> None:
    """Write an object (expedited, segmented or block)."""
    if block:
        stream = client.open(index, subindex, 'wb', buffering=0, size=len(data),
                             block_transfer=True)
    else:
        stream = DownloadStream(client, index, subindex, size=len(data))
    try:
        _write_all(stream, data)
    except BaseException:
        _close_after_failure(client, stream)
        raise
    stream.close()


def run_guarded(transfer: Callable[[], Optional[bytes]]) -> SdoResult:
    """Run one transfer and turn whatever it raises into an :class:`SdoResult`.

    This is the one place where failures become answers: an abort from the device or from
    the gateway, a timeout, a cancelled transfer, a bus that went away. Nothing raised here
    may reach a ROS callback.
    """
    try:
        return SdoResult.ok(transfer() or b'')
    except TransferAborted as error:
        return SdoResult.aborted(error.code, error.detail)
    except SdoAbortedError as error:
        return SdoResult.aborted(error.code)
    except (TransferCancelled, BusDown) as error:
        return SdoResult.failed(str(error))
    except ObjectTooLarge as error:
        return SdoResult.aborted(abort_codes.OUT_OF_MEMORY, str(error))
    except SdoCommunicationError as error:
        return SdoResult.aborted(abort_codes.GENERAL_ERROR, f'protocol error: {error}')
    except Exception as error:  # noqa: BLE001 - every failure must become an answer
        LOGGER.warning('SDO transfer failed unexpectedly: %r', error)
        return SdoResult.aborted(abort_codes.GENERAL_ERROR,
                                 f'{type(error).__name__}: {error}')


def one_each(result: SdoResult, count: Optional[int]):
    """Return ``result`` as the answer of a single request (``count`` None) or of a batch.

    A batch refused or failed before it ran gets the same result for each of its accesses.
    """
    return result if count is None else [result] * count


def answer(future: Future, result) -> None:
    """Resolve ``future`` with ``result`` unless it already has its one answer."""
    with contextlib.suppress(InvalidStateError):
        future.set_result(result)


@dataclass(frozen=True)
class SdoStatistics:
    """What one device's SDO channel answered since the gateway started.

    Every access handed to the channel counts once, in a batch too (one refused before, for
    a bad field, by write protection or while the bus is down, never reaches it):
    ``requests`` all of them, ``timeouts`` those answered 0x05040000 (no answer in time, or
    the time ran out in the queue), ``aborts`` those answered with any other abort code (the
    device's or the gateway's). Answers without an abort code (the bus went down, shutting
    down) count only as requests. ``latency_p50`` is the median time, in seconds, from the
    first frame of a successful access to its answer (queueing not included; a batch counts
    its average per access), over the last ``LATENCY_SAMPLES`` of them; None before the first.
    """

    requests: int = 0
    aborts: int = 0
    timeouts: int = 0
    latency_p50: Optional[float] = None


def resolved(result) -> Future:
    """Return a future that already holds ``result`` (for answers that need no bus)."""
    future: Future = Future()
    future.set_result(result)
    return future


@dataclass(eq=False)
class _Job:
    run: Callable[[float], object]  # given the deadline, returns the job's answer
    deadline: float
    timeout: float
    future: Future
    count: Optional[int]  # a batch's number of accesses; None for a single access
    started: Optional[float] = None  # time.monotonic() when the worker took it
    watch: Optional[list] = None  # its deadline watch while it waits (Deadlines.watch)

    def failed(self, result: SdoResult) -> object:
        """Return the job's answer when it ends with ``result`` before it ran."""
        return one_each(result, self.count)


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
                    finally:
                        self._changed.acquire()
                    continue
                self._changed.wait(self._heap[0][0] - now if self._heap else None)


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


class SdoChannel:
    """The SDO server channel of one remote device: its strict client, queue and worker.

    At most ``queue_limit`` requests wait for the device; more are refused at once. Each
    request's timeout covers its time in the queue and its transfer. Block transfer is
    tried first when enabled; a device that does not know it (abort 0x05040001, or a normal
    upload response) gets segmented transfers from then on; nothing was transferred, so
    that is safe even for writes.
    """

    def __init__(self, client: StrictSdoClient, node_id: int, deadlines: Deadlines,
                 block_transfer: bool, queue_limit: int, read_retries: int = 0):
        self.node_id = node_id
        self._client = client
        self._deadlines = deadlines
        self._block = block_transfer
        self._queue_limit = queue_limit
        self._read_retries = read_retries
        self._jobs = JobQueue()
        self._changed = self._jobs.lock
        self._requests = 0
        self._aborts = 0
        self._timeouts = 0
        self._latencies: deque = deque(maxlen=LATENCY_SAMPLES)
        self._thread = threading.Thread(target=self._work, name=f'sdo-node-{node_id}',
                                        daemon=True)
        self._thread.start()

    def single(self, access: Access, timeout: float) -> 'Future[SdoResult]':
        """Queue one access; the future resolves to its :class:`SdoResult`."""
        return self._submit(lambda deadline: self._access(access, deadline), timeout, None)

    def batch(self, accesses: Sequence[Access], timeout: float) -> 'Future[List[SdoResult]]':
        """Queue accesses to run in order as one request; resolves to their results."""
        def run(deadline: float) -> List[SdoResult]:
            results = []
            for access in accesses:
                if time.monotonic() >= deadline:
                    results.append(SdoResult.aborted(
                        abort_codes.TIMEOUT, "the batch's timeout ran out before this access; "
                                             'nothing was sent'))
                else:
                    results.append(self._access(access, deadline))
            return results
        return self._submit(run, timeout, len(accesses))

    def fail_all(self, reason: str, abort_code: Optional[int] = None) -> None:
        """Answer every queued request with ``reason`` and end the running transfer."""
        for job in self._jobs.take_all():
            self._resolve(job, job.failed(SdoResult.failed(reason)))
        self._client.cancel(reason, abort_code)

    def close(self, reason: str, abort_code: Optional[int]) -> None:
        """Refuse new requests, fail queued ones and end the running transfer."""
        self._jobs.close(SdoResult.failed(reason))
        self.fail_all(reason, abort_code)

    def join(self, timeout: float) -> None:
        """Wait for the worker to end (after :meth:`close`)."""
        self._thread.join(timeout)

    def statistics(self) -> SdoStatistics:
        """Return the requests, aborts, timeouts and p50 latency of this device so far."""
        with self._changed:
            latencies = list(self._latencies)
            counts = (self._requests, self._aborts, self._timeouts)
        return SdoStatistics(*counts, statistics.median(latencies) if latencies else None)

    def _submit(self, run: Callable[[float], object], timeout: float,
                count: Optional[int]) -> Future:
        job = _Job(run, time.monotonic() + timeout, timeout, Future(), count)
        with self._changed:
            refusal = self._jobs.closed
            if refusal is None and len(self._jobs) >= self._queue_limit:
                refusal = SdoResult.failed(
                    f'node {self.node_id} is busy: {self._queue_limit} requests are already '
                    f'waiting for it (parameter sdo.queue_limit); nothing was sent',
                    abort_codes.NO_RESOURCE)
            if refusal is None:
                self._jobs.put(job)
                job.watch = self._deadlines.watch(job.deadline, lambda: self._expire(job))
        if refusal is not None:
            self._resolve(job, job.failed(refusal))
        return job.future

    def _expire(self, job: _Job) -> None:
        if not self._jobs.withdraw(job):
            return  # running or answered: the transfer keeps its own deadline
        self._resolve(job, job.failed(self._queued_too_long(job)))

    def _queued_too_long(self, job: _Job) -> SdoResult:
        return SdoResult.aborted(
            abort_codes.TIMEOUT, f'waited {job.timeout:g} s behind earlier requests to node '
                                 f'{self.node_id}; nothing was sent')

    def _work(self) -> None:
        while True:
            job = self._jobs.next(lambda taken: setattr(taken, 'started', time.monotonic()))
            if job is None:
                return
            if job.started >= job.deadline:
                # Its time ran out in the queue; the deadline thread has not answered it yet.
                self._resolve(job, job.failed(self._queued_too_long(job)))
            else:
                self._resolve(job, job.run(job.deadline))
            del job  # an idle worker must not keep its last request (and answer) alive

    def _resolve(self, job: _Job, result) -> None:
        """Give ``job`` its one answer; every answer of this channel passes here.

        The statistics are counted first, so a caller holding its answer finds it counted.
        """
        if job.future.done():
            return  # a job is answered once by design: a stray second answer is not counted
        if job.watch is not None:
            self._deadlines.cancel(job.watch)
        results = result if job.count is not None else (result,)
        successes = aborts = timeouts = 0
        for one in results:
            if one.success:
                successes += 1
            elif one.abort_code == abort_codes.TIMEOUT:
                timeouts += 1
            elif one.abort_code:
                aborts += 1
        latency = None
        if job.started is not None and successes:
            latency = (time.monotonic() - job.started) / len(results)
        with self._changed:
            self._requests += len(results)
            self._aborts += aborts
            self._timeouts += timeouts
            if latency is not None:
                self._latencies.extend([latency] * min(successes, LATENCY_SAMPLES))
        answer(job.future, result)

    def _access(self, access: Access, deadline: float) -> SdoResult:
        index, subindex = access.index, access.subindex
        if access.write:
            return self._transfer(index, subindex, deadline, lambda block: download(
                self._client, index, subindex, access.data, block))
        attempts = self._read_retries + 1
        while True:
            # Retries share the timeout: each attempt gets an equal part of what is left.
            attempt_deadline = time.monotonic() + (deadline - time.monotonic()) / attempts
            result = self._transfer(index, subindex, attempt_deadline, lambda block: upload(
                self._client, index, subindex, access.max_size, block))
            attempts -= 1
            if result.abort_code != abort_codes.TIMEOUT or not attempts:
                return result

    def _transfer(self, index: int, subindex: int, deadline: float,
                  transfer: Callable[[bool], Optional[bytes]]) -> SdoResult:
        def attempt(block: bool) -> Optional[bytes]:
            return self._client.transfer(index, subindex, deadline, lambda: transfer(block))

        def run() -> Optional[bytes]:
            if self._block:
                try:
                    return attempt(True)
                except TransferAborted as refusal:
                    # Only a device without block transfer gets a segmented one; any other
                    # refusal is the device's answer, and a write is never offered twice.
                    if self._client.initiated or refusal.code != abort_codes.UNKNOWN_COMMAND:
                        raise
                    self._block = False
            return attempt(False)
        return run_guarded(run)
