"""The drives' safety stops: at shutdown, when targets stop coming, when the gateway dies.

- :func:`stop_motion`: ``drives.on_shutdown`` (quick stop, disable voltage) sent by SDO to
  every powered drive, so it takes effect at once whatever the PDOs' transmission types;
  called while the gateway shuts down or a managed node is deactivated, before the bus closes.
- :func:`halt_if_timed_out`: a drive in a streaming mode without a new target for
  ``drives.command_timeout`` is halted (controlword bit 8): it decelerates and holds; in the
  cyclic modes and profile torque its target is set to stop it too (:func:`stopping_target`,
  which the halt command sends as well).
- :func:`stop_unattended`: a drive found running when it is heard (again) is quick-stopped.
- :func:`watch_the_gateway`: the drive's heartbeat consumer (0x1016:1) set to the gateway's
  heartbeat, so that the drive's own 0x6007 reaction stops it when the gateway, its computer
  or the bus dies; SIGKILL and power loss included.
"""

import asyncio
from concurrent.futures import Future
from dataclasses import replace
import logging
import struct
import time
from typing import Callable, Dict, Iterable, List, Optional, Tuple

from ..nmt import consumer_entry
from ..sdo.requests import Access, SdoResult
from . import cia402
from .arrival import DEFAULT_WINDOW
from .status import DriveRecord, DriveSettings

LOGGER = logging.getLogger(__name__)

ON_SHUTDOWN = {'quick_stop': cia402.QUICK_STOP, 'disable': cia402.DISABLE_VOLTAGE,
               'none': None}
# drives.abort_connection: the 0x6007 codes of CiA 402; 0 (no reaction) is never written.
ABORT_CONNECTION = {'quick_stop': 3, 'disable': 2, 'fault': 1, 'none': 0}
NO_REACTION = 0
# Between two reads of a statusword that does not show the stop yet.
STOP_READ_INTERVAL = 0.02
# How long shutdown waits for the drives to confirm its stop commands.
SHUTDOWN_WAIT = 0.5
CONSUMER_TIMEOUT = 2.0
HALT_TIMEOUT = 2.0  # of the command timeout's halt, when it goes by SDO


def powered(drive: DriveRecord, unseen: bool = False) -> bool:
    """Return whether ``drive``'s power stage may be on (its lock held).

    A drive heard and not re-read yet counts by what its TPDOs showed meanwhile, and with
    ``unseen`` also when they showed nothing: a stop is harmless to a drive that is off.
    """
    if drive.status.state in cia402.POWERED:
        return True
    unread = drive.heard and drive.ready != drive.read_wanted
    return unread and (drive.unread_state in cia402.POWERED or unseen and not drive.unread_state)


def to_stop(drive: DriveRecord) -> bool:
    """Return whether ``stop_motion`` sends ``drive`` its stop (its lock held)."""
    return drive.heard and powered(drive, unseen=True)


def stop_motion(records: Iterable[DriveRecord], settings: DriveSettings, lock,
                reason: str) -> List[Tuple[DriveRecord, int]]:
    """Send ``on_shutdown`` by SDO to every powered drive; wait for them to take it.

    Returns each drive sent it, with the statuswords it had taken before (``updates``): one
    taken later may show the stop.
    """
    word = ON_SHUTDOWN[settings.on_shutdown]
    if word is None:
        return []
    sent = send_stops(records, word, lock)
    deadline = time.monotonic() + SHUTDOWN_WAIT
    failed = []
    for drive, _, future in sent:
        try:
            result = future.result(max(0.0, deadline - time.monotonic()))
        except TimeoutError:
            failed.append(f'{drive.node_id} (no answer)')
            continue
        if not result.success:
            failed.append(f'{drive.node_id} ({result.message})')
    if sent:
        LOGGER.info('%s: %s sent to drives %s%s', reason, settings.on_shutdown,
                    ', '.join(str(drive.node_id) for drive, *_ in sent),
                    f'; not taken by {", ".join(failed)}' if failed else '')
    return [(drive, updates) for drive, updates, _ in sent]


