"""Where a move may go, and whether it or a homing ended there, by the position, not the word.

A move's target must lie within the drive's software position limits (0x607D, read once per
drive): a target outside them is refused before anything is sent.

A drive's "target reached" (statusword bit 10) says it finished the set-point it holds, not
that this set-point is the caller's: a set-point committed before its target arrived (or
taken with a stale 0x607A) is finished at once, where the axis stands. So a move succeeds only
when, after target reached for its own set-point, the position read by SDO lies within the
drive's position window (0x6067, read once per drive) of the requested target, and a homing
whose method homes where the axis stands (35, 37) only when the position is the home offset.
"""

import asyncio
from typing import List, Optional, Tuple

from ..sdo.requests import SdoResult
from . import cia402
from .objects import decode

# Aborts that say the drive has no such object (or sub-index): it has none of the setting.
ABSENT = frozenset({0x06020000, 0x06090011})
# CiA 402: 0x6067 = 0xFFFFFFFF switches the drive's position window off.
WINDOW_OFF = 0xFFFFFFFF
# The window, in drive units, for a drive without 0x6067 or with it switched off.
DEFAULT_WINDOW = 10
# Homing methods that make the position where the axis stands the home offset.
HOME_HERE = frozenset({35, 37})


async def position_window(drive, timeout: float) -> int:
    """Return the drive's position window in drive units; once read, kept until a boot.

    A drive without 0x6067, or with it off, gets ``DEFAULT_WINDOW``; a read that failed
    otherwise (a timeout) is tried again at the next move, with the default meanwhile.
    """
    if drive.position_window is None:
        results = await _read_kept(drive, cia402.POSITION_WINDOW, (0,), timeout)
        if results is None:
            return DEFAULT_WINDOW
        result, = results
        if result.success:
            window = decode(cia402.POSITION_WINDOW, result.data)
            drive.position_window = DEFAULT_WINDOW if window == WINDOW_OFF else window
        elif result.abort_code in ABSENT:
            drive.position_window = DEFAULT_WINDOW
        else:
            return DEFAULT_WINDOW
    return drive.position_window


async def velocity_threshold(drive, timeout: float) -> int:
    """Return the velocity the drive regards as 0 (0x606F), 0 when it has none; kept as the window.

    A read that failed (a timeout too) counts as none until the drive is read again: each mode
    change would wait for it again.
    """
    if drive.velocity_threshold is None:
        results = await _read_kept(drive, cia402.VELOCITY_THRESHOLD, (0,), timeout)
        if results is None:
            return 0
        result, = results
        drive.velocity_threshold = (decode(cia402.VELOCITY_THRESHOLD, result.data)
                                    if result.success else 0)
    return drive.velocity_threshold


async def software_limits(drive, timeout: float) -> Optional[Tuple[int, int]]:
    """Return the drive's software position limits (0x607D:1, :2), None when it has none.

    Once read, kept until a boot. A drive without 0x607D, or whose minimum is not below the
    maximum (0, 0 on many drives), has none. A read that failed otherwise raises
    ``LimitsUnknown``: a move is not sent without knowing them.
    """
    if drive.position_limits is None:
        results = await _read_kept(drive, cia402.SOFTWARE_POSITION_LIMIT, (1, 2), timeout)
        if results is None:  # the move ends
            raise LimitsUnknown(f'node {drive.node_id} booted or was lost while its software '
                                f'position limits (0x607D) were read; nothing was sent')
        failed = next((result for result in results if not result.success), None)
        if failed is not None and failed.abort_code not in ABSENT:
            raise LimitsUnknown(f'node {drive.node_id}: its software position limits '
                                f'(0x607D) could not be read ({failed.message}); nothing was '
                                f'sent')
        lowest, highest = (None if failed else decode(cia402.SOFTWARE_POSITION_LIMIT,
                                                      result.data)
                           for result in results)
        drive.position_limits = ((lowest, highest) if failed is None and lowest < highest
                                 else ())
    return drive.position_limits or None


async def _read_kept(drive, index: int, subindexes: Tuple[int, ...],
                     timeout: float) -> Optional[List[SdoResult]]:
    """Read a setting the drive record keeps; None when the drive booted or was lost meanwhile.

    Then what was read is not that drive's: it is not kept.
    """
    reads = drive.read_wanted
    results = await asyncio.wrap_future(drive.objects.read_entries(index, subindexes,
                                                                   timeout))
    return results if drive.read_wanted == reads else None


class LimitsUnknown(Exception):
    """The software position limits could not be read: the message says why."""


def outside_limits(node_id: int, target: int, limits: Optional[Tuple[int, int]]) -> str:
    """Return why ``target`` is refused by ``limits``, or ''."""
    if limits is None or limits[0] <= target <= limits[1]:
        return ''
    return (f'node {node_id}: target {target} is outside its software position limits '
            f'{limits[0]}..{limits[1]} (0x607D, drive units); nothing was sent')


def missed(node_id: int, wanted: int, position: int, window: int,
           acknowledged: Optional[int]) -> str:
    """Return the answer of a move that showed target reached away from its target."""
    set_point = ('could not be read back' if acknowledged is None
                 else f'read back: {acknowledged}')
    return (f'node {node_id} shows target reached at position {position}, not at the '
            f'target {wanted} (position window {window}, all in drive units); its '
            f'set-point (0x607A) {set_point}')
