"""One program download (CiA 302-3), step by step, and what it leaves the device in.

The steps, each a phase of the feedback: STOPPING (0x1F51:n = 0), CLEARING (0x1F51:n = 3,
then 0x1F57:n until the flash is no longer busy), DOWNLOADING (the image into the DOMAIN
0x1F50:n, block transfer with CRC where the device has it, segmented otherwise), FLASHING
(0x1F57:n until it is done, or reports an error), STARTING (0x1F51:n = 1, then the device's
boot-up message) and CHECKING (0x1F56:n, the software identification). Each phase has a
timeout that fits it: an SDO answer, the flash's own time, the device's restart.

Everything goes through a :class:`ProgramLink`: the gateway's SDO channels (so a download
queues behind a user's SDO calls to the same device and never races them), and its boot-up
watch. The ROS action and the boot process (``software_file``) give their own links.
"""

from dataclasses import dataclass
import errno
import os
import stat
import time
from typing import Callable, List, Optional, Sequence

from ..sdo import abort_codes
from ..sdo.requests import Access, MAX_TIMEOUT, SdoResult

PROGRAM_DATA = 0x1F50
PROGRAM_CONTROL = 0x1F51
SOFTWARE_ID = 0x1F56
FLASH_STATUS = 0x1F57
STOP, START, CLEAR = 0, 1, 3  # what 0x1F51:n takes (CiA 302-3; 2 is reset)

STOPPING, CLEARING, DOWNLOADING, FLASHING, STARTING, CHECKING = (
    'STOPPING', 'CLEARING', 'DOWNLOADING', 'FLASHING', 'STARTING', 'CHECKING')
PHASES = (STOPPING, CLEARING, DOWNLOADING, FLASHING, STARTING, CHECKING)

# 0x1F57:n (CiA 302-3): bit 0 set while the flash is busy, bits 1..7 an error code.
FLASH_BUSY = 0x01
FLASH_ERRORS = {1: 'no valid program', 2: 'data format unknown',
                3: 'data format error or CRC error', 4: 'flash not cleared before write',
                5: 'flash write error', 6: 'general address error',
                7: 'flash secured (write access forbidden)'}
FLASH_POLL = 0.05  # s between two reads of 0x1F57 while the flash is busy
FEEDBACK_PERIOD = 0.1  # s: the download's progress is told at most this often
NO_SUCH_OBJECT = (abort_codes.OBJECT_DOES_NOT_EXIST, abort_codes.SUBINDEX_NOT_EXIST)
MAX_PROGRAM = 254  # 0x1F50..0x1F57 sub-indices 1..254; 0 holds the count
MAX_IMAGE = 64 * 1024 * 1024  # bytes: larger files are refused, not read into memory
NOTHING_SENT = 'nothing was sent'


@dataclass(frozen=True)
class ProgramSettings:
    """The timeouts of the phases (s) and whether a boot may download (parameters)."""

    answer_timeout: float = 0.5   # an SDO answer; each segment and block of the image
    flash_timeout: float = 30.0   # CLEARING and FLASHING: the flash's own time
    start_timeout: float = 10.0   # STARTING: from 0x1F51 = 1 to the device's boot-up
    restart_timeout: float = 0.0  # STOPPING: from 0x1F51 = 0 to the boot-up of a device
    #                               that restarts into its bootloader; 0: it does not
    at_boot: bool = False         # program_download.at_boot: software_file at a boot


@dataclass(frozen=True)
class Progress:
    """What a running download is doing (the action's feedback)."""

    phase: str
    bytes_sent: int = 0
    bytes_total: int = 0
    bytes_per_second: float = 0.0


@dataclass(frozen=True)
class ProgramResult:
    """How a download ended (the action's result)."""

    success: bool
    message: str
    software_id: int = 0    # 0x1F56:n read at the end; 0 not read
    abort_code: int = 0     # the SDO abort that ended it; 0 none
    flash_status: int = 0   # 0x1F57:n (its low byte) last read; 0 not read or no error
    refused: bool = False   # refused before anything was written
    cleared: bool = False   # left stopped, cleared or partly written: only a download mends it


