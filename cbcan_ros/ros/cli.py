"""Command-line client of the gateway services, for machines without the ``ros2`` CLI.

Examples (the gateway started by ``make run`` is ``/can0/cbcan``)::

    cbcan_cli sdo-read 5 0x1000
    cbcan_cli sdo-read 5 0x2003 --type i32
    cbcan_cli sdo-read 5 "Producer heartbeat time"        # named in node 5's EDS
    cbcan_cli sdo-read 5 "Identity object.Vendor-ID"
    cbcan_cli sdo-write 5 "Producer heartbeat time" 1000   # typed by the EDS
    cbcan_cli sdo-write 5 0x2002 0 0x12345678 --type u32
    cbcan_cli sdo-write 5 0x2021 0 hello --type str
    cbcan_cli nmt 5 start
    cbcan_cli state 5
    cbcan_cli states
    cbcan_cli --gateway /robot/can1/cbcan mailbox cbcan 0x0001 ...
    cbcan_cli sdo-batch r:5:0x1000 w:5:0x2002:0:78563412 r:3:0x1008
    cbcan_cli sdo-batch --file accesses.txt
    cbcan_cli lss-scan --assign-from 10 --store
    cbcan_cli lss-inquire 0x319 0x51 0x10000 7
    cbcan_cli lss-configure 0x319 0x51 0x10000 7 --node-id 12 --store
    cbcan_cli pdo-echo 5                                  # what node 5 sends (its TPDOs)
    cbcan_cli pdo-write 5 1 "Demo UNSIGNED8=7" 0x2001=300  # node 5's RPDO 1

Objects are given by index (a number) or by the name the node's EDS or DCF file gives them.
The file is the gateway's parameter ``node_<id>.eds`` (asked of the running gateway) or
``--eds FILE``.

Exit status: 0 on success, 1 when the gateway answered with an error (an SDO abort, a
refused request) or the answer does not fit the value type, 2 when there is no usable
gateway (not running, no answer) or the command line is wrong (an unknown name, a value that
does not fit its type).
"""

import argparse
from dataclasses import dataclass
import math
import sys
import time
from typing import List, Optional, Sequence, Tuple

from canopen.objectdictionary import ObjectDictionary, ODVariable
from rcl_interfaces.srv import GetParameters
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import parameter_value_to_python

from ..core import eds, lss
from ..core.gateway import own_dictionary
from ..core.sdo import MAX_NODE_ID, MAX_TIMEOUT
from ..core.text import quoted
from ..core.values import (
    data_type_name,
    decode_value,
    encode_value,
    INTEGER_TYPES,
    parse_integer,
    type_of,
    VALUE_TYPES,
)
from ..msg import LssIdentity, Pdo, PdoEntry, SdoAccess
from ..plc.mailbox import Cbcan, Me3can
from ..srv import LssConfigure, LssInquire, LssScan, PdoWrite, RegisterMailbox
from .client import (
    ANSWER_MARGIN,
    answer_within,
    DEFAULT_GATEWAY,
    DEFAULT_WAIT,
    describe,
    GatewayClient,
    GatewayUnavailable,
    NMT_COMMANDS,
    RequestFailed,
)
from .config import device_file_parameter
from .pdo import PDO_QOS

# Bytes of a written value echoed in the confirmation.
SHOWN_BYTES = 16


class UsageError(Exception):
    """The command line cannot be carried out: an unknown name, a value that does not fit."""


