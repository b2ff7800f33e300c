"""The gateway's LSS master (CiA 305): one operation at a time per bus, each answered once.

One LSS operation runs at a time per bus, on a worker thread of its own; every call gets
exactly one :class:`~cbcan_ros.core.lss.requests.LssResult`, also when the bus goes down or the
gateway shuts down. Every operation starts and ends by switching every device to the LSS
waiting state.
"""

from concurrent.futures import Future
from dataclasses import dataclass
import logging
import threading
import time
from typing import Callable, Iterable, List, Optional, Set

from canopen import lss as cia305

from ..bus import BusDown
from ..protocol import MAX_NODE_ID
from ..sdo.request_queue import answer, Deadlines, JobQueue, resolved
from .frames import Cancelled, Disturbed, LssFrames
from .requests import (
    BIT_TIMING,
    check_timeout,
    configure_problem,
    DEFAULT_TIMEOUT,
    describe_error,
    Identity,
    LssResult,
    scan_problem,
    UNCONFIGURED,
    WHAT,
)

LOGGER = logging.getLogger(__name__)

# A probe at each of 32 bits and a confirmation, for each of the 4 parts of an identity.
PROBES_PER_DEVICE = 4 * 33
# Default scan timeout: time for this many devices even if every bit of them took a full wait.
DEFAULT_SCAN_DEVICES = 4
# A scan that heard answers that did not add up (a device answering late, another master,
# a faulty device) starts again from the reset probe, at most this often per device.
SCAN_ATTEMPTS = 3
# How long a device just numbered may take to send its boot-up before the scan goes on.
BOOT_WAIT = 1.0


@dataclass(eq=False)
class _Job:
    run: Callable[[float], LssResult]
    deadline: float
    timeout: float
    future: Future


