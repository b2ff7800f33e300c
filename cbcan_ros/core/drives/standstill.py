"""When a halted drive stands, in the modes whose statusword says so.

Profile position, profile velocity and homing: judged only by what the drive showed after it
took the halt.

Feedback the gateway takes just after it sent a halt may have left the drive before the halt
reached it: frames in flight, or still in the gateway's own queue. Such a statusword can say
"target velocity reached" of an axis running at its target. So the wait reads the statusword
by SDO first, and then takes only the statuswords that come after that answer. A halt sent in
a synchronous RPDO is applied at the SYNC after the one its frame followed: the read waits for
two SYNCs then (one more than needed, for a frame that went out late).

A drive may still answer that read from its last control cycle, before the halt took effect,
so no sign that can be left over from before the halt counts:

- profile position and homing: bit 10 (with the halt bit set, the drive's own "standing",
  at its velocity window; a moving axis showed 0 there before the halt);
- profile velocity: bit 10 and bit 12 ("speed is 0": an axis at its target velocity showed
  bit 10 before the halt too).

In profile torque and the cyclic modes CiA 402 leaves bit 10 to the vendor, and a velocity
(0x606C) of 0 is no stand either (in units coarser than the position's it reads 0 while the
axis moves): the drive commands judge those by 0x606F or the position (``DriveCommands``).

A standstill the frames do not show within ``REREAD`` (its last frame may have come between
the answer and the wait, and a drive that sends its values only on change sends no more) is
read again by SDO, at that pace.
"""

import asyncio
import contextlib
from typing import Callable, Dict

from . import cia402

STANDSTILL_READS = [cia402.STATUSWORD]
REREAD = 0.5  # s
BY_STATUSWORD = {cia402.PROFILE_POSITION: cia402.TARGET_REACHED,
                 cia402.HOMING: cia402.TARGET_REACHED,
                 cia402.PROFILE_VELOCITY: cia402.TARGET_REACHED | cia402.MODE_BIT_12}


def shows_standing(statusword: int, mode: int) -> bool:
    """Return whether a halted drive's statusword shows it stand (``mode`` in BY_STATUSWORD)."""
    bits = BY_STATUSWORD[mode]
    return statusword & bits == bits


async def wait_for_standstill(service, drive, mode: int, until: Callable,
                              read_timeout: float, just_halted: bool) -> None:
    """Return once ``drive``, halted in ``mode`` (one of ``BY_STATUSWORD``), stands.

    ``service`` is the drive service (``read_feedback``, ``status``, ``sync``); ``until(drive,
    ok)`` waits for a status, and raises when the drive faults, is lost, or leaves the state
    its command needs.
    ``just_halted``: the halt was just handed out (and may wait for a SYNC to apply).
    """
    if just_halted and drive.objects.applied_at_sync(cia402.CONTROLWORD):
        await until_applied_at_sync(service.sync)
    while True:
        read = await asyncio.wrap_future(service.read_feedback(drive, STANDSTILL_READS,
                                                               read_timeout))
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(REREAD):
                await until(drive, _standing_since(drive, read, mode))
            return


async def until_applied_at_sync(sync) -> None:
    """Return once a controlword just sent in a synchronous RPDO is applied.

    The drive applies it at the SYNC after the one its frame followed: two SYNCs, one more
    than needed, for a frame that went out late.
    """
    for _ in range(2):
        await _next_sync(sync)


async def _next_sync(sync) -> None:
    """Return after the next SYNC (at once when none is coming)."""
    loop = asyncio.get_running_loop()
    done = loop.create_future()

    def wake() -> None:
        with contextlib.suppress(RuntimeError):  # the loop closed: shutdown ended the wait
            loop.call_soon_threadsafe(lambda: done.done() or done.set_result(None))
    if sync.after_next_sync(wake):
        await done


def _standing_since(drive, read: Dict[int, int], mode: int) -> Callable:
    """Return whether a status shows the axis standing, by ``read`` or what came after it."""
    if cia402.STATUSWORD in read and shows_standing(read[cia402.STATUSWORD], mode):
        return lambda status: True
    updates = drive.updates
    return lambda status: (drive.updates > updates
                           and shows_standing(status.statusword, mode))
