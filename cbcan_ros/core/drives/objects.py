"""A drive's CiA 402 objects on the bus: by PDO wherever the drive maps them, by SDO otherwise.

Writes go into the drive's receive PDOs as the PDO service read their mapping
(``pdo.nodes``); an object no usable RPDO maps is written by SDO. Which frames carry a write,
and in which order so that its controlword commits nothing early, is ``frames``'s
plan. A PDO carries every object it
maps, so each frame is built from what the gateway last commanded for all of them: a
controlword sent in the same RPDO as the target position and the mode repeats the commanded
target and mode, never a zero the drive would take as a new one. An RPDO mapping a drive
object the gateway has no commanded value for yet is not used (SDO instead).

A synchronous RPDO is used only while the gateway produces SYNC: the PDO service then sends
it right after a SYNC, and the drive applies it at the next one. Without SYNC it would never
be applied, so its objects go by SDO. PDOs of either kind are used only while the drive is
OPERATIONAL (CiA 301: a pre-operational device neither sends nor takes PDOs), and not from
an NMT command of the gateway's that left that state until the drive says OPERATIONAL again;
the gateway never changes a drive's NMT state by itself, so a drive left pre-operational is
run by SDO.
"""

import asyncio
from concurrent.futures import Future
import contextlib
import struct
import threading
from typing import Callable, Dict, FrozenSet, Iterable, List, Optional, Tuple

from ..pdo.mapping import EntryValue
from ..pdo.service import PdoService, REPLACED
from ..sdo.request_queue import answer, resolved
from ..sdo.requests import Access, SdoResult
from . import cia402
from .frames import Frame, frame_data, frame_values, Plan, plan, usable_frames

# Feedback objects: what the gateway reads of a drive, in TPDOs or by SDO.
FEEDBACK = (cia402.STATUSWORD, cia402.MODE_DISPLAY, cia402.POSITION_ACTUAL,
            cia402.VELOCITY_ACTUAL, cia402.TORQUE_ACTUAL)
# Objects the gateway commands: a frame of an RPDO mapping one of them needs its value.
COMMANDED = frozenset({cia402.CONTROLWORD, cia402.MODE, cia402.TARGET_POSITION,
                       cia402.TARGET_VELOCITY, cia402.TARGET_TORQUE,
                       cia402.PROFILE_VELOCITY_OBJECT})
# What is read of a drive when it is first heard and after each boot: its feedback, its
# error and modes, and the commanded values a PDO frame repeats.
INITIAL_READS = (*FEEDBACK, cia402.ERROR_CODE, cia402.SUPPORTED_MODES, *sorted(COMMANDED))
# ``read_held``'s answer when there is nothing to read: one shared future, not one a drive and
# beat of the feedback cycle (2,000 a second at 250 Hz with 8 drives). Done, so never changed.
NOTHING_TO_READ = resolved(None)


def encode(index: int, value: int) -> bytes:
    """Return ``value`` of a drive object as its SDO bytes; ValueError when it does not fit."""
    try:
        return struct.pack(cia402.FORMATS[index], value)
    except struct.error:
        raise ValueError(f'{value} does not fit 0x{index:04X} '
                         f'({cia402.FORMATS[index]})') from None


def decode(index: int, data: bytes) -> int:
    """Return the value of a drive object from its SDO bytes (short ones padded)."""
    size = struct.calcsize(cia402.FORMATS[index])
    return struct.unpack(cia402.FORMATS[index], bytes(data[:size]).ljust(size, b'\0'))[0]


def feedback_decoder(mapping) -> Callable[[bytes], Dict[int, int]]:
    """Return what takes the feedback objects out of a frame of TPDO ``mapping``.

    By the profile's types, as :func:`decode` reads them: without an EDS the PDO service
    takes every entry as unsigned, and a position below 0 would read as 2**32 - x. Worked
    out once a mapping: the bus thread runs it for every frame.
    """
    fields = []
    for entry in mapping.entries:
        if entry.index in FEEDBACK and entry.subindex == 0:
            width = 8 * struct.calcsize(cia402.FORMATS[entry.index])
            signed = cia402.FORMATS[entry.index][-1].islower()
            fields.append((entry.index, entry.offset, (1 << min(entry.bits, width)) - 1,
                           width if signed else 0))
    size = mapping.size

    def values(data: bytes) -> Dict[int, int]:
        frame = int.from_bytes(data[:size], 'little')
        found = {}
        for index, offset, mask, signed_width in fields:
            value = (frame >> offset) & mask
            if signed_width and value >> (signed_width - 1):
                value -= 1 << signed_width
            found[index] = value
        return found
    return values


