"""Whether a move or a homing ended where it was asked to, by the position, not the word.

A drive's "target reached" (statusword bit 10) says it finished the set-point it holds, not
that this set-point is the caller's: a set-point committed before its target arrived (or
taken with a stale 0x607A) is finished at once, where the axis stands. So a move succeeds only
when, after target reached for its own set-point, the position read by SDO lies within the
drive's position window (0x6067, read once per drive) of the requested target, and a homing
whose method homes where the axis stands (35, 37) only when the position is the home offset.
"""

import asyncio
from typing import Optional

from . import cia402

# CiA 402: 0x6067 = 0xFFFFFFFF switches the drive's position window off.
WINDOW_OFF = 0xFFFFFFFF
# The window, in drive units, for a drive without 0x6067 or with it switched off.
DEFAULT_WINDOW = 10
# Homing methods that make the position where the axis stands the home offset.
HOME_HERE = frozenset({35, 37})


async def position_window(drive, timeout: float) -> int:
    """Return the drive's position window in drive units; read once, then kept."""
    if drive.position_window is None:
        read = await asyncio.wrap_future(drive.objects.read([cia402.POSITION_WINDOW], timeout))
        window = read.get(cia402.POSITION_WINDOW, WINDOW_OFF)
        drive.position_window = DEFAULT_WINDOW if window == WINDOW_OFF else window
    return drive.position_window


def missed(node_id: int, wanted: int, position: int, window: int,
           acknowledged: Optional[int]) -> str:
    """Return the answer of a move that showed target reached away from its target."""
    set_point = ('could not be read back' if acknowledged is None
                 else f'read back: {acknowledged}')
    return (f'node {node_id} shows target reached at position {position}, not at the '
            f'target {wanted} (position window {window}, all in drive units); its '
            f'set-point (0x607A) {set_point}')