@dataclass
class ProgramLink:
    """What a download may do on the bus, for one device.

    - ``sdo(accesses, timeout)``: their results in order; stops sending once ``ended()``.
    - ``stream(access, answer_within, written)``: the image, each answer within
      ``answer_within`` s; ``written(bytes so far, block)`` (block transfer, else
      segmented) returns why to stop, or None.
    - ``await_boot_up(send, timeout)``: calls ``send()`` (returns why it failed, or ''), then
      whether the device's boot-up came within ``timeout`` s.
    - ``ended()``: why the download must end now (cancel, shutdown, bus down), or ''.
    - ``boot_ups()``: the device's boot-up messages heard so far (0 where not counted).
    """

    sdo: Callable[[Sequence[Access], float], List[SdoResult]]
    stream: Callable[[Access, float, Callable[[int, bool], Optional[str]]], SdoResult]
    await_boot_up: Callable[[Callable[[], str], float], bool]
    ended: Callable[[], str]
    boot_ups: Callable[[], int] = lambda: 0


def read_image(path: str) -> bytes:
    """Return a program image file's first ``MAX_IMAGE + 1`` bytes; OSError for any other file.

    Opened without blocking, so a FIFO or a device file given by mistake is refused at once
    instead of holding the download's thread (and its answer) for good.
    """
    descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    with os.fdopen(descriptor, 'rb') as file:
        if not stat.S_ISREG(os.fstat(descriptor).st_mode):
            raise OSError(errno.EINVAL, 'not a regular file (a directory, FIFO or device)')
        return file.read(MAX_IMAGE + 1)


class _Failed(Exception):
    def __init__(self, message: str, abort_code: int = 0, refused: bool = False):
        super().__init__(message)
        self.message = message
        self.abort_code = abort_code
        self.refused = refused


def flash_status_text(status: int) -> str:
    """Return what a 0x1F57 value says: busy, done, or its error."""
    error = (status >> 1) & 0x7F
    if error:
        meaning = FLASH_ERRORS.get(error, 'manufacturer specific' if error >= 64
                                   else 'reserved code')
        return f'0x{status:02X}: error {error}, {meaning}'
    return f'0x{status:02X}: {"busy" if status & FLASH_BUSY else "no error"}'


def _number(data: bytes) -> int:
    return int.from_bytes(bytes(data[:4]), 'little')


