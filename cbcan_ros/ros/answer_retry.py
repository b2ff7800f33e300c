"""Answers the middleware dropped because it had not met their caller yet, offered again.

A caller's first call can reach the node before the node's DDS has matched the caller's
answer reader: discovery runs on threads of its own, which a loaded machine holds up, and a
client's ``service_is_ready()`` says only that the client has found the service, not that
the service has found the client. rmw_fastrtps then waits its answer writer's
``max_blocking_time`` (100 ms) for the match and drops the answer, and the caller waits for
ever (rclpy says so with a warning: ``rclpy_gaps.send_or_report_dropped``). The answer is
already made, so nothing is done twice on the bus: it is offered again every
``RETRY_PERIOD`` until the reader matches, for up to ``RETRY_WINDOW``.
"""

from dataclasses import dataclass
import logging
import threading
import time
from typing import Callable, List

from .rclpy_gaps import send_or_report_dropped

LOGGER = logging.getLogger(__name__)

# Discovery on a loaded machine has been seen to take seconds; a caller that never matches
# (it went away) costs one attempt per period, each blocking the retry thread up to 100 ms.
RETRY_PERIOD = 0.1
RETRY_WINDOW = 10.0


@dataclass(eq=False)  # each one is itself, whatever it holds
class _Dropped:
    service: str
    send: Callable[[object, object], bool]
    response: object
    header: object
    since: float


class AnswerRetry:
    """Sends services' answers, and offers again those dropped, from one thread of its own."""

    def __init__(self):
        self._dropped: List[_Dropped] = []
        self._changed = threading.Condition()
        self._closed = False
        self._thread = None  # started by the first dropped answer

    @property
    def waiting(self) -> int:
        """Return how many dropped answers are still being offered."""
        with self._changed:
            return len(self._dropped)

    def sender(self, service, send: Callable) -> Callable[[object, object], None]:
        """Return ``answer(response, header)`` sending through ``send``, rclpy's own.

        Answers of one service leave one at a time (rcl sends on a service from one thread
        at a time); a dropped one is kept and offered again.
        """
        lock = threading.Lock()

        def send_once(response, header) -> bool:
            with lock:
                return send_or_report_dropped(send, response, header)

        def answer(response, header) -> None:
            if not send_once(response, header):
                self._keep(_Dropped(service.srv_name, send_once, response, header,
                                    time.monotonic()))
        return answer

    def retry_dropped_answers(self, service) -> None:
        """Make a service the executor answers (its callback returns the answer) retry too."""
        service.send_response = self.sender(service, service.send_response)

    def close(self) -> None:
        """Stop offering (the services are going away); log the answers given up."""
        with self._changed:
            self._closed = True
            given_up, self._dropped = self._dropped, []
            self._changed.notify_all()
        if self._thread:
            self._thread.join()
        for dropped in given_up:
            LOGGER.warning('an answer of %s never reached its caller: its DDS answer reader '
                           'was still not matched when the service went away', dropped.service)

    def _keep(self, dropped: _Dropped) -> None:
        with self._changed:
            if self._closed:
                LOGGER.warning('an answer of %s was dropped by DDS during shutdown (its '
                               'caller was not matched yet)', dropped.service)
                return
            self._dropped.append(dropped)
            self._changed.notify_all()
            if not self._thread:
                self._thread = threading.Thread(target=self._retry, name='answer retry',
                                                daemon=True)
                self._thread.start()

    def _retry(self) -> None:
        while True:
            with self._changed:
                while not self._dropped and not self._closed:
                    self._changed.wait()
                if self._closed:
                    return
                offered = list(self._dropped)
            for dropped in offered:
                self._offer(dropped)
            with self._changed:
                self._changed.wait(RETRY_PERIOD)

    def _offer(self, dropped: _Dropped) -> None:
        try:
            sent = dropped.send(dropped.response, dropped.header)
        except Exception as error:  # noqa: BLE001 - the service went away meanwhile
            sent = None
            LOGGER.warning('an answer of %s could not be offered again (%s)',
                           dropped.service, error)
        waited = time.monotonic() - dropped.since
        if sent is False and waited < RETRY_WINDOW:
            return
        with self._changed:
            if dropped not in self._dropped:
                return  # given up by close() meanwhile
            self._dropped.remove(dropped)
        if sent:
            LOGGER.info('an answer of %s reached its caller %.1f s late: DDS had not '
                        'matched the caller yet', dropped.service, waited)
        elif sent is False:
            LOGGER.warning('an answer of %s never reached its caller: its DDS answer reader '
                           'was not matched within %.0f s', dropped.service, RETRY_WINDOW)