class LssMaster:
    """The gateway's LSS master: one operation at a time on one bus, each answered once.

    ``used_ids()`` returns the node ids a scan must not give (heard or expected);
    ``detected(node_id)`` whether a node id is heard on the bus now; ``refusal()`` why no
    LSS request may be sent now (read-only, bus down, shutdown), or None.
    """

    def __init__(self, network, deadlines: Deadlines, probe_wait_s: float,
                 used_ids: Callable[[], Iterable[int]], detected: Callable[[int], bool],
                 refusal: Callable[[], Optional[str]]):
        self._frames = LssFrames(network, probe_wait_s)
        self._refusal = refusal
        self._deadlines = deadlines
        self.probe_wait = probe_wait_s
        self.default_scan_timeout = DEFAULT_SCAN_DEVICES * PROBES_PER_DEVICE * probe_wait_s
        self._used_ids = used_ids
        self._detected = detected
        self._jobs = JobQueue()
        self._thread = threading.Thread(target=self._work, name='lss', daemon=True)

    def start(self) -> None:
        """Listen on 0x7E4 and start the worker."""
        self._frames.start()
        self._thread.start()

    # -- the three services -------------------------------------------------------------

    def scan(self, first_node_id: int, store: bool, timeout: float) -> 'Future[LssResult]':
        """Find unconfigured devices by Fastscan; number them from ``first_node_id`` (0: find)."""
        problem = scan_problem(first_node_id, timeout)
        if problem:
            return resolved(LssResult(False, problem))
        return self._submit(lambda deadline: self._scan(first_node_id, store, deadline),
                            timeout or self.default_scan_timeout)

    def configure(self, identity: Identity, node_id: int, bitrate: int, store: bool,
                  timeout: float) -> 'Future[LssResult]':
        """Give the device ``identity`` a node id and/or bit rate, and store them if asked."""
        problem = configure_problem(identity, node_id, bitrate, store, timeout)
        if problem:
            return resolved(LssResult(False, problem))
        return self._submit(lambda deadline: self._configure(identity, node_id, bitrate,
                                                             store, deadline),
                            timeout or DEFAULT_TIMEOUT)

    def inquire(self, identity: Identity, timeout: float) -> 'Future[LssResult]':
        """Ask the device ``identity`` for its node id."""
        problem = identity.problem() or check_timeout(timeout)
        if problem:
            return resolved(LssResult(False, problem))
        return self._submit(lambda deadline: self._inquire(identity, deadline),
                            timeout or DEFAULT_TIMEOUT)

    # -- failures from outside ----------------------------------------------------------

    def fail_all(self, reason: str) -> None:
        """Answer every waiting call with ``reason`` and end the running operation."""
        with self._jobs.lock:
            jobs = self._jobs.take_all()
            self._frames.cancel(reason)  # under the lock: a job taken after runs anew
        for job in jobs:
            answer(job.future, LssResult(False, f'{reason}; nothing was sent'))

    def close(self, reason: str) -> None:
        """Refuse new calls, answer waiting ones, end the running one and the worker."""
        self._jobs.close(reason)
        self.fail_all(reason)
        if self._thread.is_alive():
            self._thread.join(1.0)

    # -- the worker -----------------------------------------------------------------------

    def _submit(self, run: Callable[[float], LssResult], timeout: float) -> Future:
        job = _Job(run, time.monotonic() + timeout, timeout, Future())
        refusal = self._refusal()
        with self._jobs.lock:
            refusal = refusal or self._jobs.closed
            if refusal is None:
                self._jobs.put(job)
        if refusal is not None:
            answer(job.future, LssResult(False, f'{refusal}; nothing was sent'))
        else:
            self._deadlines.watch(job.deadline, lambda: self._expire(job))
        return job.future

    def _expire(self, job: _Job) -> None:
        if not self._jobs.withdraw(job):
            return
        answer(job.future, LssResult(False, f'busy: another LSS operation on this bus was '
                                            f'still running after {job.timeout:g} s (one '
                                            f'runs at a time); nothing was sent'))

    def _work(self) -> None:
        while True:
            job = self._jobs.next(lambda _: self._frames.cancel(None))
            if job is None:
                return
            answer(job.future, self._guarded(job))

    def _guarded(self, job: _Job) -> LssResult:
        try:
            return job.run(job.deadline)
        except (Cancelled, BusDown) as error:
            return LssResult(False, str(error))
        except Exception as error:  # noqa: BLE001 - every call gets its one answer
            LOGGER.warning('LSS operation failed unexpectedly: %r', error)
            return LssResult(False, f'internal error of the gateway: {error!r}'[:300])
        finally:
            self._frames.all_waiting()

    # -- operations -------------------------------------------------------------------------

    def _scan(self, first_node_id: int, store: bool, deadline: float) -> LssResult:
        devices: List[Identity] = []
        node_ids: List[int] = []
        used: Set[int] = set(self._used_ids())

        def result(success: bool, message: str) -> LssResult:
            if devices and first_node_id:
                given = ', '.join(f'{n} to {d}' for d, n in zip(devices, node_ids,
                                                                 strict=True))
                message = f'{message}; given so far: {given}' if not success else message
            return LssResult(success, message, devices=tuple(devices),
                             node_ids=tuple(node_ids))

        attempts = 0
        try:
            while True:
                self._frames.switch_all_waiting()  # the device numbered last boots with its id
                if node_ids and node_ids[-1]:
                    booted = min(time.monotonic() + BOOT_WAIT, deadline)
                    while not self._detected(node_ids[-1]) and time.monotonic() < booted:
                        self._frames.pause(0.005)
                try:
                    identity = self._frames.fastscan(deadline, careful=attempts > 0)
                except Disturbed as why:
                    LOGGER.info('LSS scan starts again, waiting the whole probe time for '
                                'every answer: %s', why)
                    attempts += 1
                    if attempts >= SCAN_ATTEMPTS:
                        return result(False, f'the scan was disturbed {attempts} times in a '
                                             f'row ({why}): another LSS master or a faulty '
                                             f'device on 0x7E4?')
                    continue
                attempts = 0
                if identity is None:
                    break
                if identity in devices:
                    return result(False, f'{identity} was found again after it was given '
                                         f'node id {node_ids[devices.index(identity)]}: it '
                                         f'did not take the new id')
                if not first_node_id:
                    devices.append(identity)
                    node_ids.append(0)
                    return result(True, f'found 1 unconfigured device ({identity}) and left '
                                        f'it unconfigured; a scan with first_node_id > 0 '
                                        f'finds and numbers all of them')
                free = [n for n in range(first_node_id, MAX_NODE_ID + 1) if n not in used]
                if not free:
                    return result(False, f'found {identity} but no node id from '
                                         f'{first_node_id} to 127 is free (heard on the bus '
                                         f'or listed in nodes)')
                node_id = free[0]
                problem = self._refused(cia305.CS_CONFIGURE_NODE_ID, bytes([node_id]),
                                        deadline)
                if problem:
                    return result(False, f'{identity}: {problem}')
                # From here it boots with the id at the next switch to waiting, come what may.
                devices.append(identity)
                node_ids.append(node_id)
                used.add(node_id)
                problem = store and self._refused(cia305.CS_STORE_CONFIGURATION, b'', deadline)
                if problem:
                    return result(False, f'{identity} has node id {node_id} but it is not '
                                         f'stored: {problem}')
        except TimeoutError:
            return result(False, f'the scan ran out of time after finding {len(devices)} '
                                 f'device(s); scan again to find the rest')
        except (Cancelled, BusDown) as error:
            return result(False, str(error))
        if not devices:
            return result(True, f'no unconfigured device found: nothing answered the '
                                f'Fastscan within {self.probe_wait * 1000:.0f} ms')
        given = ', '.join(f'node id {n} to {d}' for d, n in zip(devices, node_ids, strict=True))
        stored = ' and stored' if store else ' (not stored: lost at power-off)'
        return result(True, f'found {len(devices)} unconfigured device(s) and gave '
                            f'{given}{stored}')

    def _refused(self, command: int, argument: bytes, deadline: float) -> Optional[str]:
        """Send a configure or store request; return why it failed, or None."""
        code = self._frames.configure_step(command, argument, deadline)
        if code is None:
            return f'no answer to {WHAT[command]}'
        if code:
            return f'the device refused {WHAT[command]}: {describe_error(command, code)}'
        return None

    def _find(self, identity: Identity, deadline: float) -> Optional[str]:
        self._frames.switch_all_waiting()
        if not self._frames.select(identity, deadline):
            return (f'no device with {identity} answered (is it on the bus, and is the '
                    f'identity right? lss_scan finds unconfigured devices)')
        return None

    def _configure(self, identity: Identity, node_id: int, bitrate: int, store: bool,
                   deadline: float) -> LssResult:
        missing = self._find(identity, deadline)
        if missing:
            return LssResult(False, missing)
        current = self._frames.inquire_node_id(deadline)
        if current is None:
            return LssResult(False, f'the device with {identity} did not tell its node id')
        done = []
        if node_id and node_id != current and self._detected(node_id):
            return LssResult(False, f'node_id {node_id} is already used by a device heard on '
                                    f'this bus: nothing was changed')
        steps = []
        if node_id:
            steps.append((cia305.CS_CONFIGURE_NODE_ID, bytes([node_id]),
                          f'node id {node_id}'))
        if bitrate:
            steps.append((cia305.CS_CONFIGURE_BIT_TIMING, bytes([0, BIT_TIMING[bitrate]]),
                          f'bit rate {bitrate} bit/s'))
        if store:
            steps.append((cia305.CS_STORE_CONFIGURATION, b'', 'stored'))
        for command, argument, what in steps:
            code = self._frames.configure_step(command, argument, deadline)
            if code is None:
                return LssResult(False, f'the device with {identity} did not answer '
                                        f'{WHAT[command]}' + _so_far(done))
            if code:
                return LssResult(False, f'the device with {identity} refused '
                                        f'{WHAT[command]} ({what}): '
                                        f'{describe_error(command, code)}' + _so_far(done),
                                 error_code=code)
            done.append(what)
        self._frames.switch_all_waiting()
        notes = []
        if node_id and node_id != current:
            if current == UNCONFIGURED:
                notes.append(f'it was unconfigured and boots now as node {node_id}')
            else:
                notes.append(f'it keeps node id {current} until its next NMT reset '
                             f'communication (cbcan_cli nmt {current} reset-comm) or power-on')
        if bitrate:
            notes.append('the bit rate takes effect when the device is next powered on; '
                         'the bus keeps its rate until then')
        if not store:
            notes.append('not stored: lost at power-off')
        return LssResult(True, f'{identity}: {", ".join(done)}' +
                         (f' ({"; ".join(notes)})' if notes else ''))

    def _inquire(self, identity: Identity, deadline: float) -> LssResult:
        missing = self._find(identity, deadline)
        if missing:
            return LssResult(False, missing, node_id=0)
        node_id = self._frames.inquire_node_id(deadline)
        if node_id is None:
            return LssResult(False, f'the device with {identity} did not tell its node id')
        state = 'unconfigured' if node_id == UNCONFIGURED else f'node id {node_id}'
        return LssResult(True, f'{identity}: {state}', node_id=node_id)


def _so_far(done: List[str]) -> str:
    return f'; done before: {", ".join(done)}' if done else '; nothing was changed'
