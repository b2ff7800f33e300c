"""The CiA 402 drive commands of ``cbcan_cli``: drive, target and drives (move: ``move``)."""

import argparse
import math
import re
import sys
from typing import Dict, List, Optional

from sensor_msgs.msg import JointState
from std_msgs.msg import Float64

from ...core.drives import cia402
from ...core.drives.checks import COMMANDS
from ...core.drives.service import DEFAULT_TIMEOUT, HOMING_TIMEOUT
from ...core.protocol import MAX_NODE_ID
from ...core.sdo.requests import MAX_TIMEOUT
from ...core.text import quoted
from ...msg import DriveState
from ...srv import DriveCommand
from ..client import answer_within, describe
from ..drives import JOINT_STATES_QOS, STATE_QOS, TARGET_QOS
from ..service_caller import GatewayError, GatewayUnavailable
from .arguments import integer, ranged, seconds
from .errors import UsageError
from .standalone_client import Client

# The modes by the abbreviations drive manuals use; the CLI also takes their numbers.
MODES = {'pp': cia402.PROFILE_POSITION, 'pv': cia402.PROFILE_VELOCITY,
         'pt': cia402.PROFILE_TORQUE, 'homing': cia402.HOMING, 'csp': cia402.CYCLIC_POSITION,
         'csv': cia402.CYCLIC_VELOCITY, 'cst': cia402.CYCLIC_TORQUE}
SHORT_MODE_NAMES = {code: name.upper() if name != 'homing' else name
                    for name, code in MODES.items()}
# The service's commands as a shell spells words: with dashes.
DRIVE_COMMANDS = tuple(command.replace('_', '-') for command in COMMANDS)
MODE_COMMANDS = ('enable', 'set-mode')
# What a target is in each mode, in the joint's units.
TARGET_KINDS = {cia402.TARGET_POSITION: 'a position', cia402.TARGET_VELOCITY: 'a velocity',
                cia402.TARGET_TORQUE: 'a torque'}
# Seconds the node stays after publishing the one target: a process that ended right after
# publish() lost 1 sample in 15 here (measured with a best-effort subscriber in another
# process); with this wait none of 55 was lost.
LINGER = 0.3
# How long a drive state that refuses a target is given to be followed by a newer one: the
# gateway publishes a change a moment after it answered the command that made it (an enable
# just answered), a few milliseconds later on a busy machine.
STATE_SETTLE = 0.5

node_argument = ranged('node', 1, MAX_NODE_ID)


def drive_mode(text: str) -> int:
    """Parse a CiA 402 mode: a name (pp, pv, pt, homing, csp, csv, cst) or its number."""
    code = MODES.get(text.strip().lower())
    if code is None:
        try:
            code = integer(text)
        except argparse.ArgumentTypeError:
            code = None
    if code not in cia402.MODE_NAMES:
        allowed = ', '.join(f'{name} ({number})' for name, number in MODES.items())
        raise argparse.ArgumentTypeError(f'{quoted(text)} is not a CiA 402 mode: use '
                                         f'{allowed}')
    return code


def finite(text: str) -> float:
    """Parse a finite number (a position, velocity or target in joint units)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f'{quoted(text)} is not a finite number')
    return value


def _command_timeout(text: str) -> float:
    value = seconds(text)
    if not 0.0 <= value <= MAX_TIMEOUT:
        raise argparse.ArgumentTypeError(f'timeout {quoted(text)} is out of range: allowed 0 '
                                         f"(the gateway's default) to {MAX_TIMEOUT:g} s")
    return value


def error_text(code: int) -> str:
    """Return an error code of 0x603F with its meaning, e.g. '0x2310 continuous over-current'."""
    return f'0x{code:04X} {cia402.error_meaning(code)}'


def status_text(state: str, mode: int, statusword: int, error_code: int) -> str:
    """Return a drive's state in words: state, mode, statusword, and its error if it has one."""
    parts = [state, cia402.mode_name(mode) if mode else 'no mode',
             f'statusword 0x{statusword:04X}']
    if error_code:
        parts.append(f'error {error_text(error_code)}')
    return ', '.join(parts)


def cmd_drive(client: Client, args) -> int:
    """Send one command to a drive; print its state afterwards in one line."""
    if args.mode is not None and args.command not in MODE_COMMANDS:
        raise UsageError(f'--mode goes with {" and ".join(MODE_COMMANDS)}, not with '
                         f'{args.command}')
    if args.command == 'set-mode' and args.mode is None:
        raise UsageError(f'set-mode needs --mode MODE: {", ".join(MODES)} or its number')
    response = client.call(DriveCommand, 'drive_command', DriveCommand.Request(
        node_id=args.node, command=args.command.replace('-', '_'), mode=args.mode or 0,
        timeout=args.timeout), answer_within(args.timeout))
    what = f'node {args.node} {args.command}'
    status = status_text(response.state, response.mode, response.statusword,
                         response.error_code)
    if response.success:
        print(f'ok: {what}: {status}')
        return 0
    # A refusal before the drive was ever heard has no state worth showing.
    known = response.state != cia402.UNKNOWN or response.statusword or response.error_code
    print(f'error: {what}: {describe(response)}' + (f' ({status})' if known else ''),
          file=sys.stderr)
    return 1


