"""The boot of one device, step by step in the order of CiA 302-2 (the boot-up process).

Each step that fails raises :class:`BootFailed` with its CiA 302-2 error status letter; a boot
that must end (shutdown, the bus down, the device booted again) raises :class:`BootEnded`, and
nothing more is sent for it. The steps talk to the bus only through :class:`BootLink`, which
the boot service gives: the gateway's SDO channels (so a boot queues behind a user's SDO
calls, never races them, and passes the write protection) and its NMT command.
"""

from dataclasses import dataclass
import logging
import struct
import time
from typing import Callable, Dict, List, Optional, Sequence, Tuple

from .. import nmt
from ..drives import cia402
from ..program.download import (
    MAX_IMAGE,
    ProgramDownload,
    ProgramLink,
    ProgramSettings,
    Progress,
    read_image,
    SOFTWARE_ID,
)
from ..sdo import abort_codes
from ..sdo.requests import Access, MAX_TIMEOUT, SdoResult
from .plan import (
    CONFIGURATION_DATE,
    DEVICE_TYPE,
    DevicePlan,
    HEARTBEAT_PERIODS,
    IDENTITY,
    IDENTITY_LETTERS,
    LOAD,
    PRODUCER_HEARTBEAT,
    RESTORE,
    SAVE,
    STORE,
    Write,
)

LOGGER = logging.getLogger(__name__)
NO_SUCH_OBJECT = (abort_codes.OBJECT_DOES_NOT_EXIST, abort_codes.SUBINDEX_NOT_EXIST)
# The COB-ID entries of the PDOs: bit 30 (no RTR) is the device's to set, whatever was written.
COB_ID_ENTRIES = (range(0x1400, 0x1600), range(0x1800, 0x1A00))
COB_NO_RTR = 1 << 30
HEARTBEAT_SLACK = 0.1  # s on top, for the host's scheduling
# The most accesses in one SDO batch of a boot; each batch queues once behind users' calls.
BATCH = 64
RETRY_PAUSE = 0.05  # s before 0x1000 is asked again after a refusal that took no time


class BootFailed(Exception):
    """The boot failed; ``letter`` is its CiA 302-2 error status (A-O)."""

    def __init__(self, letter: str, message: str):
        super().__init__(message)
        self.letter = letter
        self.message = message


class BootEnded(Exception):
    """The boot must end without a verdict (shutdown, bus down, a new boot-up)."""


@dataclass
class BootLink:
    """What a boot may do on the bus; given by the boot service, for one boot of one device.

    - ``sdo(accesses, timeout)``: the results, in order; stops sending when the boot ended.
    - ``nmt(command)``: sends an NMT command to the device; returns why not, or ''.
    - ``ended()``: why the boot must end, or ''.
    - ``await_boot_up(send, timeout)``: calls ``send()`` (a reset), then returns whether the
      device's boot-up came within ``timeout`` s (a boot-up it asked for: the boot goes on).
    - ``await_heartbeat(timeout)``: whether a heartbeat of this boot came (since it began, or
      since the boot-up of a reset it sent), waiting up to ``timeout`` s from now.
    - ``read_pdos()``: reads the device's PDO mapping again; returns why it failed, or ''.
    - ``stream(access, answer_within, written)``: a program image, as
      :class:`~cbcan_ros.core.program.download.ProgramLink` has it.
    - ``programming(progress)``: the progress of the program download this boot runs, None
      once it has ended (the device is shown as being programmed meanwhile).
    - ``boot_ups()``: the device's boot-up messages heard so far, awaited or not.
    - ``program_cleared()``: why the device's program is not whole (a program download
      failed after stopping it), or ''.
    """

    sdo: Callable[[Sequence[Access], float], List[SdoResult]]
    nmt: Callable[[int], str]
    ended: Callable[[], str]
    await_boot_up: Callable[[Callable[[], str], float], bool]
    await_heartbeat: Callable[[float], bool]
    read_pdos: Callable[[], str]
    stream: Callable[[Access, float, Callable[[int, bool], Optional[str]]], SdoResult]
    programming: Callable[[Optional[Progress]], None] = lambda progress: None
    boot_ups: Callable[[], int] = lambda: 0
    program_cleared: Callable[[], str] = lambda: ''


