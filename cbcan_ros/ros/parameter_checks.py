"""The checks a parameter value passes at start, and the one message a wrong value gets.

rclpy checks type and range against a parameter's descriptor when it is declared, but words
its refusal in its own way (``Trying to set parameter 'x' to 'y' of type 'STRING', expecting
type 'DOUBLE'``), and it cannot know what a CAN interface or a node id allows. Every wrong
value, whichever finds it, ends the node with one :class:`ConfigurationError`::

    parameter sdo.timeout: 'abc' is a string, not a number; allowed: a number from 0.001 to 60.0

naming the parameter, the value as given (cut short), what is wrong with it and what is
allowed. Doubtful but workable values give a warning instead (returned, for the node's log).
"""

import difflib
import ipaddress
import itertools
import json
import os
import re
from typing import Dict, Iterable, List, Optional, Tuple

import can
from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter

from ..core.bus import slcan_bitrates
from ..core.sdo.write_protection import parse_rule, RULE_FORMAT, WriteRule
from ..core.text import quoted
from .rclpy_gaps import parameter_overrides

# How much of a wrong value a message shows: a parameter file may hold anything.
SHOWN_LIMIT = 60

NODE_IDS = 'node ids 1..127'

# The shortest SYNC period: python-can's sending thread (where the kernel does not send it)
# cannot keep a shorter one.
MIN_SYNC_PERIOD = 0.001

# CiA 301's bit rates (100 kbit/s is listed there as not recommended for new designs).
STANDARD_BITRATES = (10_000, 20_000, 50_000, 100_000, 125_000, 250_000, 500_000, 800_000,
                     1_000_000)

# Bus options that have a parameter of their own: one way to set each.
OPTIONS_WITH_A_PARAMETER = {'interface': 'can.interface', 'channel': 'can.channel',
                            'bitrate': 'can.bitrate'}

# Linux network interface names (SocketCAN channels) are at most 15 characters.
INTERFACE_NAME = re.compile(r'[^\s/:]{1,15}')
# A parameter of one node, as written (node_6.joint; node6.joint, a slip of the underscore).
NODE_PARAMETER = re.compile(r'node_?(\d+)\.(.+)')
# What each list of node ids gives its nodes: node_<id>.eds, or a drive's parameters.
DEVICE_LISTS = 'nodes, node_guarding, pdo.nodes or drives.nodes'
DRIVE_PARAMETERS = ('joint', 'position_scale', 'velocity_scale', 'torque_scale', 'hold_torque',
                    'position_offset')

_KINDS = {
    ParameterType.PARAMETER_BOOL: 'true or false',
    ParameterType.PARAMETER_INTEGER: 'an integer',
    ParameterType.PARAMETER_DOUBLE: 'a number',
    ParameterType.PARAMETER_STRING: 'a string',
    ParameterType.PARAMETER_BYTE_ARRAY: 'a list of bytes',
    ParameterType.PARAMETER_BOOL_ARRAY: 'a list of true/false',
    ParameterType.PARAMETER_INTEGER_ARRAY: 'a list of integers',
    ParameterType.PARAMETER_DOUBLE_ARRAY: 'a list of numbers',
    ParameterType.PARAMETER_STRING_ARRAY: 'a list of strings',
}


class ConfigurationError(ValueError):
    """A parameter value the node cannot start with."""

    def __init__(self, name: str, value, problem: str, allowed: str):
        super().__init__(f'parameter {name}: {quoted(value, SHOWN_LIMIT)} {problem}; '
                         f'allowed: {allowed}')
        self.name = name


def allowed_by(descriptor: ParameterDescriptor) -> str:
    """Return what a descriptor allows, in words: the type, and its range or constraints."""
    kind = _KINDS.get(descriptor.type, 'a value')
    for ranges in (descriptor.integer_range, descriptor.floating_point_range):
        if ranges:
            return f'{kind} from {ranges[0].from_value} to {ranges[0].to_value}'
    if descriptor.additional_constraints:
        return f'{kind}, {descriptor.additional_constraints}'
    return kind


