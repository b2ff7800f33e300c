"""The checks of drive requests: what is refused before anything is sent, and the words why.

:meth:`~.drive.DriveService.command`, ``move`` and ``target`` check a request here
(:class:`RequestChecks`) and only then route it; each problem names the field or the state
that stops it.
"""

import math
from typing import Callable, Dict, Optional

from ..sdo import abort_codes
from ..sdo.requests import check_node_id, MAX_TIMEOUT
from ..text import quoted, SHUTTING_DOWN
from ..values import int_given_as_float
from . import cia402
from .status import DriveRecord, DriveResult, DriveStatus, failed, shown

COMMANDS = ('enable', 'disable', 'quick_stop', 'halt', 'resume', 'fault_reset', 'set_mode',
            'home')
# Commands that act on a drive in OPERATION_ENABLED only.
ENABLED_COMMANDS = frozenset({'halt', 'resume', 'home'})
# Who halted a drive before its mode change (``DriveCommands._halt_for_mode``), as
# ``DriveRecord.halted_by`` names it; and why such a drive is not resumed.
MODE_CHANGE = 'mode change'
RESUME_REFUSED = ("its axis is halted for a mode change: a resume would run the old mode's "
                  "target again; wait for that command's answer, or call enable (in the mode "
                  'wanted) to go on from where it stands')
# Commands that stop a drive: sent even to one not heard (by SDO: it may be alive, running).
STOPPING_COMMANDS = frozenset({'quick_stop', 'disable'})
MODES = tuple(cia402.MODE_NAMES)
NOTHING_SENT = 'nothing was sent'


def lost_problem(drive: DriveRecord, reads: Optional[int], status: DriveStatus,
                 bus_down: Optional[str] = None) -> Optional[str]:
    """Return why a sequence asked for when ``drive`` had been read ``reads`` times stops.

    ``None`` while the drive is heard and not read again since (it did not boot); ``reads``
    None (a stop): never, whatever drive is there, heard or not. ``bus_down``: why the bus is
    down, if it is: the bus going down loses every drive, and is the cause to name.
    """
    if reads is None or (drive.heard and drive.read_wanted == reads):
        return None
    if bus_down and not drive.heard:
        return (f'{bus_down}: node {drive.node_id} is no longer heard (state {status.state}); '
                f'enable it afresh once the bus is back')
    return (f'node {drive.node_id} stopped heartbeating or booted during the command: state '
            f'{status.state}; enable it afresh')


class RequestChecks:
    """The one check of each drive request against the drives as they are now.

    Each returns the answer that refuses the request (nothing is sent then), or None.
    ``drives`` and ``lock`` are the drive service's records and lock, ``protection`` the
    gateway's write rules, ``bus_down()`` why the bus is down (None while up), ``closing()``
    whether the service is shutting down.
    """

    def __init__(self, drives: Dict[int, DriveRecord], lock, protection,
                 bus_down: Callable[[], Optional[str]], closing: Callable[[], bool]):
        self._drives, self._lock, self._protection = drives, lock, protection
        self._bus_down, self._closing = bus_down, closing

    def command(self, node_id: int, command: str, mode: int,
                timeout: float) -> Optional[DriveResult]:
        """Check a ``~/drive_command`` request."""
        problem = request_problem(command, mode, timeout)
        if problem:
            return self._refused(node_id, problem)
        refused = self.drive(node_id, enabled=command in ENABLED_COMMANDS,
                             stopping=command in STOPPING_COMMANDS)
        if refused is not None:
            return refused
        with self._lock:
            drive = self._drives[node_id]
            status, halted_by = shown(drive), drive.halted_by
        problem = command_problem(status, command, mode) or (
            command == 'resume' and halted_by == MODE_CHANGE and RESUME_REFUSED)
        return failed(status, f'{problem}; {NOTHING_SENT}') if problem else None

    def move(self, node_id: int, position: int, velocity: int) -> Optional[DriveResult]:
        """Check a move (drive units)."""
        problem = (integer_problem('position', position, 32)
                   or integer_problem('velocity', velocity, 32, unsigned=True))
        refused = self.drive(node_id, enabled=True)
        if refused is not None:
            return refused
        with self._lock:
            status = shown(self._drives[node_id])
        problem = problem or command_problem(status, 'move', cia402.PROFILE_POSITION)
        return self._refused(node_id, problem) if problem else None

    def drive(self, node_id: int, enabled: bool,
              stopping: bool = False) -> Optional[DriveResult]:
        """Check that drive ``node_id`` takes a request now.

        ``enabled``: the request needs it enabled by us; ``stopping``: a command that stops
        the drive, sent even to one not heard.
        """
        problem = check_node_id(node_id, '1..127', lowest=1)
        if not problem and node_id not in self._drives:
            problem = (f'node {node_id} is not a drive (parameter drives.nodes: '
                       f'{sorted(self._drives) or "none"})')
        if problem:
            return self._refused(node_id, problem)
        with self._lock:
            drive = self._drives[node_id]
            status = shown(drive)
            heard = drive.heard and drive.ready == drive.read_wanted
            enabling = drive.enabling
        refusal = self._protection.refuses_write(node_id, cia402.CONTROLWORD)
        if refusal:
            return failed(status, f'{refusal}; {NOTHING_SENT}', abort_codes.LOCAL_CONTROL)
        problem = (SHUTTING_DOWN if self._closing() else self._bus_down()
                   or (None if stopping else state_problem(status, heard, enabled, enabling)))
        return failed(status, f'{problem}; {NOTHING_SENT}') if problem else None

    def target_object(self, status: DriveStatus, index: int) -> Optional[DriveResult]:
        """Check that the target object ``index`` may be written (the write rules)."""
        refusal = self._protection.refuses_write(status.node_id, index)
        return failed(status, refusal, abort_codes.LOCAL_CONTROL) if refusal else None

    def _refused(self, node_id: int, problem: str) -> DriveResult:
        drive = self._drives.get(node_id)
        with self._lock:
            status = shown(drive) if drive else DriveStatus(node_id)
        return failed(status, f'{problem}; {NOTHING_SENT}')