@dataclass(frozen=True)
class BootOutcome:
    """What a boot that succeeded did."""

    writes: int
    message: str


def _hex(data: bytes) -> str:
    return data.hex(' ') if len(data) > 4 else f'0x{int.from_bytes(data, "little"):X}'


def _number(data: bytes) -> int:
    return int.from_bytes(bytes(data[:4]), 'little')


def same_value(index: int, subindex: int, read: bytes, written: bytes) -> bool:
    """Return whether ``read`` back is what was ``written``.

    A number may come back in more bytes than written (zeros above); bit 30 of a PDO's
    COB-ID entry (no RTR) is the device's own.
    """
    if read == written:
        return True
    if len(written) > 8 or len(read) > 8:
        return False
    mask = (1 << 64) - 1
    if subindex == 1 and any(index in kind for kind in COB_ID_ENTRIES):
        mask &= ~COB_NO_RTR
    return (int.from_bytes(read, 'little') & mask) == (int.from_bytes(written, 'little') & mask)


class DeviceBoot:
    """One boot of one device: ``run()`` returns a :class:`BootOutcome` or raises.

    ``booted_itself``: the device sent a boot-up that started this boot (it is fresh: no reset
    of its communication first). ``sdo_timeout`` bounds each access, ``boot_timeout`` the wait
    for the device to answer at all and to boot after a reset.
    """

    def __init__(self, plan: DevicePlan, link: BootLink, sdo_timeout: float,
                 boot_timeout: float, booted_itself: bool,
                 program: ProgramSettings = ProgramSettings()):
        self.plan = plan
        self._link = link
        self._program = program
        self._sdo_timeout = sdo_timeout
        self._boot_timeout = boot_timeout
        self._booted_itself = booted_itself
        self._writes = 0
        self._notes: List[str] = []

    def run(self) -> BootOutcome:
        """Check, configure and verify the device, ready to start; raise BootFailed/BootEnded."""
        plan = self.plan
        started = time.monotonic()
        if plan.reset_communication and not self._booted_itself:
            # A device that is not there (or ignores it) is found out by 0x1000 next (B).
            self._reset(nmt.RESET_COMMUNICATION, 'reset communication', required=False)
        self._check_device_type(started)
        self._check_identity()
        self._check_software()
        cleared = '' if plan.software_version is not None else self._link.program_cleared()
        if cleared:  # with software_version, 0x1F56 read back says whether it is whole
            raise BootFailed('I', cleared)
        if plan.restore:
            self._restore()
        if self._configuration_unchanged():
            self._notes.append('configuration unchanged (0x1020 matches its DCF): no '
                               'writes')
        else:
            self._configure()
        if plan.pdos:
            self._check_ended()
            problem = self._link.read_pdos()
            if problem:
                self._check_ended()  # a read the bus or a boot-up ended says nothing of it
                raise BootFailed('J', f'its PDO mapping could not be read after the '
                                      f'configuration: {problem}')
        if plan.heartbeat_check:
            self._start_error_control()
        if plan.drive:
            self._safe_targets()
        done = f'{self._writes} objects written and verified' if self._writes else ''
        return BootOutcome(self._writes, '; '.join(filter(None, [done, *self._notes])))

    def _check_ended(self) -> None:
        reason = self._link.ended()
        if reason:
            raise BootEnded(reason)

    def _sdo(self, accesses: Sequence[Access]) -> List[SdoResult]:
        results: List[SdoResult] = []
        for start in range(0, len(accesses), BATCH):
            part = accesses[start:start + BATCH]
            self._check_ended()
            results += self._link.sdo(part, min(MAX_TIMEOUT, self._sdo_timeout * len(part)))
        self._check_ended()  # a result that came as the boot ended says nothing of the device
        return results

    def _read(self, index: int, subindex: int) -> SdoResult:
        return self._sdo([Access(self.plan.node_id, index, subindex)])[0]

    def _reset(self, command: int, what: str, required: bool = True) -> None:
        def send() -> str:
            return self._link.nmt(command)

        self._check_ended()
        if not self._link.await_boot_up(send, self._boot_timeout) and required:
            self._check_ended()
            raise BootFailed('B', f'no boot-up within {self._boot_timeout:g} s (boot_timeout) '
                                  f'after the {what}')

    def _check_device_type(self, started: float) -> None:
        deadline = started + self._boot_timeout
        while True:
            result = self._read(DEVICE_TYPE, 0)
            if result.success or time.monotonic() >= deadline:
                break
            if result.abort_code and result.abort_code != abort_codes.TIMEOUT:
                break  # the device answered: it is there, asking again changes nothing
            if not result.abort_code:  # refused here (busy): ask again a little later
                time.sleep(RETRY_PAUSE)
        if not result.success:
            raise BootFailed('B', f'0x1000 (device type) not read within '
                                  f'{self._boot_timeout:g} s (boot_timeout): {result.message}')
        expected = self.plan.device_type
        found = _number(result.data)
        if expected and found != expected:
            raise BootFailed('C', f'device type (0x1000) is 0x{found:08X}, its DCF says '
                                  f'0x{expected:08X}: another kind of device at this node id')

    def _check_identity(self) -> None:
        identity = self.plan.identity
        if not identity:
            return
        results = self._sdo([Access(self.plan.node_id, IDENTITY, sub) for sub, _ in identity])
        for (subindex, expected), result in zip(identity, results, strict=True):
            letter, key = IDENTITY_LETTERS[subindex]
            if not result.success:
                raise BootFailed(letter, f'0x1018:{subindex} ({key}) could not be read: '
                                         f'{result.message}')
            found = _number(result.data)
            if found != expected:
                raise BootFailed(letter, f'{key} (0x1018:{subindex}) is 0x{found:08X}, '
                                         f'0x{expected:08X} expected: not the device the bus '
                                         f'description names')

    def _check_software(self) -> None:
        """Check 0x1F56:1 against software_version; download software_file when allowed.

        CiA 302-2: G when the device cannot tell (no 0x1F56, or no program download objects),
        H when it differs and may not be updated here, I when the download failed.
        """
        plan = self.plan
        if plan.software_version is None:
            return
        result = self._read(SOFTWARE_ID, 1)
        if not result.success:
            raise BootFailed('G', f'0x1F56:1 (software id) could not be read: {result.message}'
                                  f'; software_version cannot be checked')
        found = _number(result.data)
        if found == plan.software_version:
            return
        differs = (f'software id (0x1F56:1) is 0x{found:08X}, software_version is '
                   f'0x{plan.software_version:08X}')
        if not plan.software_file:
            raise BootFailed('H', f'{differs}, and no software_file is given to download')
        if not self._program.at_boot:
            raise BootFailed('H', f'{differs}: a boot downloads software_file only with the '
                                  f'parameter program_download.at_boot true; or update it with '
                                  f'~/program_download')
        try:
            image = read_image(plan.software_file)
        except OSError as error:
            raise BootFailed('I', f'{differs}; software_file {plan.software_file} cannot be '
                                  f'read: {error.strerror}') from None
        if not image or len(image) > MAX_IMAGE:
            raise BootFailed('I', f'{differs}; software_file {plan.software_file} holds '
                                  f'{"no" if not image else "more than " + str(MAX_IMAGE)} '
                                  f'bytes: not a program image')
        link = self._link
        download = ProgramDownload(plan.node_id, image, 1, plan.software_version, True,
                                   ProgramLink(link.sdo, link.stream, link.await_boot_up,
                                               link.ended, link.boot_ups), self._program,
                                   link.programming)
        try:
            outcome = download.run()
        finally:
            link.programming(None)
        if not outcome.success and link.ended():
            # The boot ends (a boot-up it held, shutdown, the bus), but the download's own
            # failure may be the device's, and it is told: a boot after it may succeed.
            LOGGER.warning('node %s: downloading %s failed: %s', plan.label,
                           plan.software_file, outcome.message)
        self._check_ended()
        if not outcome.success:
            raise BootFailed('G' if outcome.refused else 'I',
                             f'{differs}; downloading {plan.software_file}: {outcome.message}')
        self._notes.append(f'software updated from 0x{found:08X} to '
                           f'0x{plan.software_version:08X} ({plan.software_file})')

    def _restore(self) -> None:
        write = Write(RESTORE, self.plan.restore, struct.pack('<I', LOAD), 'restore')
        self._write_all([write])
        self._reset(nmt.RESET_NODE, 'reset node of restore_configuration')
        self._notes.append(f'factory values restored (0x1011:{self.plan.restore})')

    def _configuration_unchanged(self) -> bool:
        date = self.plan.configuration_date
        if date is None:
            return False
        results = self._sdo([Access(self.plan.node_id, CONFIGURATION_DATE, sub)
                             for sub in (1, 2)])
        return all(result.success for result in results) and (
            tuple(_number(result.data) for result in results) == date)

    def _configure(self) -> None:
        plan = self.plan
        self._write_all(plan.writes)
        self._verify()
        self._writes += len(plan.writes)
        if plan.configuration_date is not None:
            day, moment = plan.configuration_date
            self._write_all([Write(CONFIGURATION_DATE, 1, struct.pack('<I', day), '0x1020'),
                             Write(CONFIGURATION_DATE, 2, struct.pack('<I', moment), '0x1020')])
        if plan.store:
            self._write_all([Write(STORE, 1, struct.pack('<I', SAVE), 'store_configuration')])
            self._notes.append('stored (0x1010:1)')

    def _write_all(self, writes: Sequence[Write]) -> None:
        node_id = self.plan.node_id
        results = self._sdo([Access(node_id, write.index, write.subindex, True, write.data)
                             for write in writes])
        for write, result in zip(writes, results, strict=True):
            if not result.success:
                code = f' (abort code 0x{result.abort_code:08X})' if result.abort_code else ''
                raise BootFailed('J', f'writing {_hex(write.data)} to 0x{write.index:04X}:'
                                      f'{write.subindex} ({write.source}) failed{code}: '
                                      f'{result.message}')

    def _verify(self) -> None:
        checked: Dict[Tuple[int, int], bytes] = self.plan.checked
        objects = list(checked)
        results = self._sdo([Access(self.plan.node_id, index, sub) for index, sub in objects])
        for (index, subindex), result in zip(objects, results, strict=True):
            written = checked[index, subindex]
            if not result.success:
                if result.abort_code == abort_codes.WRITE_ONLY:
                    continue
                raise BootFailed('J', f'0x{index:04X}:{subindex} could not be read back '
                                      f'after writing {_hex(written)}: {result.message}')
            if not same_value(index, subindex, result.data, written):
                raise BootFailed('J', f'0x{index:04X}:{subindex} reads back '
                                      f'{_hex(result.data)} after writing {_hex(written)}: '
                                      f'the device did not take the value')

    def _start_error_control(self) -> None:
        written = self.plan.checked.get((PRODUCER_HEARTBEAT, 0))
        if written is None:
            result = self._read(PRODUCER_HEARTBEAT, 0)
            written = result.data if result.success else b''
        period = _number(written) / 1000 if written else 0.0
        if not period:
            self._notes.append('no heartbeat producer (0x1017 is 0): not watched by '
                               'heartbeat')
            return
        self._check_ended()
        if not self._link.await_heartbeat(HEARTBEAT_PERIODS * period + HEARTBEAT_SLACK):
            self._check_ended()
            raise BootFailed('K', f'no heartbeat within {HEARTBEAT_PERIODS} periods of its '
                                  f'{period * 1000:g} ms (0x1017)')

    def _safe_targets(self) -> None:
        """Targets that hold the drive where it is, so its start moves nothing.

        One transfer each: a drive without one of them (a position-only drive has no 0x60FF)
        still gets the others, where one batch would stop at the first that fails.
        """
        node_id = self.plan.node_id
        read = self._read(cia402.POSITION_ACTUAL, 0)
        targets = [(cia402.TARGET_VELOCITY, struct.pack('<i', 0)),
                   (cia402.TARGET_TORQUE, struct.pack('<h', 0))]
        if read.success:
            targets.insert(0, (cia402.TARGET_POSITION, bytes(read.data[:4]).ljust(4, b'\0')))
        for index, data in targets:
            result = self._sdo([Access(node_id, index, 0, True, data)])[0]
            if result.success:
                self._writes += 1
            elif result.abort_code not in NO_SUCH_OBJECT:
                raise BootFailed('J', f'its safe target 0x{index:04X} = {_hex(data)} could '
                                      f'not be written before its start: {result.message}')
