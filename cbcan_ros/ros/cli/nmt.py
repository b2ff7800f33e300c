"""The NMT commands of ``cbcan_cli``: nmt, and the node states (state, states)."""

import argparse
import time

from ...core.text import quoted
from ..client import NMT_COMMANDS
from .arguments import integer, node_id
from .standalone_client import Client


def _nmt_command(text: str) -> int:
    """Parse an NMT command: a name (start, stop, preop, reset, reset-comm) or its number."""
    name = text.lower()
    if name in NMT_COMMANDS:
        return NMT_COMMANDS[name]
    try:
        value = integer(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f'{quoted(text)} is not an NMT command: use {", ".join(NMT_COMMANDS)} or a number'
        ) from None
    if not 0 <= value <= 255:
        raise argparse.ArgumentTypeError(f'NMT command {text} is out of range: allowed 0..255')
    return value


def cmd_nmt(client: Client, args) -> int:
    """Send an NMT command."""
    client.nmt(args.node, args.command)
    target = 'all nodes' if args.node == 0 else f'node {args.node}'
    print(f'ok: sent NMT command {args.command} to {target}')
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


def add_commands(commands) -> None:
    """Add nmt, state and states."""
    nmt = commands.add_parser('nmt', help='send an NMT command',
                              description='Send an NMT command to a node (0 = all nodes).')
    nmt.add_argument('node', type=node_id, metavar='NODE', help='node id 1..127, 0 = all nodes')
    nmt.add_argument('command', type=_nmt_command, metavar='COMMAND',
                     help=f'{"|".join(NMT_COMMANDS)} or the command byte')
    nmt.set_defaults(run=cmd_nmt)

    state = commands.add_parser('state', help="print a node's NMT state",
                                description='Print the NMT state a node last reported.')
    state.add_argument('node', type=node_id, metavar='NODE', help='node id 1..127')
    state.set_defaults(run=cmd_state)

    states = commands.add_parser('states', help='print the state of every known node',
                                 description='Print the latest node_states message as a '
                                             'table.')
    states.set_defaults(run=cmd_states)
