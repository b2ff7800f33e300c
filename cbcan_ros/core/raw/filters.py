"""Which raw CAN frames pass: candump's filter syntax, parsed and matched.

The raw CAN bridges of ROS (ros2_socketcan's ``filters``) and candump take the same filters,
so a robotics engineer's filters carry over unchanged. Each filter is hex without ``0x``:

- ``id:mask`` matches a frame when ``frame id & mask == id & mask``;
- ``id~mask`` matches a frame when ``frame id & mask != id & mask``;
- ``#errmask`` matches error frames whose error class has a bit of ``errmask``
  (linux/can/error.h; an error frame that names no class is matched by any mask);
- ``j`` joins the id filters: a frame must match every one, not any one.

An id of 1 to 3 hex digits (``000``..``7FF``) names standard (11-bit) frames only, one of
exactly 8 digits extended (29-bit) frames only, as candump sets its ``CAN_EFF_FLAG`` for 8
digits; ``0:0`` is every standard frame and ``00000000:00000000`` every extended one. The
mask's bit ``40000000`` (SocketCAN's ``CAN_RTR_FLAG``) compares the remote flag too, so
``123:400007FF`` takes data frames of 0x123 only; its other flag bits change nothing. Several
filters may share one string separated by commas, as ros2_socketcan's parameter holds them.
"""

from dataclasses import dataclass
import re
from typing import Iterable, Optional, Tuple

STANDARD_MASK = 0x7FF
EXTENDED_MASK = 0x1FFFFFFF
RTR_FLAG = 0x40000000  # linux/can.h CAN_RTR_FLAG, as candump's masks carry it

FILTER_FORMAT = ("candump filters, hex without 0x: 'id:mask' (id & mask equal), 'id~mask' "
                 "(not equal), '#errmask' (error frames), 'j' (every filter must match); an "
                 "id of 1-3 digits (up to 7FF) names standard frames, one of 8 digits "
                 "extended frames; e.g. '0:0' (every standard frame), '180:780', "
                 "'18FF0000:1FFF0000', '#FFFFFFFF'")

_HEX = re.compile(r'[0-9A-Fa-f]{1,8}')


@dataclass(frozen=True)
class IdFilter:
    """One ``id:mask`` or ``id~mask`` filter."""

    can_id: int
    mask: int  # the id bits compared, and RTR_FLAG when the remote flag is compared
    extended: bool
    inverted: bool = False

    @property
    def exact(self) -> bool:
        """Return whether this filter names one id only (the full mask, not inverted)."""
        full = EXTENDED_MASK if self.extended else STANDARD_MASK
        return not self.inverted and self.mask & full == full

    def matches(self, can_id: int, extended: bool, remote: bool) -> bool:
        """Return whether a data or remote frame passes this filter."""
        if extended != self.extended:
            return False
        value = can_id | RTR_FLAG if remote else can_id
        return ((value & self.mask) == (self.can_id & self.mask)) != self.inverted

    def __str__(self) -> str:
        width = 8 if self.extended else 3
        return f'{self.can_id:0{width}X}{"~" if self.inverted else ":"}{self.mask:X}'


@dataclass(frozen=True)
class FrameFilters:
    """Parsed filters: which frames a set of them lets through.

    Empty, it lets nothing through: the raw bridge is off.
    """

    ids: Tuple[IdFilter, ...] = ()
    error_mask: int = 0
    join: bool = False

    @property
    def empty(self) -> bool:
        """Return whether no frame at all passes."""
        return not self.ids and not self.error_mask

    def matches(self, can_id: int, extended: bool, remote: bool, error: bool) -> bool:
        """Return whether a received frame passes (error frames only by the error mask)."""
        if error:
            return bool(self.error_mask) and (not can_id or bool(can_id & self.error_mask))
        if not self.ids:
            return False
        if self.join:
            return all(entry.matches(can_id, extended, remote) for entry in self.ids)
        for entry in self.ids:  # (a loop, not any(): this runs for every frame received)
            if entry.matches(can_id, extended, remote):
                return True
        return False


def _hex(text: str, what: str) -> int:
    if text[:2].lower() == '0x':
        raise ValueError(f'{what} {text!r}: hex without 0x, as candump takes it')
    if not _HEX.fullmatch(text):
        raise ValueError(f'{what} {text!r} is not 1 to 8 hex digits')
    return int(text, 16)


def parse_id_filter(text: str) -> IdFilter:
    """Parse one ``id:mask`` or ``id~mask``; raise ValueError saying what is wrong."""
    separator = ':' if ':' in text else '~'
    id_text, found, mask_text = text.partition(separator)
    if not found:
        raise ValueError('not id:mask, id~mask, #errmask or j')
    can_id = _hex(id_text, 'id')
    mask = _hex(mask_text, 'mask')
    extended = len(id_text) == 8
    if not extended and len(id_text) > 3:
        raise ValueError(f'id {id_text!r} has {len(id_text)} digits: 1 to 3 name a standard '
                         f'frame (up to 7FF), exactly 8 an extended one')
    if not extended and can_id > STANDARD_MASK:
        raise ValueError(f'standard id {id_text!r} is above 7FF (give 8 digits for an '
                         f'extended id)')
    if extended and can_id > EXTENDED_MASK:
        raise ValueError(f'extended id {id_text!r} is above 1FFFFFFF')
    full = EXTENDED_MASK if extended else STANDARD_MASK
    return IdFilter(can_id, mask & (full | RTR_FLAG), extended, separator == '~')


def parse_filters(entries: Iterable[str], errors: bool = True) -> FrameFilters:
    """Parse filter strings (each may hold several, comma-separated); blank ones are skipped.

    ``errors``: whether ``#errmask`` and ``j`` are taken (they are for receiving only).
    Raises ValueError naming the filter that does not parse and why.
    """
    ids = []
    error_mask = 0
    join = False
    for entry in entries:
        for text in entry.split(','):
            text = text.strip()
            if not text:
                continue
            try:
                if text in ('j', 'J') or text.startswith('#'):
                    if not errors:
                        raise ValueError('error frames cannot be sent and there is nothing to '
                                         'join: id:mask or id~mask only')
                    if text.startswith('#'):
                        error_mask |= _hex(text[1:], 'error mask')
                    else:
                        join = True
                else:
                    ids.append(parse_id_filter(text))
            except ValueError as error:
                raise ValueError(f'{text[:40]!r}: {error}') from None
    return FrameFilters(tuple(ids), error_mask, join)


def exact_entry(filters: FrameFilters, can_id: int, extended: bool,
                remote: bool) -> Optional[IdFilter]:
    """Return the filter that names this id itself (full mask, not inverted), if one does."""
    for entry in filters.ids:
        if entry.exact and entry.matches(can_id, extended, remote):
            return entry
    return None
