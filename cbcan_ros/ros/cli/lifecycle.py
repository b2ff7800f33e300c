"""The lifecycle command of ``cbcan_cli``: a managed gateway's state and its transitions.

What ``ros2 lifecycle get`` and ``ros2 lifecycle set`` do, for machines without the ros2 CLI:
the transition is asked by its label among those the node offers from its present state.
"""

import sys
import time

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetAvailableTransitions, GetState

from .arguments import positive_seconds
from .standalone_client import Client

TRANSITIONS = ('configure', 'activate', 'deactivate', 'cleanup', 'shutdown')
# Seconds a transition may take by default: configure opens the bus and reads the drives,
# cleanup and shutdown answer the calls waiting (about a second).
TRANSITION_TIMEOUT = 30.0
GRAPH_LOOK = 0.05  # s between looks at the ROS graph for the gateway's services


def _state(client: Client) -> str:
    return client.call(GetState, 'get_state', GetState.Request()).current_state.label


def _plain(client: Client) -> bool:
    """Return whether the gateway is a plain node: it serves, with no lifecycle services.

    Waits (up to the client's wait) until either shows in the ROS graph; False when neither
    does, so the call that follows says there is no gateway.
    """
    deadline = time.monotonic() + client.wait
    while True:
        names = {name for name, _types in client.node.get_service_names_and_types()}
        if f'{client.gateway}/get_state' in names:
            return False
        if f'{client.gateway}/sdo_read' in names:
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(GRAPH_LOOK)


def cmd_lifecycle(client: Client, args) -> int:
    """Print the managed gateway's state, or make a transition and print the state it left."""
    if _plain(client):
        print(f'error: {client.gateway} is not a managed node (it serves without a '
              f'lifecycle: cbcan_node, not cbcan_lifecycle_node)', file=sys.stderr)
        return 2
    state = _state(client)
    if args.transition is None:
        print(state)
        return 0
    offered = client.call(GetAvailableTransitions, 'get_available_transitions',
                          GetAvailableTransitions.Request()).available_transitions
    chosen = next((each.transition for each in offered
                   if each.transition.label == args.transition), None)
    if chosen is None:
        labels = ', '.join(sorted({each.transition.label for each in offered})) or 'none'
        print(f'error: {client.gateway} is {state}: {args.transition} is not a transition '
              f'from there (from {state}: {labels})', file=sys.stderr)
        return 1
    answer = client.call(ChangeState, 'change_state', ChangeState.Request(
        transition=Transition(id=chosen.id, label=chosen.label)), args.timeout)
    state = _state(client)
    if not answer.success:
        print(f'error: {args.transition} failed: {client.gateway} is {state} (its log says '
              f'why)', file=sys.stderr)
        return 1
    print(f'ok: {client.gateway} is {state}')
    return 0


def add_commands(commands) -> None:
    """Add lifecycle."""
    lifecycle = commands.add_parser(
        'lifecycle', help="a managed gateway's lifecycle state, or a transition",
        description='Without TRANSITION: print the lifecycle state of a managed gateway '
                    '(cbcan_lifecycle_node): unconfigured, inactive, active or finalized. '
                    'With one: make it (as ros2 lifecycle set does) and print the state '
                    'the gateway is in afterwards.')
    lifecycle.add_argument('transition', nargs='?', choices=TRANSITIONS, metavar='TRANSITION',
                           help=f'one of {", ".join(TRANSITIONS)}')
    lifecycle.add_argument('--timeout', type=positive_seconds, default=TRANSITION_TIMEOUT,
                           metavar='S',
                           help=f'seconds to wait for the transition (default '
                                f'{TRANSITION_TIMEOUT:g})')
    lifecycle.set_defaults(run=cmd_lifecycle)
