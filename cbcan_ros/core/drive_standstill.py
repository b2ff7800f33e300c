"""When a halted drive stands: judged only by what the drive showed after it took the halt.

Feedback the gateway takes just after it sent a halt may have left the drive before the halt
reached it: frames in flight, or still in the gateway's own queue. Such a statusword can say
"target velocity reached" of an axis running at its target, next to a velocity from before
the motion began. So the wait starts with an SDO read of the statusword and the velocity: the
drive answers it after it took the frames sent to it before, and the gateway takes frames in
the order they came, so those values and every velocity taken after them are from after the
halt (a synchronous RPDO's halt is applied at the next SYNC: until then they show the axis as
it is, which the halt only slows).

Bit 10 says a halted axis stands in the profile modes. In the cyclic modes (CSP, CSV, CST)
CiA 402 leaves it to the vendor and many drives never set it there: a velocity of 0 does.
"""

import asyncio
from typing import Callable

from . import cia402

STANDSTILL_READS = [cia402.STATUSWORD, cia402.VELOCITY_ACTUAL]


def stands(statusword: int, velocity: int, mode: int) -> bool:
    """Return whether a halted drive's statusword and velocity show its axis standing."""
    return velocity == 0 and (mode in cia402.CYCLIC_MODES
                              or bool(statusword & cia402.TARGET_REACHED))


async def wait_for_standstill(service, drive, until: Callable, read_timeout: float) -> None:
    """Return once ``drive``, halted, stands; ``until(drive, ok)`` waits for a status.

    ``service`` is the drive service (``read_feedback``, ``status``). Velocities come by TPDO
    or by the SDO polls of what no TPDO brings, each waking the wait.
    """
    read = await asyncio.wrap_future(service.read_feedback(drive, STANDSTILL_READS,
                                                           read_timeout))
    updates, velocities = drive.updates, drive.velocities
    mode = service.status(drive.node_id).mode
    if cia402.VELOCITY_ACTUAL in read and stands(read.get(cia402.STATUSWORD, 0),
                                                 read[cia402.VELOCITY_ACTUAL], mode):
        return

    def standing(status) -> bool:
        if drive.velocities <= velocities:
            return False  # no velocity since the read
        word = status.statusword if drive.updates > updates else read.get(cia402.STATUSWORD, 0)
        return stands(word, status.velocity, mode)
    await until(drive, standing)
