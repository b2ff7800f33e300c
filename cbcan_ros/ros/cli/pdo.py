"""The PDO commands of ``cbcan_cli``: pdo-echo (a device's TPDOs) and pdo-write (its RPDO)."""

import argparse
import math

from ...core.protocol import MAX_NODE_ID
from ...core.text import quoted
from ...core.values import encode_value, parse_integer
from ...msg import Pdo, PdoEntry
from ...srv import PdoWrite
from ..pdo import PDO_QOS
from .arguments import ranged
from .errors import print_refusal, UsageError
from .object_names import resolve_name
from .standalone_client import Client


def _pdo_value(entry) -> str:
    if entry.index in range(1, 8):
        return 'dummy'
    value = entry.value
    return str(int(value)) if math.isfinite(value) and value.is_integer() else repr(value)


def describe_pdo(message) -> str:
    """Return one line for a received PDO: number, COB-ID, bytes, then each entry's value."""
    entries = ' '.join(f'{entry.name or f"0x{entry.index:04X}:{entry.subindex}"}='
                       f'{_pdo_value(entry)}' for entry in message.entries)
    return (f'TPDO {message.pdo} 0x{message.cob_id:03X} [{len(message.data)}] '
            f'{bytes(message.data).hex(" ").upper()} | {entries}')


def cmd_pdo_echo(client: Client, args) -> int:
    """Print what a device sends (its TPDOs, the gateway's ~/node_<id>/rpdo topic)."""
    client.follow(Pdo, f'node_{args.node}/rpdo', PDO_QOS,
                  lambda message: print(describe_pdo(message), flush=True), args.count)
    return 0


def _pdo_entry(client: Client, args, assignment: str) -> PdoEntry:
    """Return the entry of one NAME_OR_INDEX=VALUE (an index as 0x6040 or 0x6040:0)."""
    target, equals, text = assignment.rpartition('=')
    if not equals or not target.strip() or not text.strip():
        raise UsageError(f'{quoted(assignment)} is not NAME_OR_INDEX=VALUE, e.g. '
                         f'0x6040=15 or "Controlword=15"')
    index_text, _, sub_text = target.partition(':')
    try:
        index, subindex = parse_integer(index_text), parse_integer(sub_text or '0')
    except ValueError:
        args.object = target.strip()
        found, _ = resolve_name(client, args, [])
        index, subindex = found.index, found.subindex
    if not 0 <= index <= 0xFFFF or not 0 <= subindex <= 0xFF:
        raise UsageError(f'{quoted(target)}: index 0x0000..0xFFFF, sub-index 0..255')
    try:
        value = float(parse_integer(text))
    except ValueError:
        try:
            value = float(text)
        except ValueError:
            raise UsageError(f'{quoted(assignment)}: {quoted(text)} is not a number') from None
    return PdoEntry(index=index, subindex=subindex, value=value)


def cmd_pdo_write(client: Client, args) -> int:
    """Send a device's RPDO with the values given (the others keep their last value)."""
    if bool(args.assignments) == bool(args.data):
        raise UsageError('give NAME_OR_INDEX=VALUE assignments or --data HEXBYTES, not both '
                         'nor neither')
    try:
        data = encode_value([args.data], 'hex') if args.data else b''
    except ValueError as error:
        raise UsageError(f'--data: {error}') from None
    entries = [_pdo_entry(client, args, assignment) for assignment in args.assignments]
    response = client.call(PdoWrite, 'pdo_write', PdoWrite.Request(
        node_id=args.node, pdo=args.pdo, entries=entries, data=list(data)), client.wait)
    if not response.success:
        return print_refusal(response)
    print(f'ok: RPDO {args.pdo} of node {args.node} sent')
    return 0


def _pdo_node_argument(command: argparse.ArgumentParser) -> None:
    """Add the NODE of pdo-echo and pdo-write: a device of the gateway's pdo.nodes."""
    command.add_argument('node', type=ranged('node', 1, MAX_NODE_ID), metavar='NODE',
                         help='node id 1..127 (one of the gateway parameter pdo.nodes)')


def add_commands(commands) -> None:
    """Add pdo-echo and pdo-write."""
    echo = commands.add_parser('pdo-echo', help="print a device's PDOs as they arrive",
                               description='Print every PDO a device sends (its TPDOs, on '
                                           "the gateway's ~/node_<id>/rpdo topic), decoded by "
                                           'its mapping, by EDS names where the gateway has '
                                           'node_<id>.eds. Ctrl-C ends it.')
    _pdo_node_argument(echo)
    echo.add_argument('--count', type=ranged('count', 0, 1 << 31), default=0, metavar='N',
                      help='stop after N PDOs (default 0: until Ctrl-C)')
    echo.set_defaults(run=cmd_pdo_echo)

    pdo_write = commands.add_parser('pdo-write', help="send a device's RPDO",
                                    description="Send a device's RPDO (its receive PDO). "
                                                'Mapped objects not given keep the value last '
                                                'sent (0 at first). Names come from the '
                                                "node's EDS.")
    _pdo_node_argument(pdo_write)
    pdo_write.add_argument('pdo', type=ranged('pdo', 1, 512), metavar='PDO',
                           help="the device's RPDO number 1..512")
    pdo_write.add_argument('assignments', nargs='*', metavar='NAME_OR_INDEX=VALUE',
                           help='e.g. 0x6040=15, 0x607A:0=-1000 or "Controlword=15"')
    pdo_write.add_argument('--data', metavar='HEXBYTES',
                           help='the whole frame instead, as on the bus (e.g. 0F00E8030000)')
    pdo_write.add_argument('--eds', metavar='FILE',
                           help="EDS or DCF naming the node's objects (default: the gateway's "
                                'node_<id>.eds)')
    pdo_write.set_defaults(run=cmd_pdo_write)
