"""When a halted drive stands: judged only by what the drive showed after it took the halt.

Feedback the gateway takes just after it sent a halt may have left the drive before the halt
reached it: frames in flight, or still in the gateway's own queue. Such a statusword can say
"target velocity reached" of an axis running at its target, next to a velocity from before
the motion began. So the wait reads the statusword and the velocity by SDO first: the drive
answers after it took the frames sent to it before the request (while the gateway produces
SYNC, the read waits for the next SYNC, which applies a halt sent in a synchronous RPDO).
What that read shows, and what the drive sends after it, is from after the halt.

In the profile modes the statusword says it: with the halt bit set, bit 10 means the axis
stands (at the drive's own velocity window). In the cyclic modes (CSP, CSV, CST) CiA 402
leaves bit 10 to the vendor and many drives never set it there: a velocity of exactly 0
does (CiA 402 gives every drive with a velocity or torque loop the object, 0x606C).

A standstill the frames do not show within ``REREAD`` (its last frame may have come between
the answer and the wait, and a drive that sends its values only on change sends no more) is
read again by SDO, at that pace.
"""

import asyncio
import contextlib
from typing import Callable, Dict

from . import cia402

STANDSTILL_READS = [cia402.STATUSWORD, cia402.VELOCITY_ACTUAL]
REREAD = 0.5  # s


def read_shows_standing(read: Dict[int, int], mode: int) -> bool:
    """Return whether a statusword and velocity read after a halt show the axis standing."""
    if mode in cia402.CYCLIC_MODES:
        return read.get(cia402.VELOCITY_ACTUAL) == 0
    return bool(read.get(cia402.STATUSWORD, 0) & cia402.TARGET_REACHED)


async def wait_for_standstill(service, drive, until: Callable, read_timeout: float) -> None:
    """Return once ``drive``, halted, stands; ``until(drive, ok)`` waits for a status.

    ``service`` is the drive service (``read_feedback``, ``status``, ``sync``). ``until``
    raises when the drive faults, is lost, or leaves the state its command needs.
    """
    loop = asyncio.get_running_loop()
    applied = loop.create_future()
    if service.sync.after_next_sync(
            lambda: loop.call_soon_threadsafe(lambda: applied.done() or applied.set_result(0))):
        await applied
    while True:
        read = await asyncio.wrap_future(service.read_feedback(drive, STANDSTILL_READS,
                                                               read_timeout))
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(until(drive, _standing_since(
                drive, read, service.status(drive.node_id).mode)), REREAD)
            return


def _standing_since(drive, read: Dict[int, int], mode: int) -> Callable:
    """Return whether a status shows the axis standing, by ``read`` or what came after it."""
    if read_shows_standing(read, mode):
        return lambda status: True
    updates, velocities = drive.updates, drive.velocities
    if mode in cia402.CYCLIC_MODES:
        return lambda status: drive.velocities > velocities and status.velocity == 0
    return lambda status: (drive.updates > updates
                           and bool(status.statusword & cia402.TARGET_REACHED))
