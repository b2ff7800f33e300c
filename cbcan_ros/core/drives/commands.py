"""The CiA 402 sequences behind drive commands, moves and set-points, as coroutines.

Each runs on the drives' event loop (``drive.DriveService``): it sends a controlword, then
awaits the statusword that shows the drive took it, and decides the next step from that, so
a transition takes as long as the drive needs and no longer (python canopen's
``BaseNode402`` blocks its caller in a polling loop with fixed timeouts instead). One sequence
runs per drive: a new command, move or set-point replaces the one running, which is answered
"replaced"; shutdown answers every one "shutting down".
"""

import asyncio
import contextlib
import contextvars
from typing import Callable, Dict, Optional, Tuple

from ..text import SHUTTING_DOWN
from . import cia402
from .arrival import (
    DEFAULT_WINDOW,
    HOME_HERE,
    LimitsUnknown,
    missed,
    outside_limits,
    position_window,
    software_limits,
    velocity_threshold,
)
from .checks import ENABLED_COMMANDS, lost_problem, MODE_CHANGE, RESUME_REFUSED, state_problem
from .standstill import BY_STATUSWORD, until_applied_at_sync, wait_for_standstill
from .status import DriveResult

# The timeout of each SDO a sequence sends (a PDO goes out without an answer).
SEND_TIMEOUT = 1.0
# How long a cancelled move waits for the halted axis to stand still before it answers.
HALT_WAIT = 2.0
# How long enable waits for the drive's PDO mapping being read (``mapping_known``).
MAPPING_WAIT = 2.0
# Halted (for a mode change, a halt or a cancel) in a cyclic mode or profile torque, an axis
# of a drive without a velocity threshold (0x606F) stands once it moves less than its
# position window (at most DEFAULT_WINDOW) in this long: a velocity read may jitter around 0
# for good, or read 0 in units coarser than the position's while the axis still moves.
STILL_SPAN = 0.1
# As long for a halt, whose answer says the axis stands (the velocity reading 0 all along):
# within a window of 10 counts for this long, an axis still moving creeps at under 35
# counts/s, and one braking harder than about 220 counts/s² has stood.
AT_REST_SPAN = 0.3
# What the answer of a sequence that ended with the axis halted for a mode change adds.
HELD_FOR_THE_MODE_CHANGE = ('; the axis was halted for the mode change and is held there: call '
                            'enable (in the mode wanted) to go on from where it stands')
# The drive's re-reads (``read_wanted``) when the running sequence was asked for; None for
# a stop, which goes to whatever drive is there.
READS_AT_START: contextvars.ContextVar = contextvars.ContextVar('reads_at_start')
# Whether the running sequence needs the drive OPERATION_ENABLED by an enable of ours (a move,
# halt, resume, homing): it ends when the drive leaves that, however it left.
ENABLED_ONLY: contextvars.ContextVar = contextvars.ContextVar('enabled_only', default=False)
# The running sequence's time limit (an ``asyncio.timeout``; its deadline None: no limit).
TIME_LIMIT: contextvars.ContextVar = contextvars.ContextVar('time_limit', default=None)
# What the answer of a sequence adds when its time runs out now ('' = nothing).
ON_TIMEOUT: contextvars.ContextVar = contextvars.ContextVar('on_timeout', default='')
# The running homing's start (the statuswords taken before it), and whether it was seen
# attained: a homing ended early by a newer command says that it had set the position.
HOMING_STARTED: contextvars.ContextVar = contextvars.ContextVar('homing_started', default=None)
HOMING_ATTAINED: contextvars.ContextVar = contextvars.ContextVar('homing_attained',
                                                                 default=False)
# What an enable's answer adds when its time ran out while the halted axis braked (halted
# before the enable, or by it for the mode change).
STILL_BRAKING = ('; the axis was still braking from its halt and stays halted: call enable '
                 'again once it stands, or give the enable a timeout longer than its ramp')
# What a resume in PP or homing that timed out adds: it waits for the axis to stand.
RESUME_BRAKING = ('; the axis was still braking from its halt and stays halted: call resume '
                  'again once it stands, or give it a timeout longer than its ramp')
# What an enable adds that timed out after it wrote the new mode.
MODE_CHANGED = ('; the new mode was written: the drive needs a fresh enable (it holds where '
                'it stood)')
# What a halt that timed out adds: the drive holds the halt, whether or not it shows a stand.
HALT_HOLDS = ('; the halt holds, but the drive did not show a stand in time (how a stand '
              'is told in each mode: docs/drives.md, halt)')


class DriveFailed(Exception):
    """A command cannot go on: the message says why, ``abort_code`` an SDO abort if any."""

    def __init__(self, message: str, abort_code: int = 0):
        super().__init__(message)
        self.abort_code = abort_code


class _Unheard(Exception):
    """A stop's drive stopped heartbeating: the stop goes on by SDO (``_stop``)."""


