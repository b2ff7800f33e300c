"""CiA 402 drives run by the gateway: state from every statusword, commands, targets, safety.

Each drive of ``drives.nodes`` is followed from the frames it sends: its TPDOs (statusword,
mode display, actual values), or SDO reads of what no TPDO maps, once a feedback cycle.
Every statusword updates the drive's state at once, in the thread that received it, and wakes
what waits on it: a command (``commands``) runs as a coroutine that sends one
controlword, awaits the statusword that shows its effect and sends the next, never sleeping
or polling. Targets from a caller go out at once, from the caller's thread.

Safety lives here, below ROS:

- enabling, and every change of mode, first sets the mode's target to hold the axis
  (``commands``);
- in the streaming modes a drive whose targets stop for ``command_timeout`` is halted;
- the gateway's shutdown (and a managed node's deactivation) sends ``on_shutdown`` to every
  powered drive before the bus closes;
- with a gateway heartbeat, each drive watches it (0x1016, written when first heard and after
  each boot, then a beat at once) and stops by itself when the gateway dies;
- a drive that faults, stops heartbeating or boots refuses targets until a fresh ``enable``,
  and is UNKNOWN until re-read; one found running when re-read is quick-stopped.
"""

import asyncio
from concurrent.futures import Future
import contextlib
from dataclasses import replace
import logging
import threading
import time
from typing import Callable, Dict, List, Optional, Tuple

from ..bus import prompt
from ..coroutine_runner import CoroutineRunner
from ..nmt import BOOT_UP, HEARTBEAT_COB_BASE, NOT_DETECTED
from ..pdo.mapping import ReceivedPdo
from ..pdo.service import REPLACED
from ..sdo.request_queue import answer, resolved
from ..sdo.requests import SdoResult
from ..text import HEARTBEAT_SILENT, SHUTTING_DOWN
from . import checks as checks
from . import cia402
from . import safety as safety
from .commands import DriveCommands
from .cycle import FeedbackCycle, poll
from .objects import decode, DriveObjects, FEEDBACK, feedback_decoder
from .status import DriveRecord, DriveResult, DriveSettings, DriveStatus, failed, shown, updated

LOGGER = logging.getLogger(__name__)

# A command's time unless its caller says: a transition takes ms, homing as long as it travels.
DEFAULT_TIMEOUT = 2.0
# SYNC periods a command's default timeout adds, while the gateway produces SYNC: a step in
# a synchronous RPDO waits up to three (sent after one, applied at the next, shown after it),
# and a step after it for two more (commands._send); an enable into a new mode has four.
SYNC_CYCLES_PER_COMMAND = 12
HOMING_TIMEOUT = 60.0
MOVE_TIMEOUT = 60.0
# A drive's initial read that failed is tried again on a later heartbeat, at most this often.
REREAD_INTERVAL = 1.0
# Targets going out this long (s) in a row end an incident of targets not sent (one log line).
TARGETS_SENT_AGAIN = 1.0
# A stream of targets is kept up for at most this many SYNC cycles after its last target:
# a controller late by a cycle or two still has an RPDO each cycle, but every frame kept up
# carries the controlword that enabled the drive, which a drive that stopped by itself
# (quick stop options 5..8) takes as transition 16 and runs again. A longer pause sends
# nothing: the drive holds its last target, and the command timeout halts it.
STREAM_KEPT_CYCLES = 3
# The settings of a drive the gateway reads once and keeps (until a boot): a caller's write
# of one through the gateway is followed (``writing``).
KEPT_SETTINGS = frozenset({cia402.PROFILE_VELOCITY_OBJECT, cia402.POSITION_WINDOW,
                           cia402.VELOCITY_THRESHOLD, cia402.SOFTWARE_POSITION_LIMIT})