def drive_topics(client: Client, leaf: str, count) -> Dict[int, str]:
    """Return ``{node id: topic}`` of the gateway's ``node_<id>/<leaf>`` topics in the graph.

    ``count(topic)`` counts the gateway's side of a topic (its publishers of drive_state, its
    subscriptions of target): a topic is in the graph as soon as anyone, this CLI too, uses it.
    """
    pattern = re.compile(rf'{re.escape(client.gateway)}/node_(\d+)/{leaf}')
    found = {}
    for name, _types in client.node.get_topic_names_and_types():
        match = pattern.fullmatch(name)
        if match and count(name):
            found[int(match[1])] = name
    return found


def _gateway_seen(client: Client) -> bool:
    """Return whether the graph has the gateway: every gateway publishes node_states."""
    return client.node.count_publishers(f'{client.gateway}/node_states') > 0


def _no_drive(client: Client, node_id: int) -> Exception:
    """Return the error of a node whose target nobody subscribes: no gateway, or no drive."""
    if not _gateway_seen(client):
        return GatewayUnavailable(f'no gateway at {client.gateway}: is cbcan_node running? '
                                  f'(waited {client.wait:g} s; check the gateway name and '
                                  f'ROS_DOMAIN_ID)')
    drives = sorted(drive_topics(client, 'target', client.node.count_subscribers))
    return UsageError(f'node {node_id} is not a drive of {client.gateway}: nothing subscribes '
                      f'node_{node_id}/target (its drives: {drives or "none"}; parameter '
                      f'drives.nodes); nothing was sent')


def _target_refusal(state: DriveState) -> Optional[str]:
    """Return why the gateway would drop a target for the drive in ``state``, or None.

    The gateway drops such a target with a line in its log only; the CLI says it here.
    """
    node_id = state.node_id
    if state.state != cia402.OPERATION_ENABLED:
        return (f'node {node_id} is {state.state}: targets go to an enabled drive only '
                f'(cbcan_cli drive {node_id} enable --mode MODE); nothing was sent')
    if state.mode not in cia402.TARGET_OF_MODE:
        return (f'node {node_id} is in {cia402.mode_name(state.mode)}, which takes no target '
                f'(cbcan_cli drive {node_id} set-mode --mode MODE); nothing was sent')
    return None


def _command_timeout_note(client: Client, node_id: int, mode: int) -> Optional[str]:
    if mode not in cia402.STREAMING_MODES:
        return None
    try:
        limit = client.parameter('drives.command_timeout')
    except GatewayError:
        limit = None  # the note is a courtesy: the target went out all the same
    if limit == 0.0:
        return None
    after = (f'{limit:g} s (parameter drives.command_timeout)' if isinstance(limit, float)
             else 'drives.command_timeout seconds')
    return (f'in {SHORT_MODE_NAMES[mode]} the gateway halts node {node_id} {after} after its '
            f'last target: stream targets to keep it moving')


def cmd_target(client: Client, args) -> int:
    """Publish one target on the gateway's node_<id>/target topic."""
    gateway, node_id = client.gateway, args.node
    publisher = client.node.create_publisher(Float64, f'{gateway}/node_{node_id}/target',
                                             TARGET_QOS)
    states = []
    subscription = client.node.create_subscription(
        DriveState, f'{gateway}/node_{node_id}/drive_state', states.append, STATE_QOS)
    try:
        with client.spinning() as spin_until:
            spin_until(lambda: publisher.get_subscription_count() and states, client.wait)
            if not publisher.get_subscription_count():
                raise _no_drive(client, node_id)
            if states and _target_refusal(states[-1]):
                spin_until(lambda: not _target_refusal(states[-1]), STATE_SETTLE)
            refusal = _target_refusal(states[-1]) if states else None
            if refusal:
                print(f'error: {refusal}', file=sys.stderr)
                return 1
            publisher.publish(Float64(data=args.value))
            spin_until(lambda: False, LINGER)
    finally:
        client.node.destroy_subscription(subscription)
        client.node.destroy_publisher(publisher)
    mode = states[-1].mode if states else 0
    kind = TARGET_KINDS.get(cia402.TARGET_OF_MODE.get(mode), 'the target')
    print(f'ok: node {node_id} target {args.value:g} sent ({kind} in {cia402.mode_name(mode)})'
          if mode else f'ok: node {node_id} target {args.value:g} sent')
    note = _command_timeout_note(client, node_id, mode)
    if note:
        print(f'note: {note}', file=sys.stderr)
    return 0


HEADER = ('node', 'joint', 'state', 'mode', 'position', 'velocity', 'error')