class DriveCommands:
    """The sequences of :class:`~.drive.DriveService` ``service``, one at a time per drive.

    They read single fields of a drive's record (its controlword, statuswords taken, whether
    it is heard) without the service's lock: each is one reference, read whole.
    """

    def __init__(self, service):
        self._service = service
        self._tasks: Dict[int, asyncio.Task] = {}
        self._reasons: Dict[asyncio.Task, str] = {}
        self._tokens: Dict[asyncio.Task, object] = {}  # what names a move to its cancel
        self._halt_when_cancelled: set = set()
        self._set_points: Dict[int, int] = {}
        self._streams: Dict[int, asyncio.Task] = {}  # by drive: its last set-point stream
        self._mode_changes: set = set()  # the set_mode sequences running

    async def run(self, drive, command: str, mode: int, timeout: float,
                  reads: Optional[int]):
        """Run ``command`` (checked by the service) on ``drive``; return its DriveResult.

        ``reads``: the drive's re-reads when the request was checked (``DriveRecord``
        ``read_wanted``); the command fails if the drive is read again meanwhile. None for a
        stop: it goes to whatever drive is there.
        """
        sequence = getattr(self, f'_{command}')
        return await self._own(drive, lambda: sequence(drive, mode), timeout, reads,
                               enabled=command in ENABLED_COMMANDS,
                               halt_on_timeout=command == 'home',
                               changes_mode=command == 'set_mode',
                               enabling=command == 'enable')

    async def move(self, drive, position: int, relative: bool, velocity: int,
                   on_feedback: Optional[Callable], token: object, reads: int,
                   timeout: float) -> object:
        """Move in profile position to ``position``; return the DriveResult.

        ``token`` names this move to :meth:`cancel`, which then ends it only while it runs;
        past ``timeout`` the drive is halted where it is.
        """
        return await self._own(drive, lambda: self._move(drive, position, relative, velocity,
                                                         on_feedback), timeout, reads, token,
                               enabled=True, halt_on_timeout=True)

    def set_point(self, drive, position: int, reads: int) -> None:
        """Take ``position`` as the next PP set-point (on the loop); the latest one wins."""
        self._set_points[drive.node_id] = position
        stream = self._streams.get(drive.node_id)
        if stream is not None and not stream.done() and not stream.cancelling():
            # Running or about to start (not replaced): it takes the newest, even waiting.
            self._service.wake(drive)
            return
        self._streams[drive.node_id] = asyncio.ensure_future(self._own(
            drive, lambda: self._stream(drive), None, reads, enabled=True))

    def cancel(self, drive, reason: str, halt: bool = False, token: object = None) -> None:
        """End the sequence running on ``drive`` (on the loop), answered ``reason``.

        With ``token``, only the sequence started with it: a move already replaced is done.
        """
        task = self._tasks.get(drive.node_id)
        if task is None or task.done() or (token is not None
                                           and self._tokens.get(task) is not token):
            return
        self._reasons[task] = reason
        if halt:
            self._halt_when_cancelled.add(task)
        task.cancel()

    async def cancel_all(self, reason: str) -> None:
        """End every sequence running, answered ``reason``, and wait until they have ended."""
        tasks = [task for task in self._tasks.values() if not task.done()]
        for task in tasks:
            self._reasons[task] = reason
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    async def _own(self, drive, sequence: Callable, timeout: Optional[float],
                   reads: Optional[int], token: object = None, enabled: bool = False,
                   halt_on_timeout: bool = False, changes_mode: bool = False,
                   enabling: bool = False):
        task = asyncio.current_task()
        # First: a request checked from here on sees the enable under way.
        drive.enabling = enabling  # the current sequence's (one attribute: read as it is)
        previous = self._tasks.get(drive.node_id)
        if previous is not None and not previous.done():
            # A cancel not taken yet keeps its reason: the caller asked for it first.
            earlier = self._reasons.get(previous)
            replaced = 'replaced by a newer command, move or target'
            self._reasons[previous] = f'{earlier}; {replaced}' if earlier else replaced
            previous.cancel()
            if previous in self._mode_changes and not changes_mode:
                # Now, not when the set_mode ends (later): the command replacing it needs
                # the drive as it was before (a halt, a move); a set_mode takes it over. An
                # enable leaves it to be enabled: a halt or move checked before the enable
                # reaches its own step is refused as one checked during it.
                still = self._still_enabled(drive, True) and drive.mode_pending is None
                self._service.set_enabled(drive, not enabling and still,
                                          changing_mode=enabling and still)
        self._tasks[drive.node_id] = task
        self._tokens[task] = token
        READS_AT_START.set(reads)  # this task's own context
        ENABLED_ONLY.set(enabled)
        ON_TIMEOUT.set('')
        HOMING_STARTED.set(None)
        HOMING_ATTAINED.set(False)
        service, node_id = self._service, drive.node_id
        try:
            # In this task (not wait_for's own): a cancel reaches the sequence at once, and
            # what the sequence raises as it is cancelled is the sequence's (every wait of a
            # sequence is timed so: an exception of wait_for's task would go unretrieved).
            async with asyncio.timeout(timeout or None) as limit:
                TIME_LIMIT.set(limit)
                message = await sequence()
            # A halt, or a fault_reset with no fault, during another's braking keeps its mark.
            held = self._held_for_the_mode(drive, _halted_for_a_mode(drive))
            return DriveResult(True, message + held, service.status(node_id))
        except DriveFailed as failure:
            held = self._held_for_the_mode(drive, _halted_for_a_mode(drive))
            return DriveResult(False, f'{failure}{held}', service.status(node_id),
                               failure.abort_code)
        except TimeoutError:
            status, said = service.status(node_id), ON_TIMEOUT.get()
            message = (f'timed out after {timeout:g} s: node {node_id} is {status.state} '
                       f'(statusword 0x{status.statusword:04X}, mode {status.mode}){said}')
            held = _halted_for_a_mode(drive)  # before the timeout's halt takes its place
            message += self._homed_meanwhile(drive)
            if halt_on_timeout:  # a motion that did not end in time does not run on
                message = await self._halt_answered(drive, task, message)
            held_note = self._held_for_the_mode(drive, held)  # marks it needing an enable
            # An enable that ran out while the axis braked says how to go on already; the
            # mode change's note would tell its caller to call enable, as it just did.
            return DriveResult(False, message + ('' if said == STILL_BRAKING else held_note),
                               service.status(node_id))
        except asyncio.CancelledError:
            reason = self._reasons.pop(task, SHUTTING_DOWN) + self._homed_meanwhile(drive)
            held = _halted_for_a_mode(drive)  # before the cancel's halt takes its place
            halting = task in self._halt_when_cancelled
            self._halt_when_cancelled.discard(task)
            # A move replaced before its cancel came halts nothing: the drive is the newer
            # sequence's.
            if halting and self._is_current(drive):
                reason = await self._halt_answered(drive, task, reason)
            return DriveResult(False, reason + self._held_for_the_mode(drive, held),
                               service.status(node_id))
        finally:
            self._tokens.pop(task, None)
            if self._tasks.get(node_id) is task:
                del self._tasks[node_id]
                drive.enabling = False

    def _homed_meanwhile(self, drive) -> str:
        """Return what the answer of a homing that ended early adds when the drive had homed.

        Its position counts from the home position from then on, whatever ended the
        sequence before it could answer (a newer command, a cancel, its time). Also when the
        statusword showing it came but was not taken by the sequence yet.
        """
        started = HOMING_STARTED.get()
        if started is None:
            return ''
        status = self._service.status(drive.node_id)
        attained = HOMING_ATTAINED.get() or (
            drive.updates > started and status.mode == cia402.HOMING
            and bool(status.statusword & cia402.MODE_BIT_12) and status.target_reached)
        # No position named: the one known may be from before (its TPDO after the
        # statusword's), and a read would hold up the answer of what replaced the homing.
        return (f'; node {drive.node_id} had shown homing attained before that (statusword '
                f'bits 10 and 12): its position counts from the home position now'
                if attained else '')

    def _is_current(self, drive) -> bool:
        """Return whether the running task is still ``drive``'s sequence (none replaced it)."""
        return self._tasks.get(drive.node_id) is asyncio.current_task()

    # Waiting and sending.

    async def _until(self, drive, ok: Callable, fault_ok: bool = False):
        """Return the drive's status once ``ok(status)``; raise when it faults or is lost.

        A sequence that needs the drive enabled (``ENABLED_ONLY``) also ends when it leaves
        OPERATION_ENABLED (a quick-stop input, another master) or needs a fresh enable.

        A drive read again since the sequence started (it booted, or was heard again) is not
        the one the sequence was asked for, whatever its state now.
        """
        loop = asyncio.get_running_loop()
        while True:
            woken = loop.create_future()
            self._service.when_updated(drive, lambda f=woken: f.done() or f.set_result(None))
            status = self._service.status(drive.node_id)
            _check_same_drive(drive, status, self._service.bus_down())
            if status.faulted and not fault_ok:
                raise DriveFailed(f'node {drive.node_id} went to {status.state}: error '
                                  f'0x{status.error_code:04X} ({status.error or "reading"})',
                                  0)
            problem = ENABLED_ONLY.get() and state_problem(status, True, True)
            if problem:
                raise DriveFailed(f'{problem} (it left OPERATION_ENABLED, or was stopped, '
                                  f'during the command)')
            if ok(status):
                return status
            await woken

    async def _send(self, drive, values: Dict[int, int], halt: Optional[str] = None,
                    stopping: Optional[Dict[int, int]] = None) -> int:
        """Send ``values``; return the statuswords taken before (what a reply must exceed).

        ``halt``: set or release the halt with them; ``stopping``: filled with the target
        that stops the axis (both as ``DriveService.send``).
        """
        indexes = [*values, *([cia402.CONTROLWORD] if halt is not None else [])]
        at_once, at_sync = drive.objects.timing(indexes)
        stop = bool(halt) or stopping is not None or cia402.stops(
            values.get(cia402.CONTROLWORD, cia402.ENABLE_OPERATION))
        pending = drive.applied_at_sync
        if at_once and not stop and pending is not None and not pending.done():
            # A step before this one waits in a synchronous RPDO (a holding target): applied
            # after this step's frames, it would come too late (the drive would take the new
            # mode or enable with the target it held before). A stop goes at once all the
            # same: early is what it wants.
            await asyncio.shield(pending)
        mark = drive.updates
        try:
            sent = self._service.send(drive, values, SEND_TIMEOUT, READS_AT_START.get(),
                                      ENABLED_ONLY.get(), halt, stopping=stopping)
        except ValueError as error:
            raise DriveFailed(f'node {drive.node_id}: {error}; nothing was sent') from None
        # Most writes are sent by the time send returns: no round through the loop for them.
        result = sent.result() if sent.done() else await asyncio.wrap_future(sent)
        if not result.success:
            # The send's own refusals name the node already; the SDO layer's do not.
            named = result.message.startswith(f'node {drive.node_id} ')
            raise DriveFailed(result.message if named
                              else f'node {drive.node_id}: {result.message}', result.abort_code)
        if at_sync:
            drive.applied_at_sync = asyncio.ensure_future(
                until_applied_at_sync(self._service.sync))
        if cia402.STATUSWORD not in drive.objects.mapped_feedback():
            self._service.request_feedback(drive)
        return mark

    async def _after(self, drive, mark: int, ok: Callable, fault_ok: bool = False):
        """Return the first status newer than ``mark`` for which ``ok(status)``."""
        return await self._until(drive, lambda status: drive.updates > mark
                                 and ok(status), fault_ok)

    async def _reach(self, drive, wanted: str, done: Callable, fault_ok: bool = False,
                     first: Optional[Dict[int, int]] = None):
        """Step the drive towards ``wanted`` until ``done(status)``, a transition at a time.

        ``first``: values sent before any step, in the first step's write when there is one
        (its frames come before the controlword's, ``frames.plan``).
        """
        values = dict(first or {})
        status = self._service.status(drive.node_id)
        while not done(status):
            if status.faulted and not fault_ok:
                raise DriveFailed(f'node {drive.node_id} is in {status.state} (error '
                                  f'0x{status.error_code:04X} {status.error}): call '
                                  f'fault_reset first')
            step = cia402.step_towards(status.state, wanted)
            before = status.state
            if step is not None:
                values[cia402.CONTROLWORD] = step
            if values:
                await self._send(drive, values)
                values = {}
            status = await self._until(
                drive, lambda s, before=before: s.state != before or done(s), fault_ok)
        if values:
            await self._send(drive, values)
        return status

    async def _hold(self, drive, mode: int) -> Dict[int, int]:
        """Return ``mode``'s target that keeps the axis where it is, not sent yet.

        {} for a mode that takes none.
        """
        index = cia402.TARGET_OF_MODE.get(mode)
        if index is None:
            return {}
        value = 0
        if index == cia402.TARGET_TORQUE:
            value = self._service.settings.hold_torques.get(drive.node_id, 0)
        if index == cia402.TARGET_POSITION:
            read = await asyncio.wrap_future(drive.objects.read([cia402.POSITION_ACTUAL],
                                                                SEND_TIMEOUT))
            if cia402.POSITION_ACTUAL not in read:
                raise DriveFailed(f'node {drive.node_id}: its actual position (0x6064) could '
                                  f'not be read, so no target could hold the axis; neither '
                                  f'the mode nor the state was changed')
            value = read[cia402.POSITION_ACTUAL]
        return {index: value}

    async def _change_mode(self, drive, mode: int,
                           hold: Optional[Dict[int, int]] = None) -> Optional[Dict[int, int]]:
        """Hold the axis (``hold``, else ``mode``'s holding target), then change to ``mode``.

        The holding target goes in a write of its own before the mode: the drive must not
        take the old mode's target in the new one. Neither write may enable a drive that
        stopped by itself meanwhile (``DriveService.keep_state``). Without ``hold``, an axis
        enabled in another mode is halted first (``_halt_for_mode``): then return the holding
        target, for the caller to release the halt on it or start its motion; else None.
        """
        halted_here = False
        if hold is None:
            halted_here = self._stands_first(drive, mode) and await self._halt_for_mode(drive)
            hold = await self._hold(drive, mode)
        self._service.keep_state(drive)  # after the wait for the axis: it may have stopped
        if hold:
            await self._send(drive, hold)
        if not self._shows_mode(drive, mode):
            drive.pp_goal = None  # the set-point of another mode is no base for a move
            drive.mode_pending = mode
            await self._send(drive, {cia402.MODE: mode})
            await self._until(drive, lambda status: status.mode == mode)
            drive.mode_pending = None
        return hold if halted_here else None

    async def _halt_for_mode(self, drive, braking: str = '') -> bool:
        """Bring an enabled axis to a stand before its mode changes; return whether it halted it.

        The new mode's holding target is read once the axis stands: read while it moves, it
        is where the axis was some milliseconds before the change, and a drive entering CSP
        would run back to it. An axis whose velocity reads 0 stands already, once its
        velocity threshold (0x606F) or its position confirms it (``_standing_confirmed``);
        another is halted (a halt of a mode change before, replaced or timed out, counts as
        this one's) and waited for within the command's time (``_until_standing``): a long
        braking ramp is never cut short; ``braking``, when given, is what the answer adds if
        that time runs out once the axis is halted (``ON_TIMEOUT``). One halted by a halt, a
        cancelled move or the command timeout stays halted. A drive that leaves
        OPERATION_ENABLED meanwhile ends the command: nothing more is sent to it.
        """
        status = self._service.status(drive.node_id)
        if status.state != cia402.OPERATION_ENABLED:
            return False
        ours = _halted_for_a_mode(drive)
        halting = not drive.controlword & cia402.HALT
        if halting:
            read = await asyncio.wrap_future(self._service.read_feedback(
                drive, [cia402.VELOCITY_ACTUAL], SEND_TIMEOUT))
            if (read.get(cia402.VELOCITY_ACTUAL) == 0
                    and await self._standing_confirmed(drive)):
                return False
            await self._halt_and_stop(drive, MODE_CHANGE)
            ours = True
        if braking:
            ON_TIMEOUT.set(braking)
        # Read after the halt went out: a drive slow to answer it must not delay the halt.
        threshold = await velocity_threshold(drive, SEND_TIMEOUT)
        await self._until_standing(drive, status.mode, threshold, halting)
        return ours

    async def _halt_and_stop(self, drive, halt: str) -> None:
        """Set the halt bit (naming ``halt``), then the target that stops the axis in its mode.

        The halt's frames that map the target repeat the stopping one, not an older target
        the axis has left (moved since by an SDO write, or another master). The halt bit
        alone leaves a drive that ignores it (the cyclic modes, several vendors) running: the
        stopping target follows in a write of its own, after the halt (in one write, a frame
        carrying the target with the controlword could follow another carrying the halt,
        and a SYNC of another master between the two would apply the older frame the drive
        holds). Both go out even when the command ends between them (its time runs out
        while the halt's write waits for its SDO answer or a SYNC, a newer command replaces
        it): the halt alone would leave such a drive running, marked halted.
        """
        async def both() -> None:
            stopping: Dict[int, int] = {}
            try:
                await self._send(drive, {}, halt=halt, stopping=stopping)
            finally:  # a halt the drive did not confirm: the target stops it all the same
                if stopping:
                    await self._send(drive, stopping)
        sending = asyncio.ensure_future(both())
        # Its failure after the command ended is the command's no more: taken, not raised.
        sending.add_done_callback(lambda done: done.cancelled() or done.exception())
        await asyncio.shield(sending)

    async def _standing_confirmed(self, drive) -> bool:
        """Return whether an axis whose velocity read 0 stands, by the drive's own measure.

        Its velocity threshold (0x606F), in the units of its velocity; without one, its
        position moving no more than its window (at most ``DEFAULT_WINDOW``) in
        ``STILL_SPAN``: a velocity unit coarser than the position's (rpm against an encoder's
        counts) reads 0 while the axis still moves.
        """
        if await velocity_threshold(drive, SEND_TIMEOUT):
            return True
        window = min(await position_window(drive, SEND_TIMEOUT), DEFAULT_WINDOW)
        before = await self._read_position(drive)
        await asyncio.sleep(STILL_SPAN)
        after = await self._read_position(drive)  # a position not read confirms nothing
        return before is not None and after is not None and abs(after - before) <= window

    async def _until_standing(self, drive, mode: int, threshold: int, halting: bool) -> None:
        """Return once the halted axis stands, by the drive's own sign where it gives one.

        In profile position, profile velocity and homing, as ``halt`` judges it (statusword
        bits 10 and 12, at the drive's own windows). In the cyclic modes and profile torque,
        where CiA 402 leaves those bits to the vendor: a velocity within the drive's velocity
        threshold (0x606F), or, without one, less motion than its position window (at most
        ``DEFAULT_WINDOW``: a wide window would let a braking axis pass) in ``STILL_SPAN``.
        Raises when the drive leaves OPERATION_ENABLED, faults or is lost meanwhile.
        """
        async def until(drive, ok: Callable):
            status = await self._until(drive, lambda s: s.state != cia402.OPERATION_ENABLED
                                       or ok(s))
            if status.state != cia402.OPERATION_ENABLED:
                raise DriveFailed(f'node {drive.node_id} left OPERATION_ENABLED ({status.state})'
                                  f' while it braked (for the mode change or the enable); '
                                  f'nothing more was sent')
            return status
        await self._stands(drive, mode, threshold, halting, until)

    async def _standstill(self, drive, just_halted: bool = True) -> None:
        """Return once the drive, halted by a halt or a cancel, stands (as ``_stands``)."""
        mode = self._service.status(drive.node_id).mode
        threshold = (0 if mode in BY_STATUSWORD
                     else await velocity_threshold(drive, SEND_TIMEOUT))
        await self._stands(drive, mode, threshold, just_halted, self._until, at_rest=True)

    async def _stands(self, drive, mode: int, threshold: int, just_halted: bool,
                      until: Callable, at_rest: bool = False) -> None:
        """Return once the halted axis stands: ``_until_standing``'s judgement.

        ``until(drive, ok)`` waits for a status and raises when the command cannot go on.
        ``at_rest`` (a halt, which answers that the axis stands; a mode change needs it only
        slow enough to hold): without 0x606F, the position stays within the window for
        ``AT_REST_SPAN``, not ``STILL_SPAN``, and the velocity reads 0 all along. A velocity
        that jitters around 0 then never shows a stand.
        """
        if mode in BY_STATUSWORD:
            await wait_for_standstill(self._service, drive, mode, until, SEND_TIMEOUT,
                                      just_halted)
            return
        window = min(await position_window(drive, SEND_TIMEOUT), DEFAULT_WINDOW)
        span = AT_REST_SPAN if at_rest else STILL_SPAN
        loop, reference, since = asyncio.get_running_loop(), None, 0.0
        while True:
            read = await asyncio.wrap_future(self._service.read_feedback(
                drive, [cia402.VELOCITY_ACTUAL, cia402.POSITION_ACTUAL], SEND_TIMEOUT))
            await until(drive, lambda s: True)
            velocity = read.get(cia402.VELOCITY_ACTUAL)
            # Only a position read now: a read that failed (a loaded machine, a busy drive)
            # leaves the last one known, and two alike would pass for a stand.
            position = read.get(cia402.POSITION_ACTUAL)
            # Not a velocity of 0 alone: in units coarser than the position's (rpm against an
            # encoder's counts), a braking axis reads 0 long before it stands.
            if threshold and velocity is not None:
                if abs(velocity) <= threshold:
                    return
            elif position is None:
                reference = None  # nothing to judge by: the next read begins again
            elif (reference is None or abs(position - reference) > window
                  or (at_rest and velocity != 0)):
                reference, since = position, loop.time()  # from here on
            elif loop.time() - since >= span:
                return
            await asyncio.sleep(STILL_SPAN)

    def _held_for_the_mode(self, drive, held: bool) -> str:
        """Return what an answer adds when its sequence left the axis ``held`` for a mode change.

        The drive then needs a fresh enable: a resume would run the old mode's target again.
        A sequence a newer one replaced leaves that to the newer one, which has the drive
        now: a move, homing, set_mode or enable goes on from the halt, a stop ends it, and
        any other keeps it and says so when it ends.
        """
        if not held or not self._is_current(drive):
            return ''
        self._service.set_enabled(drive, False)
        status = self._service.status(drive.node_id)
        # A drive that faulted or left OPERATION_ENABLED says what it needs by its state.
        return HELD_FOR_THE_MODE_CHANGE if status.state == cia402.OPERATION_ENABLED else ''

    async def _release_held(self, drive, mode: int, held: int) -> None:
        """Release the halt of an axis held where it stands (at ``held`` in a position mode).

        In profile position with a new set-point there: released alone, the drive would go
        on to the set-point it was halted on its way to. In homing with the start bit down:
        a halted homing does not start again.
        """
        if mode == cia402.PROFILE_POSITION:
            await self._new_set_point(drive, held)
            return
        self._service.set_halted(drive, '')
        await self._release(drive, {cia402.CONTROLWORD: drive.controlword & ~(
            cia402.HALT | cia402.MODE_BITS)})

    async def _mapping_known(self, drive) -> None:
        """Wait for the drive's PDO mapping being read; that wait is not the command's time."""
        loop, limit = asyncio.get_running_loop(), TIME_LIMIT.get()
        deadline = limit.when() if limit is not None else None
        if deadline is not None:
            limit.reschedule(deadline + MAPPING_WAIT)
        began = loop.time()
        await drive.objects.mapping_known(MAPPING_WAIT)
        if deadline is not None:
            limit.reschedule(deadline + loop.time() - began)

    def _stands_first(self, drive, mode: int) -> bool:
        """Return whether going to ``mode`` brings the axis to a stand first.

        When the drive shows another mode, and when a replaced command halted it for its mode
        change (the new mode may be the one it brakes in).
        """
        return not self._shows_mode(drive, mode) or _halted_for_a_mode(drive)

    def _shows_mode(self, drive, mode: int) -> bool:
        """Return whether the drive shows ``mode``; if so, its frames carry that mode now.

        The mode may have been set another way (``sdo_write``, another master, a tool): the
        gateway's own last mode, in an RPDO that maps 0x6060 beside the controlword, would
        put the old mode back with the next step, and the drive would run on that mode's
        target, whatever was left in it.
        """
        shown = self._service.status(drive.node_id).mode
        if drive.mode_pending == shown:
            drive.mode_pending = None  # the write of an ended sequence landed
        if shown != mode or drive.mode_pending is not None:
            # Not while a mode written by an ended sequence may still land: the drive
            # would go to that mode after this command took the one it shows.
            return False
        drive.objects.know({cia402.MODE: mode})
        return True

    # The commands.

    async def _enable(self, drive, mode: int) -> str:
        status = self._service.status(drive.node_id)
        # Enabled before (or by a set_mode this enable replaced): given back so when this
        # enable fails before it halts the axis, as a set_mode is, and the command timeout
        # watches it again. Marked ``changing_mode``, which whatever makes a fresh enable
        # needed meanwhile clears (a stop, a fault, leaving OPERATION_ENABLED, a boot).
        enabled = status.state == cia402.OPERATION_ENABLED and (not status.needs_enable
                                                              or status.changing_mode)
        self._service.set_enabled(drive, False, changing_mode=enabled)
        commanded = drive.objects.value(cia402.MODE)
        try:
            return await self._enable_from_here(drive, mode)
        except BaseException as failure:
            # Halted for the mode change, it needs a fresh enable (``_own``): not given back
            # meanwhile, when a target would resume it in the old mode. Nor once the new mode
            # was written: a target of the old mode would be taken as one of the new (a
            # velocity of 0 as position 0).
            if self._is_current(drive) and not _halted_for_a_mode(drive):
                self._give_back(drive, failure, commanded, status.mode,
                                self._still_enabled(drive, enabled))
            raise

    def _give_back(self, drive, failure: BaseException, commanded: Optional[int], shown: int,
                   enabled: bool) -> None:
        """Give a drive back as an enable or set_mode that ``failure`` ended found it.

        ``enabled`` as it was, unless the sequence wrote a mode other than ``commanded`` and
        ``shown`` at its start, or a mode written is not shown yet: a target of the old mode
        would then be taken as one of the new (a velocity of 0 as position 0), so the drive
        needs a fresh enable, and the answer says so (a DriveFailed is raised with that
        said; a timeout says it itself).
        """
        if (drive.mode_pending is None
                and drive.objects.value(cia402.MODE) in (commanded, shown)):
            self._service.set_enabled(drive, enabled)
            return
        self._service.set_enabled(drive, False)
        ON_TIMEOUT.set(MODE_CHANGED)
        if isinstance(failure, DriveFailed):
            raise DriveFailed(f'{failure}{MODE_CHANGED}', failure.abort_code) from None

    async def _enable_from_here(self, drive, mode: int) -> str:
        unbooted = self._service.boot_refusal(drive.node_id)
        if unbooted:
            raise DriveFailed(f'node {drive.node_id}: {unbooted}; enable refused, nothing was '
                              f'sent to the controlword')
        if drive.unwatched:  # written since, or a write that failed once: tried again
            await self._service.watch_again(drive)
            if drive.unwatched:
                raise DriveFailed(f'node {drive.node_id}: {drive.unwatched}; enable refused, '
                                  f'nothing was sent to the controlword (or give that up: '
                                  f'drives.keep_running_if_gateway_dies)')
        await self._mapping_known(drive)
        if self._service.status(drive.node_id).state != cia402.OPERATION_ENABLED:
            drive.pp_goal = None  # enabled afresh, a drive takes where it stands as its base
        mode = mode or self._service.status(drive.node_id).mode
        if not self._shows_mode(drive, mode) or drive.controlword & cia402.HALT:
            # Held where it stands, not where it slows: an axis braking (for a mode change,
            # a halt, a cancelled move, the command timeout) is waited for as a mode change
            # waits, within the command's time. Released earlier, a drive that ramps its halt
            # in CSP would stop short of the ramp's end, and run back to the position read.
            # The answer of one that runs out meanwhile says the axis still brakes, not to
            # call enable (as its caller just did): once halted, whoever halted it.
            ON_TIMEOUT.set(STILL_BRAKING if drive.controlword & cia402.HALT else '')
            await self._halt_for_mode(drive, braking=STILL_BRAKING)
            ON_TIMEOUT.set('')
        hold = await self._hold(drive, mode)
        held = hold.get(cia402.TARGET_POSITION, 0)
        if not self._shows_mode(drive, mode):
            await self._change_mode(drive, mode, hold)
            hold = {}
        self._service.set_halted(drive, '')
        # In the mode already: the holding target goes with the first step's controlword
        # (before it, frames.plan), a round trip less than a write of its own.
        status = await self._reach(drive, cia402.OPERATION_ENABLED,
                                   lambda s: s.state == cia402.OPERATION_ENABLED, first=hold)
        if drive.controlword & cia402.HALT:  # already enabled, halted: released, held
            await self._release_held(drive, status.mode, held)
            status = self._service.status(drive.node_id)
        self._service.set_enabled(drive, True)
        return f'node {drive.node_id} is OPERATION_ENABLED in {cia402.mode_name(status.mode)}'

    async def _disable(self, drive, _mode: int) -> str:
        async def heard() -> str:
            status = await self._reach(
                drive, cia402.SWITCH_ON_DISABLED,
                lambda s: s.state == cia402.SWITCH_ON_DISABLED or s.faulted, fault_ok=True)
            return f'node {drive.node_id} is {status.state}: its power stage is off'
        return await self._stop(drive, cia402.DISABLE_VOLTAGE, heard)

    async def _quick_stop(self, drive, _mode: int) -> str:
        async def heard() -> str:
            status = self._service.status(drive.node_id)
            if _stopped(status) or status.state not in cia402.POWERED:
                return f'node {drive.node_id} is {status.state}: nothing to stop'
            mark = await self._send(drive, {cia402.CONTROLWORD: cia402.QUICK_STOP})
            status = await self._after(drive, mark, _stopped, fault_ok=True)
            return f'node {drive.node_id} stopped: {status.state}'
        return await self._stop(drive, cia402.QUICK_STOP, heard)

    async def _stop(self, drive, word: int, heard: Callable) -> str:
        """Stop the drive with ``heard()``, or with ``word`` by SDO when it is not heard.

        Also when it stops heartbeating during ``heard()``: no statusword would confirm it.
        """
        self._service.set_enabled(drive, False)
        self._service.set_halted(drive, '')
        if drive.heard and self._service.status(drive.node_id).state != cia402.UNKNOWN:
            with contextlib.suppress(_Unheard):
                return await heard()
        return await self._stop_unheard(drive, word)

    async def _stop_unheard(self, drive, word: int) -> str:
        """Send a stop to a drive not heard, by SDO: no statusword can confirm it."""
        result = await asyncio.wrap_future(self._service.send(
            drive, {cia402.CONTROLWORD: word}, SEND_TIMEOUT, None, by_sdo=True))
        if not result.success:
            raise DriveFailed(f'node {drive.node_id} is not heard, and the controlword '
                              f'0x{word:04X} was not taken: {result.message}',
                              result.abort_code)
        return (f'node {drive.node_id} is not heard: controlword 0x{word:04X} written by SDO '
                f'(the drive confirmed the write; no statusword shows its state)')

    async def _halt(self, drive, _mode: int) -> str:
        await self._halt_and_stop(drive, 'command')
        ON_TIMEOUT.set(HALT_HOLDS)
        await self._standstill(drive)
        await self._read_position(drive)
        position = self._service.status(drive.node_id).position
        return f'node {drive.node_id} halted at position {position} (drive units)'

    async def _resume(self, drive, _mode: int) -> str:
        if _halted_for_a_mode(drive):  # since the request was checked
            raise DriveFailed(f'node {drive.node_id}: {RESUME_REFUSED}; nothing was sent')
        mode = self._service.status(drive.node_id).mode
        if mode in (cia402.PROFILE_POSITION, cia402.HOMING):
            # The move, set-points or homing it was halted in have ended (a command ends
            # them, this one too): released as it is, the drive would run on to their
            # set-point, or home, with nobody watching. Held where it stands, as enable
            # holds: once it stands (a set-point where a braking axis is would cut its ramp
            # short, and a real drive would overshoot it and come back).
            if not drive.controlword & cia402.HALT:
                return f'node {drive.node_id} is not halted: nothing to resume'
            ON_TIMEOUT.set(RESUME_BRAKING)
            await self._standstill(drive, just_halted=False)
            ON_TIMEOUT.set('')
            held = await self._hold(drive, mode)
            await self._release_held(drive, mode, held.get(cia402.TARGET_POSITION, 0))
            return (f'node {drive.node_id} resumed, held where it stands: the '
                    f'{"move or set-points" if mode == cia402.PROFILE_POSITION else "homing"} '
                    f'it was halted in ended with the halt; send a new one to go on')
        await self._release(drive, {}, halt='')
        return f'node {drive.node_id} resumed'

    async def _release(self, drive, values: Dict[int, int], halt: Optional[str] = None) -> None:
        """Send ``values`` releasing the halt (``halt`` as ``_send``); return once applied.

        A drive applies a synchronous RPDO only at the SYNC after its frame: a statusword
        before that shows it halted still, so the statusword is read after that SYNC, as a
        halt's standstill is (``standstill.until_applied_at_sync``).
        """
        at_sync = drive.objects.applied_at_sync(cia402.CONTROLWORD)
        mark = await self._send(drive, values, halt)
        if at_sync:
            await until_applied_at_sync(self._service.sync)
            mark = drive.updates  # those taken meanwhile may be from before that SYNC
            await asyncio.wrap_future(self._service.read_feedback(drive, [cia402.STATUSWORD],
                                                                  SEND_TIMEOUT))
        await self._after(drive, mark, lambda status: True)

    async def _fault_reset(self, drive, _mode: int) -> str:
        status = self._service.status(drive.node_id)
        if not status.faulted:
            return f'node {drive.node_id} is {status.state}: no fault to reset'
        await self._until(drive, lambda s: s.state != cia402.FAULT_REACTION_ACTIVE,
                          fault_ok=True)
        if drive.controlword & cia402.FAULT_RESET:
            await self._send(drive, {cia402.CONTROLWORD: cia402.DISABLE_VOLTAGE})
        await self._send(drive, {cia402.CONTROLWORD: cia402.FAULT_RESET})
        status = await self._until(drive, lambda s: not s.faulted, fault_ok=True)
        await asyncio.wrap_future(self._service.read_feedback(drive, [cia402.ERROR_CODE],
                                                              SEND_TIMEOUT))
        return (f'fault reset: node {drive.node_id} is {status.state}; enable it to move '
                f'again')

    async def _set_mode(self, drive, mode: int) -> str:
        # No target of the old mode may be taken as one of the new (the drive shows the new
        # mode before the release): refused until the answer. One that fails with the axis
        # halted for it leaves the drive to a fresh enable (``_held_for_the_mode``); one that
        # failed to halt it leaves it as it was, the command timeout watching it. Marked
        # ``changing_mode`` only when it was enabled: a set_mode replacing this one takes
        # that over, and gives the drive back enabled as this one would have.
        status = self._service.status(drive.node_id)
        enabled = not status.needs_enable or status.changing_mode
        self._service.set_enabled(drive, False, changing_mode=enabled)
        task = asyncio.current_task()
        self._mode_changes.add(task)
        commanded = drive.objects.value(cia402.MODE)
        try:
            hold = await self._change_mode(drive, mode)
            if hold is not None:
                await self._release_held(drive, mode, hold.get(cia402.TARGET_POSITION, 0))
        except BaseException as failure:
            # Halted for it, the drive needs a fresh enable all the same (``_own``): not
            # given back meanwhile, when a target would resume it in the old mode. Nor once
            # the new mode was written (``_enable``'s rule). Replaced, the drive is the newer
            # command's, which had it given back (``_own``).
            if self._is_current(drive) and not _halted_for_a_mode(drive):
                self._give_back(drive, failure, commanded, status.mode,
                                self._still_enabled(drive, enabled))
            raise
        finally:
            self._mode_changes.discard(task)
        enabled = self._still_enabled(drive, enabled)
        self._service.set_enabled(drive, enabled)
        status = self._service.status(drive.node_id)
        fresh = ('; it takes targets after an enable' if not enabled
                 and status.state == cia402.OPERATION_ENABLED else '')
        return f'node {drive.node_id} is in {cia402.mode_name(mode)}{fresh}'

    def _still_enabled(self, drive, enabled: bool) -> bool:
        """Return ``enabled``, unless the drive needs a fresh enable since set_mode began.

        It left OPERATION_ENABLED, faulted, booted or was stopped meanwhile (each clears
        ``changing_mode``).
        """
        return enabled and self._service.status(drive.node_id).changing_mode

    async def _home(self, drive, _mode: int) -> str:
        await self._change_mode(drive, cia402.HOMING)
        drive.pp_goal = None  # homing moves the coordinates the set-point was in
        word = drive.controlword & ~(cia402.MODE_BITS | cia402.HALT)
        self._service.set_halted(drive, '')
        if drive.controlword & cia402.NEW_SET_POINT:
            await self._send(drive, {cia402.CONTROLWORD: word})
        mark = await self._send(drive, {cia402.CONTROLWORD: word | cia402.NEW_SET_POINT})
        HOMING_STARTED.set(mark)
        status = await self._after(drive, mark, lambda s: bool(
            s.statusword & cia402.MODE_BIT_13
            or (s.statusword & cia402.MODE_BIT_12 and s.target_reached)))
        HOMING_ATTAINED.set(not status.statusword & cia402.MODE_BIT_13)
        await self._send(drive, {cia402.CONTROLWORD: word})
        if status.statusword & cia402.MODE_BIT_13:
            raise DriveFailed(f'node {drive.node_id}: homing failed (statusword bit 13, '
                              f'homing error; method in 0x6098)')
        return await self._homed_here(drive)

    async def _homed_here(self, drive) -> str:
        """Return the answer of a homing attained; raise when it did not set the position.

        Checked for the methods that home where the axis stands (``arrival``).
        """
        window = await position_window(drive, SEND_TIMEOUT)
        read = await asyncio.wrap_future(self._service.read_feedback(
            drive, [cia402.POSITION_ACTUAL], SEND_TIMEOUT))
        setting = await asyncio.wrap_future(drive.objects.read(
            [cia402.HOMING_METHOD, cia402.HOME_OFFSET], SEND_TIMEOUT))
        position = read.get(cia402.POSITION_ACTUAL, self._service.status(drive.node_id).position)
        offset = setting.get(cia402.HOME_OFFSET)
        if (setting.get(cia402.HOMING_METHOD) in HOME_HERE and offset is not None
                and abs(position - offset) > window):
            raise DriveFailed(f'node {drive.node_id} shows homing attained at position '
                              f'{position}, not at its home offset {offset} (0x607C; '
                              f'position window {window}, in drive units)')
        return f'node {drive.node_id} homed: position {position} (drive units)'

    # Profile position: moves and streamed set-points share the set-point handshake.

    async def _move(self, drive, position: int, relative: bool, velocity: int,
                    on_feedback: Optional[Callable]) -> str:
        window = await position_window(drive, SEND_TIMEOUT)
        wanted = position
        if relative:
            # From the set-point the gateway last gave it since its enable (a cancelled
            # move's too), else from where it stands; sent as that absolute target, so the
            # drive's own base for relative set-points (0x60F2) does not matter.
            if drive.pp_goal is None:
                await self._read_position(drive)
            base = drive.pp_goal
            wanted += base if base is not None else self._service.status(
                drive.node_id).position
        try:
            limits = await software_limits(drive, SEND_TIMEOUT)
        except LimitsUnknown as error:
            raise DriveFailed(str(error)) from None
        problem = outside_limits(drive.node_id, wanted, limits)
        if problem:
            raise DriveFailed(problem)
        await self._change_to_pp(drive)
        await self._profile_velocity(drive, velocity)
        mark = await self._new_set_point(drive, wanted)
        while True:
            status = await self._after(drive, mark, lambda s: True)
            mark = drive.updates
            if on_feedback is not None:
                on_feedback(status)
            if status.target_reached:
                here, why = await self._arrival(drive, wanted, window)
                if why:
                    raise DriveFailed(why)
                return f'node {drive.node_id} reached position {here} (drive units)'

    async def _arrival(self, drive, wanted: int, window: int) -> Tuple[int, str]:
        """Return where a drive showing target reached stands, and why that misses ``wanted``.

        '' when it stands within ``window``; else the miss, with the set-point it holds.
        """
        # The TPDO with the position may lag the statusword's: the position is read.
        await self._read_position(drive)
        here = self._service.status(drive.node_id).position
        if abs(here - wanted) <= window:
            return here, ''
        read = await asyncio.wrap_future(drive.objects.read([cia402.TARGET_POSITION],
                                                            SEND_TIMEOUT))
        return here, missed(drive.node_id, wanted, here, window,
                            read.get(cia402.TARGET_POSITION))

    async def _read_position(self, drive) -> Optional[int]:
        """Read the drive's position by SDO (taken as its status); None when not read."""
        read = await asyncio.wrap_future(self._service.read_feedback(
            drive, [cia402.POSITION_ACTUAL], SEND_TIMEOUT))
        return read.get(cia402.POSITION_ACTUAL)

    async def _stream(self, drive) -> str:
        """Hand the drive each set-point given; then check it arrived at the last one.

        Like a move, the last set-point counts as reached only when the drive shows target
        reached for it within its position window; a miss is logged and shown in
        ``/diagnostics`` (nobody waits for an answer of a stream). A set-point given
        meanwhile is taken at once, and the check is then the new one's.
        """
        await self._change_to_pp(drive)
        await self._profile_velocity(drive)
        node_id = drive.node_id
        if node_id not in self._set_points:
            return 'no set-point left to take'  # a stream replaced before it began
        while True:
            while node_id in self._set_points:
                position = self._set_points.pop(node_id)
                mark = await self._new_set_point(drive, position)
            await self._until(drive, lambda s, m=mark: node_id in self._set_points
                              or (drive.updates > m and s.target_reached))
            if node_id in self._set_points:
                continue
            here, why = await self._arrival(drive, position, await position_window(
                drive, SEND_TIMEOUT))
            self._service.set_missed_set_point(drive, why)
            return why or f'set-points taken; node {node_id} reached {here} (drive units)'

    async def _change_to_pp(self, drive) -> None:
        # Also in PP already, braking for another command's mode change: waited for before
        # a set-point releases the halt.
        if self._stands_first(drive, cia402.PROFILE_POSITION):
            await self._change_mode(drive, cia402.PROFILE_POSITION)

    async def _profile_velocity(self, drive, velocity: int = 0) -> None:
        """Have the drive's profile velocity (0x6081) be ``velocity``.

        0: the one the drive was configured with, not the last move's.
        """
        velocity = velocity or drive.profile_velocity
        if velocity and velocity != drive.objects.value(cia402.PROFILE_VELOCITY_OBJECT):
            await self._send(drive, {cia402.PROFILE_VELOCITY_OBJECT: velocity})

    async def _new_set_point(self, drive, position: int) -> int:
        """Hand the drive a set-point (bit 4 up, wait for bit 12, bit 4 down); return a mark.

        The mark is taken when the drive acknowledged: target reached counts from there.
        """
        self._service.set_halted(drive, '')
        word = drive.controlword & ~(cia402.MODE_BITS | cia402.HALT)
        status = self._service.status(drive.node_id)
        if (drive.controlword & cia402.NEW_SET_POINT
                or status.statusword & cia402.MODE_BIT_12):
            # A halt stays on until the new set-point: released with bit 4 down, a drive
            # halted on its way would head for the old one meanwhile.
            mark = await self._send(drive, {
                cia402.CONTROLWORD: drive.controlword & ~cia402.MODE_BITS})
            await self._after(drive, mark, lambda s: not s.statusword & cia402.MODE_BIT_12)
        bits = cia402.NEW_SET_POINT | cia402.CHANGE_SET_IMMEDIATELY
        drive.pp_goal = None  # until the drive takes this one: then it is the base
        mark = await self._send(drive, {cia402.TARGET_POSITION: position,
                                        cia402.CONTROLWORD: word | bits})
        await self._after(drive, mark, lambda s: bool(s.statusword & cia402.MODE_BIT_12))
        drive.pp_goal = position
        acknowledged = drive.updates - 1
        await self._send(drive, {cia402.CONTROLWORD: word})
        return acknowledged

    async def _halt_answered(self, drive, task: asyncio.Task, reason: str) -> str:
        """Halt the drive of a sequence ``task`` that ended; return its answer, whatever comes.

        Replaced or shut down while the halt is confirmed, it is answered all the same.
        """
        try:
            return await self._halt_after_cancel(drive, reason)
        except asyncio.CancelledError:
            return (f'{reason}; {self._reasons.pop(task, SHUTTING_DOWN)} before the halt was '
                    f'confirmed')

    async def _halt_after_cancel(self, drive, reason: str) -> str:
        """Halt the drive of a cancelled move; return the answer with where it stopped."""
        try:
            await self._send(drive, {}, halt='cancel')
            async with asyncio.timeout(HALT_WAIT):
                await self._standstill(drive)
        except DriveFailed as error:
            return f'{reason}; the halt was not confirmed: {error}'
        except TimeoutError:
            return (f'{reason}; the halt was not confirmed: the axis did not stand within '
                    f'{HALT_WAIT:g} s (the halt holds)')
        await self._read_position(drive)
        return (f'{reason}: halted at position '
                f'{self._service.status(drive.node_id).position} (drive units)')


def _check_same_drive(drive, status, bus_down: Optional[str]) -> None:
    """Raise when ``drive`` is lost, or was read again since the sequence was asked for.

    A drive that booted (or was heard again) is not the one the sequence was asked for,
    whatever its state now: nothing more is sent to it (``DriveService.send`` checks too).
    A stop (``READS_AT_START`` None) is for whatever drive is there, but raises
    :class:`_Unheard` once that drive is not heard: no statusword will confirm it.
    """
    reads = READS_AT_START.get()
    if reads is None and not drive.heard:
        raise _Unheard
    problem = lost_problem(drive, reads, status, bus_down)
    if problem:
        raise DriveFailed(problem)


def _halted_for_a_mode(drive) -> bool:
    return drive.halted_by == MODE_CHANGE


def _stopped(status) -> bool:
    return (status.state == cia402.SWITCH_ON_DISABLED or status.faulted
            or (status.state == cia402.QUICK_STOP_ACTIVE and status.target_reached))
