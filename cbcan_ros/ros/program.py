"""The ``~/program_download`` action (``cbcan_ros/ProgramDownload``) onto the program service.

A goal runs on the core's download thread from the moment it is accepted; its execute
callback runs only once the download has ended, to hand rclpy the result. The executor
holds nothing meanwhile: an ``async`` execute callback awaiting the download's end would be
resumed by rclpy's EventsExecutor over and over (it does not wait for the awaited future),
holding the interpreter's lock from the transfer (a 256 KiB image went at two thirds of the
speed). So the goal shows ACCEPTED while the download runs (its feedback tells the phase)
and EXECUTING only as it ends. Feedback is published from the download's thread; a cancel
ends the download between two segments or blocks, and the result says what the device was
left in.
"""

import logging
import threading
from typing import Callable, Dict, Optional

from rclpy.node import Node

from ..action import ProgramDownload
from ..core.program.download import ProgramResult, Progress
from ..core.program.service import ProgramRequest, ProgramService
from ..core.sdo.request_queue import resolved
from .goals import GoalCallbacks, KeptActionServer

LOGGER = logging.getLogger(__name__)


class ProgramAction:
    """The action server of the program downloads; ``refusal()``: why no goal now, or None."""

    def __init__(self, node: Node, service: ProgramService,
                 refusal: Callable[[], Optional[str]]):
        self._service = service
        self._refusal = refusal
        self._cancels: Dict[bytes, Callable[[], None]] = {}
        self._results: Dict[bytes, ProgramResult] = {}  # downloads ended, goals to answer
        self._running = 0
        self.answered = 0  # goals answered (results handed to ROS) since the start
        self._idle = threading.Condition()
        self._server = KeptActionServer.of(node, ProgramDownload, '~/program_download')
        self._server.attach(GoalCallbacks(self._answer, self._cancels, accepted=self._start))

    def wait_until_answered(self, timeout: float) -> None:
        """Wait (shutdown) until every goal's result is decided and handed to ROS."""
        with self._idle:
            self._idle.wait_for(lambda: not self._running, timeout)

    def destroy(self) -> None:
        """Answer the goals that come from now on as no gateway's (the server stays)."""
        self._server.detach()

    def _start(self, goal_handle) -> None:
        """Start the download of an accepted goal; the goal is executed once it has ended."""
        goal = goal_handle.request
        key = bytes(goal_handle.goal_id.uuid)

        def feedback(progress: Progress) -> None:
            goal_handle.publish_feedback(ProgramDownload.Feedback(
                phase=progress.phase, bytes_sent=progress.bytes_sent,
                bytes_total=progress.bytes_total,
                bytes_per_second=float(progress.bytes_per_second)))

        with self._idle:
            self._running += 1
        refusal = self._refusal()
        if refusal:
            future = resolved(ProgramResult(False, refusal, refused=True))
        else:
            future, self._cancels[key] = self._service.download(ProgramRequest(
                goal.node_id, goal.file, goal.program, goal.expected_software_id, goal.start),
                feedback)
        future.add_done_callback(lambda done: self._ended(goal_handle, done.result()))

    def _ended(self, goal_handle, result: ProgramResult) -> None:
        """Have the executor answer the goal (``_answer``) now that its download ended."""
        key = bytes(goal_handle.goal_id.uuid)
        self._cancels.pop(key, None)
        self._results[key] = result
        try:
            goal_handle.execute()
        except Exception as error:  # noqa: BLE001 - rclpy is gone: nobody can be answered
            LOGGER.warning('node %d: the result of a program download could not be handed to '
                           'ROS (%r): %s', goal_handle.request.node_id, error, result.message)
            with self._idle:
                self._running -= 1
                self._idle.notify_all()

    def _answer(self, goal_handle):
        """End the goal with its download's result (the execute callback)."""
        try:
            result = self._results.pop(bytes(goal_handle.goal_id.uuid))
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
            with self._idle:
                self._running -= 1
                self.answered += 1
                self._idle.notify_all()