def _drive_row(node_id: int, state: Optional[DriveState],
               joint_states: Optional[JointState]) -> List[str]:
    """Return the columns of one drive's line of the table (HEADER)."""
    if state is None:
        return [str(node_id), '-', '(no drive_state yet: is the gateway active?)']
    shown = state.state + (' (halted)' if state.halted else '')
    mode = SHORT_MODE_NAMES.get(state.mode, str(state.mode) if state.mode else '-')
    error = error_text(state.error_code) if state.error_code else '-'
    # drive_state comes on a change of state, mode, error or halt, with the position of that
    # moment; joint_states brings the actual values every feedback cycle.
    position, velocity = state.position, state.velocity
    if joint_states is not None and state.joint in joint_states.name:
        at = list(joint_states.name).index(state.joint)
        position, velocity = joint_states.position[at], joint_states.velocity[at]
    return [str(node_id), state.joint, shown, mode, f'{position:.6g}', f'{velocity:.6g}',
            error]


def print_table(rows: List[List[str]]) -> None:
    """Print HEADER and ``rows`` in columns: numbers right-aligned, the last column as it is."""
    widths = [max((len(row[column]) for row in [list(HEADER), *rows] if column < len(row) - 1),
                  default=0) for column in range(len(HEADER))]
    right = {0, 4, 5}
    for row in [list(HEADER), *rows]:
        cells = [cell.rjust(widths[column]) if column in right else cell.ljust(widths[column])
                 for column, cell in enumerate(row[:-1])]
        print('  '.join([*cells, row[-1]]))


def cmd_drives(client: Client, args) -> int:
    """Print every drive's state, mode, error (drive_state) and actual values (joint_states)."""
    latest: Dict[int, DriveState] = {}
    subscriptions = {}
    joint_states: List[JointState] = []
    actual_values = client.node.create_subscription(
        JointState, f'{client.gateway}/joint_states', joint_states.append, JOINT_STATES_QOS)

    def all_heard() -> bool:
        # Topics are looked for again on every turn: the gateway's may be found one by one.
        for node_id, topic in drive_topics(client, 'drive_state',
                                           client.node.count_publishers).items():
            if node_id not in subscriptions:
                subscriptions[node_id] = client.node.create_subscription(
                    DriveState, topic, lambda message, n=node_id: latest.update({n: message}),
                    STATE_QOS)
        return bool(subscriptions) and len(latest) == len(subscriptions) and bool(joint_states)
    try:
        with client.spinning() as spin_until:
            spin_until(all_heard, client.wait)
    finally:
        for subscription in [actual_values, *subscriptions.values()]:
            client.node.destroy_subscription(subscription)
    if not subscriptions:
        if not _gateway_seen(client):
            raise GatewayUnavailable(f'no gateway at {client.gateway}: is cbcan_node running? '
                                     f'(waited {client.wait:g} s for its drive_state topics; '
                                     f'check the gateway name and ROS_DOMAIN_ID)')
        print(f'error: {client.gateway} has no drives (its parameter drives.nodes is empty)',
              file=sys.stderr)
        return 1
    print_table([_drive_row(node_id, latest.get(node_id),
                            joint_states[-1] if joint_states else None)
                 for node_id in sorted(subscriptions)])
    return 0


def add_commands(commands) -> None:
    """Add drive, target and drives."""
    drive = commands.add_parser(
        'drive', help='command a CiA 402 drive: enable, disable, halt, ...',
        description='Send one command to a CiA 402 drive of the gateway (parameter '
                    "drives.nodes) and print the drive's state once its statusword shows the "
                    'result.')
    drive.add_argument('node', type=node_argument, metavar='NODE', help='node id 1..127')
    drive.add_argument('command', type=lambda text: text.lower().replace('_', '-'),
                       choices=DRIVE_COMMANDS, metavar='COMMAND',
                       help=f'{"|".join(DRIVE_COMMANDS)}')
    drive.add_argument('--mode', type=drive_mode, metavar='MODE',
                       help='the mode of operation for enable (default: keep the present one) '
                            f'and set-mode: {", ".join(MODES)} or its CiA 402 number')
    drive.add_argument('--timeout', type=_command_timeout, default=0.0, metavar='S',
                       help='seconds the drive has to show the result (default 0: the '
                            f"gateway's, {DEFAULT_TIMEOUT:g} s, home {HOMING_TIMEOUT:g} s)")
    drive.set_defaults(run=cmd_drive)

    target = commands.add_parser(
        'target', help='send one target to a drive in its present mode',
        description="Publish one target on the gateway's node_<id>/target topic: a position, "
                    "velocity or torque in the joint's units, as the drive's present mode "
                    'takes it. In the streaming modes (PV, PT, CSP, CSV, CST) the gateway halts '
                    'the drive drives.command_timeout seconds after the last target: a single '
                    'target moves it that long only, unless the parameter is 0.')
    target.add_argument('node', type=node_argument, metavar='NODE', help='node id 1..127')
    target.add_argument('value', type=finite, metavar='VALUE', help='the target, joint units')
    target.set_defaults(run=cmd_target)

    drives = commands.add_parser(
        'drives', help="print every drive's state",
        description="Print every drive's state, mode and error (the gateway's "
                    'node_<id>/drive_state topics) and its position and velocity (its '
                    'joint_states), in joint units.')
    drives.set_defaults(run=cmd_drives)
