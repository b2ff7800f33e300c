"""Layer setting services (CiA 305): find unconfigured devices, give them node ids, bit rates.

The frames and command specifiers are python-canopen's (``canopen.lss``); its ``LssMaster``
is not used because it does not fit a gateway (see the README's library gaps): it waits
0.5 s on every unanswered request, and a Fastscan probes bit by bit (silence means a 1 bit),
so a scan finding nothing took 0.5 s and one device tens of seconds; it keeps one queue for
every answer, so a late or foreign frame answers the next request; it returns nothing for
requests nobody answers and raises on others, and drops the error code of a refusal.

Here answers are matched by command specifier and only frames the bus thread took after the
request went out count (frames carry the host's monotonic receive time). A Fastscan probe
waits a short time that fits the bus's bit rate; every other request waits longer. One LSS
operation runs at a time per bus, on a worker thread of its own; every call gets exactly one
:class:`LssResult`, also when the bus goes down or the gateway shuts down. Every operation
starts and ends by switching every device to the LSS waiting state.
"""

from collections import deque
from concurrent.futures import Future
from dataclasses import dataclass
import logging
import math
import struct
import threading
import time
from typing import Callable, Iterable, List, Optional, Set, Tuple

from canopen import lss as cia305

from .bus import BusDown, prompt
from .request_queue import answer, Deadlines, JobQueue, resolved
from .sdo import MAX_NODE_ID

LOGGER = logging.getLogger(__name__)

MASTER_COB = cia305.LssMaster.LSS_TX_COBID  # 0x7E5, master to devices
SLAVE_COB = cia305.LssMaster.LSS_RX_COBID   # 0x7E4, devices to master
WAITING = cia305.LssMaster.WAITING_STATE
UNCONFIGURED = 0xFF

# CiA 305's bit timing table: bit/s to the index a device is sent (5 is reserved).
BIT_TIMING = {1000000: 0, 800000: 1, 500000: 2, 250000: 3, 125000: 4, 50000: 6, 20000: 7,
              10000: 8}

# A probe and its answer are two 8-byte frames: at most 135 bits each with stuffing. The bit
# rate of a bus the gateway does not set (SocketCAN) is not known: take the slowest.
FRAME_BITS = 135
SLOWEST_BIT_RATE = 10000
# python-can buses without a wire: frames take no time on them.
SIMULATED_INTERFACES = frozenset({'virtual', 'udp_multicast'})
# What a device may take to answer, on top of the frames' time on the wire: generous, so a
# busy machine (or a device stack in Python) is not taken for an absent device.
DEVICE_MARGIN = 0.04
# Requests other than Fastscan probes are few: they may wait longer for their answer.
ANSWER_WAIT_MIN = 0.5
ANSWER_WAIT_PROBES = 8
# A probe at each of 32 bits and a confirmation, for each of the 4 parts of an identity.
PROBES_PER_DEVICE = 4 * 33
# Default scan timeout: time for this many devices even if every bit of them took a full wait.
DEFAULT_SCAN_DEVICES = 4
DEFAULT_TIMEOUT = 5.0  # configure and inquire
MAX_TIMEOUT = 600.0
# A scan that heard answers that did not add up (a device answering late, another master,
# a faulty device) starts again from the reset probe, at most this often per device.
SCAN_ATTEMPTS = 3
# The shortest time answers to one probe are taken in after the first (see _probe).
SETTLE_MIN = 0.002
# How long a device just numbered may take to send its boot-up before the scan goes on.
BOOT_WAIT = 1.0

ERRORS = {
    cia305.CS_CONFIGURE_NODE_ID: {1: 'node id out of range'},
    cia305.CS_CONFIGURE_BIT_TIMING: {1: 'bit timing (bit rate) not supported'},
    cia305.CS_STORE_CONFIGURATION: {1: 'storing the configuration is not supported',
                                    2: 'storage media access error'},
}
WHAT = {cia305.CS_CONFIGURE_NODE_ID: 'configure node id',
        cia305.CS_CONFIGURE_BIT_TIMING: 'configure bit timing',
        cia305.CS_STORE_CONFIGURATION: 'store configuration'}


