"""Answers the middleware dropped because it had not met their caller yet, offered again.

A caller's first call can reach the node before the node's DDS has matched the caller's
answer reader: discovery runs on threads of its own, which a loaded machine holds up, and a
client's ``service_is_ready()`` says only that the client has found the service, not that
the service has found the client. rmw_fastrtps then waits its answer writer's
``max_blocking_time`` (100 ms) for the match and drops the answer, and the caller waits for
ever (rclpy says so with a warning: ``rclpy_gaps.send_or_report_dropped``). The answer is
already made, so nothing is done twice on the bus: it is offered again, for up to
``RETRY_WINDOW``.

An offer to a caller still unmatched costs the whole process that 100 ms wait (rclpy keeps
the GIL through it), so offers are few: each answer's are spaced ``FIRST_DELAY`` doubling up
to ``LONGEST_DELAY``, one that is dropped again pauses every offer for ``DROPPED_PAUSE`` (the
process is never held more than a fifth of the time), and at most ``MOST_KEPT`` are kept.
Each episode (from the first dropped answer until none is kept) is logged in two lines.
"""

from dataclasses import dataclass, field
import logging
import threading
import time
from typing import Callable, List, Set

from .rclpy_gaps import send_or_report_dropped, watch_for_dropped_answers

LOGGER = logging.getLogger(__name__)

# A match usually follows within a few milliseconds of the drop; discovery on a loaded
# machine has been seen to take seconds. A caller that never matches (its QoS does not fit
# the service's, or it crashed and its DDS lease has not run out yet) costs ten offers.
RETRY_WINDOW = 10.0
FIRST_DELAY = 0.1
LONGEST_DELAY = 1.6
DROPPED_PAUSE = 0.4
MOST_KEPT = 100


@dataclass(eq=False)  # each one is itself, whatever it holds
class _Dropped:
    service: str
    send: Callable[[object, object], bool]
    response: object
    header: object
    since: float
    due: float
    delay: float = FIRST_DELAY


@dataclass
class _Episode:
    services: Set[str] = field(default_factory=set)
    late: int = 0
    latest: float = 0.0
    given_up: int = 0


class AnswerRetry:
    """Sends services' answers, and offers again those dropped, from one thread of its own."""

    def __init__(self):
        watch_for_dropped_answers()
        self._dropped: List[_Dropped] = []
        self._changed = threading.Condition()
        self._closed = False
        self._thread = None  # started by the first dropped answer
        self._episode = _Episode()

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
                now = time.monotonic()
                self._keep(_Dropped(service.srv_name, send_once, response, header, now,
                                    now + FIRST_DELAY))
        return answer

    def retry_dropped_answers(self, service) -> None:
        """Make a service the executor answers (its callback returns the answer) retry too."""
        service.send_response = self.sender(service, service.send_response)

    def close(self) -> None:
        """Stop offering (the services are going away); log the answers given up."""
        with self._changed:
            self._closed = True
            self._episode.given_up += len(self._dropped)
            self._dropped = []
            self._changed.notify_all()
        if self._thread:
            self._thread.join()
        self._end_episode(' when the services went away')

    def _keep(self, dropped: _Dropped) -> None:
        with self._changed:
            episode = self._episode
            first = not episode.services
            episode.services.add(dropped.service)
            closed = self._closed
            if closed or len(self._dropped) >= MOST_KEPT:
                episode.given_up += 1
            else:
                self._dropped.append(dropped)
                self._changed.notify_all()
                if not self._thread:
                    self._thread = threading.Thread(target=self._retry, name='answer retry',
                                                    daemon=True)
                    self._thread.start()
        if first:
            LOGGER.info('DDS dropped an answer of %s: it had not matched the caller yet (a '
                        'first call right after discovery); offered again for up to %g s',
                        dropped.service, RETRY_WINDOW)
        if closed:
            self._end_episode(' during shutdown')

    def _retry(self) -> None:
        paused_until = 0.0
        while True:
            with self._changed:
                while not self._closed:
                    due = min((d.due for d in self._dropped), default=None)
                    now = time.monotonic()
                    wake = None if due is None else max(due, paused_until)
                    if wake is not None and wake <= now:
                        break
                    self._changed.wait(None if wake is None else wake - now)
                if self._closed:
                    return
                dropped = min(self._dropped, key=lambda d: d.due)
                sent = dropped.send(dropped.response, dropped.header)
                now = time.monotonic()
                if not sent:
                    paused_until = now + DROPPED_PAUSE
                    if now - dropped.since < RETRY_WINDOW:
                        dropped.delay = min(dropped.delay * 2, LONGEST_DELAY)
                        dropped.due = now + dropped.delay
                        continue
                    self._episode.given_up += 1
                else:
                    self._episode.late += 1
                    self._episode.latest = max(self._episode.latest, now - dropped.since)
                self._dropped.remove(dropped)
                if self._dropped:
                    continue
            self._end_episode(f' (their callers not matched within {RETRY_WINDOW:g} s)')

    def _end_episode(self, given_up_why: str) -> None:
        with self._changed:
            if self._dropped or not self._episode.services:
                return
            episode, self._episode = self._episode, _Episode()
        level = logging.WARNING if episode.given_up else logging.INFO
        LOGGER.log(level, 'answers DDS dropped (of %s): %d left the node on a later offer (up '
                   'to %.1f s late), %d given up%s', ', '.join(sorted(episode.services)),
                   episode.late, episode.latest, episode.given_up,
                   given_up_why if episode.given_up else '')


def retry_the_node_services(node) -> AnswerRetry:
    """Make the services rclpy gave ``node`` (parameters, lifecycle) retry dropped answers.

    Returns their ``AnswerRetry``, to close when the node is destroyed.
    """
    retry = AnswerRetry()
    for service in node.services:
        retry.retry_dropped_answers(service)
    return retry