def send_stops(records: Iterable[DriveRecord], word: int, lock,
               tell: Callable[[DriveRecord], None] = lambda drive: None
               ) -> List[Tuple[DriveRecord, int, 'Future[SdoResult]']]:
    """Send the stop ``word`` to every powered drive, without waiting for the answers.

    By SDO, and at once in every RPDO frame that maps the controlword (``write_by_sdo``), so
    a frame a drive holds for the next SYNC carries the stop too. Returns each drive sent it,
    with the statuswords it had taken before, and the SDO write's answer; tells each
    (``tell``, with the lock held).
    """
    sent = []
    for drive in records:
        with drive.sending:  # after a target or halt being sent, before any later one
            with lock:
                if not to_stop(drive):
                    continue
                drive.controlword = word
                # The stop's controlword has no halt bit: shown halted, the drive would say so.
                drive.halted_by = ''
                drive.status = replace(drive.status, needs_enable=True, changing_mode=False,
                                       halted=False)
                updates = drive.updates
                tell(drive)
            sent.append((drive, updates, drive.objects.write_by_sdo(
                {cia402.CONTROLWORD: word}, SHUTDOWN_WAIT)))
    return sent


async def stop_unattended(drive: DriveRecord, lock, why: str) -> bool:
    """Quick-stop a drive nothing of ours commands any more, by SDO (applied at once).

    Returns whether the drive took the stop.

    ``why``: 'found running' when heard (again without a boot, its heartbeat paused, it runs
    on at its last target; or one a crashed gateway left running at the gateway's start), or
    'lost' when its heartbeat stopped while it was powered (it may still be alive, running,
    deaf only to its own heartbeat; if it is gone, the transfer times out).
    """
    with drive.sending:
        with lock:
            drive.controlword = cia402.QUICK_STOP
        stopped = drive.objects.write_by_sdo({cia402.CONTROLWORD: cia402.QUICK_STOP},
                                             CONSUMER_TIMEOUT)
    result = await asyncio.wrap_future(stopped)
    if result.success:
        LOGGER.warning('drive %d %s, commanded by nobody here: quick stop sent; enable it to '
                       'move it', drive.node_id, why)
    else:
        LOGGER.error('drive %d %s, commanded by nobody here, and could not be stopped: %s',
                     drive.node_id, why, result.message)
    return result.success


async def secure_heard_drive(drive: DriveRecord, lock, sdo_batch, settings: DriveSettings,
                             beat_now: Callable[[], None], read_feedback) -> None:
    """Quick-stop ``drive`` if it was found running, then have it watch the gateway.

    The last steps of a re-read; its TPDOs count meanwhile. The stop's statusword is read
    back (``read_feedback``, the drive service's): its TPDO may be taken only after the
    re-read is shown, and the drive shown running after it was stopped.
    """
    try:
        with lock:
            running = drive.status.state == cia402.OPERATION_ENABLED
        if running and await stop_unattended(drive, lock, 'was OPERATION_ENABLED when heard'):
            await _read_back_stop(drive, read_feedback)
        await watch_the_gateway(sdo_batch, drive, lock, settings, beat_now)
    except Exception as error:  # noqa: BLE001 - the drive is read; say what failed
        LOGGER.error('drive %d: its re-read could not finish (%r)', drive.node_id, error)


async def _read_back_stop(drive: DriveRecord, read_feedback) -> None:
    """Read the statusword until it shows the stop, within ``CONSUMER_TIMEOUT``.

    CiA 402 lets a drive confirm the write before it acts on it: the first read can still
    show OPERATION_ENABLED, and the drive would be shown running until its next statusword.
    """
    deadline = time.monotonic() + CONSUMER_TIMEOUT
    while True:
        read = await asyncio.wrap_future(read_feedback(drive, [cia402.STATUSWORD],
                                                       CONSUMER_TIMEOUT))
        if cia402.STATUSWORD not in read:
            LOGGER.warning('drive %d: its statusword after the quick stop could not be read; '
                           'it is shown as read before until its next one', drive.node_id)
            return
        if cia402.state_of(read[cia402.STATUSWORD]) != cia402.OPERATION_ENABLED:
            return
        if time.monotonic() >= deadline:
            LOGGER.warning('drive %d still shows OPERATION_ENABLED %.1f s after it took the '
                           'quick stop', drive.node_id, CONSUMER_TIMEOUT)
            return
        await asyncio.sleep(STOP_READ_INTERVAL)