class DriveService:
    """The drives of ``settings.node_ids`` on the gateway's bus.

    ``network`` is the gateway's canopen network, ``monitor`` its heartbeat monitor, ``pdo``
    its PDO service, ``sdo_batch`` its SDO batch call, ``sync`` its SYNC producer,
    ``write_protection`` its write rules, ``bus_down()`` why the bus is down (None while it
    is up), ``beat_now()`` sends the gateway's heartbeat at once, ``end_transfers(reason,
    node_ids)`` ends the SDO transfers under way with those drives and answers the queued
    ones with ``reason``.
    """

    def __init__(self, network, settings: DriveSettings, monitor, pdo, sdo_batch,
                 sync, write_protection,
                 bus_down: Callable[[], Optional[str]] = lambda: None,
                 beat_now: Callable[[], None] = lambda: None,
                 end_transfers: Callable[[str, List[int]], None] = lambda *_: None):
        self.settings, self._network, self._monitor, self.sync = settings, network, monitor, sync
        self._pdo = pdo
        self._sdo_batch, self._beat_now = sdo_batch, beat_now
        # So that the stops (at shutdown, at deactivate) are not queued behind a caller's
        # transfer or a poll past their wait, and never sent.
        self._end_transfers = end_transfers
        # Held by a beat of the feedback cycle, and to hold the beats: none queues a poll or
        # a halt between the drives' transfers ended and their stops queued.
        self._beats = threading.Lock()
        self._beats_held = False
        self._bus_down = bus_down
        self._lock = threading.RLock()
        # Notified at every statusword taken: shutdown waits there for those of its stops.
        self._statuswords = threading.Condition(self._lock)
        self._drives = {
            node_id: DriveRecord(node_id, DriveObjects(
                node_id, pdo, sdo_batch, lambda: sync.producing,
                lambda n=node_id: monitor.operational(n)), DriveStatus(node_id))
            for node_id in sorted(set(settings.node_ids))}
        self._listeners: List[Callable[[DriveStatus], None]] = []
        # (node, TPDO): (mapping, its feedback decoder); the bus thread's alone.
        self._decoders: Dict[Tuple[int, int], tuple] = {}
        # Why a drive may not be enabled though it answers (its boot failed), or None.
        self.boot_refusal: Callable[[int], Optional[str]] = lambda node_id: None
        self._held_back: Callable[[], Optional[str]] = lambda: None
        self._runner = CoroutineRunner('drives')
        self._commands = DriveCommands(self)
        self._closing = False
        # Set once shutdown has shown the drives' stops: what is taken later is not told.
        self._stops_shown = False
        # Drives whose targets are not sent (an incident: its first failure is logged, the
        # rest not, as a stream at 250 Hz would log every one): since when they go out again
        self._targets_failing: Dict[int, Optional[float]] = {}
        self._checks = checks.RequestChecks(self._drives, self._lock, write_protection,
                                            bus_down, lambda: self._closing)
        self._cycle = FeedbackCycle(settings.feedback_period, self._tick, sync.next_point,
                                    self.statuses)
        if self._drives:
            pdo.add_listener(self._on_pdo)
            monitor.add_listener(self._on_node_states)

    @property
    def node_ids(self) -> List[int]:
        """Return the drives run."""
        return list(self._drives)

    def add_listener(self, listener: Callable[[DriveStatus], None]) -> None:
        """Call ``listener(status)`` on every change of a drive's state, mode, fault or halt.

        Called with the service's lock held (told in order): it returns at once, calls nothing.
        """
        self._listeners.append(listener)

    def add_cycle_listener(self, listener: Callable[[], None]) -> None:
        """Call ``listener()`` once every feedback cycle (the joint states' rhythm)."""
        self._cycle.add_listener(listener)

    def status(self, node_id: int) -> DriveStatus:
        """Return what is known of drive ``node_id`` now: UNKNOWN until it is re-read."""
        with self._lock:
            return shown(self._drives[node_id])

    def hold_back_while(self, why: Callable[[], Optional[str]]) -> None:
        """Send the drives nothing that could enable them while ``why()`` says why not."""
        self._held_back = why

    def after_gateway_silence(self, seconds: float) -> None:
        """Quick-stop every drive: the gateway's heartbeat was silent ``seconds``.

        Longer than the drives' consumer time (the gateway held up, or the bus down): each
        drive that watches it took its abort connection option (a quick stop) meanwhile. One
        that stays in QUICK_STOP_ACTIVE would take a frame of the gateway's carrying enable
        operation as transition 16 and run again: the frame it holds for the next SYNC (the
        gateway's SYNC waits for this), one built before the silence, a target queued
        meanwhile. The quick stop goes into every RPDO frame that maps the controlword at
        once, and by SDO; a fresh enable is needed. Called before the gateway's next beat,
        while nothing else may go out (``hold_back_while``).
        """
        LOGGER.warning('the heartbeat of the gateway was silent for %.2f s, longer than the '
                       'drives watch it (drives.consumer_time %g s): they stopped by '
                       'themselves; each is quick-stopped and needs a fresh enable', seconds,
                       self.settings.consumer_time)
        def taken(node_id: int, done: Future) -> None:
            if not done.result().success:
                LOGGER.error('drive %d: the quick stop after the silence was not taken: %s',
                             node_id, done.result().message)
        for drive, _, sent in safety.send_stops(self._drives.values(), cia402.QUICK_STOP,
                                                self._lock, self._tell):
            sent.add_done_callback(lambda done, node_id=drive.node_id: taken(node_id, done))
            self._wake(drive)  # a command under way ends: the drive needs a fresh enable

    def refuse_enable_when(self, refusal: Callable[[int], Optional[str]]) -> None:
        """Have ``refusal(node_id)`` (why a drive may not be enabled, or None) asked first."""
        self.boot_refusal = refusal

    def enabled(self, node_id: int) -> bool:
        """Return whether ``node_id`` is a drive shown OPERATION_ENABLED (it may move)."""
        with self._lock:
            drive = self._drives.get(node_id)
            return drive is not None and shown(drive).state == cia402.OPERATION_ENABLED

    def statuses(self) -> List[DriveStatus]:
        """Return every drive's status, by node id."""
        with self._lock:
            return [shown(drive) for drive in self._drives.values()]

    def cycle_statuses(self) -> List[DriveStatus]:
        """Return every drive's status as the feedback cycle's beat tells it, by node id.

        In a beat that came with a SYNC cycle's last TPDO, the statuses as they were then
        (every drive's feedback of that cycle, none of the next); else as they are now.
        """
        taken = self._cycle.beat_snapshot
        return taken if taken is not None else self.statuses()

    def want_cycle_statuses(self, wanted: bool) -> None:
        """Say whether :meth:`cycle_statuses` is read: the statuses are then taken each cycle.

        While not, the receive thread takes none (a beat's statuses are then as they are
        now): 8 drives at 250 Hz are 2,000 statuses a second nobody reads.
        """
        self._cycle.snapshots = wanted

    def command_timeouts(self, node_id: int) -> int:
        """Return how often the command timeout halted drive ``node_id``."""
        with self._lock:
            return self._drives[node_id].timeouts

    def missed_set_point(self, node_id: int) -> str:
        """Return why the last set-point of drive ``node_id``'s last PP stream was missed.

        '' when it was reached (or no stream ended yet).
        """
        with self._lock:
            return self._drives[node_id].missed_set_point

    def start(self) -> None:
        """Listen to the drives' heartbeats and start the feedback cycle."""
        for node_id in self._drives:
            self._network.subscribe(HEARTBEAT_COB_BASE + node_id, self._on_heartbeat)
        if self._drives:
            self._cycle.start()

    def stop(self) -> None:
        """Answer every command in progress, then send ``on_shutdown`` to every powered drive.

        Called first in the gateway's shutdown, while frames may still go out and TPDOs are
        still taken. Waits at most ``safety.SHUTDOWN_WAIT`` for the drives to take the stop,
        and as long again for their statuswords to show it (``_show_stops``).
        """
        with self._lock:
            if self._closing:
                return
            self._closing = True
        self._cycle.stop()
        self._runner.close()
        self._hold_beats()  # for good: the cycle has stopped, a beat may still be under way
        self._show_stops(self._stop_motion(SHUTTING_DOWN))
        for node_id in self._drives:
            self._network.unsubscribe(HEARTBEAT_COB_BASE + node_id, self._on_heartbeat)

    def _show_stops(self, stopped: List[Tuple[DriveRecord, int]]) -> None:
        """Wait until the drives stopped at shutdown show it in a statusword; tell it.

        ``stopped``: each drive sent the stop, with the statuswords it had taken before. The
        last state its subscribers get must not say OPERATION_ENABLED of a stopped drive. Its
        TPDOs are still taken; one whose statusword no TPDO brings is read once by SDO (the
        feedback cycle that polls it has ended). A drive that shows no stop within
        ``safety.SHUTDOWN_WAIT`` is shown UNKNOWN: nothing follows it any more.
        """
        deadline = time.monotonic() + safety.SHUTDOWN_WAIT
        for drive, _ in stopped:
            if cia402.STATUSWORD not in drive.objects.mapped_feedback():
                self.read_feedback(drive, [cia402.STATUSWORD], safety.SHUTDOWN_WAIT)

        def shows_stop(drive: DriveRecord, before: int) -> bool:
            return drive.updates > before and shown(drive).state != cia402.OPERATION_ENABLED
        with self._statuswords:
            self._statuswords.wait_for(lambda: all(shows_stop(*each) for each in stopped),
                                       max(0.0, deadline - time.monotonic()))
            for drive, before in stopped:
                if not shows_stop(drive, before):
                    drive.status = replace(drive.status, state=cia402.UNKNOWN)
                    self._tell(drive)
            # Final: a TPDO or an SDO answer still taken after this (one in flight as the
            # wait ended, of a drive that ignored the stop) must not tell OPERATION_ENABLED
            # after the UNKNOWN its subscribers were told last.
            self._stops_shown = True

    def pause(self, reason: str) -> None:
        """End what runs, then stop every powered drive as at shutdown (a node deactivated).

        The sequences are ended, and waited for, first: one could send an enable step after.
        """
        ended = self._runner.submit(self._commands.cancel_all(reason))
        if ended is not None:  # None: shutting down, the loop ended them
            with contextlib.suppress(TimeoutError):  # stop them anyway
                ended.result(safety.SHUTDOWN_WAIT)
        self._hold_beats()
        try:
            self._stop_motion(reason)
        finally:
            with self._beats:
                self._beats_held = False

    def _hold_beats(self) -> None:
        """Return once no beat of the feedback cycle runs, and none will until released."""
        with self._beats:
            self._beats_held = True

    def _stop_motion(self, reason: str) -> List[Tuple[DriveRecord, int]]:
        """Send ``drives.on_shutdown`` to every powered drive, ahead of what else it waits for.

        The transfers under way with those drives (a caller's long upload or batch, a poll
        of a drive fallen silent) are ended first: the stop would wait behind them past its
        own wait, and never be sent. A drive that gets no stop (booting, off) keeps its own.
        """
        if safety.ON_SHUTDOWN[self.settings.on_shutdown]:
            with self._lock:
                stopped = [node_id for node_id, drive in self._drives.items()
                           if safety.to_stop(drive)]
            self._end_transfers(reason, stopped)
        return safety.stop_motion(self._drives.values(), self.settings, self._lock, reason)

    def command(self, node_id: int, command: str, mode: int = 0,
                timeout: float = 0.0) -> 'Future[DriveResult]':
        """Run ``command`` on drive ``node_id``; resolves when its statusword shows the result.

        A command replaces one still running on the same drive (answered "replaced"). Never
        raises; a request that cannot be run is answered at once, nothing sent.
        """
        # A stop goes to whatever drive is there: it may have booted, and be powered again.
        reads = None if command in checks.STOPPING_COMMANDS else self._reads(node_id)
        refused = self._checks.command(node_id, command, mode, timeout)
        if refused is not None:
            return resolved(refused)
        drive = self._drives[node_id]
        limit = timeout or (HOMING_TIMEOUT if command == 'home' else
                            DEFAULT_TIMEOUT + SYNC_CYCLES_PER_COMMAND * self.sync.period)
        return self._submit(drive, self._commands.run(drive, command, mode, limit, reads))

    def move(self, node_id: int, position: int, relative: bool = False, velocity: int = 0,
             on_feedback: Optional[Callable[[DriveStatus], None]] = None,
             timeout: float = 0.0) -> Tuple['Future[DriveResult]', Callable[[], None]]:
        """Move drive ``node_id`` in profile position; return (result future, cancel()).

        Succeeds on the drive's target reached within its position window of the goal
        (``arrival``); ``cancel()`` and ``timeout`` (s, 0 = 60 s) halt the drive and
        answer where it stopped. A new move or target for the drive replaces this one.
        """
        reads = self._reads(node_id)
        refused = self._checks.move(node_id, position, velocity)
        if refused:
            return resolved(refused), lambda: None
        drive, token = self._drives[node_id], object()
        future = self._submit(drive, self._commands.move(
            drive, position, relative, velocity, on_feedback, token, reads,
            timeout or MOVE_TIMEOUT))
        return future, lambda: self._runner.call_soon(
            lambda: self._commands.cancel(drive, 'cancelled', halt=True, token=token))

    def one_cycle(self):
        """Return a context within which the targets given reach the drives in one SYNC cycle.

        For the targets of one command message (``PdoService.one_cycle``).
        """
        return self._pdo.one_cycle()

    def target(self, node_id: int, value: float) -> DriveResult:
        """Send ``value`` as the target of the drive's present mode, in the drive's units.

        Position in PP (a new set-point applied at once) and CSP, velocity in PV and CSV,
        torque in CST. Restarts the command timeout; resumes a drive it halted. Refused
        (nothing sent) when the drive is not enabled, faulted, halted by a halt command, or
        the value does not fit.
        """
        reads = self._reads(node_id)
        refused = self._checks.drive(node_id, enabled=True)
        if refused is not None:
            return refused
        drive = self._drives[node_id]
        held = self._held_back()
        with drive.sending:
            with self._lock:
                status = drive.status
                problem = (f'{SHUTTING_DOWN}; {checks.NOTHING_SENT}' if self._closing
                           else f'{held}; {checks.NOTHING_SENT}' if held
                           else checks.target_problem(status, drive.halted_by, value))
                if problem:
                    return failed(status, problem)
                index = cia402.TARGET_OF_MODE[status.mode]
                refused = self._checks.target_object(status, index)
                if refused:
                    return refused
                drive.last_target = time.monotonic()
                values = {index: round(value)}
                if drive.halted_by and status.mode != cia402.PROFILE_POSITION:
                    # Halted by the command timeout or a cancelled move: a target resumes it.
                    drive.halted_by = ''
                    drive.controlword &= ~cia402.HALT
                    values[cia402.CONTROLWORD] = drive.controlword
                    drive.status = replace(drive.status, halted=False)
                    self._tell(drive)
            if status.mode == cia402.PROFILE_POSITION:
                self._runner.call_soon(lambda: self._commands.set_point(drive, round(value),
                                                                        reads))
                return DriveResult(True, 'set-point handed to the drive', status)
            # A target alone is one of a stream, which the PDO service keeps up for a few
            # SYNC cycles the caller leaves without one (a late cycle, not a pause).
            stream = (0.0 if cia402.CONTROLWORD in values
                      else STREAM_KEPT_CYCLES * self.sync.period)
            sent = drive.objects.write(values, self.settings.feedback_period * 10 or 0.5,
                                       stream, replaceable=cia402.CONTROLWORD not in values)
        sent.add_done_callback(lambda done: self._log_failed_target(node_id, done))
        return DriveResult(True, 'sent', status)

    # Used by the command sequences (commands), on the drives' event loop.

    def send(self, drive: DriveRecord, values: Dict[int, int], timeout: float,
             reads: Optional[int], enabled: bool = False, halt: Optional[str] = None,
             by_sdo: bool = False, stopping: Optional[Dict[int, int]] = None) -> 'Future':
        """Send ``values`` to ``drive`` (the controlword kept as the drive's commanded one).

        Nothing when the drive was read again since ``reads`` (``checks.lost_problem``), or
        with ``enabled`` when it is no longer enabled by us: a step of a move or a halt would
        enable one that stopped itself. ``halt``: set the halt bit (naming who, as
        ``set_halted``; one halted for a mode change keeps that name) or release it ('') with
        them, shown only past those checks. A release
        restarts the command timeout in the same step, so no timeout halt comes between (it
        would stay shown, and stop later ones). ``by_sdo``: whatever the PDOs map.
        ``stopping``: filled with the target that stops the axis in its mode
        (``safety.stopping_target``), which the frames of this write then repeat; decided
        with the halt under ``drive.sending``, so no target streamed meanwhile comes between.
        """
        switching_off = (halt is None and cia402.CONTROLWORD in values
                         and cia402.switches_off(values[cia402.CONTROLWORD]))
        held = None if switching_off else self._held_back()
        with drive.sending:
            # Before the lock (the objects' own), as the command timeout's halt reads it.
            commanded = (drive.objects.value(cia402.TARGET_POSITION) if stopping is not None
                         else None)
            with self._lock:
                status = shown(drive)
                problem = (checks.lost_problem(drive, reads, status, self._bus_down()) or held
                           or (enabled and checks.state_problem(status, True, True)))
                if problem:
                    return resolved(SdoResult.failed(problem))
                if stopping is not None:
                    stopping.update(safety.stopping_target(drive, status, self.settings,
                                                           commanded))
                if halt is not None:
                    # A drive halted for a mode change stays so until released: a resume
                    # would run its old mode's target (``checks.RESUME_REFUSED``).
                    self.set_halted(drive, drive.halted_by if halt and drive.halted_by
                                    == checks.MODE_CHANGE else halt)
                    if not halt:
                        drive.last_target = time.monotonic()
                    word = (drive.controlword | cia402.HALT if halt
                            else drive.controlword & ~cia402.HALT)
                    values = {**values, cia402.CONTROLWORD: word}
                if cia402.CONTROLWORD in values:
                    drive.controlword = values[cia402.CONTROLWORD]
            if stopping:
                drive.objects.know(stopping)
            write = drive.objects.write_by_sdo if by_sdo else drive.objects.write
            return write(values, timeout)

    async def watch_again(self, drive: DriveRecord) -> None:
        """Have ``drive`` watch the gateway again (0x1016:1, 0x6007); ``unwatched`` tells."""
        await safety.watch_the_gateway(self._sdo_batch, drive, self._lock, self.settings,
                                       self._beat_now)

    def bus_down(self) -> Optional[str]:
        """Return why the bus is down, None while it is up."""
        return self._bus_down()

    def when_updated(self, drive: DriveRecord, wake: Callable[[], None]) -> None:
        """Call ``wake()`` on the drives' loop at the next feedback or loss of ``drive``."""
        with self._lock:
            drive.waiters.append(wake)

    def wake(self, drive: DriveRecord) -> None:
        """Wake what waits on ``drive`` (``when_updated``) as its next feedback would."""
        self._wake(drive)

    def set_missed_set_point(self, drive: DriveRecord, why: str) -> None:
        """Record why the last set-point of a PP stream was missed ('' reached); log a miss."""
        with self._lock:
            drive.missed_set_point = why
        if why:
            LOGGER.warning('drive %d: the last set-point of a stream of PP targets was not '
                           'reached: %s', drive.node_id, why)

    def request_feedback(self, drive: DriveRecord) -> None:
        """Read by SDO at once what no TPDO brings (after an SDO controlword, say)."""
        poll(drive, self._lock, self.read_feedback, now=True)

    def keep_state(self, drive: DriveRecord) -> None:
        """Have frames that repeat the controlword repeat one that keeps the drive's state.

        A write without a controlword, in an RPDO that maps it, repeats the one the gateway
        commanded last (``frames``). A drive may have left the state that word put it in by
        itself (its quick-stop input, another master): "enable operation" repeated would
        take it from QUICK_STOP_ACTIVE (quick stop options 5..8, transition 16) or from
        SWITCHED_ON back to OPERATION_ENABLED, in the mode it is in, on whatever target that
        mode holds. Nothing is sent here.
        """
        with drive.sending:
            with self._lock:
                word = cia402.KEEPS.get(shown(drive).state)
                if (word is None or drive.controlword & cia402.COMMAND_BITS
                        != cia402.ENABLE_OPERATION or word == cia402.ENABLE_OPERATION):
                    return
                drive.controlword = word
            drive.objects.know({cia402.CONTROLWORD: word})

    def set_halted(self, drive: DriveRecord, by: str) -> None:
        """Record who halted the drive ('' = nobody), and show it."""
        with self._lock:
            drive.halted_by = by
            changed = drive.status.halted != bool(by)
            drive.status = replace(drive.status, halted=bool(by))
            if changed:
                self._tell(drive)

    def set_enabled(self, drive: DriveRecord, enabled: bool, changing_mode: bool = False) -> None:
        """Record that an enable succeeded (targets taken) or that a fresh one is needed.

        ``changing_mode``: not enabled only while a set_mode runs (``DriveStatus``).
        """
        with self._lock:
            drive.status = replace(drive.status, needs_enable=not enabled,
                                   changing_mode=changing_mode)
            drive.last_target = time.monotonic()

    def read_feedback(self, drive: DriveRecord, indexes: List[int],
                      timeout: float) -> 'Future[Dict[int, int]]':
        """Read ``indexes`` by SDO and take them (``DriveRecord.newest``); then resolve."""
        with self._lock:
            since = drive.tpdos
        done: Future = Future()

        def taken(read: Future) -> None:
            try:
                self._apply(drive, read.result(), time.monotonic(), since=since)
            finally:  # whatever happened, the reader (a poll, a move) goes on
                answer(done, read.result())
        drive.objects.read(indexes, timeout).add_done_callback(taken)
        return done

    # Frames and node states, from the bus thread.

    def _on_pdo(self, received: ReceivedPdo) -> None:
        mapping = received.mapping
        drive = self._drives.get(mapping.node_id)
        if drive is None:
            return
        key = (mapping.node_id, mapping.number)
        known = self._decoders.get(key)
        if known is None or known[0] is not mapping:  # a mapping read replaced it
            known = self._decoders[key] = (mapping, feedback_decoder(mapping))
        values = known[1](received.data)
        if values:
            with self._lock:
                drive.took_tpdo(values)
            self._apply(drive, values, received.timestamp)
            if received.mapping.transmission_type == 1:
                self._cycle.took(key)

    @prompt
    def _on_heartbeat(self, can_id: int, data: bytearray, _timestamp: float) -> None:
        if not data:
            return
        drive = self._drives[can_id - HEARTBEAT_COB_BASE]
        boot = data[0] == BOOT_UP
        with self._lock:
            first = not drive.heard
            drive.heard = True
            retry = (drive.read_done == -drive.read_wanted  # the latest failed, none runs
                     and time.monotonic() - drive.read_failed_at >= REREAD_INTERVAL)
            if not (boot or first or retry):
                return
            drive.read_wanted += 1
            request = drive.read_wanted
            if boot or first:  # it may have booted unheard: its settings are read again
                drive.unread_state = ''
                drive.position_window = drive.position_limits = drive.pp_goal = None
                drive.velocity_threshold = None
            if boot:  # UNKNOWN until re-read: its feedback waits for that read (_apply)
                drive.objects.forget()
                drive.mode_pending = None
                drive.halted_by = ''
                drive.status = replace(drive.status, state=cia402.UNKNOWN, needs_enable=True,
                                       changing_mode=False, halted=False)
                self._tell(drive)
        if boot:  # a command running ends (commands._until)
            self._wake(drive)
        self._runner.submit(self._initial_read(drive, request))

    def _on_node_states(self) -> None:
        lost = []
        with self._lock:
            for drive in self._drives.values():
                if drive.heard and self._monitor.status(drive.node_id).state == NOT_DETECTED:
                    drive.lost_powered = safety.powered(drive)
                    drive.heard = False
                    self._pdo.end_streams(drive.node_id)
                    drive.halted_by = ''
                    drive.status = DriveStatus(drive.node_id,
                                               supported_modes=drive.status.supported_modes,
                                               position=drive.status.position)
                    self._tell(drive)
                    lost.append(drive)
        for drive in lost:
            LOGGER.warning('drive %d stopped heartbeating: state UNKNOWN, targets refused; it '
                           'needs a fresh enable once it is heard again', drive.node_id)
            self._wake(drive)
            if drive.lost_powered and not self._bus_down():  # it may be alive and running
                self._runner.submit(safety.stop_unattended(
                    drive, self._lock, 'stopped heartbeating while powered'))

    def _apply(self, drive: DriveRecord, values: Dict[int, int], stamp: float,
               reread: int = 0, since: Optional[int] = None) -> None:
        """Take feedback values of ``drive``: update its status, wake what waits, tell.

        Until its re-read (number ``reread``) is in, only that read's values; until the
        re-read is done, nothing is told (it is told at its end). ``since``: the values were
        read by SDO, asked after that many TPDOs; what later TPDOs brought is newer.
        """
        with self._lock:
            if self._stops_shown:
                return  # shutdown has shown what it decided (``_show_stops``)
            if since is not None:
                values = drive.newest(values, since, bool(reread))
            if not values:
                return  # nothing was read, or only what TPDOs brought since: no new stamp
            old = drive.status
            if not drive.heard or (drive.read_done != drive.read_wanted
                                   and reread != drive.read_wanted):
                if drive.heard and cia402.STATUSWORD in values:  # the re-read will decide
                    drive.unread_state = cia402.state_of(values[cia402.STATUSWORD])
                return
            told = drive.ready == drive.read_wanted  # else told once the re-read is done
            new = updated(old, values, stamp, drive.emcy_code)
            if new.state != old.state and new.state != cia402.OPERATION_ENABLED:
                # A frame kept up each cycle carries the controlword that enabled it: a drive
                # that stopped by itself (quick stop options 5..8) would take it as transition
                # 16 and run again. Only a command enables it now.
                self._pdo.end_streams(drive.node_id)
                if (old.state == cia402.OPERATION_ENABLED and drive.controlword
                        & cia402.COMMAND_BITS == cia402.ENABLE_OPERATION):
                    drive.left_by_itself = True
            # Back in OPERATION_ENABLED though nothing of the gateway enabled it since it left
            # by itself: a frame already on its way (one held for the next SYNC) did. It
            # needs a fresh enable, so targets and the command timeout leave it alone: it
            # would run on at that frame's target. Stopped as a drive found running is.
            ran_again = (new.state == cia402.OPERATION_ENABLED
                         and old.state != cia402.OPERATION_ENABLED
                         and drive.left_by_itself
                         and not self._closing)  # the shutdown stop is the last word
            if ran_again:
                drive.left_by_itself = False
            drive.status = new
            drive.count(values)
            if cia402.STATUSWORD in values:
                self._statuswords.notify_all()
            changed = old.told != new.told
            if changed and told:
                self._tell(drive)
        if cia402.POSITION_ACTUAL in values:
            drive.objects.saw_position(values[cia402.POSITION_ACTUAL], safety.window_of(drive))
        if new.faulted and not old.faulted:
            self._runner.submit(self._read_error(drive))
        if ran_again:
            self._runner.submit(safety.stop_unattended(
                drive, self._lock, 'ran again by itself after it left OPERATION_ENABLED (a '
                'frame it held for SYNC, another master)'))
        if changed or cia402.STATUSWORD in values:
            self._wake(drive)

    def writing(self, node_id: int, index: int, subindex: int,
                data: bytes) -> Optional[Callable[[bool], None]]:
        """Follow a caller's SDO write to drive ``node_id`` through the gateway, as it is sent.

        What the gateway keeps of the drive must not undo it: an object its RPDOs map beside
        the commanded ones goes into their frames now (``DriveObjects.hold``); a setting read
        once is taken (0x6081, the profile velocity a move at velocity 0 uses) or read again
        at the next move (0x6067 the position window, 0x606F the velocity threshold, 0x607D
        the software position limits)
        once the write is confirmed. Return what to call with whether it succeeded; None when
        the write touches nothing kept.
        """
        drive = self._drives.get(node_id)
        if drive is None:
            return None
        put_back = drive.objects.hold(index, subindex, data)
        if put_back is None and index not in KEPT_SETTINGS:
            return None

        def settle(success: bool) -> None:
            if not success:
                if put_back is not None:
                    put_back()
                return
            with self._lock:
                if index == cia402.PROFILE_VELOCITY_OBJECT and subindex == 0:
                    drive.profile_velocity = decode(index, data)
                elif index == cia402.POSITION_WINDOW:
                    drive.position_window = None
                elif index == cia402.VELOCITY_THRESHOLD:
                    drive.velocity_threshold = None
                elif index == cia402.SOFTWARE_POSITION_LIMIT:
                    drive.position_limits = None
        return settle

    def on_emcy(self, node_id: int, error_code: int) -> None:
        """Take the error code of an EMCY a drive sent (0: its errors are gone)."""
        drive = self._drives.get(node_id)
        if drive is None:
            return
        with self._lock:
            drive.emcy_code = error_code
            update = error_code and drive.status.faulted and not drive.status.error_code
        if update:
            self._apply(drive, {cia402.ERROR_CODE: error_code}, time.monotonic())

    def _wake(self, drive: DriveRecord) -> None:
        with self._lock:  # for most TPDOs: mostly nobody waits
            if not drive.waiters:
                return
            waiters, drive.waiters = drive.waiters, []
        for wake in waiters:
            self._runner.call_soon(wake)

    def _tell(self, drive: DriveRecord) -> None:
        """Tell every listener what callers see of ``drive`` now.

        Called with the lock held, in the section that made the change: changes made in
        several threads are told in the order they were made.
        """
        status = shown(drive)
        for listener in self._listeners:
            listener(status)

    # The drives' loop: reads when heard, the error code of a fault.

    async def _initial_read(self, drive: DriveRecord, request: int) -> None:
        with self._lock:
            since = drive.tpdos
        values = await asyncio.wrap_future(drive.objects.read_initial(DEFAULT_TIMEOUT))
        with self._lock:
            if request != drive.read_wanted:
                return  # it booted again meanwhile: a newer read follows
            read = cia402.STATUSWORD in values
            drive.read_done = request if read else -request
            drive.read_failed_at = time.monotonic()
            drive.objects.know_commanded(values)
            drive.controlword = values.get(cia402.CONTROLWORD, 0)
            drive.profile_velocity = values.get(cia402.PROFILE_VELOCITY_OBJECT, 0)
            drive.status = replace(drive.status, supported_modes=values.get(
                cia402.SUPPORTED_MODES, 0))
        if not read:
            LOGGER.warning('drive %d: its statusword could not be read; tried again on a '
                           'later heartbeat', drive.node_id)
            return
        self._apply(drive, {index: values[index] for index in (*FEEDBACK, cia402.ERROR_CODE)
                            if index in values}, time.monotonic(), reread=request, since=since)
        await safety.secure_heard_drive(drive, self._lock, self._sdo_batch, self.settings,
                                        self._beat_now, self.read_feedback)
        await asyncio.wrap_future(drive.objects.read_held(DEFAULT_TIMEOUT))
        with self._lock:
            if request != drive.read_wanted:
                return  # it booted meanwhile: a newer read follows
            drive.ready = request  # commands go, and its feedback counts, from now
            self._tell(drive)
        self._wake(drive)  # a stop waiting across a boot sees the drive read

    async def _read_error(self, drive: DriveRecord) -> None:
        await asyncio.wrap_future(self.read_feedback(drive, [cia402.ERROR_CODE],
                                                     DEFAULT_TIMEOUT))
        status = self.status(drive.node_id)
        LOGGER.error('drive %d FAULT: error code 0x%04X (%s); targets are refused until '
                     'fault_reset and enable', drive.node_id, status.error_code, status.error)

    # Each beat of the feedback cycle: SDO reads of what no TPDO brings, the command timeout.

    def _tick(self) -> None:
        with self._beats:
            if self._beats_held:
                return
            self._cycle.expect(sum(drive.objects.tpdos_every_sync()
                                   for drive in self._drives.values() if drive.heard))
            for drive in self._drives.values():
                if not self._closing:
                    poll(drive, self._lock, self.read_feedback)
                if safety.halt_if_timed_out(drive, self.settings, self._lock,
                                            lambda: self._closing or bool(self._held_back()),
                                            self._tell):
                    with self._lock:
                        self._tell(drive)

    # Checks, and the way out.

    def _reads(self, node_id: int) -> int:
        """Return how often a drive was read afresh, taken just before its request's check.

        A sequence fails when the drive is read again while it runs (it booted, or was heard
        again): taken before the check, a boot after the check always counts.
        """
        drive = self._drives.get(node_id)
        return drive.read_wanted if drive else 0

    def _submit(self, drive: DriveRecord, coroutine) -> 'Future[DriveResult]':
        """Run a sequence on the drives' loop; its future always resolves to a DriveResult.

        A sequence ended from outside (the loop closing) or by a defect is answered too: a
        caller waiting on it would otherwise never hear back.
        """
        running = self._runner.submit(coroutine)
        if running is None:
            return resolved(failed(self.status(drive.node_id),
                                   f'{SHUTTING_DOWN}; {checks.NOTHING_SENT}'))
        done: Future = Future()

        def settle(finished: Future) -> None:
            if finished.cancelled():
                result = failed(self.status(drive.node_id), f'{SHUTTING_DOWN}: the command '
                                                            f'was ended')
            elif finished.exception() is not None:
                LOGGER.error('drive %d: a command failed: %r', drive.node_id,
                             finished.exception())
                result = failed(self.status(drive.node_id), f'node {drive.node_id}: the '
                                f'command failed: {finished.exception()!r}')
            else:
                result = finished.result()
            answer(done, result)
        running.add_done_callback(settle)
        return done

    def _log_failed_target(self, node_id: int, done: Future) -> None:
        """Log the first target of an incident that was not sent, not the ones after it.

        An incident ends once targets went out for ``TARGETS_SENT_AGAIN`` s in a row: targets
        that go out and time out by turns (an overloaded SDO channel) are one incident. One
        a newer target replaced in the queue was not lost.
        """
        result = done.result()
        # Neither a target a newer one replaced nor one the shutdown or the gateway's silence
        # kept back (each said once) was lost.
        failed = (not result.success and REPLACED not in result.message
                  and SHUTTING_DOWN not in result.message
                  and HEARTBEAT_SILENT not in result.message)
        if not failed and node_id not in self._targets_failing:
            return  # sent, and no incident open: all but a few of a stream's targets
        now = time.monotonic()
        with self._lock:
            first = failed and node_id not in self._targets_failing
            if failed:
                self._targets_failing[node_id] = None
            elif node_id in self._targets_failing:
                since = self._targets_failing[node_id]
                if since is None:
                    self._targets_failing[node_id] = now
                elif now - since >= TARGETS_SENT_AGAIN:
                    del self._targets_failing[node_id]
        if first:
            LOGGER.warning('drive %d: a target was not sent: %s; the targets after it that are '
                           'not sent either are not logged, until targets have gone out for '
                           '%g s', node_id, result.message, TARGETS_SENT_AGAIN)

