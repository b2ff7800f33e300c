"""The ``~/program_download`` action (``cbcan_ros/ProgramDownload``) onto the program service.

A goal runs on the core's download thread: the execute callback only awaits its answer, so
the executor goes on serving every other call meanwhile. Feedback is published from that
thread; a cancel ends the download between two segments or blocks, and the result says what
the device was left in.
"""

import threading
from typing import Callable, Dict, Optional

from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.task import Future as RclpyFuture

from ..action import ProgramDownload
from ..core.program.download import ProgramResult, Progress
from ..core.program.service import ProgramRequest, ProgramService


class ProgramAction:
    """The action server of the program downloads; ``refusal()``: why no goal now, or None."""

    def __init__(self, node: Node, service: ProgramService,
                 refusal: Callable[[], Optional[str]]):
        self._service = service
        self._refusal = refusal
        self._cancels: Dict[bytes, Callable[[], None]] = {}
        self._running = 0
        self.answered = 0  # goals answered (results handed to ROS) since the start
        self._idle = threading.Condition()
        self._server = ActionServer(node, ProgramDownload, '~/program_download',
                                    execute_callback=self._execute,
                                    goal_callback=lambda goal: GoalResponse.ACCEPT,
                                    cancel_callback=self._on_cancel,
                                    callback_group=ReentrantCallbackGroup())

    def wait_until_answered(self, timeout: float) -> None:
        """Wait (shutdown) until every goal's result is decided and handed to ROS."""
        with self._idle:
            self._idle.wait_for(lambda: not self._running, timeout)

    def destroy(self) -> None:
        """Take the action server away."""
        self._server.destroy()

    def _on_cancel(self, goal_handle) -> CancelResponse:
        cancel = self._cancels.get(bytes(goal_handle.goal_id.uuid))
        if cancel is None:
            return CancelResponse.REJECT
        cancel()
        return CancelResponse.ACCEPT

    async def _execute(self, goal_handle):
        goal = goal_handle.request
        refusal = self._refusal()
        if refusal:
            goal_handle.abort()
            return ProgramDownload.Result(success=False, message=refusal)

        def feedback(progress: Progress) -> None:
            goal_handle.publish_feedback(ProgramDownload.Feedback(
                phase=progress.phase, bytes_sent=progress.bytes_sent,
                bytes_total=progress.bytes_total,
                bytes_per_second=float(progress.bytes_per_second)))

        with self._idle:
            self._running += 1
        key = bytes(goal_handle.goal_id.uuid)
        try:
            future, cancel = self._service.download(ProgramRequest(
                goal.node_id, goal.file, goal.program, goal.expected_software_id, goal.start),
                feedback)
            self._cancels[key] = cancel
            done = RclpyFuture()
            future.add_done_callback(lambda finished: done.set_result(finished.result()))
            result: ProgramResult = await done
            self._cancels.pop(key, None)
            if result.success:
                goal_handle.succeed()
            elif goal_handle.is_cancel_requested and not result.refused:
                goal_handle.canceled()
            else:
                goal_handle.abort()
            return ProgramDownload.Result(success=result.success, message=result.message,
                                          software_id=result.software_id,
                                          abort_code=result.abort_code,
                                          flash_status=result.flash_status)
        finally:
            # rclpy sends the result in this same step of the executor, right after the
            # return: a shutdown waiting for this count sees the result leave before the
            # executor stops.
            self._cancels.pop(key, None)
            with self._idle:
                self._running -= 1
                self.answered += 1
                self._idle.notify_all()
