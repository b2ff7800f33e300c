"""The boot commands of ``cbcan_cli``: boot (run a device's boot again) and boot-states."""

import sys

from ...core.boot.service import DEFAULT_CALL_TIMEOUT
from ...core.protocol import MAX_NODE_ID
from ...core.sdo.requests import MAX_TIMEOUT
from ..client import RequestFailed
from .arguments import bounded_seconds, ranged
from .standalone_client import Client


def _table(states) -> None:
    print(f'{"node":>4}  {"name":<20}  {"state":<8}  {"error":<5}  {"writes":>6}  '
          f'{"boots":>5}  message')
    for state in states:
        print(f'{state.node_id:>4}  {state.name:<20}  {state.state:<8}  '
              f'{state.error_status or "-":<5}  {state.writes:>6}  {state.boots:>5}  '
              f'{state.message}')


def cmd_boot(client: Client, args) -> int:
    """Run the boot of a device (0: every device) again and print how each one ended."""
    try:
        response = client.boot(args.node, args.timeout)
    except RequestFailed as failed:
        if failed.response.states:
            _table(failed.response.states)
        print(f'error: {failed.response.message}', file=sys.stderr)
        return 1
    _table(response.states)
    print(f'ok: {response.message}')
    return 0


def cmd_boot_states(client: Client, args) -> int:
    """Print every booted device's boot state from the boot_states topic."""
    message = client.boot_states()
    if not message.states:
        print('the gateway boots no device (no bus_config, no pdo.configure)')
        return 0
    _table(message.states)
    return 0


_boot_seconds = bounded_seconds(MAX_TIMEOUT, f'the default, {DEFAULT_CALL_TIMEOUT:g} s')


def add_commands(commands) -> None:
    """Add boot and boot-states."""
    boot = commands.add_parser(
        'boot', help="run a device's boot again (check, configure, start)",
        description='Run the boot of a device of the bus description again (CiA 302-2): '
                    'its identity checked, its configuration written and read back, then '
                    'started. Prints how each boot ended, with its error letter.')
    boot.add_argument('node', type=ranged('node', 0, MAX_NODE_ID), nargs='?', default=0,
                      metavar='NODE', help='node id 1..127; 0 or none: every device')
    boot.add_argument('--timeout', type=_boot_seconds, default=0.0, metavar='S',
                      help=f'seconds to wait for the boots (default 0: '
                           f'{DEFAULT_CALL_TIMEOUT:g} s); a boot still running goes on')
    boot.set_defaults(run=cmd_boot)
    states = commands.add_parser(
        'boot-states', help='print the boot state of every booted device',
        description='Print the latest boot_states message as a table: state, CiA 302-2 '
                    'error letter, objects written, boots completed.')
    states.set_defaults(run=cmd_boot_states)
