"""One goal of a gateway's action, sent and followed by ``cbcan_cli``; Ctrl-C cancels it.

Shared by ``move`` and ``program-download``: the first Ctrl-C cancels the goal and waits for
its answer (which says where the drive stopped, or what the device was left in), a second
one ends the wait at once.
"""

import signal
import sys
import threading
from typing import Callable, Optional, Tuple

from ..client import PRESENCE_CHECK
from ..rclpy_gaps import FeedbackFirstActionClient
from ..service_caller import ANSWER_MARGIN, GatewayUnavailable
from .standalone_client import Client

INTERRUPTED = 130  # the shell's status for a command ended by Ctrl-C


class Interrupts:
    """Ctrl-C while a goal runs: the first cancels the goal, a second ends the wait at once.

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


def follow_goal(client: Client, action_type, name: str, goal,
                feedback: Callable[[object], None], what: str,
                left_running: str) -> Tuple[Optional[object], bool]:
    """Send ``goal`` to the action ``gateway/name`` and wait for its answer.

    Returns (the result response, with ``result`` and ``status``, or None when Ctrl-C came
    before the goal was sent; whether Ctrl-C was pressed). ``what`` names the goal in
    messages ("move of node 7"), ``left_running`` says what a cancel left unanswered may have
    left. Raises GatewayUnavailable when no gateway takes or answers the goal.
    """
    action = FeedbackFirstActionClient(client.node, action_type, f'{client.gateway}/{name}')
    try:
        with Interrupts() as interrupts, client.spinning() as spin_until:
            if not spin_until(lambda: action.server_is_ready() or interrupts.count,
                              client.wait):
                raise GatewayUnavailable(
                    f'no gateway at {client.gateway}: is cbcan_node running? (waited '
                    f'{client.wait:g} s for its {name} action; check the gateway name and '
                    f'ROS_DOMAIN_ID)')
            if interrupts.count:
                return None, True
            sent = action.send_goal_async(goal, feedback_callback=feedback)
            # Ctrl-C meanwhile is kept: the goal is cancelled once it is known.
            if not spin_until(sent.done, client.wait + ANSWER_MARGIN):
                raise GatewayUnavailable(f'{client.gateway}/{name} did not take the goal')
            handle = sent.result()
            if not handle.accepted:
                raise GatewayUnavailable(f'{client.gateway}/{name} refused the goal')
            answered = handle.get_result_async()
            while not spin_until(lambda: answered.done() or interrupts.count,
                                 PRESENCE_CHECK):
                if not action.server_is_ready():
                    raise GatewayUnavailable(f'{client.gateway} went away during the {what}')
            if not answered.done():
                print(f'cancelling the {what}', file=sys.stderr, flush=True)
                handle.cancel_goal_async()
                if not spin_until(answered.done, client.wait + ANSWER_MARGIN):
                    raise GatewayUnavailable(f'{client.gateway} did not answer the cancel: '
                                             f'{left_running}')
            return answered.result(), bool(interrupts.count)
    finally:
        action.destroy()
