"""The SDO commands of ``cbcan_cli``: sdo-read, sdo-write and sdo-batch."""

import argparse
import sys
from typing import List, Optional

from ...core.sdo.requests import MAX_TIMEOUT
from ...core.text import quoted
from ...core.values import (
    data_type_name,
    decode_value,
    encode_value,
    INTEGER_TYPES,
    type_of,
    VALUE_TYPES,
)
from ...msg import SdoAccess
from .arguments import bounded_seconds, node_id, ranged
from .errors import UsageError
from .object_names import resolve_object, Target
from .standalone_client import Client

# Bytes of a written value echoed in the confirmation.
SHOWN_BYTES = 16


# An SDO timeout in seconds: 0 (the gateway's sdo.timeout) up to MAX_TIMEOUT.
_sdo_timeout = bounded_seconds(MAX_TIMEOUT, "the gateway's sdo.timeout")


def _type_name(text: str) -> str:
    """Parse a value type name (u8 .. u64, i8 .. i64, f32, f64, str, hex)."""
    if text.lower() not in VALUE_TYPES:
        raise argparse.ArgumentTypeError(f'{quoted(text)} is not a value type: allowed '
                                         f'{" ".join(VALUE_TYPES)}')
    return text.lower()


_index = ranged('index', 0, 0xFFFF, 4)
_subindex = ranged('subindex', 0, 0xFF, 2)


def _data_line(data: bytes) -> str:
    size = len(data)
    hex_bytes = ' '.join(f'{byte:02X}' for byte in data) if data else '(none)'
    return f'data:  {hex_bytes}  ({size} byte{"" if size == 1 else "s"})'


def describe_data(data: bytes) -> List[str]:
    """Return the lines sdo-read prints for ``data`` of no known type: hex, number, text."""
    size = len(data)
    lines = [_data_line(data)]
    if size in (1, 2, 4):
        value = int.from_bytes(data, 'little')
        lines.append(f'value: 0x{value:0{size * 2}X} = {value}  (unsigned, little-endian)')
    if data and all(0x20 <= byte <= 0x7E for byte in data):
        lines.append(f'text:  {data.decode("ascii")!r}')
    return lines


def describe_typed(data: bytes, value_type: str) -> List[str]:
    """Return the lines sdo-read prints for ``data`` read as ``value_type``.

    Raises ValueError naming the type and the size when ``data`` does not fit the type.
    """
    value = decode_value(data, value_type)
    lines = [_data_line(data)]
    if value_type in INTEGER_TYPES:
        bits = int.from_bytes(data, 'little')
        lines.append(f'value: {value}  ({value_type}, 0x{bits:0{len(data) * 2}X})')
    elif value_type != 'hex':  # hex: the data line is the value
        lines.append(f'value: {value!r}  ({value_type})')
    return lines


def _value_type(args, target: Target) -> Optional[str]:
    """Return --type, or else the type of the object's EDS entry (None: not known)."""
    if args.value_type:
        return args.value_type
    return type_of(target.variable.data_type) if target.variable else None


def cmd_sdo_read(client: Client, args) -> int:
    """Read an object and print its bytes, and its value as its type or as a guess."""
    words = [args.subindex] if args.subindex is not None else []
    target, extra = resolve_object(client, args, words, False)
    if extra:
        raise UsageError(f'{target.variable.qualname!r} is one value (0x{target.index:04X}:'
                         f'{target.subindex:02X}): give no sub-index after its name')
    data = client.read(target.node, target.index, target.subindex, max_size=args.max_size,
                       timeout=args.timeout)
    value_type = _value_type(args, target)
    if target.variable:
        print(f'object: {target.variable.qualname} = 0x{target.index:04X}:'
              f'{target.subindex:02X}, {data_type_name(target.variable.data_type)}')
    if value_type is None:
        print('\n'.join(describe_data(data)))
        return 0
    try:
        print('\n'.join(describe_typed(data, value_type)))
    except ValueError as error:
        print(_data_line(data))
        origin = '--type' if args.value_type else 'the EDS'
        print(f'error: {target}: {error} (type from {origin})', file=sys.stderr)
        return 1
    return 0


def cmd_sdo_write(client: Client, args) -> int:
    """Write an object."""
    words = ([args.subindex] if args.subindex is not None else []) + args.value
    target, value = resolve_object(client, args, words, True)
    if not value:
        raise UsageError(f'no VALUE to write to {target}')
    try:
        data = encode_value(value, _value_type(args, target) or 'hex')
    except ValueError as error:
        raise UsageError(f'{target}: {error}') from None
    client.write(target.node, target.index, target.subindex, data, timeout=args.timeout)
    shown = data[:SHOWN_BYTES].hex(' ').upper() + (' ...' if len(data) > SHOWN_BYTES else '')
    print(f'ok: wrote {len(data)} byte{"" if len(data) == 1 else "s"} ({shown}) to {target}')
    return 0


ACCESS_FORMAT = ('r:NODE:INDEX[:SUB] to read, w:NODE:INDEX:SUB:HEXBYTES to write (bytes as '
                 'on the bus), e.g. r:5:0x1000 w:5:0x2002:0:78563412')