def probe_wait(interface: str, bitrate: int, configured: float = 0.0) -> float:
    """Return the seconds a Fastscan probe waits for an answer (``configured`` if > 0)."""
    if configured > 0:
        return configured
    if interface in SIMULATED_INTERFACES:
        return DEVICE_MARGIN
    return 2 * FRAME_BITS / (bitrate or SLOWEST_BIT_RATE) + DEVICE_MARGIN


@dataclass(frozen=True)
class Identity:
    """A device's LSS address: object 0x1018:1..4."""

    vendor_id: int
    product_code: int
    revision: int
    serial: int

    def parts(self) -> Tuple[int, int, int, int]:
        """Return the four numbers in LSS order."""
        return self.vendor_id, self.product_code, self.revision, self.serial

    def problem(self) -> Optional[str]:
        """Return why this identity cannot be sent, or None."""
        for name, value in zip(('vendor_id', 'product_code', 'revision', 'serial'),
                               self.parts(), strict=True):
            if not 0 <= value <= 0xFFFFFFFF:
                return (f'identity.{name} {value} is out of range: allowed 0..0xFFFFFFFF '
                        f'(object 0x1018 of the device)')
        return None

    def __str__(self) -> str:
        return (f'vendor 0x{self.vendor_id:08X} product 0x{self.product_code:08X} '
                f'revision 0x{self.revision:08X} serial 0x{self.serial:08X}')


@dataclass(frozen=True)
class LssResult:
    """The one answer of every LSS call; fields a service does not have stay empty."""

    success: bool
    message: str = ''
    error_code: int = 0        # configure: the device's LSS error code
    node_id: int = 0           # inquire: the device's node id (255 unconfigured)
    devices: Tuple[Identity, ...] = ()
    node_ids: Tuple[int, ...] = ()


def check_timeout(timeout: float) -> Optional[str]:
    """Return why an LSS call's timeout is not valid, or None."""
    if math.isnan(timeout) or not 0.0 <= timeout <= MAX_TIMEOUT:
        return (f'timeout {timeout} s is out of range: allowed 0 (a default that fits the '
                f'bus) up to {MAX_TIMEOUT:g} s')
    return None


def scan_problem(first_node_id: int, timeout: float) -> Optional[str]:
    """Return why a scan request is not valid, or None."""
    if not 0 <= first_node_id <= MAX_NODE_ID:
        return (f'first_node_id {first_node_id} is out of range: allowed 1..127 (ids are '
                f'given from there upward), or 0 to only find one device')
    return check_timeout(timeout)


def configure_problem(identity: Identity, node_id: int, bitrate: int, store: bool,
                      timeout: float) -> Optional[str]:
    """Return why a configure request is not valid, or None."""
    if not 0 <= node_id <= MAX_NODE_ID:
        return f'node_id {node_id} is out of range: allowed 1..127, or 0 to keep it'
    if bitrate and bitrate not in BIT_TIMING:
        rates = ', '.join(str(rate) for rate in BIT_TIMING)
        return (f'bitrate {bitrate} is not in the CiA 305 table: allowed {rates}, or 0 to '
                f'keep it')
    if bitrate and not store:
        return (f'bitrate {bitrate} needs store: true: a new bit rate takes effect when the '
                f'device starts again with its stored configuration (the gateway does not '
                f'switch the bus to another rate)')
    if not (node_id or bitrate or store):
        return 'nothing to configure: give node_id, bitrate or store'
    return identity.problem() or check_timeout(timeout)


class Cancelled(Exception):
    """The operation was ended from outside: the bus went down, or shutdown began."""


class Disturbed(Exception):
    """Answers on 0x7E4 did not add up; the scan starts again."""