def stopping_target(drive: DriveRecord, status, settings: DriveSettings,
                    commanded_position: Optional[int]) -> Dict[int, int]:
    """Return the target that stops the axis in ``status``'s mode without the halt bit, or {}.

    Several vendors' drives ignore controlword bit 8 in the cyclic modes (their manuals say it
    has no function there), so a halt there also sets the target: velocity 0, the hold
    torque (CST, PT), and in CSP where the axis stands (``_where_it_stands``).
    """
    index = cia402.HALT_BY_TARGET.get(status.mode)
    if index is None:
        return {}
    if index == cia402.TARGET_POSITION:
        return {index: _where_it_stands(drive, status, commanded_position)}
    if index == cia402.TARGET_TORQUE:
        return {index: settings.hold_torques.get(drive.node_id, 0)}
    return {index: 0}


def window_of(drive: DriveRecord) -> int:
    """Return the drive's position window (0x6067) in drive units, a default until read."""
    return DEFAULT_WINDOW if drive.position_window is None else drive.position_window


def _where_it_stands(drive: DriveRecord, status, commanded: Optional[int]) -> int:
    """Return the CSP position target that holds the axis where it stands.

    ``commanded``, the target last sent, until the drive has shown it stood there (a drive
    following its stream is on its way there; the position it shows, a TPDO old, would send
    it back); after that, a position shown outside its window of that target says the axis
    left it (moved by an SDO write or another master), and that position holds it.
    """
    if commanded is None:
        return status.position
    if (abs(commanded - status.position) <= window_of(drive)
            or not drive.objects.position_target_shown):
        return commanded
    return status.position


def halt_if_timed_out(drive: DriveRecord, settings: DriveSettings, lock,
                      closing: Callable[[], bool], tell: Callable[[DriveRecord], None]) -> bool:
    """Halt ``drive`` if it has waited too long for a target; return whether it did.

    Not once ``closing()``: the gateway's shutdown stop must be the last word, and while
    the gateway's heartbeat is silent too long its quick stop after the silence is. A halt
    that could not be sent is taken back (``_halt_answered``, which ``tell``s it with the
    lock held), so the next tick tries again.
    """
    limit = settings.command_timeout
    with drive.sending:
        # Before the lock (the objects' own), and under drive.sending: no target goes meanwhile.
        commanded = drive.objects.value(cia402.TARGET_POSITION)
        with lock:
            status = drive.status
            if (not limit or status.state != cia402.OPERATION_ENABLED or status.needs_enable
                    or drive.halted_by or status.mode not in cia402.STREAMING_MODES
                    or time.monotonic() - drive.last_target < limit or closing()):
                return False
            drive.timeouts += 1
            drive.halted_by = 'timeout'
            drive.controlword |= cia402.HALT
            drive.status = replace(status, halted=True)
            word, count = drive.controlword, drive.timeouts
            values = {**stopping_target(drive, status, settings, commanded),
                      cia402.CONTROLWORD: word}
        written = drive.objects.write(values, HALT_TIMEOUT)
    written.add_done_callback(lambda done: _halt_answered(drive, lock, count, done.result(),
                                                          tell))
    # One line per drive; later halts are counted (diagnostics), not logged again.
    (LOGGER.warning if count == 1 else LOGGER.debug)(
        'drive %d: no target for %.3f s (drives.command_timeout): halted; the next target '
        'resumes it (halted this way %d times)', drive.node_id, limit, count)
    return True