def parse_access(text: str) -> SdoAccess:
    """Parse one batch access (see ``ACCESS_FORMAT``); raise ArgumentTypeError if wrong."""
    fields = text.strip().split(':')
    kind = fields[0].lower()
    if kind not in ('r', 'w') or not 3 <= len(fields) <= (4 if kind == 'r' else 5) or (
            kind == 'w' and len(fields) != 5):
        raise argparse.ArgumentTypeError(f'access {quoted(text)}: expected {ACCESS_FORMAT}')
    access = SdoAccess(node_id=node_id(fields[1]), index=_index(fields[2]),
                       subindex=_subindex(fields[3]) if len(fields) > 3 else 0,
                       write=kind == 'w')
    if access.write:
        try:
            access.data = list(encode_value([fields[4]], 'hex'))
        except ValueError as error:
            raise argparse.ArgumentTypeError(f'access {quoted(text)}: {error}') from None
    return access


def cmd_sdo_batch(client: Client, args) -> int:
    """Run several accesses in one call and print one line per result."""
    accesses = list(args.accesses)
    if args.file:
        try:
            with open(args.file) as lines:
                accesses += [parse_access(line) for line in lines
                             if line.strip() and not line.lstrip().startswith('#')]
        except (OSError, argparse.ArgumentTypeError) as error:
            print(f'error: --file {args.file}: {error}', file=sys.stderr)
            return 2
    if not accesses:
        print('error: no accesses: give them as arguments or with --file', file=sys.stderr)
        return 2
    results = client.batch(accesses, timeout=args.timeout)
    failed = 0
    for number, (access, result) in enumerate(zip(accesses, results, strict=True), 1):
        what = (f'{number:>4} {"write" if access.write else "read "} node {access.node_id} '
                f'0x{access.index:04X}:{access.subindex:02X}')
        if result.success:
            data = result.data
            print(f'{what}  ok  {data.hex(" ").upper()}' if data else f'{what}  ok')
        else:
            failed += 1
            print(f'{what}  error: {result.message}')
    return 1 if failed else 0


def _object_arguments(command: argparse.ArgumentParser, subindex_help: str) -> None:
    """Add what sdo-read and sdo-write share: NODE OBJECT [SUBINDEX], --eds and --timeout."""
    command.add_argument('node', type=node_id, metavar='NODE',
                         help='node id 1..127 (0 = gateway)')
    command.add_argument('object', metavar='OBJECT',
                         help='object index (e.g. 0x1017) or its name in the EDS (e.g. '
                              '"Producer heartbeat time", "Identity object.Vendor-ID"; any '
                              'case)')
    command.add_argument('subindex', nargs='?', metavar='SUBINDEX', help=subindex_help)
    command.add_argument('--eds', metavar='FILE',
                         help="EDS or DCF file naming the node's objects (default: the file "
                              "in the gateway's parameter node_<NODE>.eds, asked when OBJECT "
                              "is a name)")
    command.add_argument('--timeout', type=_sdo_timeout, default=0.0, metavar='S',
                         help="SDO timeout in seconds (default 0: the gateway's sdo.timeout)")


def add_commands(commands) -> None:
    """Add sdo-read, sdo-write and sdo-batch."""
    types = ' '.join(VALUE_TYPES)

    read = commands.add_parser('sdo-read', help='read an object (SDO upload)',
                               description='Read an object and print its bytes and its value: '
                                           'as --type, as its EDS type when named by name, '
                                           'or else 1, 2 and 4 bytes as an unsigned '
                                           'little-endian number and printable ASCII as text.')
    _object_arguments(read, 'sub-index (default 0), or the entry of a record or array named by '
                            'OBJECT: its sub-index or its name')
    read.add_argument('--type', dest='value_type', type=_type_name, metavar='TYPE',
                      help=f'decode the answer as TYPE: {types} (default: the EDS type of a '
                           f'named object)')
    read.add_argument('--max-size', type=ranged('max-size', 0, 0xFFFFFFFF), default=0,
                      metavar='N', help='largest answer accepted in bytes (default 0: no '
                                        'limit)')
    read.set_defaults(run=cmd_sdo_read)

    write = commands.add_parser('sdo-write', help='write an object (SDO download)',
                                description='Write an object. An object given by index takes '
                                            'SUBINDEX, and its value is hex bytes as on the '
                                            'bus unless --type says otherwise (78563412 or '
                                            '"78 56 34 12"); an object named by name is '
                                            'written as its EDS type. Numbers are written '
                                            'little-endian.')
    _object_arguments(write, 'sub-index: required after an index; after a name only for the '
                             'entry of a record or array (its sub-index or name)')
    write.add_argument('value', nargs='+', metavar='VALUE',
                       help='the value; several words are joined (hex: without spaces, '
                            'str: with one space)')
    write.add_argument('--type', dest='value_type', type=_type_name, metavar='TYPE',
                       help=f'how to read VALUE: {types} (default: the EDS type of a named '
                            f'object, else hex)')
    write.set_defaults(run=cmd_sdo_write)

    batch = commands.add_parser('sdo-batch', help='several reads and writes in one call',
                                description='Run several SDO accesses in one call: those to '
                                            'one device in the order given, devices in '
                                            f'parallel. Each access is {ACCESS_FORMAT}.')
    batch.add_argument('accesses', type=parse_access, nargs='*', metavar='ACCESS',
                       help='r:NODE:INDEX[:SUB] or w:NODE:INDEX:SUB:HEXBYTES')
    batch.add_argument('--file', metavar='FILE',
                       help='read accesses from FILE too, one a line (# starts a comment)')
    batch.add_argument('--timeout', type=_sdo_timeout, default=0.0, metavar='S',
                       help="seconds for the whole batch (default 0: the gateway's "
                            'sdo.timeout)')
    batch.set_defaults(run=cmd_sdo_batch)