def declare(node: Node, name: str, default, descriptor: ParameterDescriptor) -> Parameter:
    """Declare a parameter; a given value its descriptor refuses raises ConfigurationError.

    ``default`` is the value, or the ``Parameter.Type`` of a parameter without default. An
    integer given for a floating-point parameter (``timeout: 2``) is taken as that number:
    rclpy alone refuses it.
    """
    if not isinstance(default, Parameter.Type):
        descriptor.type = Parameter.Type.from_parameter_value(default).value
    try:
        return node.declare_parameter(name, default, descriptor)
    except (InvalidParameterTypeException, InvalidParameterValueException):
        pass
    # rclpy's exceptions do not carry the value: declare the parameter untyped to read it.
    given = node.declare_parameter(
        name, None, ParameterDescriptor(dynamic_typing=True)).value
    node.undeclare_parameter(name)
    if descriptor.type == ParameterType.PARAMETER_DOUBLE and type(given) is int:
        try:
            return node.declare_parameter(name, float(given), descriptor, ignore_override=True)
        except InvalidParameterValueException:
            pass
    given_type = Parameter.Type.from_parameter_value(given).value
    if given_type == descriptor.type or (given_type == ParameterType.PARAMETER_INTEGER and
                                         descriptor.type == ParameterType.PARAMETER_DOUBLE):
        problem = 'is out of range'
    else:
        problem = f'is {_KINDS.get(given_type, "no value")}, not {_KINDS[descriptor.type]}'
    raise ConfigurationError(name, given, problem, allowed_by(descriptor))


def check_unknown(node: Node, declared: Iterable[str]) -> None:
    """Refuse a given parameter the node does not have, if it looks like one of ``declared``.

    ROS ignores a parameter nobody declares, so a misspelt ``sdo.timout`` or ``can.options``
    written as a map (``can.options.tty_baudrate``) would silently do nothing. Refused: a
    name in one of the groups of ``declared`` (``can.``, ``sdo.`` ...) or close to one of
    its names. Other names are left alone (other code may declare them).
    """
    overrides = parameter_overrides(node)
    declared = sorted(declared)
    groups = {name.split('.')[0] + '.' for name in declared if '.' in name}
    for name in sorted(overrides):
        if node.has_parameter(name):
            continue
        of_a_node = NODE_PARAMETER.fullmatch(name)
        if of_a_node:
            raise ConfigurationError(name, overrides[name].value,
                                     *_node_parameter_problem(name, *of_a_node.groups()))
        group = name.split('.')[0] + '.'
        close = difflib.get_close_matches(name, declared, n=3, cutoff=0.8)
        if group not in groups and not close:
            continue
        candidates = close or [known for known in declared if known.startswith(group)]
        hint = (' (a list of key=value strings, not a map)'
                if name.startswith('can.options.') else '')
        raise ConfigurationError(name, overrides[name].value,
                                 f'is given, but {node.get_name()} has no such parameter',
                                 ', '.join(candidates) + hint)


def _node_parameter_problem(name: str, node_id: str, key: str) -> Tuple[str, str]:
    """Return (problem, allowed) of a parameter of a node that no list made exist.

    A node's parameters exist only for the ids of the lists that name it: given for
    another, or misspelt, it would do nothing, silently.
    """
    right = f'node_{int(node_id)}.{key}'
    if name != right:
        return "is not a parameter name: a node's parameters are node_<id>.NAME", right
    if key in DRIVE_PARAMETERS:
        return (f'is given, but node {int(node_id)} is not in drives.nodes: a node has the '
                f'parameters of a drive only there'), f'drives.nodes with {int(node_id)} in it'
    if key == 'eds':
        return (f'is given, but node {int(node_id)} is in none of {DEVICE_LISTS}'), (
            f'one of those lists with {int(node_id)} in it')
    return ('is given, but no node has such a parameter', ', '.join(
        f'node_<id>.{known}' for known in ('eds', *DRIVE_PARAMETERS)))


def check_interface(interface: str) -> None:
    """Refuse a python-can interface name python-can does not know."""
    if interface not in can.interfaces.BACKENDS:
        raise ConfigurationError('can.interface', interface, 'is not a python-can interface',
                                 ', '.join(sorted(can.interfaces.BACKENDS)))


