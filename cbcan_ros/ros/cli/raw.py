"""The raw CAN commands of ``cbcan_cli``: dump (as candump) and send (as cansend).

``dump`` prints what the gateway publishes on ``~/from_can_bus`` (its ``raw.filters``), one
line a frame, CANopen frames named by their COB-ID: ``0x705 [1] 05  heartbeat node 5
OPERATIONAL``. ``send`` takes cansend's ``ID#DATA`` and sends through ``~/send_frames``, so
it learns that the frames went out, or why not.
"""

import re
from typing import List, Optional

from ...core.nmt import COMMAND_NAMES, reported_state_name
from ...core.raw.filters import FILTER_FORMAT, parse_filters
from ...core.text import quoted
from ...msg import CanFrame
from ...srv import SendFrames
from ..raw_frames import RAW_QOS
from .arguments import ranged
from .errors import print_refusal, UsageError
from .standalone_client import Client

# cansend's frame: 3 hex digits standard, 8 extended; data as hex bytes, optionally dotted;
# R for a remote frame, with its length digit.
FRAME = re.compile(r'(?P<id>[0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})#'
                   r'(?:(?P<remote>[Rr])(?P<length>[0-8])?|(?P<data>(?:[0-9A-Fa-f]{2}\.?)*))')
FRAME_FORMAT = ("cansend's ID#DATA: 3 hex digits for a standard id, 8 for an extended one, up "
                "to 8 data bytes in hex (dots allowed between them), or ID#R for a remote "
                "frame (ID#R4: asking for 4 bytes), e.g. 7F0#DEADBEEF, 18FF0001#01.02, 7F1#R")

# COB-ID ranges of CiA 301 (the function code is the id's top 4 bits), by their first id.
PDO_NAMES = {0x180: 'TPDO1', 0x200: 'RPDO1', 0x280: 'TPDO2', 0x300: 'RPDO2',
             0x380: 'TPDO3', 0x400: 'RPDO3', 0x480: 'TPDO4', 0x500: 'RPDO4'}
SDO_COMMANDS = {1: 'write', 2: 'read'}  # initiate download / upload, as the client asks


def _node_range(can_id: int, base: int) -> Optional[int]:
    node_id = can_id - base
    return node_id if 1 <= node_id <= 127 else None


def _sdo(direction: str, node_id: int, data: bytes) -> str:
    text = f'SDO {direction} node {node_id}'
    if not data:
        return text
    command = data[0] >> 5
    if command == 4 and len(data) >= 8:
        return f'{text} abort 0x{int.from_bytes(data[4:8], "little"):08X}'
    if len(data) >= 4 and (direction == 'request' and command in SDO_COMMANDS or
                           direction == 'answer' and command in (2, 3)):
        what = SDO_COMMANDS.get(command, 'read') if direction == 'request' else \
            ('read' if command == 2 else 'write ok')
        return f'{text} {what} 0x{data[1] | data[2] << 8:04X}:{data[3]:02X}'
    return text


def canopen_name(can_id: int, data: bytes, remote: bool = False) -> str:
    """Return what a standard frame is in CANopen (CiA 301, 305) by its COB-ID, or ''."""
    if can_id == 0x000:
        if len(data) >= 2:
            command = COMMAND_NAMES.get(data[0], f'0x{data[0]:02X}')
            return f'NMT {command} node {data[1] or "all"}'
        return 'NMT'
    if can_id == 0x080:
        return f'SYNC {data[0]}' if data else 'SYNC'
    if can_id == 0x100:
        return 'TIME'
    if can_id in (0x7E4, 0x7E5):
        return 'LSS answer' if can_id == 0x7E4 else 'LSS request'
    for base, name in PDO_NAMES.items():
        node_id = _node_range(can_id, base)
        if node_id:
            return f'{name} node {node_id}'
    for base, kind in ((0x080, 'EMCY'), (0x580, 'answer'), (0x600, 'request'),
                       (0x700, 'heartbeat')):
        node_id = _node_range(can_id, base)
        if not node_id:
            continue
        if kind == 'EMCY':
            code = f' 0x{data[0] | data[1] << 8:04X}' if len(data) >= 2 else ''
            return f'EMCY node {node_id}{code}{" (error reset)" if code == " 0x0000" else ""}'
        if kind == 'heartbeat':
            if remote:
                return f'node guarding request node {node_id}'
            state = f' {reported_state_name(data[0] & 0x7F)}' if data else ''
            return f'heartbeat node {node_id}{state}'
        return _sdo(kind, node_id, data)
    return ''


