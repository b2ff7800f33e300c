"""Program downloads as a service: one per device at a time, each on a thread of its own.

A request is checked (its fields, a download already running for the device, the file, a
drive that is enabled, a device not heard) before anything is sent; then
:class:`~.download.ProgramDownload` runs its phases on the download's own thread, through the
gateway's SDO channels, so other devices' SDO, PDO and drives go on, and the caller (the ROS
action) is answered from that thread. A cancel or shutdown ends a download between two
segments or blocks, with an SDO abort; the bus going down ends it where it is (nothing can
be sent then). The answer says what the device was left in.
"""

from concurrent.futures import Future
from dataclasses import dataclass
import logging
import threading
import time
from typing import Callable, Dict, List, Optional, Tuple

from .. import nmt
from ..bus import prompt
from ..protocol import MAX_NODE_ID
from ..sdo.request_queue import answer, resolved
from ..text import SHUTTING_DOWN
from .download import (
    MAX_IMAGE,
    MAX_PROGRAM,
    NOTHING_SENT,
    PROGRAM_CONTROL,
    PROGRAM_DATA,
    ProgramDownload,
    ProgramLink,
    ProgramResult,
    ProgramSettings,
    Progress,
    read_image,
)

LOGGER = logging.getLogger(__name__)

CANCELLED = 'cancelled by the caller'
STOP_WAIT = 2.0  # s shutdown waits for the downloads to end and be answered


@dataclass(frozen=True)
class ProgramRequest:
    """A download as asked for (the action's goal)."""

    node_id: int
    file: str
    program: int = 1
    expected_software_id: int = 0
    start: bool = True


class _Run:
    """One download under way: why it must end, the device's boot-ups, its progress."""

    def __init__(self, node_id: int):
        self.node_id = node_id
        self.future: Future = Future()
        self.changed = threading.Condition()
        self.reason = ''  # why it must end (cancel, shutdown); '' while it may go on
        self.boot_ups = 0
        self.progress = Progress('')
        self.telling = True  # its progress is told to the caller (until that fails once)
        self.thread: Optional[threading.Thread] = None

    @prompt
    def on_heartbeat(self, _can_id: int, data: bytearray, _timestamp: float) -> None:
        if data[:1] == bytes([nmt.BOOT_UP]):
            with self.changed:
                self.boot_ups += 1
                self.changed.notify_all()

    def end(self, reason: str) -> None:
        with self.changed:
            self.reason = self.reason or reason
            self.changed.notify_all()