def _integer(text: str) -> int:
    """Parse a number: decimal, or with a 0x/0o/0b prefix (as ``int(text, 0)``)."""
    try:
        return parse_integer(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _ranged(name: str, lowest: int, highest: int, hex_digits: int = 0):
    """Return an argparse type: an integer in ``lowest..highest``."""
    def parse(text: str) -> int:
        value = _integer(text)
        if not lowest <= value <= highest:
            shown = (f'0x{lowest:0{hex_digits}X}..0x{highest:0{hex_digits}X}' if hex_digits
                     else f'{lowest}..{highest}')
            raise argparse.ArgumentTypeError(f'{name} {text} is out of range: allowed {shown}')
        return value
    parse.__name__ = name  # argparse names the type in its messages
    return parse


def _parse_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{quoted(text)} is not a number of seconds') from None
    if math.isnan(value):
        raise argparse.ArgumentTypeError(f'{quoted(text)} is not a number of seconds')
    return value


def _seconds(text: str) -> float:
    """Parse an SDO timeout in seconds: 0 (the gateway's sdo.timeout) up to MAX_TIMEOUT."""
    value = _parse_seconds(text)
    if not 0.0 <= value <= MAX_TIMEOUT:
        raise argparse.ArgumentTypeError(
            f"timeout {quoted(text)} is out of range: allowed 0 (the gateway's sdo.timeout) "
            f'to {MAX_TIMEOUT:g} s')
    return value


def _positive_seconds(text: str) -> float:
    value = _parse_seconds(text)
    if not value > 0.0:
        raise argparse.ArgumentTypeError(f'{quoted(text)} must be more than 0 s')
    return value


def _type_name(text: str) -> str:
    """Parse a value type name (u8 .. u64, i8 .. i64, f32, f64, str, hex)."""
    if text.lower() not in VALUE_TYPES:
        raise argparse.ArgumentTypeError(f'{quoted(text)} is not a value type: allowed '
                                         f'{" ".join(VALUE_TYPES)}')
    return text.lower()


def _nmt_command(text: str) -> int:
    """Parse an NMT command: a name (start, stop, preop, reset, reset-comm) or its number."""
    name = text.lower()
    if name in NMT_COMMANDS:
        return NMT_COMMANDS[name]
    try:
        value = _integer(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f'{quoted(text)} is not an NMT command: use {", ".join(NMT_COMMANDS)} or a number'
        ) from None
    if not 0 <= value <= 255:
        raise argparse.ArgumentTypeError(f'NMT command {text} is out of range: allowed 0..255')
    return value


_node = _ranged('node', 0, MAX_NODE_ID)
_index = _ranged('index', 0, 0xFFFF, 4)
_subindex = _ranged('subindex', 0, 0xFF, 2)
_word = _ranged('word', 0, 0xFFFF, 4)


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


class Client(GatewayClient):
    """The gateway's client on a node of its own, in a private context (one per CLI run)."""

    def __init__(self, gateway: str, wait: float):
        self._context = rclpy.Context()
        rclpy.init(args=[], context=self._context)
        self._cli_node = rclpy.create_node('cbcan_cli', context=self._context,
                                           start_parameter_services=False,
                                           enable_rosout=False)
        super().__init__(self._cli_node, gateway, wait)

    def close(self) -> None:
        """Close the client, destroy the node and shut the private context down."""
        super().close()
        self._cli_node.destroy_node()
        rclpy.try_shutdown(context=self._context)

    def parameter(self, name: str):
        """Return the value of the gateway's parameter ``name``; None if it has none."""
        response = self.call(GetParameters, 'get_parameters', GetParameters.Request(
            names=[name]), self.wait)
        return parameter_value_to_python(response.values[0]) if response.values else None

    def follow(self, message_type, topic: str, qos, handle, count: int = 0) -> None:
        """Call ``handle(message)`` for messages of ``gateway/topic``; stop after ``count``.

        ``count`` 0 follows until interrupted (Ctrl-C).
        """
        received = []
        subscription = self._cli_node.create_subscription(
            message_type, f'{self.gateway}/{topic}', received.append, qos)
        executor = SingleThreadedExecutor(context=self._context)
        executor.add_node(self._cli_node)
        handled = 0
        try:
            while not count or handled < count:
                executor.spin_once(timeout_sec=0.1)
                while received and (not count or handled < count):
                    handle(received.pop(0))
                    handled += 1
        finally:
            executor.shutdown(timeout_sec=1.0)
            self._cli_node.destroy_subscription(subscription)


def _failed(response) -> int:
    """Print what the gateway refused: the abort code, its name and meaning, or why."""
    kind = 'SDO abort ' if getattr(response, 'abort_code', 0) else ''
    print(f'error: {kind}{describe(response)}', file=sys.stderr)
    return 1


@dataclass(frozen=True)
class Target:
    """The object a command names; ``variable`` is its EDS entry when it was named by name."""

    node: int
    index: int
    subindex: int
    variable: Optional[ODVariable] = None

    def __str__(self) -> str:
        where = f'node {self.node} object 0x{self.index:04X}:{self.subindex:02X}'
        return f'{where} ({self.variable.qualname})' if self.variable else where


def _dictionary(client: Client, args) -> Tuple[ObjectDictionary, str]:
    """Return the dictionary that names the objects of ``args.node``, and where it is from."""
    if args.eds:
        try:
            return eds.load(args.eds, args.node), quoted(args.eds, eds.PATH_LIMIT)
        except ValueError as error:
            raise UsageError(f'--eds {error}') from None
    if args.node == 0:
        return own_dictionary().object_dictionary, "the gateway's own dictionary"
    name = device_file_parameter(args.node)
    path = client.parameter(name)
    if path is None:
        raise UsageError(f'the gateway {client.gateway} has no parameter {name}: list node '
                         f'{args.node} in its nodes (or node_guarding) parameter and set {name} '
                         f'to its EDS, or give --eds FILE')
    if not path:
        raise UsageError(f"node {args.node} has no EDS: the gateway's parameter {name} is "
                         f'empty; set it, or give --eds FILE')
    try:
        return eds.load(path, args.node), quoted(path, eds.PATH_LIMIT)
    except ValueError as error:
        raise UsageError(f"the gateway's parameter {name}: {error} (this command reads the "
                         f'file on this machine; give --eds FILE if it is elsewhere)') from None


def _target(client: Client, args, words: List[str], value_follows: bool
            ) -> Tuple[Target, List[str]]:
    """Resolve OBJECT and the words after it; return the target and the words left over.

    OBJECT is an index, followed by its sub-index (optional for reads), or a name from the
    node's EDS: of one value, or of a record or array followed by the entry's name or
    sub-index.
    """
    try:
        index = parse_integer(args.object)
    except ValueError:
        return _named(client, args, words)
    if not 0 <= index <= 0xFFFF:
        raise UsageError(f'index {quoted(args.object)} is out of range: allowed '
                         f'0x0000..0xFFFF')
    if value_follows and len(words) < 2:
        raise UsageError('an object given by index takes SUBINDEX and VALUE, e.g. '
                         'sdo-write 5 0x2002 0 78563412')
    try:
        subindex = parse_integer(words[0]) if words else 0
    except ValueError as error:
        raise UsageError(f'sub-index: {error}') from None
    if not 0 <= subindex <= 0xFF:
        raise UsageError(f'sub-index {quoted(words[0])} is out of range: allowed 0..255')
    return Target(args.node, index, subindex), words[1:]


def _named(client: Client, args, words: List[str]) -> Tuple[Target, List[str]]:
    dictionary, source = _dictionary(client, args)
    try:
        found = eds.find(dictionary, args.object, source)
        if isinstance(found, ODVariable):
            return Target(args.node, found.index, found.subindex, found), words
        if not words:
            raise UsageError(f'{found.name!r} has several entries: name one as '
                             f'"{found.name}.ENTRY" or give its sub-index after the name '
                             f'({eds.describe_entries(found)})')
        variable = eds.entry(found, words[0])
    except ValueError as error:
        raise UsageError(str(error)) from None
    return Target(args.node, variable.index, variable.subindex, variable), words[1:]


def _value_type(args, target: Target) -> Optional[str]:
    """Return --type, or else the type of the object's EDS entry (None: not known)."""
    if args.value_type:
        return args.value_type
    return type_of(target.variable.data_type) if target.variable else None


def cmd_sdo_read(client: Client, args) -> int:
    """Read an object and print its bytes, and its value as its type or as a guess."""
    words = [args.subindex] if args.subindex is not None else []
    target, extra = _target(client, args, words, False)
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
    target, value = _target(client, args, words, True)
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
    access = SdoAccess(node_id=_node(fields[1]), index=_index(fields[2]),
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


def cmd_nmt(client: Client, args) -> int:
    """Send an NMT command."""
    client.nmt(args.node, args.command)
    target = 'all nodes' if args.node == 0 else f'node {args.node}'
    print(f'ok: sent NMT command {args.command} to {target}')
    return 0


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
        found, _ = _named(client, args, [])
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
        return _failed(response)
    print(f'ok: RPDO {args.pdo} of node {args.node} sent')
    return 0


def _age(seconds: float) -> str:
    return 'never' if seconds < 0 else f'{seconds:.2f} s ago'


def cmd_state(client: Client, args) -> int:
    """Print a node's NMT state as last reported by the node."""
    response = client.state(args.node)
    print(f'node {args.node}: {response.state_name} (last seen {_age(response.last_seen_age)})')
    return 0


def cmd_states(client: Client, args) -> int:
    """Print the table of every known node's state from the node_states topic."""
    message = client.node_states()
    if not message.nodes:
        print('no nodes known (none expected, none heard)')
        return 0
    now = time.time()
    print(f'{"node":>4}  {"state":<16}  last seen')
    for node in message.nodes:
        seen = node.last_seen.sec + node.last_seen.nanosec * 1e-9
        age = max(0.0, now - seen) if seen else -1.0
        print(f'{node.node_id:>4}  {node.state_name:<16}  {_age(age)}')
    return 0


BLOCK_LENGTHS = {'cbcan': Cbcan.LENGTH, 'me3can': Me3can.LENGTH}


def cmd_mailbox(client: Client, args) -> int:
    """Execute one PLC register block and print the block as returned."""
    words = list(args.words)
    length = BLOCK_LENGTHS.get(args.format or 'cbcan')
    if length and len(words) < length:
        words += [0] * (length - len(words))  # the unwritten registers of the PLC are 0
    response = client.call(RegisterMailbox, 'plc_mailbox', RegisterMailbox.Request(
        format=args.format, registers=words), answer_within(0.0))
    words = list(response.registers)
    for offset in range(0, len(words), 8):
        row = words[offset:offset + 8]
        if args.decimal:
            print(f'{offset:>3}: ' + ' '.join(f'{word:>5}' for word in row))
        else:
            print(f'{offset:>3}: ' + ' '.join(f'0x{word:04X}' for word in row))
    if response.message:
        print(f'error: {response.message}', file=sys.stderr)
        return 1
    return 0


def _lss_identity(args) -> LssIdentity:
    return LssIdentity(vendor_id=args.vendor, product_code=args.product, revision=args.revision,
                       serial=args.serial)


def _lss_answer_within(timeout: float) -> float:
    return (timeout or lss.MAX_TIMEOUT) + ANSWER_MARGIN


def _identity_text(identity) -> str:
    return (f'vendor 0x{identity.vendor_id:08X} product 0x{identity.product_code:08X} '
            f'revision 0x{identity.revision:08X} serial 0x{identity.serial:08X}')


def cmd_lss_scan(client: Client, args) -> int:
    """Find unconfigured devices (LSS Fastscan) and, with --assign-from, number them."""
    response = client.call(LssScan, 'lss_scan', LssScan.Request(
        first_node_id=args.assign_from, store=args.store, timeout=args.timeout),
        _lss_answer_within(args.timeout))
    for identity, node_id in zip(response.devices, response.node_ids, strict=True):
        given = f'  -> node {node_id}' if node_id else '  (left unconfigured)'
        print(f'{_identity_text(identity)}{given}')
    if not response.success:
        print(f'error: {response.message}', file=sys.stderr)
        return 1
    print(response.message)
    return 0


def cmd_lss_configure(client: Client, args) -> int:
    """Give one device a node id and/or bit rate (LSS), stored if asked."""
    response = client.call(LssConfigure, 'lss_configure', LssConfigure.Request(
        identity=_lss_identity(args), node_id=args.node_id, bitrate=args.bitrate,
        store=args.store, timeout=args.timeout), _lss_answer_within(args.timeout))
    if not response.success:
        code = f' (LSS error code {response.error_code})' if response.error_code else ''
        print(f'error: {response.message}{code}', file=sys.stderr)
        return 1
    print(f'ok: {response.message}')
    return 0


def cmd_lss_inquire(client: Client, args) -> int:
    """Print the node id of one device, found by its identity (LSS)."""
    response = client.call(LssInquire, 'lss_inquire', LssInquire.Request(
        identity=_lss_identity(args), timeout=args.timeout), _lss_answer_within(args.timeout))
    if not response.success:
        print(f'error: {response.message}', file=sys.stderr)
        return 1
    shown = 'unconfigured (255)' if response.node_id == lss.UNCONFIGURED else response.node_id
    print(f'node id: {shown}')
    return 0


def _lss_seconds(text: str) -> float:
    value = _parse_seconds(text)
    if not 0.0 <= value <= lss.MAX_TIMEOUT:
        raise argparse.ArgumentTypeError(
            f'timeout {quoted(text)} is out of range: allowed 0 (the default) to '
            f'{lss.MAX_TIMEOUT:g} s')
    return value


def _lss_arguments(command: argparse.ArgumentParser, identity: bool, default: str) -> None:
    """Add the device's identity (VENDOR PRODUCT REVISION SERIAL) and --timeout."""
    if identity:
        for name, meaning in (('vendor', 'vendor id, 0x1018:1'),
                              ('product', 'product code, 0x1018:2'),
                              ('revision', 'revision number, 0x1018:3'),
                              ('serial', 'serial number, 0x1018:4')):
            command.add_argument(name, type=_ranged(name, 0, 0xFFFFFFFF, 8),
                                 metavar=name.upper(), help=meaning)
    command.add_argument('--timeout', type=_lss_seconds, default=0.0, metavar='S',
                         help=f'seconds for the whole call (default 0: {default})')


def _add_lss_commands(commands) -> None:
    scan = commands.add_parser(
        'lss-scan', help='find unconfigured devices (LSS Fastscan) and number them',
        description='Find the devices without a node id (LSS Fastscan, CiA 305). With '
                    '--assign-from, give each a node id from ID upward, skipping ids heard on '
                    "the bus or listed in the gateway's nodes; each then boots with its id. "
                    'Without, report one device found and leave it unconfigured.')
    scan.add_argument('--assign-from', type=_ranged('assign-from', 1, MAX_NODE_ID),
                      default=0, metavar='ID', help='first node id to give (1..127)')
    scan.add_argument('--store', action='store_true',
                      help='store the ids in the devices (kept after power-off)')
    _lss_arguments(scan, False, 'a default that fits the bus')
    scan.set_defaults(run=cmd_lss_scan)

    configure = commands.add_parser(
        'lss-configure', help="set one device's node id and/or bit rate (LSS)",
        description='Give the device with this identity a node id and/or bit rate (LSS '
                    'selective switch, CiA 305); also renumbers a configured device, which '
                    'takes the id at its next NMT reset communication.')
    _lss_arguments(configure, True, '5 s')
    configure.add_argument('--node-id', type=_ranged('node-id', 1, MAX_NODE_ID), default=0,
                           metavar='ID', help='new node id 1..127')
    configure.add_argument('--bitrate', type=_ranged('bitrate', 0, 0xFFFFFFFF), default=0,
                           metavar='BPS',
                           help=f'new bit rate in bit/s ({", ".join(map(str, lss.BIT_TIMING))}'
                                f'); needs --store, takes effect at the next power-on')
    configure.add_argument('--store', action='store_true',
                           help='store the configuration in the device')
    configure.set_defaults(run=cmd_lss_configure)

    inquire = commands.add_parser(
        'lss-inquire', help='ask one device for its node id (LSS)',
        description='Print the node id of the device with this identity (255: '
                    'unconfigured).')
    _lss_arguments(inquire, True, '5 s')
    inquire.set_defaults(run=cmd_lss_inquire)


def _pdo_node_argument(command: argparse.ArgumentParser) -> None:
    """Add the NODE of pdo-echo and pdo-write: a device of the gateway's pdo.nodes."""
    command.add_argument('node', type=_ranged('node', 1, MAX_NODE_ID), metavar='NODE',
                         help='node id 1..127 (one of the gateway parameter pdo.nodes)')


def _object_arguments(command: argparse.ArgumentParser, subindex_help: str) -> None:
    """Add what sdo-read and sdo-write share: NODE OBJECT [SUBINDEX], --eds and --timeout."""
    command.add_argument('node', type=_node, metavar='NODE',
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
    command.add_argument('--timeout', type=_seconds, default=0.0, metavar='S',
                         help="SDO timeout in seconds (default 0: the gateway's sdo.timeout)")


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``cbcan_cli``."""
    parser = argparse.ArgumentParser(
        prog='cbcan_cli',
        description='Call the services of a cbcan_ros CANopen gateway. Numbers take '
                    'decimal or 0x hex.',
        epilog='Exit status: 0 ok, 1 the gateway answered with an error, 2 no gateway or a '
               'wrong command line.')
    parser.add_argument('--gateway', default=DEFAULT_GATEWAY,
                        help='the gateway node: namespace and name (default %(default)s)')
    parser.add_argument('--wait', type=_positive_seconds, default=DEFAULT_WAIT,
                        help='seconds to wait for the gateway to be found (default '
                             '%(default)g)')
    commands = parser.add_subparsers(dest='command', required=True, metavar='COMMAND')

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
    read.add_argument('--max-size', type=_ranged('max-size', 0, 0xFFFFFFFF), default=0,
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
    batch.add_argument('--timeout', type=_seconds, default=0.0, metavar='S',
                       help="seconds for the whole batch (default 0: the gateway's "
                            'sdo.timeout)')
    batch.set_defaults(run=cmd_sdo_batch)

    nmt = commands.add_parser('nmt', help='send an NMT command',
                              description='Send an NMT command to a node (0 = all nodes).')
    nmt.add_argument('node', type=_node, metavar='NODE', help='node id 1..127, 0 = all nodes')
    nmt.add_argument('command', type=_nmt_command, metavar='COMMAND',
                     help=f'{"|".join(NMT_COMMANDS)} or the command byte')
    nmt.set_defaults(run=cmd_nmt)

    state = commands.add_parser('state', help="print a node's NMT state",
                                description='Print the NMT state a node last reported.')
    state.add_argument('node', type=_node, metavar='NODE', help='node id 1..127')
    state.set_defaults(run=cmd_state)

    states = commands.add_parser('states', help='print the state of every known node',
                                 description='Print the latest node_states message as a '
                                             'table.')
    states.set_defaults(run=cmd_states)

    mailbox = commands.add_parser('mailbox', help='execute one PLC register block',
                                  description='Execute one PLC mailbox block (all its '
                                              'registers) and print the block returned.')
    mailbox.add_argument('format', metavar='FORMAT', help='cbcan or me3can')
    mailbox.add_argument('words', type=_word, nargs='+', metavar='WORD',
                         help='the registers from the first, 0..65535 (decimal or 0x hex); '
                              'a shorter block is padded with zeros to its full length')
    mailbox.add_argument('--decimal', action='store_true', help='print words in decimal')
    mailbox.set_defaults(run=cmd_mailbox)
    _add_lss_commands(commands)

    echo = commands.add_parser('pdo-echo', help="print a device's PDOs as they arrive",
                               description='Print every PDO a device sends (its TPDOs, on '
                                           "the gateway's ~/node_<id>/rpdo topic), decoded by "
                                           'its mapping, by EDS names where the gateway has '
                                           'node_<id>.eds. Ctrl-C ends it.')
    _pdo_node_argument(echo)
    echo.add_argument('--count', type=_ranged('count', 0, 1 << 31), default=0, metavar='N',
                      help='stop after N PDOs (default 0: until Ctrl-C)')
    echo.set_defaults(run=cmd_pdo_echo)

    pdo_write = commands.add_parser('pdo-write', help="send a device's RPDO",
                                    description="Send a device's RPDO (its receive PDO). "
                                                'Mapped objects not given keep the value last '
                                                'sent (0 at first). Names come from the '
                                                "node's EDS.")
    _pdo_node_argument(pdo_write)
    pdo_write.add_argument('pdo', type=_ranged('pdo', 1, 512), metavar='PDO',
                           help="the device's RPDO number 1..512")
    pdo_write.add_argument('assignments', nargs='*', metavar='NAME_OR_INDEX=VALUE',
                           help='e.g. 0x6040=15, 0x607A:0=-1000 or "Controlword=15"')
    pdo_write.add_argument('--data', metavar='HEXBYTES',
                           help='the whole frame instead, as on the bus (e.g. 0F00E8030000)')
    pdo_write.add_argument('--eds', metavar='FILE',
                           help="EDS or DCF naming the node's objects (default: the gateway's "
                                'node_<id>.eds)')
    pdo_write.set_defaults(run=cmd_pdo_write)
    return parser


def run(client: Client, args: argparse.Namespace) -> int:
    """Run one parsed command through ``client`` (several may share one); return the status."""
    try:
        return args.run(client, args)
    except RequestFailed as error:
        return _failed(error.response)
    except (GatewayUnavailable, UsageError) as error:
        print(f'error: {error}', file=sys.stderr)
        return 2


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run one command of ``cbcan_cli``; return the exit status."""
    args = build_parser().parse_args(argv)
    client = None
    try:
        client = Client(args.gateway, args.wait)
        return run(client, args)
    except KeyboardInterrupt:
        return 130
    finally:
        if client is not None:
            client.close()
