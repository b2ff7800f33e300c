"""The move command of ``cbcan_cli``: a drive to a position through the ``~/move`` action."""

import argparse
import sys
import time

from action_msgs.msg import GoalStatus

from ...action import DriveMove
from ...core.drives.checks import NOTHING_SENT
from .drive import error_text, finite, node_argument
from .goals import follow_goal, INTERRUPTED
from .standalone_client import Client

# Seconds between two feedback lines: the gateway sends feedback on every statusword.
FEEDBACK_PERIOD = 0.25


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
    goal = DriveMove.Goal(node_id=args.node, position=args.position, relative=args.relative,
                          velocity=args.velocity)
    response, interrupted = follow_goal(client, DriveMove, 'move', goal,
                                        FeedbackLines(args.node), f'move of node {args.node}',
                                        f'node {args.node} may still be moving')
    if response is None:
        print('interrupted: no move was sent', file=sys.stderr)
        return INTERRUPTED
    return _answer(args, response.result, response.status, interrupted)


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