class ProgramService:
    """The program downloads of the devices on the gateway's network.

    ``sdo_batch(accesses, timeout, stop)`` and ``sdo_stream(access, answer_within, written)``
    are the gateway's; ``monitor`` its heartbeat monitor (a device not heard is refused);
    ``drive_enabled(node_id)`` whether a drive is OPERATION_ENABLED (refused: disable it
    first); ``refuses_write(node_id, index)`` the gateway's write protection.
    """

    def __init__(self, network, sdo_batch, sdo_stream, monitor,
                 drive_enabled: Callable[[int], bool],
                 refuses_write: Callable[[int, int], Optional[str]],
                 settings: ProgramSettings):
        self._network = network
        self._sdo_batch = sdo_batch
        self._sdo_stream = sdo_stream
        self._monitor = monitor
        self._drive_enabled = drive_enabled
        self._refuses_write = refuses_write
        self.settings = settings
        self._runs: Dict[int, _Run] = {}
        # Why a device's program is not whole (a download failed after it was stopped), until
        # a download succeeds: its boots must not start it.
        self._cleared: Dict[int, str] = {}
        self._lock = threading.Lock()
        self._closing = False
        self._listeners: List[Callable[[], None]] = []
        # Why a download must not run now (its device's boot runs, or would undo it), or None.
        self._booting: Callable[[ProgramRequest], Optional[str]] = lambda request: None

    def refuse_when(self, booting: Callable[['ProgramRequest'], Optional[str]]) -> None:
        """Refuse a download while ``booting(request)`` says why (the boot service's)."""
        self._booting = booting

    def add_listener(self, listener: Callable[[], None]) -> None:
        """Call ``listener()`` when a download begins or ends (no lock held)."""
        self._listeners.append(listener)

    def programming(self) -> Dict[int, Progress]:
        """Return the devices being programmed now, each with its download's progress."""
        with self._lock:
            return {node_id: run.progress for node_id, run in self._runs.items()}

    def refusal(self, node_id: int) -> Optional[str]:
        """Return why ``node_id`` must not be enabled now (it is being programmed), or None."""
        with self._lock:
            running = node_id in self._runs
        return f'node {node_id} is being programmed (~/program_download)' if running else None

    def cleared(self, node_id: int) -> str:
        """Return why ``node_id``'s program is not whole (its last download failed), or ''."""
        with self._lock:
            return self._cleared.get(node_id, '')

    def download(self, request: ProgramRequest,
                 feedback: Callable[[Progress], None] = lambda progress: None
                 ) -> Tuple['Future[ProgramResult]', Callable[[], None]]:
        """Start a download; return its future (one answer, never an exception) and a cancel.

        ``feedback(Progress)`` is called from the download's thread.
        """
        problem = _field_problem(request)
        if problem:
            return resolved(ProgramResult(False, f'{problem}; {NOTHING_SENT}',
                                          refused=True)), _nothing
        run = _Run(request.node_id)
        with self._lock:
            if self._closing:
                problem = SHUTTING_DOWN
            elif request.node_id in self._runs:
                problem = (f'node {request.node_id} is being programmed already: one download '
                           f'per device at a time')
            else:
                self._runs[request.node_id] = run
        # Asked once the download is known: a boot starting from now on is held for it, one
        # started before is seen here.
        booting = None if problem else self._booting(request)
        if booting:
            with self._lock:
                self._runs.pop(request.node_id, None)
            self._tell()  # a boot-up held for it meanwhile is booted now
            problem = booting
        if problem:
            return resolved(ProgramResult(False, f'{problem}; {NOTHING_SENT}',
                                          refused=True)), _nothing
        self._network.subscribe(nmt.HEARTBEAT_COB_BASE + request.node_id, run.on_heartbeat)
        run.thread = threading.Thread(target=self._work, args=(run, request, feedback),
                                      name=f'program-{request.node_id}', daemon=True)
        run.thread.start()
        self._tell()
        return run.future, lambda: run.end(CANCELLED)

    def stop(self) -> None:
        """End every download (between two segments, with an abort) and wait for its answer."""
        with self._lock:
            self._closing = True
            runs = list(self._runs.values())
        for run in runs:
            run.end(SHUTTING_DOWN)
        deadline = time.monotonic() + STOP_WAIT
        for run in runs:
            run.thread.join(max(0.0, deadline - time.monotonic()))

    def _work(self, run: _Run, request: ProgramRequest,
              feedback: Callable[[Progress], None]) -> None:
        def told(progress: Progress) -> None:
            run.progress = progress
            if run.telling:
                try:
                    feedback(progress)
                except Exception as error:  # noqa: BLE001 - the download goes on without it
                    run.telling = False
                    LOGGER.warning('node %d: progress of the program download cannot be told '
                                   '(%r); the download goes on', request.node_id, error)

        try:
            result, image = self._refusal(request)
            if result is None:
                download = ProgramDownload(request.node_id, image, request.program,
                                           request.expected_software_id, request.start,
                                           self._link(run), self.settings, told)
                result = download.run()
        except Exception as error:  # noqa: BLE001 - a defect must still answer the caller
            LOGGER.exception('node %d: the program download stopped on an error',
                             request.node_id)
            result = ProgramResult(False, f'the download stopped on an error of the gateway: '
                                          f'{error!r}; the device is in an unknown state: '
                                          f'download again')
        finally:
            self._network.unsubscribe(nmt.HEARTBEAT_COB_BASE + request.node_id,
                                      run.on_heartbeat)
            with self._lock:
                self._runs.pop(request.node_id, None)
                if result.success:
                    self._cleared.pop(request.node_id, None)
                elif result.cleared:
                    self._cleared[request.node_id] = (
                        f'its program download of {request.file} failed: {result.message}')
        if result.success:
            LOGGER.info('node %d: %s', request.node_id, result.message)
        else:
            LOGGER.warning('node %d: program download %s: %s', request.node_id,
                           'refused' if result.refused else 'failed', result.message)
        answer(run.future, result)
        self._tell()

    def _refusal(self, request: ProgramRequest) -> Tuple[Optional[ProgramResult], bytes]:
        """Return the answer refusing ``request`` before anything is sent (or None), the image."""
        node_id = request.node_id
        problem = None
        image = b''
        try:
            image = read_image(request.file)
        except OSError as error:
            problem = f'file {request.file!r} cannot be read: {error.strerror}'
        else:
            if not image:
                problem = f'file {request.file!r} is empty: no program to download'
            elif len(image) > MAX_IMAGE:
                problem = (f'file {request.file!r} holds more than {MAX_IMAGE} bytes: not a '
                           f'program image for one device')
        if problem is None:
            problem = self._refuses_write(node_id, PROGRAM_CONTROL) or self._refuses_write(
                node_id, PROGRAM_DATA)
        if problem is None and self._drive_enabled(node_id):
            problem = (f'drive {node_id} is OPERATION_ENABLED: disable it first, a program '
                       f'download stops its program')
        if problem is None and not self._monitor.status(node_id).detected:
            problem = (f'node {node_id} is not heard on the bus (no heartbeat or boot-up '
                       f'within heartbeat_timeout): check its power and node id')
        if problem:
            return ProgramResult(False, f'{problem}; {NOTHING_SENT}', refused=True), b''
        return None, image

    def _link(self, run: _Run) -> ProgramLink:
        def ended() -> str:
            return run.reason

        def sdo(accesses, timeout):
            return self._sdo_batch(accesses, timeout, lambda _results: ended() or None).result()

        def stream(access, answer_within, written):
            return self._sdo_stream(access, answer_within, written).result()

        def await_boot_up(send: Callable[[], str], timeout: float) -> bool:
            with run.changed:
                seen = run.boot_ups
            if send():
                return False
            deadline = time.monotonic() + timeout
            with run.changed:
                while run.boot_ups == seen and not run.reason:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    run.changed.wait(left)
                return run.boot_ups != seen

        def boot_ups() -> int:
            with run.changed:
                return run.boot_ups

        return ProgramLink(sdo, stream, await_boot_up, ended, boot_ups)

    def _tell(self) -> None:
        for listener in self._listeners:
            listener()


def _nothing() -> None:
    """Cancel a download that was refused: nothing to do."""


def _field_problem(request: ProgramRequest) -> Optional[str]:
    if not 1 <= request.node_id <= MAX_NODE_ID:
        return f'node_id {request.node_id} is out of range: allowed 1..{MAX_NODE_ID}'
    if not 1 <= request.program <= MAX_PROGRAM:
        return (f'program {request.program} is out of range: allowed 1..{MAX_PROGRAM} (the '
                f'sub-index of 0x1F50/0x1F51)')
    if not request.file:
        return 'file is empty: give the path of the program image, as the gateway reads it'
    if not 0 <= request.expected_software_id <= 0xFFFFFFFF:
        return (f'expected_software_id {request.expected_software_id} is out of range: '
                f'allowed 0 (not checked) to 0xFFFFFFFF')
    return None