class _Responses:
    """Frames on 0x7E4 while a request waits; only those taken after it was sent count."""

    def __init__(self):
        self._changed = threading.Condition()
        self._frames: deque = deque(maxlen=64)
        self._cancelled: Optional[str] = None

    @prompt
    def on_frame(self, _can_id: int, data: bytearray, timestamp: float) -> None:
        with self._changed:
            self._frames.append((timestamp, bytes(data)))
            self._changed.notify_all()

    def cancel(self, reason: Optional[str]) -> None:
        """Make waiting and later requests raise :class:`Cancelled` (None: allow again)."""
        with self._changed:
            self._cancelled = reason
            self._changed.notify_all()

    def pause(self, seconds: float) -> None:
        """Wait ``seconds``; raise :class:`Cancelled` at once when cancelled meanwhile."""
        deadline = time.monotonic() + seconds
        with self._changed:
            while self._cancelled is None and time.monotonic() < deadline:
                self._changed.wait(deadline - time.monotonic())
            if self._cancelled is not None:
                raise Cancelled(self._cancelled)

    def check(self) -> None:
        """Raise :class:`Cancelled` when cancelled."""
        with self._changed:
            if self._cancelled is not None:
                raise Cancelled(self._cancelled)

    def wait(self, sent: float, command: int, size: int, wait: float,
             settle: Optional[float] = None) -> Optional[bytes]:
        """Return the first answer with ``command`` and ``size`` bytes or more, or None.

        With ``settle``, further answers of that kind are taken in until none came for that
        long (several devices answering one request, one after the other), or for ``wait``
        seconds in all with ``settle`` < 0; so none of them is left to seem to answer the
        next request.
        """
        deadline = time.monotonic() + wait
        first = None
        with self._changed:
            while True:
                if self._cancelled is not None:
                    raise Cancelled(self._cancelled)
                while self._frames:
                    taken, data = self._frames.popleft()
                    if taken >= sent and len(data) >= size and data[0] == command:
                        if settle is None:
                            return data
                        first = first or data
                        if settle >= 0:
                            deadline = time.monotonic() + settle
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return first
                self._changed.wait(remaining)


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
        self._network = network
        self._refusal = refusal
        self._deadlines = deadlines
        self.probe_wait = probe_wait_s
        self.answer_wait = max(ANSWER_WAIT_MIN, ANSWER_WAIT_PROBES * probe_wait_s)
        self.default_scan_timeout = DEFAULT_SCAN_DEVICES * PROBES_PER_DEVICE * probe_wait_s
        self._used_ids = used_ids
        self._detected = detected
        self._responses = _Responses()
        self._jobs = JobQueue()
        self._thread = threading.Thread(target=self._work, name='lss', daemon=True)

    def start(self) -> None:
        """Listen on 0x7E4 and start the worker."""
        self._network.subscribe(SLAVE_COB, self._responses.on_frame)
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
            self._responses.cancel(reason)  # under the lock: a job taken after runs anew
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
            job = self._jobs.next(lambda _: self._responses.cancel(None))
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
            self._all_waiting()

    # -- frames -----------------------------------------------------------------------------

    def _send(self, data: bytes) -> float:
        """Send one LSS request (8 bytes); return the time before it went out."""
        self._responses.check()
        sent = time.monotonic()
        self._network.send_message(MASTER_COB, data.ljust(8, b'\0'))
        return sent

    def _request(self, data: bytes, command: int, size: int, wait: float,
                 deadline: float) -> Optional[bytes]:
        sent = self._send(data)
        return self._responses.wait(sent, command, size,
                                    max(0.0, min(wait, deadline - time.monotonic())))

    def _all_waiting(self) -> None:
        """Switch every device to the waiting state; the only frame sent after a failure."""
        try:
            self._network.send_message(MASTER_COB, bytes([cia305.CS_SWITCH_STATE_GLOBAL,
                                                          WAITING]).ljust(8, b'\0'))
        except BusDown:
            pass  # the bus is gone, or shutdown forbids it: nothing more can be done

    def _switch_all_waiting(self) -> None:
        self._send(bytes([cia305.CS_SWITCH_STATE_GLOBAL, WAITING]))

    def _selective(self, identity: Identity, deadline: float) -> bool:
        """Switch the device with ``identity`` (only it) to the configuration state."""
        commands = (cia305.CS_SWITCH_STATE_SELECTIVE_VENDOR_ID,
                    cia305.CS_SWITCH_STATE_SELECTIVE_PRODUCT_CODE,
                    cia305.CS_SWITCH_STATE_SELECTIVE_REVISION_NUMBER)
        for command, value in zip(commands, identity.parts()[:3], strict=True):
            self._send(struct.pack('<BI', command, value))
        return self._request(struct.pack('<BI', cia305.CS_SWITCH_STATE_SELECTIVE_SERIAL_NUMBER,
                                         identity.serial),
                             cia305.CS_SWITCH_STATE_SELECTIVE_RESPONSE, 1, self.answer_wait,
                             deadline) is not None

    def _inquire_node_id(self, deadline: float) -> Optional[int]:
        data = self._request(bytes([cia305.CS_INQUIRE_NODE_ID]), cia305.CS_INQUIRE_NODE_ID,
                             2, self.answer_wait, deadline)
        return None if data is None else data[1]

    def _inquire_identity(self, deadline: float) -> Optional[Identity]:
        parts = []
        for command in (cia305.CS_INQUIRE_VENDOR_ID, cia305.CS_INQUIRE_PRODUCT_CODE,
                        cia305.CS_INQUIRE_REVISION_NUMBER, cia305.CS_INQUIRE_SERIAL_NUMBER):
            data = self._request(bytes([command]), command, 5, self.answer_wait, deadline)
            if data is None:
                return None
            parts.append(struct.unpack_from('<I', data, 1)[0])
        return Identity(*parts)

    def _configure_step(self, command: int, argument: bytes, deadline: float) -> Optional[int]:
        """Send a configure or store request; return the device's error code, None if silent."""
        data = self._request(bytes([command]) + argument, command, 2, self.answer_wait,
                             deadline)
        return None if data is None else data[1]

    def _probe(self, id_number: int, bit: int, sub: int, next_sub: int, deadline: float,
               careful: bool) -> bool:
        """Send one Fastscan probe; return whether any device answered.

        Every device matching a probe answers it. On a real bus identical answers sent at
        once are one frame, but a slower device's answer (always, on a bus that does not
        merge frames, such as python-can's virtual one) comes after: answers are taken in
        until none came for twice the time the first took, or (``careful``) for the whole
        probe wait.
        """
        if time.monotonic() >= deadline:
            raise TimeoutError
        frame = struct.pack('<BIBBB', cia305.CS_FAST_SCAN, id_number, bit, sub, next_sub)
        sent = self._send(frame)
        wait = max(0.0, min(self.probe_wait, deadline - time.monotonic()))
        if careful:
            return self._responses.wait(sent, cia305.CS_IDENTIFY_SLAVE, 1, wait,
                                        -1.0) is not None
        answered = self._responses.wait(sent, cia305.CS_IDENTIFY_SLAVE, 1, wait)
        if answered is None:
            return False
        settle = min(self.probe_wait, max(SETTLE_MIN, 2 * (time.monotonic() - sent)))
        self._responses.wait(time.monotonic(), cia305.CS_IDENTIFY_SLAVE, 1, settle, settle)
        return True

    # -- operations -------------------------------------------------------------------------

    def _fastscan(self, deadline: float, careful: bool) -> Optional[Identity]:
        """Find the unconfigured device with the lowest identity and switch it to configuration.

        CiA 305: after the reset probe (bit 0x80) every unconfigured device answers; then, part
        by part and bit by bit from the top, a probe asks for the bits so far with this bit 0:
        an answer means some device has it 0, silence that it is 1. Every part is confirmed
        (the devices matching it move on to the next part); the device matching all four
        parts enters the configuration state. The identity is then read back from it, so a
        late or foreign answer cannot make up a device.
        """
        if not self._probe(0, 0x80, 0, 0, deadline, careful):
            return None
        parts = [0, 0, 0, 0]
        for sub in range(4):
            for bit in range(31, -1, -1):
                if not self._probe(parts[sub], bit, sub, sub, deadline, careful):
                    parts[sub] |= 1 << bit
            if not self._probe(parts[sub], 0, sub, (sub + 1) % 4, deadline, careful):
                raise Disturbed(f'no device confirmed part {sub + 1} of the identity')
        found = Identity(*parts)
        read_back = self._inquire_identity(deadline)
        if read_back != found:
            raise Disturbed(f'the device found as {found} read back as {read_back}')
        node_id = self._inquire_node_id(deadline)
        if node_id != UNCONFIGURED:
            raise Disturbed(f'the device found as {found} reports node id {node_id}')
        return found

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
                self._switch_all_waiting()  # the device numbered last boots with its id
                if node_ids and node_ids[-1]:
                    booted = min(time.monotonic() + BOOT_WAIT, deadline)
                    while not self._detected(node_ids[-1]) and time.monotonic() < booted:
                        self._responses.pause(0.005)
                try:
                    identity = self._fastscan(deadline, careful=attempts > 0)
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
        code = self._configure_step(command, argument, deadline)
        if code is None:
            return f'no answer to {WHAT[command]}'
        if code:
            return f'the device refused {WHAT[command]}: {describe_error(command, code)}'
        return None

    def _find(self, identity: Identity, deadline: float) -> Optional[str]:
        self._switch_all_waiting()
        if not self._selective(identity, deadline):
            return (f'no device with {identity} answered (is it on the bus, and is the '
                    f'identity right? lss_scan finds unconfigured devices)')
        return None

    def _configure(self, identity: Identity, node_id: int, bitrate: int, store: bool,
                   deadline: float) -> LssResult:
        missing = self._find(identity, deadline)
        if missing:
            return LssResult(False, missing)
        current = self._inquire_node_id(deadline)
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
            code = self._configure_step(command, argument, deadline)
            if code is None:
                return LssResult(False, f'the device with {identity} did not answer '
                                        f'{WHAT[command]}' + _so_far(done))
            if code:
                return LssResult(False, f'the device with {identity} refused '
                                        f'{WHAT[command]} ({what}): '
                                        f'{describe_error(command, code)}' + _so_far(done),
                                 error_code=code)
            done.append(what)
        self._switch_all_waiting()
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
        node_id = self._inquire_node_id(deadline)
        if node_id is None:
            return LssResult(False, f'the device with {identity} did not tell its node id')
        state = 'unconfigured' if node_id == UNCONFIGURED else f'node id {node_id}'
        return LssResult(True, f'{identity}: {state}', node_id=node_id)


def describe_error(command: int, code: int) -> str:
    """Return a device's LSS error code in words, e.g. 'LSS error 1 (node id out of range)'."""
    if code == cia305.ERROR_VENDOR_SPECIFIC:
        return 'LSS error 255 (manufacturer-specific)'
    meaning = ERRORS.get(command, {}).get(code, 'reserved')
    return f'LSS error {code} ({meaning})'


def _so_far(done: List[str]) -> str:
    return f'; done before: {", ".join(done)}' if done else '; nothing was changed'


def is_all_waiting(message) -> bool:
    """Return whether ``message`` is the LSS switch of every device to the waiting state."""
    return (message.arbitration_id == MASTER_COB
            and bytes(message.data[:2]) == bytes([cia305.CS_SWITCH_STATE_GLOBAL, WAITING]))