def check_channel(interface: str, channel: str) -> None:
    """Refuse a channel the interface can never open (a missing adapter is not refused)."""
    if interface == 'socketcan' and not INTERFACE_NAME.fullmatch(channel):
        raise ConfigurationError('can.channel', channel,
                                 'is not a network interface name for socketcan',
                                 'a CAN network interface as `ip link` lists it, at most 15 '
                                 'characters, e.g. can0, vcan0')
    elif interface == 'pcan':
        from can.interfaces.pcan.basic import PCAN_CHANNEL_NAMES
        names = [name for name in PCAN_CHANNEL_NAMES if name != 'PCAN_NONEBUS']
        if channel not in names:
            raise ConfigurationError('can.channel', channel, 'is not a PCAN channel',
                                     _numbered_ranges(names))
    elif interface == 'kvaser' and not channel.isdigit():
        raise ConfigurationError('can.channel', channel, 'is not a Kvaser channel number',
                                 'the CANlib channel number, 0 for the first')
    elif interface == 'slcan' and not _serial_port(channel.partition('@')[0]):
        raise ConfigurationError('can.channel', channel, 'is not a serial device for slcan',
                                 'the serial device path, e.g. /dev/ttyACM0 or '
                                 '/dev/serial/by-id/usb-..., optionally @<tty baud rate>')
    elif interface == 'udp_multicast' and not _multicast_address(channel):
        raise ConfigurationError('can.channel', channel, 'is not a multicast address',
                                 'an IPv4 or IPv6 multicast group, e.g. 239.74.163.2')
    elif not channel.strip():
        raise ConfigurationError('can.channel', channel, 'is empty',
                                 'the channel name of the interface, e.g. can0')


def check_bitrate(interface: str, bitrate: int) -> Optional[str]:
    """Refuse a bit rate the interface cannot set; return a warning for a doubtful one.

    Refused only where python-can would fail at every open (slcan: the gateway would keep
    reopening the bus) or silently use another rate (pcan falls back to 500 kbit/s). Other
    adapters (Kvaser, ...) can run rates outside CiA 301's list, which some older machines
    use: those start, with a warning.
    """
    if not bitrate:
        return None
    if interface == 'slcan':
        rates = slcan_bitrates()
    elif interface == 'pcan':
        from can.interfaces.pcan.basic import PCAN_BITRATES
        rates = sorted(PCAN_BITRATES)
    elif interface == 'socketcan':
        return (f'parameter can.bitrate: {bitrate} is not applied by socketcan, which keeps '
                f'the bit rate the network interface was set up with (ip link set <channel> '
                f'up type can bitrate {bitrate}); set can.bitrate to 0')
    elif interface in ('virtual', 'udp_multicast') or bitrate in STANDARD_BITRATES:
        return None
    else:
        return (f'parameter can.bitrate: {bitrate} is not a CiA 301 bit rate '
                f'({_rates(STANDARD_BITRATES)}); every device on the bus must use exactly '
                f'this rate')
    if bitrate not in rates:
        raise ConfigurationError('can.bitrate', bitrate, f'is not a bit rate {interface} sets',
                                 f'0 (keep the setting of the adapter) or {_rates(rates)}')
    return None


def bus_options(options: List[str]) -> Dict[str, object]:
    """Return ``key=value`` strings as python-can keyword options (values read as JSON)."""
    result = {}
    for option in options:
        key, equals, text = option.partition('=')
        key = key.strip()
        if not equals or not key.isidentifier():
            raise ConfigurationError('can.options', option, 'is not key=value',
                                     'strings key=value, e.g. tty_baudrate=115200')
        if key in OPTIONS_WITH_A_PARAMETER:
            raise ConfigurationError('can.options', option,
                                     f'sets {key}, which has a parameter of its own',
                                     f'other python-can options; set {key} with '
                                     f'{OPTIONS_WITH_A_PARAMETER[key]}')
        if key in result:
            raise ConfigurationError('can.options', option, f'sets {key} a second time',
                                     'each option once')
        try:
            result[key] = json.loads(text)
        except ValueError:
            result[key] = text
    return result


def check_node_ids(name: str, node_ids: List[int]) -> None:
    """Refuse a list of node ids with one outside 1..127."""
    wrong = [node_id for node_id in node_ids if not 1 <= node_id <= 127]
    if wrong:
        raise ConfigurationError(name, node_ids, f'holds node id {wrong[0]}, out of range',
                                 NODE_IDS)


def check_guarding(guarded: List[int], expected: List[int], period: float,
                   timeout: float) -> Optional[str]:
    """Refuse a guarding period that lets guarded nodes time out between two polls.

    Return a warning for guarded nodes missing from ``nodes``: those appear on the state
    topic only once they answer.
    """
    if guarded and period >= timeout:
        raise ConfigurationError('node_guarding_period', period,
                                 f'is not shorter than heartbeat.timeout ({timeout}), so '
                                 'guarded nodes would turn NOT_DETECTED between two polls',
                                 f'a period below {timeout}, best a third of it or less')
    missing = sorted(set(guarded) - set(expected))
    if missing:
        return (f'parameter node_guarding: {missing} are not in nodes: they appear on '
                f'~/node_states only once they answer; add them to nodes to see them '
                f'NOT_DETECTED until then')
    return None