class ProgramDownload:
    """One download of ``image`` into program ``program`` of ``node_id``.

    ``run()`` returns a :class:`ProgramResult`, never raises; ``feedback(Progress)`` is called
    on each phase and, while downloading, every ``FEEDBACK_PERIOD`` at most.
    ``expected_software_id``: what 0x1F56 must read afterwards (0: not checked); ``start``:
    False leaves the new program written, not started.
    """

    def __init__(self, node_id: int, image: bytes, program: int, expected_software_id: int,
                 start: bool, link: ProgramLink, settings: ProgramSettings,
                 feedback: Callable[[Progress], None] = lambda progress: None):
        self.node_id = node_id
        self._image = image
        self._program = program
        self._expected = expected_software_id
        self._start = start
        self._link = link
        self._settings = settings
        self._feedback = feedback
        self.phase = ''
        self._sent = 0
        self._flash = 0
        self._has_flash_status = True
        self._program_running = True  # 0x1F51:n read non-zero (or not at all) before the stop
        self._software_id = 0
        self._id_text = ''  # what the check found of the software id, for the answer
        self._transfer = ''
        n = program
        self._left = 'unchanged'  # until the first phase begins
        self._states = {  # what the device is left in once a phase has begun
            STOPPING: f'program {n} perhaps stopped (0x1F51:{n} = 0 sent): start it again '
                      f'(0x1F51:{n} = 1) or download again',
            CLEARING: f'program {n} stopped and perhaps cleared, not started: download again',
            DOWNLOADING: f'program {n} cleared and partly written, not started: download '
                         f'again',
            FLASHING: f'program {n} written, flashing not confirmed, not started: download '
                      f'again',
            STARTING: f'program {n} written and told to start (0x1F51:{n} = 1); its '
                      f'start was not seen: look at the device (a power cycle may be needed)',
            CHECKING: f'program {n} written and started',
        }

    def run(self) -> ProgramResult:
        """Run every phase; return how it ended."""
        try:
            self._check_objects()
            self._clear(self._stop())
            self._await_flash(CLEARING)
            self._download()
            self._begin(FLASHING)
            self._await_flash(FLASHING)
            if not self._start:
                return self._result(True, f'{self._done_text()}; not started (start: false): '
                                          f'start it with 0x1F51:{self._program} = 1')
            self._start_program()
            self._check()
        except _Failed as failure:
            return self._failed(failure)
        return self._result(True, f'{self._done_text()}; started, {self._id_text}')

    # The phases.

    def _check_objects(self) -> None:
        """Refuse a device without 0x1F50/0x1F51 (0x1F56 when checked): read before writing.

        0x1F50 is read with room for one byte: a device answers with the image's size first,
        so whatever it holds costs one round trip (or it says write-only: it is there).
        """
        n = self._program
        reads = [Access(self.node_id, PROGRAM_CONTROL, n), Access(self.node_id, PROGRAM_DATA, n,
                                                                   max_size=1),
                 Access(self.node_id, SOFTWARE_ID, n), Access(self.node_id, FLASH_STATUS, n)]
        # One at a time: a caller's batch may stop at the first failure, and 0x1F50 fails.
        results = [self._sdo([read], self._settings.answer_timeout)[0] for read in reads]
        reason = self._link.ended()
        if reason:  # a cancel, not a refusal: the action ends CANCELED
            raise _Failed(f'{reason}; {NOTHING_SENT}')
        for access, result in zip(reads[:2], results[:2], strict=True):
            if result.abort_code in NO_SUCH_OBJECT:
                raise _Failed(f'node {self.node_id} has no 0x{access.index:04X}:{n} '
                              f'({result.message}): it offers no program download (CiA '
                              f'302-3) for program {n}; {NOTHING_SENT}', result.abort_code,
                              refused=True)
            if result.abort_code == abort_codes.TIMEOUT or not result.abort_code and \
                    not result.success:
                raise _Failed(f'node {self.node_id} did not answer reading '
                              f'0x{access.index:04X}:{n}: {result.message}; {NOTHING_SENT}',
                              result.abort_code, refused=True)
        if self._expected and not results[2].success:
            raise _Failed(f'expected_software_id 0x{self._expected:08X} cannot be checked: '
                          f'node {self.node_id} does not give 0x1F56:{n} ({results[2].message});'
                          f' give 0 or leave it out; {NOTHING_SENT}', results[2].abort_code,
                          refused=True)
        self._has_flash_status = results[3].success
        self._program_running = not results[0].success or _number(results[0].data) != 0

    def _begin(self, phase: str) -> None:
        self._ended()
        self.phase = phase
        self._left = self._states[phase]
        self._feedback(Progress(phase, self._sent, len(self._image)))

    def _stop(self) -> int:
        """Stop the program; return the device's boot-ups counted once it is stopped."""
        self._begin(STOPPING)
        # A program stopped already (0x1F51 read 0: the device runs its bootloader) does
        # not restart when stopped again.
        if self._settings.restart_timeout and self._program_running:
            self._command_until_boot_up(STOP, self._settings.restart_timeout,
                                        'program_download.restart_timeout',
                                        'the device did not restart, or took longer; 0 is '
                                        'for a device that does not restart when stopped')
            return self._link.boot_ups()
        boot_ups = self._link.boot_ups()
        try:
            self._write(PROGRAM_CONTROL, STOP, self._settings.answer_timeout)
        except _Failed as failure:
            if self._settings.restart_timeout or failure.abort_code != abort_codes.TIMEOUT:
                raise
            raise self._restart_hint(failure, 'did not answer the stop') from None
        return boot_ups

    def _clear(self, boot_ups: int) -> None:
        """Clear the program; ``boot_ups``: the device's count once it was stopped."""
        self._begin(CLEARING)
        try:
            self._write(PROGRAM_CONTROL, CLEAR, self._settings.flash_timeout)
        except _Failed as failure:
            # Its boot-up, not an answer, came (a boot then ends at once, without one).
            if self._link.boot_ups() == boot_ups or failure.abort_code not in (
                    0, abort_codes.TIMEOUT):
                raise
            raise self._restart_hint(failure, 'restarted after the stop (its boot-up message '
                                              'came) and did not hear the clear') from None

    def _restart_hint(self, failure: _Failed, what: str) -> _Failed:
        """Return ``failure`` of a command the device did not answer, with why it may not."""
        if self._settings.restart_timeout:
            hint = f'; the device {what}'
        else:
            hint = (f'; the device {what}: a device that restarts into its bootloader when '
                    f'stopped needs parameter program_download.restart_timeout')
        return _Failed(failure.message + hint, failure.abort_code)

    def _write(self, index: int, value: int, timeout: float) -> SdoResult:
        access = Access(self.node_id, index, self._program, True, bytes([value]))
        result = self._sdo([access], timeout)[0]
        if not result.success:
            self._ended()
            raise _Failed(f'writing {value} to 0x{index:04X}:{self._program} failed: '
                          f'{result.message}', result.abort_code)
        return result

    def _await_flash(self, phase: str) -> None:
        """Read 0x1F57 until the flash is no longer busy; fail on its error, or past its time."""
        if not self._has_flash_status:
            return  # the device answers the write once done, or tells nothing
        timeout = self._settings.flash_timeout
        deadline = time.monotonic() + timeout
        while True:
            self._ended()
            result = self._sdo([Access(self.node_id, FLASH_STATUS, self._program)],
                               self._settings.answer_timeout)[0]
            if not result.success:
                self._ended()
                raise _Failed(f'0x1F57:{self._program} (flash status) could not be read: '
                              f'{result.message}', result.abort_code)
            self._flash = _number(result.data) & 0xFF
            if (self._flash >> 1) & 0x7F:
                raise _Failed(f'the device reports a flash error in 0x1F57:{self._program}: '
                              f'{flash_status_text(self._flash)}')
            if not self._flash & FLASH_BUSY:
                return
            if time.monotonic() >= deadline:
                raise _Failed(f'the flash was still busy {timeout:g} s after {phase} began '
                              f'(0x1F57:{self._program} = 0x{self._flash:02X}; parameter '
                              f'program_download.flash_timeout)')
            time.sleep(FLASH_POLL)

    def _download(self) -> None:
        self._begin(DOWNLOADING)
        total = len(self._image)
        began = time.monotonic()
        told = [began]
        by_block = [False]
        boot_ups = self._link.boot_ups()

        def reset() -> str:
            if self._link.boot_ups() == boot_ups:
                return ''
            return (f'the device reset (it sent its boot-up message) at byte {self._sent} of '
                    f'{total}: it took no more of the image')

        def written(position: int, block: bool) -> Optional[str]:  # after every segment
            self._sent = position
            by_block[0] = block
            now = time.monotonic()
            if now - told[0] >= FEEDBACK_PERIOD or position == total:
                told[0] = now
                self._feedback(Progress(DOWNLOADING, position, total,
                                        position / max(now - began, 1e-6)))
            # The rest of the image would reach the restarted device as commands it does
            # not know, each answered with an abort that a later request could take for its
            # own answer.
            return self._link.ended() or reset() or None

        result = self._link.stream(Access(self.node_id, PROGRAM_DATA, self._program, True,
                                          self._image),
                                   self._settings.answer_timeout, written)
        if not result.success:
            restarted = reset()
            if restarted:
                raise _Failed(restarted)
            reason = self._link.ended()
            if reason and result.abort_code in (abort_codes.LOCAL_CONTROL,
                                                abort_codes.DEVICE_STATE, 0):
                raise _Failed(reason, result.abort_code)
            # An abort of the device's, or no answer in time, is the device's; anything else
            # (the bus went down, the gateway's own refusal) stopped it on this side.
            who = ('the device ended the download' if result.abort_code
                   else 'the download stopped')
            raise _Failed(f'{who} at byte {self._sent} of {total}: {result.message}',
                          result.abort_code)
        self._sent = total
        elapsed = max(time.monotonic() - began, 1e-6)
        kind = ('block transfer' if by_block[0] else 'expedited transfer' if total <= 4
                else 'segmented transfer')
        self._transfer = (f'{kind}, {total} bytes in {elapsed:.2f} s, '
                          f'{total / elapsed / 1024:.1f} KiB/s')

    def _start_program(self) -> None:
        self._begin(STARTING)
        n = self._program
        refused = f'program {n} written, its start refused by the device: not started; start ' \
                  f'it (0x1F51:{n} = 1) once the device allows it, or download again'
        self._command_until_boot_up(START, self._settings.start_timeout,
                                    'program_download.start_timeout',
                                    'the new program did not come up', refused)

    def _command_until_boot_up(self, command: int, timeout: float, parameter: str,
                               not_came: str, refused_leaves: str = '') -> None:
        """Write ``command`` to 0x1F51 and wait up to ``timeout`` s for the boot-up it brings.

        ``refused_leaves``: what a refusal leaves the device in, if not the phase's default.
        """
        access = Access(self.node_id, PROGRAM_CONTROL, self._program, True, bytes([command]))
        refused: List[SdoResult] = []

        def send_once() -> str:
            result = self._sdo([access], self._settings.answer_timeout)[0]
            # A device may restart without answering: its boot-up tells.
            if result.success or result.abort_code == abort_codes.TIMEOUT:
                return ''
            refused.append(result)
            return result.message

        came = self._link.await_boot_up(send_once, timeout)
        if refused:
            self._ended()
            self._left = refused_leaves or self._left
            raise _Failed(f'writing {command} to 0x1F51:{self._program} failed: '
                          f'{refused[0].message}', refused[0].abort_code)
        if not came:
            self._ended()
            raise _Failed(f'no boot-up message within {timeout:g} s after writing {command} '
                          f'to 0x1F51:{self._program} (parameter {parameter}): {not_came}')

    def _check(self) -> None:
        self._begin(CHECKING)
        result = self._sdo([Access(self.node_id, SOFTWARE_ID, self._program)],
                           self._settings.answer_timeout)[0]
        if not result.success:
            if self._expected:
                raise _Failed(f'0x1F56:{self._program} (software id) could not be read after '
                              f'the start: {result.message}', result.abort_code)
            self._id_text = (f'its software id not read (0x1F56:{self._program}: '
                             f'{result.message})')
            return
        self._software_id = _number(result.data)
        self._id_text = f'software id 0x{self._software_id:08X}'
        if self._expected and self._software_id != self._expected:
            self._left = (f'program {self._program} started, running software id '
                          f'0x{self._software_id:08X}')
            raise _Failed(f'software id (0x1F56:{self._program}) is 0x{self._software_id:08X}, '
                          f'0x{self._expected:08X} expected: the device runs another program '
                          f'than the one expected')

    # Helpers.

    def _sdo(self, accesses: Sequence[Access], timeout: float) -> List[SdoResult]:
        return self._link.sdo(accesses, min(MAX_TIMEOUT, timeout))

    def _ended(self) -> None:
        reason = self._link.ended()
        if reason:
            raise _Failed(reason)

    def _done_text(self) -> str:
        kind = f' ({self._transfer})' if self._transfer else ''
        return f'program {self._program} written{kind}'

    def _failed(self, failure: _Failed) -> ProgramResult:
        if failure.refused:
            return self._result(False, failure.message, failure.abort_code, refused=True)
        where = f'{self.phase} ' if self.phase else ''
        return self._result(False, f'{where}failed: {failure.message}; the device is left '
                                   f'{self._left}', failure.abort_code,
                            cleared=self.phase in (CLEARING, DOWNLOADING, FLASHING))

    def _result(self, success: bool, message: str, abort_code: int = 0,
                refused: bool = False, cleared: bool = False) -> ProgramResult:
        return ProgramResult(success, message, self._software_id, abort_code, self._flash,
                             refused, cleared)
