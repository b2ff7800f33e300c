"""Services answered when their result is ready, from whichever thread has it.

rclpy (Jazzy) runs a service callback with the request only, and sends what the callback
returns through ``Service.send_response(response, header)``: the header that routes an answer
back to its caller reaches ``send_response`` alone. A callback that awaits a slow device as a
coroutine costs the executor a pass over every waiting coroutine on each wake, which grows
with the square of the calls waiting (a burst of 1,000 calls to silent devices was answered
seconds after its timeout).

So a :class:`DeferredService` callback only hands the request to the gateway and returns the
empty response as a placeholder; the service's ``send_response`` (rclpy's own, documented to
take the request's header) is wrapped to keep that header until the gateway's future
resolves, and the answer then leaves from the thread that resolved it: a device's worker, the
deadline watcher, the bus supervisor or shutdown. The executor holds nothing per waiting call,
and an answer never waits for the executor. rclcpp has this as deferred responses; rclpy has
no such API yet: the wrapping is ``rclpy_gaps.intercept_responses``.
"""

from concurrent.futures import Future
import logging
import threading
import time
from typing import Callable, Dict, Tuple

from .answer_retry import AnswerRetry
from .rclpy_gaps import intercept_responses

LOGGER = logging.getLogger(__name__)


class CallsInProgress:
    """Counts the calls taken but not answered yet, and those answered, so shutdown can wait."""

    def __init__(self):
        self._count = 0
        self._answered = 0
        self._idle = threading.Condition()

    @property
    def waiting(self) -> int:
        """Return how many calls were taken and are not answered yet."""
        with self._idle:
            return self._count

    @property
    def answered(self) -> int:
        """Return how many calls were answered (handed to ROS) since the services began."""
        with self._idle:
            return self._answered

    def begin(self) -> None:
        """Count one more call."""
        with self._idle:
            self._count += 1

    def end(self) -> None:
        """Count one call answered."""
        with self._idle:
            self._count -= 1
            self._answered += 1
            if not self._count:
                self._idle.notify_all()

    def wait_until_idle(self, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds for every call to be answered; return whether so."""
        deadline = time.monotonic() + timeout
        with self._idle:
            while self._count:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._idle.wait(remaining)
        return True


class DeferredService:
    """A ROS service whose callback starts work that resolves a future, answered when done.

    ``start(request)`` returns a ``concurrent.futures.Future``; ``fill(result, response)``
    writes its result into the response. Neither may raise for a valid request; if one does,
    the caller still gets its one answer, naming the failure.
    """

    def __init__(self, node, srv_type, name: str, start: Callable[[object], Future],
                 fill: Callable[[object, object], None], calls: CallsInProgress,
                 retry: AnswerRetry, **options):
        self._start = start
        self._fill = fill
        self._calls = calls
        self._pending: Dict[int, Tuple[Future, object]] = {}
        self._lock = threading.Lock()
        self._send_failures = set()
        self._node = node
        self._service = node.create_service(srv_type, name, self._take, **options)
        self._send = retry.sender(
            self._service, intercept_responses(self._service, self._send_when_ready))

    @property
    def service(self):
        """The rclpy service this answers through."""
        return self._service

    def _take(self, request, response):
        self._calls.begin()
        try:
            future = self._start(request)
        except Exception as error:  # noqa: BLE001 - every request gets its one answer
            future = Future()
            future.set_exception(error)
        with self._lock:
            self._pending[id(response)] = (future, response)
        return response

    def _send_when_ready(self, response, header) -> None:
        with self._lock:
            future, response = self._pending.pop(id(response))
        future.add_done_callback(lambda done: self._answer(done, response, header))

    def _answer(self, done: Future, response, header) -> None:
        try:
            self._fill(done.result(), response)
        except Exception as error:  # noqa: BLE001 - say so rather than stay silent
            LOGGER.error('a %s call failed inside the gateway: %r', self._service.srv_name,
                         error)
            if hasattr(response, 'message'):
                response.message = f'internal error of the gateway: {error}'[:300]
        try:
            self._send(response, header)
        except Exception as error:  # noqa: BLE001 - a lost answer must be seen, once
            kind = type(error).__name__
            if kind not in self._send_failures:
                self._send_failures.add(kind)
                LOGGER.error('an answer of %s could not be sent (%s: %s); later failures of '
                             'this kind are not logged', self._service.srv_name, kind, error)
        finally:
            self._calls.end()