def _halt_answered(drive: DriveRecord, lock, count: int, result: SdoResult,
                   tell: Callable[[DriveRecord], None]) -> None:
    """Take back the command timeout's halt number ``count`` when ``result`` says it failed.

    The drive did not get it (NMT stopped: neither PDO nor SDO reaches it), so it may run on
    at its last target: it is shown not halted, and the next tick halts it again. Not when
    something came since (a target, a command, another halt): that decided afresh. Logged
    once until a halt is sent again.
    """
    with lock:
        if result.success:
            drive.halt_failing = False
            return
        if drive.halted_by != 'timeout' or drive.timeouts != count:
            return
        drive.halted_by = ''
        drive.controlword &= ~cia402.HALT
        drive.status = replace(drive.status, halted=False)
        first, drive.halt_failing = not drive.halt_failing, True
        tell(drive)
    (LOGGER.error if first else LOGGER.debug)(
        'drive %d: the command timeout could not halt it (%s): it may run on at its last '
        'target; tried again until sent (not logged again until then)', drive.node_id,
        result.message)


async def watch_the_gateway(sdo_batch, drive: DriveRecord, lock, settings: DriveSettings,
                            beat_now: Callable[[], None]) -> None:
    """Have ``drive`` stop by itself when the gateway dies: 0x1016:1, then 0x6007.

    A beat follows the consumer's write at once: a consumer watches from the first beat it
    hears, and a drive enabled before the next beat on the grid would run on if the gateway
    died then. A drive whose 0x6007 is 0 would take no action on the loss: it is set to
    ``settings.abort_connection``, or, with that 0, ``drive.unwatched`` says why enable is
    refused; as it does when 0x1016:1 could not be written. An enable tries it all again.
    """
    node_id = drive.node_id
    if settings.abort_connection is None:
        return
    entry = consumer_entry(settings.heartbeat_node_id, round(settings.consumer_time * 1000))
    written = await asyncio.wrap_future(sdo_batch(
        [Access(node_id, cia402.CONSUMER_HEARTBEAT, 1, True, struct.pack('<I', entry))],
        CONSUMER_TIMEOUT))
    if not written[0].success:
        unwatched = (f'its heartbeat consumer (0x1016:1) could not be written '
                     f'({written[0].message}): it would run on if the gateway died')
        with lock:
            drive.unwatched = unwatched
        LOGGER.warning('drive %d: %s; enable is refused until it is written', node_id,
                       unwatched)
        return
    beat_now()
    reaction, unwatched = await _abort_connection(sdo_batch, node_id, settings)
    with lock:
        drive.unwatched = unwatched
    if unwatched:
        LOGGER.warning('drive %d: %s; enable is refused', node_id, unwatched)
        return
    LOGGER.info('drive %d stops by itself %.3f s after the gateway heartbeat (node %d) ends: '
                '0x1016:1 = 0x%08X, 0x6007 = %s', node_id, settings.consumer_time,
                settings.heartbeat_node_id, entry, reaction)


async def _abort_connection(sdo_batch, node_id: int, settings: DriveSettings):
    """Read 0x6007, set it when it is 0; return (its reaction in words, why unwatched or '')."""
    read = await asyncio.wrap_future(sdo_batch(
        [Access(node_id, cia402.ABORT_CONNECTION_OPTION, 0)], CONSUMER_TIMEOUT))
    if not read[0].success:
        # A drive without 0x6007 reacts as its vendor decided (most: fault).
        return f'not readable ({read[0].message}): its own reaction', ''
    code = struct.unpack('<h', bytes(read[0].data[:2]).ljust(2, b'\0'))[0]
    if code != NO_REACTION:
        return f'{code}', ''
    if not settings.abort_connection:
        return '0', ('its abort connection option (0x6007) is 0: it would run on if the '
                     'gateway died; set drives.abort_connection, or write 0x6007')
    set_to = await asyncio.wrap_future(sdo_batch(
        [Access(node_id, cia402.ABORT_CONNECTION_OPTION, 0, True,
                struct.pack('<h', settings.abort_connection))], CONSUMER_TIMEOUT))
    if not set_to[0].success:
        return '0', (f'its abort connection option (0x6007) is 0 (it would run on if the '
                     f'gateway died) and could not be set: {set_to[0].message}')
    return f'{settings.abort_connection} (set from 0 by drives.abort_connection)', ''
