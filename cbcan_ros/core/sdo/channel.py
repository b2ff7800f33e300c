"""SDO channels: one bounded queue and one worker thread per device.

Every transfer runs on the worker thread of its device, so requests to one device are
serialized (a device has one SDO server channel) while different devices run in parallel.
Callers get a ``concurrent.futures.Future`` that always resolves to exactly one
:class:`~cbcan_ros.core.sdo.requests.SdoResult` (a list of them for a batch), within the request's
timeout: also for a full queue, a lost bus and shutdown.
"""

from collections import deque
from concurrent.futures import Future
from dataclasses import dataclass
import statistics
import threading
import time
from typing import Callable, List, Optional, Sequence

from ..canopen_gaps.sdo_client import StrictSdoClient, TransferAborted
from . import abort_codes
from .request_queue import answer, Deadlines, JobQueue
from .requests import Access, one_each, SdoResult
from .transfer import download, run_guarded, upload

# The p50 latency of a device is taken over its last this many successful accesses: a
# bounded sample, so a long-running gateway holds a few kilobytes per device, not a history.
LATENCY_SAMPLES = 1000


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


class SdoChannel:
    """The SDO server channel of one remote device: its strict client, queue and worker.

    At most ``queue_limit`` requests wait for the device; more are refused at once. Each
    request's timeout covers its time in the queue and its transfer. Block transfer is
    tried first when enabled; a device that does not know it (abort 0x05040001, or a normal
    upload response) gets segmented transfers from then on; nothing was transferred, so
    that is safe even for writes. ``silence()`` says how long the device has not been heard,
    '' while it is: a request that timed out adds it, so a caller who typed a wrong node id
    or whose device is off learns that, not only that no answer came.
    """

    def __init__(self, client: StrictSdoClient, node_id: int, deadlines: Deadlines,
                 block_transfer: bool, queue_limit: int, read_retries: int = 0,
                 silence: Callable[[], str] = str):
        self.node_id = node_id
        self._silence = silence
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
        self._cancels = 0  # the client's cancels when the running job was taken
        self._running = False  # the worker has a job (set when taken, until answered)
        self._thread = threading.Thread(target=self._work, name=f'sdo-node-{node_id}',
                                        daemon=True)
        self._thread.start()

    def single(self, access: Access, timeout: float) -> 'Future[SdoResult]':
        """Queue one access; the future resolves to its :class:`SdoResult`."""
        return self._submit(lambda deadline: self._access(access, deadline), timeout, None)

    def batch(self, accesses: Sequence[Access], timeout: float,
              stop: Optional[Callable[[List[SdoResult]], Optional[str]]] = None
              ) -> 'Future[List[SdoResult]]':
        """Queue accesses to run in order as one request; resolves to their results.

        ``stop(results so far)``, asked before each access is sent, says why the rest must
        not be sent (a boot that ended), or None.
        """
        def run(deadline: float) -> List[SdoResult]:
            results = []
            for access in accesses:
                reason = stop(results) if stop is not None else None
                if reason:
                    results.append(SdoResult.failed(f'{reason}; not sent'))
                elif time.monotonic() >= deadline:
                    results.append(SdoResult.aborted(
                        abort_codes.TIMEOUT, "the batch's timeout ran out before this access; "
                                             'nothing was sent'))
                else:
                    results.append(self._access(access, deadline))
            return results
        return self._submit(run, timeout, len(accesses))

    def stream(self, access: Access, answer_within: float,
               written: Callable[[int, bool], Optional[str]]) -> 'Future[SdoResult]':
        """Queue a long write (a program image); block transfer first, whatever the parameter.

        No deadline bounds the whole: it waits ``answer_within`` s at most in the queue, and
        the device must answer each segment (each block) within ``answer_within`` s, so only
        a device that stops answering ends it, however large the data. ``written(bytes so
        far, block)`` (block: by block transfer, else segmented) is called after each
        segment; a reason it returns ends the transfer there with an abort 0x08000021 (local
        control) on the bus.
        """
        index, subindex = access.index, access.subindex

        def attempt(block: bool) -> None:
            def each_segment(position: int) -> None:  # one call per segment, no more
                reason = written(position, block)
                if reason:
                    raise self._client.fail(abort_codes.LOCAL_CONTROL, reason)
            download(self._client, index, subindex, access.data, block, each_segment)

        def run(deadline: float) -> SdoResult:
            return self._transfer(index, subindex, deadline, attempt, block_first=True,
                                  answer_within=answer_within)
        return self._submit(run, answer_within, None)

    def fail_all(self, reason: str, abort_code: Optional[int] = None) -> None:
        """Answer every queued request with ``reason`` and end the running one.

        The running request's transfer ends, and so does the rest of it: a batch sends no
        further access (a silent device would hold each until its timeout, and a stop sent
        right after this behind them). Requests queued from now on run as usual.
        """
        with self._changed:  # each job is either taken here or taken before the cancel
            jobs = self._jobs.take_all()
            self._client.cancel(reason, abort_code)
        for job in jobs:
            self._resolve(job, job.failed(SdoResult.failed(reason)))

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
                if self._running or len(self._jobs):
                    # It waits for the worker: answered at its deadline if still waiting.
                    job.watch = self._deadlines.watch(job.deadline, lambda: self._expire(job))
                self._jobs.put(job)
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
            job = self._jobs.next(self._take)
            if job is None:
                return
            if job.started >= job.deadline:
                # Its time ran out in the queue; the deadline thread has not answered it yet.
                self._resolve(job, job.failed(self._queued_too_long(job)))
            else:
                self._resolve(job, job.run(job.deadline))
            with self._changed:
                self._running = False
            del job  # an idle worker must not keep its last request (and answer) alive

    def _take(self, job: _Job) -> None:
        """Start ``job`` (the queue's lock held): a :meth:`fail_all` from now on ends it."""
        job.started = time.monotonic()
        self._running = True
        self._cancels = self._client.cancels

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
        result = self._attempts(access, deadline)
        if result.abort_code == abort_codes.TIMEOUT:
            silence = self._silence()
            if silence:
                return SdoResult.failed(f'{result.message}; {silence}', abort_codes.TIMEOUT)
        return result

    def _attempts(self, access: Access, deadline: float) -> SdoResult:
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
                  transfer: Callable[[bool], Optional[bytes]],
                  block_first: Optional[bool] = None,
                  answer_within: Optional[float] = None) -> SdoResult:
        """Run ``transfer``; ``block_first``: try block transfer (None: ``sdo.block_transfer``).

        ``answer_within``: each answer due that long after its request, not by ``deadline``.
        """
        def attempt(block: bool) -> Optional[bytes]:
            return self._client.transfer(index, subindex, deadline, lambda: transfer(block),
                                         answer_within, self._cancels)

        def run() -> Optional[bytes]:
            if self._block if block_first is None else block_first:
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