def describe_frame(message) -> str:
    """Return one line for a frame of ~/from_can_bus, as candump shows it, CANopen named."""
    if message.is_error:
        return f'0x{message.id:08X} [{message.dlc}] error frame (class 0x{message.id:X})'
    data = bytes(message.data[:message.dlc])
    can_id = f'0x{message.id:08X}' if message.is_extended else f'0x{message.id:03X}'
    body = 'remote request' if message.is_rtr else data.hex(' ').upper()
    name = '' if message.is_extended else canopen_name(message.id, data, message.is_rtr)
    return f'{can_id} [{message.dlc}] {body}{"  " + name if name else ""}'.rstrip()


def parse_frame(text: str) -> CanFrame:
    """Return the frame of one cansend ``ID#DATA``; raise UsageError saying why not."""
    match = FRAME.fullmatch(text.strip())
    if match is None:
        raise UsageError(f'{quoted(text)} is not a frame: {FRAME_FORMAT}')
    extended = len(match['id']) == 8
    can_id = int(match['id'], 16)
    if match['remote']:
        return CanFrame(id=can_id, is_extended=extended, is_rtr=True,
                        dlc=int(match['length'] or 0))
    data = bytes.fromhex(match['data'].replace('.', ''))
    if len(data) > 8:
        raise UsageError(f'{quoted(text)} has {len(data)} data bytes: at most 8')
    return CanFrame(id=can_id, is_extended=extended, dlc=len(data),
                    data=list(data.ljust(8, b'\0')))


def cmd_dump(client: Client, args) -> int:
    """Print every frame the gateway publishes (those of ``FILTER``s only, if given)."""
    try:
        filters = parse_filters(args.filters)
    except ValueError as error:
        raise UsageError(f'FILTER {error}; allowed: {FILTER_FORMAT}') from None
    if not [text for text in client.parameter('raw.filters') or [] if text.strip()]:
        raise UsageError(f'{client.gateway} publishes no raw frames: its parameter '
                         f'raw.filters is empty (["0:0"] publishes every standard frame)')

    shown = [0]

    def show(message) -> None:
        if filters.empty or filters.matches(message.id, message.is_extended, message.is_rtr,
                                            message.is_error):
            print(describe_frame(message), flush=True)
            shown[0] += 1
            if shown[0] == args.count:
                raise _Enough

    from can_msgs.msg import Frame  # only here: the other commands run without can_msgs
    try:
        client.follow(Frame, 'from_can_bus', RAW_QOS, show)
    except _Enough:
        pass
    return 0


class _Enough(Exception):
    """``--count`` frames were shown (the frames filtered out do not count)."""


def cmd_send(client: Client, args) -> int:
    """Send the frames given, in order, through ~/send_frames."""
    frames: List[CanFrame] = [parse_frame(text) for text in args.frames]
    response = client.call(SendFrames, 'send_frames', SendFrames.Request(frames=frames),
                           client.wait)
    if not response.success:
        return print_refusal(response)
    print(f'ok: {response.sent} frame{"s" * (response.sent != 1)} sent')
    return 0


def add_commands(commands) -> None:
    """Add dump and send."""
    dump = commands.add_parser('dump', help='print the raw CAN frames the gateway publishes',
                               description='Print the frames the gateway publishes on '
                                           '~/from_can_bus (its parameter raw.filters decides '
                                           'which), one line a frame, as candump does; '
                                           'CANopen frames are named by their COB-ID. Ctrl-C '
                                           'ends it.')
    dump.add_argument('filters', nargs='*', metavar='FILTER',
                      help=f'show only these frames: {FILTER_FORMAT}')
    dump.add_argument('--count', type=ranged('count', 0, 1 << 31), default=0, metavar='N',
                      help='stop after N frames (default 0: until Ctrl-C)')
    dump.set_defaults(run=cmd_dump)

    send = commands.add_parser('send', help='send raw CAN frames (cansend syntax)',
                               description='Send raw CAN frames through the gateway, in the '
                                           'order given, all or none (its parameter '
                                           'raw.send_allow says which ids may go).')
    send.add_argument('frames', nargs='+', metavar='ID#DATA', help=FRAME_FORMAT)
    send.set_defaults(run=cmd_send)
