"""What the gateway's action servers (``~/move``, ``~/program_download``) share.

An action server lives as long as its node (:class:`KeptActionServer`): destroyed while
rclpy's ``EventsExecutor`` spins, as a managed node's cleanup did, the process died of a
segmentation fault when a goal or result request for it came within milliseconds (7 of 7
tries, docs/library_gaps.md). A gateway attaches its callbacks when it is made and detaches
them when it goes; a goal that comes while none is attached is answered at once.
"""

from dataclasses import dataclass
from typing import Callable, Dict, Optional

from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import await_or_execute
from rclpy.node import Node

from .service_qos import ACTION_RESULT_KEPT, ACTION_SERVICES_QOS

# What a goal that comes while no gateway serves the action is answered.
UNSERVED = ('the gateway is not configured (a managed node after cleanup: configure and '
            'activate it first); nothing was sent')


@dataclass(frozen=True)
class GoalCallbacks:
    """A gateway's side of one action: rclpy's execute and accepted callbacks, its cancels.

    ``cancels``: the cancel of each goal under way, by goal id (a goal without one has ended,
    and a cancel of it is rejected).
    """

    execute: Callable
    cancels: Dict[bytes, Callable[[], None]]
    accepted: Optional[Callable] = None  # None: the goal is executed at once


class KeptActionServer:
    """An action server made once per node and name, serving the callbacks attached now.

    Each goal stays with the callbacks it was accepted by until it is executed to its end,
    so a goal under way when they are detached is still ended by its own gateway.
    """

    _kept: Dict[Node, Dict[str, 'KeptActionServer']] = {}  # until destroy_all

    @classmethod
    def of(cls, node: Node, action_type, name: str) -> 'KeptActionServer':
        """Return ``node``'s server of action ``name``, made at its first use."""
        servers = cls._kept.setdefault(node, {})
        if name not in servers:
            servers[name] = cls(node, action_type, name)
        return servers[name]

    @classmethod
    def destroy_all(cls, node: Node) -> None:
        """Destroy ``node``'s action servers (once its executor no longer spins)."""
        for server in cls._kept.pop(node, {}).values():
            server._server.destroy()

    def __init__(self, node: Node, action_type, name: str):
        self._type = action_type
        self._callbacks: Optional[GoalCallbacks] = None
        self._of_goal: Dict[bytes, Optional[GoalCallbacks]] = {}
        self._server = ActionServer(node, action_type, name, execute_callback=self._execute,
                                    goal_callback=lambda goal: GoalResponse.ACCEPT,
                                    handle_accepted_callback=self._accepted,
                                    cancel_callback=self._cancel,
                                    callback_group=ReentrantCallbackGroup(),
                                    result_timeout=ACTION_RESULT_KEPT, **ACTION_SERVICES_QOS)

    def attach(self, callbacks: GoalCallbacks) -> None:
        """Serve the goals that come from now on with ``callbacks``."""
        self._callbacks = callbacks

    def detach(self) -> None:
        """Answer the goals that come from now on ``UNSERVED``."""
        self._callbacks = None

    def _accepted(self, goal_handle) -> None:
        callbacks = self._of_goal[bytes(goal_handle.goal_id.uuid)] = self._callbacks
        if callbacks is not None and callbacks.accepted is not None:
            callbacks.accepted(goal_handle)
        else:
            goal_handle.execute()

    async def _execute(self, goal_handle):
        key = bytes(goal_handle.goal_id.uuid)
        callbacks = self._of_goal.get(key)
        try:
            if callbacks is None:
                goal_handle.abort()
                return self._type.Result(success=False, message=UNSERVED)
            return await await_or_execute(callbacks.execute, goal_handle)
        finally:
            self._of_goal.pop(key, None)

    def _cancel(self, goal_handle) -> CancelResponse:
        key = bytes(goal_handle.goal_id.uuid)
        callbacks = self._of_goal.get(key)
        cancel = callbacks.cancels.get(key) if callbacks is not None else None
        if cancel is None:
            return CancelResponse.REJECT
        cancel()
        return CancelResponse.ACCEPT