def check_sync(period: float, counter_overflow: int) -> None:
    """Refuse a SYNC period too short to produce, and a counter CiA 301 does not allow."""
    if 0 < period < MIN_SYNC_PERIOD:
        raise ConfigurationError('sync.period', period, 'is too short',
                                 f'0 (no SYNC) or {MIN_SYNC_PERIOD} to 60 seconds')
    if counter_overflow == 1:
        raise ConfigurationError('sync.counter_overflow', counter_overflow,
                                 'is no counter CiA 301 allows',
                                 '0 (SYNC without counter) or 2..240')


def check_own_node_id(node_id: int, devices: Dict[str, List[int]]) -> None:
    """Refuse a heartbeat node id of the gateway's that a device parameter lists too.

    ``devices`` maps each parameter holding device node ids to its ids. Two nodes with one
    node id share the COB-ID 0x700 + id: neither heartbeat could be told from the other.
    """
    if not node_id:
        return
    for name, node_ids in devices.items():
        if node_id in node_ids:
            raise ConfigurationError('heartbeat.node_id', node_id,
                                     f'is also a device in {name} ({node_ids}): the '
                                     f"gateway's heartbeat would share COB-ID "
                                     f'0x{0x700 + node_id:03X} with it',
                                     '0 (no heartbeat) or a node id no device on the bus uses')


def pdo_configure_warning(configure: bool, without_file: List[int]) -> Optional[str]:
    """Return a warning when pdo.configure is set for devices that have no file to write."""
    if configure and without_file:
        return (f'parameter pdo.configure: nodes {without_file} of pdo.nodes have no '
                f'node_<id>.eds: their PDO parameters are read, not written')
    return None


def write_rules(rules: List[str]) -> Tuple[WriteRule, ...]:
    """Return the parsed ``sdo.write_allow`` rules; refuse one that does not parse."""
    parsed = []
    for rule in rules:
        if not rule.strip():
            continue
        try:
            parsed.append(parse_rule(rule))
        except ValueError as error:
            raise ConfigurationError('sdo.write_allow', rule,
                                     f'is not a valid write rule: {error}',
                                     RULE_FORMAT) from None
    return tuple(parsed)


def check_file(name: str, path: str) -> None:
    """Refuse a path that is set but is not a readable file."""
    if path and not (os.path.isfile(path) and os.access(path, os.R_OK)):
        raise ConfigurationError(name, path, 'is not a readable file',
                                 'the path of an existing file, or empty')


def check_simulated(lists: Dict[str, List[int]]) -> None:
    """Refuse a node id that two kinds of simulated device (``{parameter: ids}``) both hold."""
    seen: Dict[int, str] = {}
    for name, node_ids in lists.items():
        for node_id in node_ids:
            if node_id in seen:
                raise ConfigurationError(name, node_ids,
                                         f'holds node id {node_id}, which {seen[node_id]} '
                                         f'{lists[seen[node_id]]} holds too: two devices '
                                         f'would answer as one',
                                         f'node ids that are not in {seen[node_id]}')
            seen[node_id] = name


def simulation_warning(interface: str, channel: str, devices: List[int]) -> Optional[str]:
    """Return a warning when simulated devices join a bus that may be a real one."""
    if devices and interface not in ('virtual', 'udp_multicast') and \
            not channel.startswith('vcan'):
        return (f'parameters simulation.devices, drives and bootloaders: simulated devices '
                f'{devices} answer as node ids on {interface} channel {channel!r}; on a real '
                f'bus they collide with real devices: keep both empty there')
    return None


def _serial_port(port: str) -> bool:
    return port.startswith('/') or '://' in port or bool(re.fullmatch(r'COM\d+', port))


def _multicast_address(text: str) -> bool:
    try:
        return ipaddress.ip_address(text).is_multicast
    except ValueError:
        return False


def _rates(rates: Iterable[int]) -> str:
    return ', '.join(str(rate) for rate in rates)


def _numbered_ranges(names: List[str]) -> str:
    """Return names like PCAN_USBBUS1..PCAN_USBBUS16 as one range per stem."""
    ranges = []
    for _, group in itertools.groupby(names, key=lambda name: name.rstrip('0123456789')):
        group = list(group)
        ranges.append(group[0] if len(group) == 1 else f'{group[0]}..{group[-1]}')
    return ', '.join(ranges)