def request_problem(command: str, mode: int, timeout: float) -> Optional[str]:
    """Return what is wrong with a command request itself, or None."""
    if command not in COMMANDS:
        return f'command {quoted(command)} is unknown: allowed {", ".join(COMMANDS)}'
    if mode and mode not in MODES:
        allowed = ', '.join(f'{code} {name}' for code, name in cia402.MODE_NAMES.items())
        return f'mode {mode} is not a CiA 402 mode of operation: allowed 0 (keep), {allowed}'
    if command == 'set_mode' and not mode:
        return f'set_mode needs a mode: {", ".join(map(str, MODES))}'
    problem = int_given_as_float('timeout', timeout)
    if problem:
        return problem
    if not (timeout == 0 or 0 < timeout <= MAX_TIMEOUT):
        return (f'timeout {timeout} is out of range: allowed 0 (the default) or up to '
                f'{MAX_TIMEOUT:g} s')
    return None


def state_problem(status: DriveStatus, heard: bool, enabled: bool,
                  enabling: bool = False) -> Optional[str]:
    """Return why the drive takes no request now, or None.

    ``enabled``: the request needs the drive in OPERATION_ENABLED after an enable of ours;
    ``enabling``: an enable of ours runs (``DriveRecord.enabling``).
    """
    node_id = status.node_id
    if not heard or status.state == cia402.UNKNOWN:
        return (f'node {node_id} is not heard (no heartbeat or statusword yet, or it is still '
                f'being read after a boot or a silence): state {status.state}')
    if enabled and status.faulted:
        return (f'node {node_id} is in {status.state} (error 0x{status.error_code:04X} '
                f'{status.error}): call fault_reset and enable')
    if enabled and status.changing_mode and not enabling:  # an enable's own: said below
        return (f'node {node_id} is changing its mode (set_mode): targets and commands that '
                f'need it enabled are taken once that has answered')
    if enabled and (status.state != cia402.OPERATION_ENABLED or status.needs_enable
                    or status.changing_mode):
        if enabling:  # not "call enable": one runs (it may wait for a braking axis to stand)
            return (f'node {node_id} is being enabled: halt, resume, home, moves and targets '
                    f'are refused until that enable has answered; quick_stop or disable stop '
                    f'the drive now')
        fresh = ' and needs a fresh enable' if status.needs_enable else ''
        return f'node {node_id} is {status.state}{fresh}: call drive_command enable first'
    return None


def command_problem(status: DriveStatus, command: str, mode: int) -> Optional[str]:
    """Return why ``command`` with ``mode`` cannot run on this drive now, or None."""
    mode = cia402.HOMING if command == 'home' else mode
    if mode and status.supported_modes and not cia402.supports(status.supported_modes, mode):
        have = [cia402.mode_name(code) for code in MODES
                if cia402.supports(status.supported_modes, code)]
        return (f'node {status.node_id} does not support {cia402.mode_name(mode)} (0x6502 '
                f'lists: {", ".join(have) or "none"})')
    if command == 'enable' and status.faulted:
        return (f'node {status.node_id} is in {status.state} with error '
                f'0x{status.error_code:04X} ({status.error}): call fault_reset first')
    return None


def target_problem(status: DriveStatus, halted_by: str, value: float) -> Optional[str]:
    """Return why ``value`` cannot go out as the target of the drive's present mode, or None."""
    index = cia402.TARGET_OF_MODE.get(status.mode)
    if index is None:
        return (f'node {status.node_id} is in {cia402.mode_name(status.mode)}, which takes no '
                f'target; {NOTHING_SENT}')
    if halted_by == 'command':
        return (f'node {status.node_id} was halted by a halt command: call resume first; '
                f'{NOTHING_SENT}')
    if halted_by == MODE_CHANGE:
        return (f'node {status.node_id} is halted for a mode change: targets are taken once '
                f'the command that changes it has answered (if it failed, call enable); '
                f'{NOTHING_SENT}')
    problem = target_value_problem(status.mode, value)
    return f'{problem}; {NOTHING_SENT}' if problem else None


def target_value_problem(mode: int, value: float) -> Optional[str]:
    """Return why ``value`` (drive units) does not fit the target object of ``mode``, or None."""
    index = cia402.TARGET_OF_MODE.get(mode)
    if index is None:
        return None
    return value_problem('target', value, 16 if index == cia402.TARGET_TORQUE else 32)


def value_problem(name: str, value: float, bits: int) -> Optional[str]:
    """Return why ``value`` (drive units) cannot be sent to a signed ``bits`` object, or None."""
    if not math.isfinite(value):
        return f'{name} {value} is not a finite number'
    return integer_problem(name, round(value), bits)


def integer_problem(name: str, value: int, bits: int, unsigned: bool = False) -> Optional[str]:
    """Return why ``value`` does not fit a ``bits`` object, or None."""
    if unsigned:
        lowest, highest = 0, (1 << bits) - 1
    else:
        lowest, highest = -(1 << bits - 1), (1 << bits - 1) - 1
    if not lowest <= value <= highest:
        return (f"{name} {quoted(value)} (drive units) does not fit the drive's {bits}-bit "
                f'object: allowed {lowest}..{highest}')
    return None
