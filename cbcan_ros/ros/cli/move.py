"""The move command of ``cbcan_cli``: a drive to a position through the ``~/move`` action."""

import argparse
import signal
import sys
import threading
import time

from action_msgs.msg import GoalStatus
from rclpy.action import ActionClient

from ...action import DriveMove
from ...core.drives.checks import NOTHING_SENT
from ..service_caller import ANSWER_MARGIN, GatewayUnavailable
from .drive import error_text, finite, node_argument
from .standalone_client import Client

# Seconds between two feedback lines: the gateway sends feedback on every statusword.
FEEDBACK_PERIOD = 0.25
# Seconds between looks at whether the gateway is still there while a move runs.
PRESENCE_CHECK = 1.0
INTERRUPTED = 130  # the shell's status for a command ended by Ctrl-C


class Interrupts:
    """Ctrl-C while a move runs: the first cancels the move, a second ends the wait at once.

    The first is counted, the second raises KeyboardInterrupt. Taking the signal as a count,
    not as an exception raised somewhere inside rclpy, leaves the action client able to send
    the cancel.
    """

    def __init__(self):
        self.count = 0
        self._previous = None

    def __enter__(self) -> 'Interrupts':
        if threading.current_thread() is threading.main_thread():  # only it takes signals
            self._previous = signal.signal(signal.SIGINT, self._on_signal)
        return self

    def __exit__(self, *_exception) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)

    def _on_signal(self, *_arguments) -> None:
        self.count += 1
        if self.count > 1:
            raise KeyboardInterrupt


class FeedbackLines:
    """Prints a move's feedback, one line every FEEDBACK_PERIOD at most."""

    def __init__(self, node_id: int):
        self._node_id = node_id
        self._printed = -FEEDBACK_PERIOD

    def __call__(self, message) -> None:
        """Take one feedback message of the action; print it unless one was just printed."""
        now = time.monotonic()
        if now - self._printed >= FEEDBACK_PERIOD:
            self._printed = now
            feedback = message.feedback
            print(f'node {self._node_id}: position {feedback.position:.6g}, velocity '
                  f'{feedback.velocity:.6g}', flush=True)


def speed(text: str) -> float:
    """Parse a velocity for a move: a finite number, 0 or more."""
    value = finite(text)
    if value < 0.0:
        raise argparse.ArgumentTypeError(f'velocity {text} is a speed: give 0 or more (the '
                                         f'direction comes from the goal)')
    return value


def _answer(args, result, status: int, interrupted: bool) -> int:
    """Print how the move ended; return the exit status."""
    where = f'position {result.position:.6g}'
    error = f', error {error_text(result.error_code)}' if result.error_code else ''
    if status == GoalStatus.STATUS_SUCCEEDED:
        print(f'ok: node {args.node} reached {where}{error}')
        return INTERRUPTED if interrupted else 0
    if status == GoalStatus.STATUS_CANCELED:
        print(f'cancelled: node {args.node} halted at {where}{error}')
        return INTERRUPTED if interrupted else 1
    # A refused goal (nothing sent) has no position to tell.
    at = '' if NOTHING_SENT in result.message else f' (at {where}{error})'
    print(f'error: node {args.node} move: {result.message}{at}', file=sys.stderr)
    return INTERRUPTED if interrupted else 1


def cmd_move(client: Client, args) -> int:
    """Move a drive to a position (profile position mode), following it; Ctrl-C cancels."""
    action = ActionClient(client.node, DriveMove, f'{client.gateway}/move')
    goal = DriveMove.Goal(node_id=args.node, position=args.position, relative=args.relative,
                          velocity=args.velocity)
    try:
        with Interrupts() as interrupts, client.spinning() as spin_until:
            if not spin_until(lambda: action.server_is_ready() or interrupts.count,
                              client.wait):
                raise GatewayUnavailable(
                    f'no gateway at {client.gateway}: is cbcan_node running? (waited '
                    f'{client.wait:g} s for its move action; check the gateway name and '
                    f'ROS_DOMAIN_ID)')
            if interrupts.count:
                print('interrupted: no move was sent', file=sys.stderr)
                return INTERRUPTED
            sent = action.send_goal_async(goal, feedback_callback=FeedbackLines(args.node))
            # Ctrl-C meanwhile is kept: the goal is cancelled once it is known.
            if not spin_until(sent.done, client.wait + ANSWER_MARGIN):
                raise GatewayUnavailable(f'{client.gateway}/move did not take the goal')
            handle = sent.result()
            if not handle.accepted:
                print(f'error: node {args.node} move: the gateway refused the goal',
                      file=sys.stderr)
                return 1
            answered = handle.get_result_async()
            while not spin_until(lambda: answered.done() or interrupts.count,
                                 PRESENCE_CHECK):
                if not action.server_is_ready():
                    raise GatewayUnavailable(f'{client.gateway} went away during the move')
            if not answered.done():
                print(f'cancelling the move of node {args.node}', file=sys.stderr, flush=True)
                handle.cancel_goal_async()
                if not spin_until(answered.done, client.wait + ANSWER_MARGIN):
                    raise GatewayUnavailable(f'{client.gateway} did not answer the cancel: '
                                             f'node {args.node} may still be moving')
            response = answered.result()
            return _answer(args, response.result, response.status, bool(interrupts.count))
    finally:
        action.destroy()


def add_commands(commands) -> None:
    """Add move."""
    move = commands.add_parser(
        'move', help='move a drive to a position and follow it there',
        description="Move a CiA 402 drive to a position (the gateway's move action, in "
                    'profile position mode), printing its position on the way and where it '
                    'ended. The drive must be enabled (cbcan_cli drive NODE enable). Ctrl-C '
                    'cancels the move: the gateway halts the drive, the command prints where '
                    'it stopped and exits with status 130.')
    move.add_argument('node', type=node_argument, metavar='NODE', help='node id 1..127')
    move.add_argument('position', type=finite, metavar='POSITION',
                      help="the goal, in the joint's units")
    move.add_argument('--relative', action='store_true',
                      help='POSITION is relative to the present target, not absolute')
    move.add_argument('--velocity', type=speed, default=0.0, metavar='V',
                      help="joint units/s (default 0: the drive's profile velocity, 0x6081)")
    move.set_defaults(run=cmd_move)