def all_of(futures: List[Future]) -> 'Future[SdoResult]':
    """Return a future of the first failure among ``futures`` (SdoResults), else success."""
    if not futures:
        return resolved(SdoResult.ok())
    if len(futures) == 1:
        return futures[0]
    done: Future = Future()
    remaining = [len(futures)]
    lock = threading.Lock()

    def collect(_finished: Future) -> None:
        with lock:
            remaining[0] -= 1
            last = remaining[0] == 0
        if last:
            results = [future.result() for future in futures]
            answer(done, next((r for r in results if not r.success), results[0]))

    for future in futures:
        future.add_done_callback(collect)
    return done


class DriveObjects:
    """The objects of drive ``node_id``: commanded values kept, reads and writes routed.

    ``sdo_batch`` is the gateway's (its SDO channels and write protection), ``pdo`` its PDO
    service, ``sync_producing()`` whether the gateway produces SYNC now, ``operational()``
    whether the drive's PDOs are usable (``HeartbeatMonitor.operational``).
    """

    def __init__(self, node_id: int, pdo: PdoService, sdo_batch, sync_producing,
                 operational):
        self.node_id = node_id
        self._operational = operational
        self._pdo = pdo
        self._sdo_batch = sdo_batch
        self._sync_producing = sync_producing
        self._lock = threading.RLock()  # a future resolved at once runs callbacks under it
        self.commanded: Dict[int, int] = {}
        # Whether the drive has shown a position within its window of the position target
        # last commanded, since it was: a CSP stop holds there only until the axis left it.
        self.position_target_shown = False
        # Objects its RPDOs map that the gateway does not command, as read from the drive
        # after the mapping read number ``_held_reads`` (-1: to be read).
        self._held: Dict[Tuple[int, int], bytes] = {}
        self._held_reads = -1
        self._writes = 0  # writes begun, numbered
        self._controlword_write = 0  # the number of the latest write with a controlword
        self._target_writes: Dict[int, int] = {}  # object: the latest replaceable write of it
        # Plans made on the RPDO mappings and held bytes ``_plans_for`` (the PDO service and
        # this class replace those, never change them): a stream of targets plans once.
        self._plans: Dict[tuple, Plan] = {}
        self._plans_for: Tuple[object, object] = (None, None)
        self._feedback_of: Tuple[object, bool] = (None, False)
        self._feedback_found: Tuple[FrozenSet[int], int] = (frozenset(), 0)

    def forget(self) -> None:
        """Drop the commanded values (the drive booted: they are read again)."""
        with self._lock:
            self.commanded.clear()
            self.position_target_shown = False
            self._held, self._held_reads = {}, -1

    def know(self, values: Dict[int, int]) -> None:
        """Take ``values`` as what the drive has now, without sending them."""
        with self._lock:
            self.commanded.update(values)
            if cia402.TARGET_POSITION in values:
                self.position_target_shown = False

    def saw_position(self, position: int, window: int) -> None:
        """Note a position the drive showed: whether it stood at its position target."""
        if self.position_target_shown:
            return  # most TPDOs: no lock (a new target resets it under the lock)
        with self._lock:
            target = self.commanded.get(cia402.TARGET_POSITION)
            if target is not None and abs(position - target) <= window:
                self.position_target_shown = True

    def mapped_feedback(self) -> FrozenSet[int]:
        """Return the feedback objects the drive sends in an enabled, usable TPDO.

        A synchronous TPDO is sent only after a SYNC: while the gateway produces none, its
        objects are read by SDO (another master's SYNC is not counted on).
        """
        return self._feedback()[0]

    def tpdos_every_sync(self) -> int:
        """Return how many TPDOs with feedback the drive sends after every SYNC (type 1)."""
        return self._feedback()[1]

    def _feedback(self) -> Tuple[FrozenSet[int], int]:
        if not self._pdo.serves(self.node_id) or not self._operational():
            return frozenset(), 0
        tpdos = self._pdo.transmit_mappings(self.node_id)
        producing = self._sync_producing()
        with self._lock:  # worked out once a mapping read (the feedback cycle asks each beat)
            if self._feedback_of[0] is not tpdos or self._feedback_of[1] != producing:
                usable = [[entry.index for entry in mapping.entries
                           if entry.index in FEEDBACK and entry.subindex == 0]
                          for mapping in tpdos.values()
                          if mapping.enabled and not mapping.problem
                          and (producing or not mapping.synchronous)]
                every_sync = sum(1 for mapping in tpdos.values()
                                 if mapping.enabled and not mapping.problem and producing
                                 and mapping.transmission_type == 1
                                 and any(entry.index in FEEDBACK and entry.subindex == 0
                                         for entry in mapping.entries))
                self._feedback_of = (tpdos, producing)
                self._feedback_found = (frozenset(index for indexes in usable
                                                  for index in indexes), every_sync)
            return self._feedback_found

    def mapping_reads(self) -> int:
        """Return how many times the PDO service read the drive's mapping (0: none)."""
        return self._pdo.mapping_reads(self.node_id) if self.node_id in self._pdo.node_ids else 0

    def write(self, values: Dict[int, int], timeout: float, stream: float = 0.0,
              replaceable: bool = False) -> 'Future[SdoResult]':
        """Send ``values`` (object: value) to the drive; resolves when all went out or why not.

        Frames are chosen and ordered by ``frames.plan``: what no usable RPDO carries
        goes by SDO first, the controlword last. Raises ValueError when a value does not fit
        its object (nothing is sent then). The caller holds the drive's ``sending`` lock:
        frames built from ``commanded`` go out in the order it changed. A part that waits
        (for an SDO confirmation or a SYNC) is not sent when a later write changed the
        controlword meanwhile: the drive has that one, and this write is answered failed.
        ``stream``: the write is a target of a stream (``PdoService.write``). ``replaceable``:
        a target that a newer one of the same objects replaces while it waits to go by SDO.
        """
        data = {index: encode(index, value) for index, value in values.items()}
        with self._lock:
            previous = self.commanded.get(cia402.CONTROLWORD)
            self.know(values)
            commanded = dict(self.commanded)
            self._writes += 1
            if cia402.CONTROLWORD in values:
                self._controlword_write = self._writes
            write = self._writes
            if replaceable:
                self._target_writes.update(dict.fromkeys(values, write))
        chosen = self._plan(list(values), commanded, previous is not None)
        frames = list(chosen.frames)
        last = (frames.pop() if cia402.CONTROLWORD in values and frames else None)
        steps = []
        if chosen.by_sdo:
            steps.append(lambda: self._write_by_sdo(
                [(index, data[index]) for index in chosen.by_sdo], timeout,
                None if cia402.CONTROLWORD in values else write, replaceable))
        if frames:
            steps.append(lambda: self._send_frames(frames, previous, write, last is None,
                                                   stream))
        if last is not None:
            steps.append(lambda: self._send_frames([last], previous, write, True))
        return _chain(steps)

    def _send_frames(self, frames: List[Frame], previous: Optional[int], write: int,
                     carry_controlword: bool, stream: float = 0.0) -> 'Future[SdoResult]':
        """Send ``frames`` of write number ``write`` (the last one with its controlword).

        Checked and sent under the lock a stop by SDO takes too (``write_by_sdo``): a part
        that waited is sent before the stop, or not at all. The write's controlword, once
        sent, goes into the drive's other RPDO frames (``PdoService.carry``): one of them
        waiting for SYNC with an older controlword would undo it.
        """
        with self._lock:
            if self._controlword_write > write:
                return resolved(SdoResult.failed(
                    f'node {self.node_id}: a later command changed the controlword before '
                    f'this one was sent in full; the rest was not sent'))
            commanded, held = self.commanded, self._held
            if not all(all(map(held.__contains__, frame.held))
                       and all(map(commanded.__contains__, frame.indexes))
                       for frame in frames):
                return resolved(SdoResult.failed(
                    f'node {self.node_id} booted before this command was sent in full; the '
                    f'rest was not sent'))
            futures = []
            for frame in frames:
                carried = frame_values(frame, commanded, previous, carry_controlword)
                if frame.layout is not None:
                    futures.append(self._pdo.write(self.node_id, frame.number,
                                                   data=frame_data(frame, carried, held),
                                                   stream=stream))
                    continue
                # As bytes of the profile's types, whatever type the PDO service knows.
                futures.append(self._pdo.write(self.node_id, frame.number, [
                    EntryValue(index, 0, data=encode(index, value))
                    for index, value in carried.items()] + [
                    EntryValue(index, sub, data=held[(index, sub)])
                    for index, sub in frame.held], stream=stream))
            if carry_controlword and write == self._controlword_write:
                # A synchronous controlword frame is applied a SYNC after the frames before
                # it: the others are not sent again at once, or the controlword would come
                # with them, early; waiting ones go out with it all the same. A stop is sent
                # again at once all the same: early is what it wants, and a frame the drive
                # holds with an older controlword, sent again only after the stop's, would be
                # applied after it at a SYNC (another master's) that came between the two.
                word = commanded[cia402.CONTROLWORD]
                self._pdo.carry(self.node_id,
                                [EntryValue(cia402.CONTROLWORD, 0,
                                            data=encode(cia402.CONTROLWORD, word))],
                                skip={frame.number for frame in frames},
                                resend=not frames[-1].synchronous or cia402.stops(word))
        return all_of(futures)

    def write_by_sdo(self, values: Dict[int, int], timeout: float) -> 'Future[SdoResult]':
        """Send ``values`` by SDO whatever the PDOs map (applied at once, with an answer).

        A controlword among them ends what an earlier write still had to send.
        """
        data = [(index, encode(index, value)) for index, value in values.items()]
        with self._lock:
            self.commanded.update(values)
            self._writes += 1
            if cia402.CONTROLWORD in values:
                self._controlword_write = self._writes
            return self._write_by_sdo(data, timeout)

    def value(self, index: int) -> Optional[int]:
        """Return the value last commanded (or read) of ``index``, None when unknown."""
        with self._lock:
            return self.commanded.get(index)

    def read_entries(self, index: int, subindexes: Iterable[int],
                     timeout: float) -> 'Future[List[SdoResult]]':
        """Read sub-entries of object ``index`` by SDO; resolves to one SdoResult each."""
        return self._sdo_batch([Access(self.node_id, index, sub) for sub in subindexes],
                               timeout)

    def read_initial(self, timeout: float) -> 'Future[Dict[int, int]]':
        """Read what the gateway needs of a drive it now hears (see ``know_commanded``)."""
        return self.read(INITIAL_READS, timeout)

    async def mapping_known(self, timeout: float) -> None:
        """Wait until the PDO mapping being read (and what its RPDOs hold) is known.

        Until then the drive is run by SDO: a mapping read takes some 0.1 s a device, one
        device after the other, and a drive enabled meanwhile would take its first targets
        by SDO (applied at once, not at a SYNC). Gives up after ``timeout`` (the drive is
        then run by SDO until the read is done).
        """
        if self.node_id not in self._pdo.node_ids:
            return
        with contextlib.suppress(TimeoutError):
            # Known already at nearly every command: no wait (each a few turns of the loop).
            read = self._pdo.mapping_read(self.node_id)
            if not read.done():
                await asyncio.wait_for(asyncio.wrap_future(read), timeout)
            held = self.read_held(timeout)
            if not held.done():
                await asyncio.wait_for(asyncio.wrap_future(held), timeout)

    def read_held(self, timeout: float) -> 'Future[None]':
        """Read what its RPDOs map and the gateway has no value of, when not yet.

        Once per mapping read (and again after a boot), and at each poll while a read
        failed: the objects the gateway does not command, whose bytes go into every frame of
        those RPDOs as the drive holds them (``frames.usable_frames``), and the commanded
        ones the initial read missed (a request that timed out on a busy bus). Until they
        are read, those RPDOs are not used: the controlword goes by SDO. Resolves once they
        are read (at once when there is nothing to read).
        """
        reads = self.mapping_reads()
        with self._lock:
            if not reads or reads == self._held_reads:
                return NOTHING_TO_READ
            self._held_reads = reads
            known = set(self.commanded)
        _, rpdos = self._pdo.mappings(self.node_id)
        mapped = {(entry.index, entry.subindex) for mapping in rpdos.values()
                  for entry in mapping.entries if not entry.dummy}
        others = sorted(key for key in mapped if key[1] != 0 or key[0] not in COMMANDED)
        unknown = sorted(index for index, subindex in mapped
                         if subindex == 0 and index in COMMANDED and index not in known)
        if not others and not unknown:
            return NOTHING_TO_READ
        batch = self._sdo_batch([Access(self.node_id, index, sub) for index, sub in others]
                                + [Access(self.node_id, index, 0) for index in unknown],
                                timeout)
        done: Future = Future()

        def keep(finished: Future) -> None:
            results = finished.result()
            with self._lock:
                if self._held_reads != reads:  # read again meanwhile, or it booted
                    answer(done, None)
                    return
                self._held = {key: bytes(result.data) for key, result
                              in zip(others, results[:len(others)], strict=True)
                              if result.success}
                # A value commanded since the request went out is the newer one.
                self.know({index: decode(index, result.data) for index, result
                           in zip(unknown, results[len(others):], strict=True)
                           if result.success and index not in self.commanded})
                if (len(self._held) < len(others)
                        or any(index not in self.commanded for index in unknown)):
                    self._held_reads = -1  # a read failed: tried again at the next poll
            answer(done, None)
        batch.add_done_callback(keep)
        return done

    def hold(self, index: int, subindex: int, data: bytes) -> Optional[Callable[[], None]]:
        """Take ``data`` as what the drive holds in ``index:subindex``, as it is written.

        An object its RPDOs map and the gateway does not command (``read_held``), by a
        caller's SDO write through the gateway (a lower max torque, an offset), from
        the moment it is sent: a frame built from the copy read when the drive was heard,
        even one sent just after the drive confirmed the write, would undo it. Return what
        puts the copy back, for a write that failed; None when no frame carries the object.
        """
        key = (index, subindex)
        with self._lock:
            previous = self._held.get(key)
            if previous is None:
                return None
            self._held = {**self._held, key: bytes(data)}  # replaced, never changed (_plan)
        self._pdo.carry(self.node_id, [EntryValue(index, subindex, data=bytes(data))])

        def put_back() -> None:
            with self._lock:
                if self._held.get(key) != bytes(data):
                    return  # written again (or the drive read again) since
                self._held = {**self._held, key: previous}
            self._pdo.carry(self.node_id, [EntryValue(index, subindex, data=previous)])
        return put_back

    def know_commanded(self, values: Dict[int, int]) -> None:
        """Take the commanded objects among ``values`` (an initial read) as the drive's now."""
        self.know({index: value for index, value in values.items() if index in COMMANDED})

    def read(self, indexes: Iterable[int], timeout: float) -> 'Future[Dict[int, int]]':
        """Read ``indexes`` by SDO; resolves to the values read (failed ones left out)."""
        indexes = list(indexes)
        batch = self._sdo_batch([Access(self.node_id, index, 0) for index in indexes],
                                timeout)
        done: Future = Future()

        def collect(finished: Future) -> None:
            answer(done, {index: decode(index, result.data) for index, result
                             in zip(indexes, finished.result(), strict=True)
                             if result.success})

        batch.add_done_callback(collect)
        return done

    def _write_by_sdo(self, data, timeout: float, write: Optional[int] = None,
                      replaceable: bool = False) -> 'Future[SdoResult]':
        """Write ``data`` by SDO (object, bytes); resolves to the first failure, else success.

        Of write number ``write`` (None: always), only while no later write changed the
        controlword: a target waiting in the device's SDO queue as a halt or a stop goes out
        must not follow it. A ``replaceable`` target, only while no newer target of the same
        object came (``REPLACED``): targets at a control rate by SDO would fill the device's
        queue, and what waits behind them (its PDO mapping read) would time out.
        """
        if self.node_id in self._pdo.node_ids:  # no RPDO frame may undo it
            self._pdo.carry(self.node_id, [EntryValue(index, 0, data=value)
                                                    for index, value in data])

        def superseded(_results) -> Optional[str]:
            with self._lock:
                later = self._controlword_write > write
                replaced = replaceable and any(self._target_writes.get(index, 0) > write
                                               for index, _ in data)
            if later:
                return (f'node {self.node_id}: a later command changed the controlword before '
                        f'this write was sent')
            return f'node {self.node_id}: {REPLACED}' if replaced else None
        batch = self._sdo_batch([Access(self.node_id, index, 0, True, value)
                                 for index, value in data], timeout,
                                None if write is None else superseded)
        done: Future = Future()
        batch.add_done_callback(lambda finished: answer(done, next(
            (result for result in finished.result() if not result.success),
            SdoResult.ok())))
        return done

    def applied_at_sync(self, index: int) -> bool:
        """Return whether a write of ``index`` goes now in a synchronous RPDO."""
        chosen = self._plan_now([index])
        return any(frame.synchronous and index in frame.indexes for frame in chosen.frames)

    def timing(self, indexes: Iterable[int]) -> Tuple[bool, bool]:
        """Return whether a write of ``indexes`` now has parts applied (at once, at a SYNC).

        At once: what goes by SDO or in an event-driven RPDO; at the next SYNC: what goes
        in a synchronous RPDO.
        """
        chosen = self._plan_now(list(dict.fromkeys(indexes)))
        return (bool(chosen.by_sdo) or any(not frame.synchronous for frame in chosen.frames),
                any(frame.synchronous for frame in chosen.frames))

    def _plan_now(self, indexes: List[int]) -> Plan:
        """Return how a write of ``indexes`` would go out now, its values as commanded."""
        with self._lock:
            commanded = {**dict.fromkeys(indexes, 0), **self.commanded}
        return self._plan(indexes, commanded, cia402.CONTROLWORD in commanded)

    def _plan(self, indexes: List[int], commanded: Dict[int, int],
              controlword_known: bool) -> Plan:
        """Return how a write of ``indexes`` goes out now (``frames.plan``)."""
        if not self._pdo.serves(self.node_id) or not self._operational():
            return plan(indexes, (), controlword_known)
        rpdos = self._pdo.receive_mappings(self.node_id)
        producing = self._sync_producing()
        key = (tuple(indexes), frozenset(commanded), controlword_known, producing)
        with self._lock:
            held = self._held
            if self._plans_for[0] is not rpdos or self._plans_for[1] is not held:
                self._plans, self._plans_for = {}, (rpdos, held)
            chosen = self._plans.get(key)
            if chosen is None:
                chosen = self._plans[key] = plan(
                    indexes, usable_frames(rpdos, commanded, producing, held),
                    controlword_known)
        return chosen


def _chain(steps: List[Callable[[], 'Future[SdoResult]']]) -> 'Future[SdoResult]':
    """Run ``steps`` one after the other, each once the one before succeeded.

    Resolves to the first failure, else to success once the last step's future resolved.
    """
    if not steps:
        return resolved(SdoResult.ok())
    try:
        first = steps[0]()
    except Exception as error:  # noqa: BLE001 - a step run from a callback must be answered
        return resolved(SdoResult.failed(f'the write could not go on: {error!r}'))
    if len(steps) == 1:
        return first
    done: Future = Future()

    def go_on(finished: Future) -> None:
        result = finished.result()
        if not result.success:
            answer(done, result)
            return
        _chain(steps[1:]).add_done_callback(lambda rest: answer(done, rest.result()))

    first.add_done_callback(go_on)
    return done
