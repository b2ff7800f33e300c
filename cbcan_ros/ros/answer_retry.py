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
to ``LONGEST_DELAY``; an offer dropped again (or kept waiting) pauses every offer of the
process for ``DROPPED_PAUSE``; answers offered least go first, so a caller that never
matches, calling now and then, does not hold up a new one (calling several times a second,
it still can: rclpy does not say which caller an answer is for); and at most ``MOST_KEPT``
are kept, the most offered given up first. Each episode, from the first dropped answer
until none is kept, is logged: one line when it begins, one at its first give-up, one when
it ends.
"""

from dataclasses import dataclass, field
import logging
import threading
import time
from typing import Callable, List, Optional, Set

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
# An offer that took this long waited for the match (the GIL held): it pauses offers too.
KEPT_WAITING = 0.01

# Why answers were given up, as the episode's summary counts them and as one is told,
# formatted with the limits when logged.
GIVEN_UP = {'unmatched': ('whose callers never matched within {window:g} s',
                          'its caller never matched within {window:g} s'),
            'crowded': ('beyond the {most} kept', 'more than {most} were kept'),
            'failed': ('that could not be sent', 'it could not be sent'),
            'closed': ('at shutdown', 'the services went away')}


def _why(why: str, alone: bool = False) -> str:
    return GIVEN_UP[why][alone].format(window=RETRY_WINDOW, most=MOST_KEPT)


@dataclass(eq=False)  # each one is itself, whatever it holds
class _Dropped:
    service: str
    send: Callable[[object, object], bool]
    response: object
    header: object
    since: float
    due: float
    delay: float = FIRST_DELAY
    offers: int = 1


@dataclass
class _Episode:
    services: Set[str] = field(default_factory=set)
    late: int = 0
    latest: float = 0.0
    unmatched: int = 0  # given up: their callers never matched within RETRY_WINDOW
    crowded: int = 0  # given up: more than MOST_KEPT were kept
    failed: int = 0  # given up: sending failed otherwise (the service went away)
    closed: int = 0  # given up: the services went away

    @property
    def given_up(self) -> int:
        return self.unmatched + self.crowded + self.failed + self.closed


class AnswerRetry:
    """Sends services' answers, and offers again those dropped, from one thread of its own."""

    # Shared by every instance (a node has two): the GIL they cost is the process's.
    paused_until = 0.0

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
            self._episode.closed += len(self._dropped)
            self._dropped = []
            self._changed.notify_all()
        if self._thread:
            self._thread.join()
        self._end_episode()

    def _keep(self, dropped: _Dropped) -> None:
        with self._changed:
            episode = self._episode
            first = not episode.services
            episode.services.add(dropped.service)
            closed = self._closed
            if closed:
                episode.closed += 1
            else:
                if len(self._dropped) >= MOST_KEPT:
                    self._give_up(max(self._dropped, key=lambda d: (d.offers, -d.since)),
                                  'crowded')
                self._dropped.append(dropped)
                self._changed.notify_all()
                if not self._thread:
                    self._thread = threading.Thread(target=self._retry, name='answer retry',
                                                    daemon=True)
                    self._thread.start()
        if closed:
            self._end_episode()
        elif first:
            LOGGER.info('DDS dropped an answer of %s: it had not matched the caller yet (a '
                        'first call right after discovery); offered again for up to %g s',
                        dropped.service, RETRY_WINDOW)

    def _give_up(self, dropped: _Dropped, why: str) -> None:
        """Drop ``dropped`` for good, counted by ``why`` (called holding ``_changed``)."""
        self._dropped.remove(dropped)
        episode = self._episode
        if not episode.given_up:
            LOGGER.warning('an answer of %s was given up: %s (the episode is summed up when '
                           'no answer is left)', dropped.service, _why(why, alone=True))
        setattr(episode, why, getattr(episode, why) + 1)

    def _next(self) -> Optional[_Dropped]:
        """Wait for the next answer to offer (holding ``_changed``); None once closed."""
        while not self._closed:
            now = time.monotonic()
            for old in [d for d in self._dropped if now - d.since >= RETRY_WINDOW]:
                self._give_up(old, 'unmatched')
            if not self._dropped:
                return None
            wake = max(min(d.due for d in self._dropped), AnswerRetry.paused_until)
            if wake <= now:
                return min((d for d in self._dropped if d.due <= now),
                           key=lambda d: (d.offers, d.due))
            self._changed.wait(wake - now)
        return None

    def _retry(self) -> None:
        failures = set()
        while True:
            with self._changed:
                while True:
                    dropped = self._next()
                    if dropped is None:
                        break
                    began = time.monotonic()
                    try:
                        sent = dropped.send(dropped.response, dropped.header)
                    except Exception as error:  # noqa: BLE001 - this answer, not the rest
                        if type(error) not in failures:
                            failures.add(type(error))
                            LOGGER.error('an answer of %s could not be offered again (%r); '
                                         'later failures of this kind are not logged',
                                         dropped.service, error)
                        self._give_up(dropped, 'failed')
                        continue
                    now = time.monotonic()
                    if not sent or now - began > KEPT_WAITING:
                        AnswerRetry.paused_until = max(AnswerRetry.paused_until,
                                                       now + DROPPED_PAUSE)
                    if sent:
                        self._dropped.remove(dropped)
                        self._episode.late += 1
                        self._episode.latest = max(self._episode.latest, now - dropped.since)
                    else:
                        dropped.offers += 1
                        dropped.delay = min(dropped.delay * 2, LONGEST_DELAY)
                        dropped.due = now + dropped.delay
                closed = self._closed
            self._end_episode()
            if closed:
                return
            with self._changed:
                while not self._dropped and not self._closed:
                    self._changed.wait()

    def _end_episode(self) -> None:
        with self._changed:
            if self._dropped or not self._episode.services:
                return
            episode, self._episode = self._episode, _Episode()
        given_up = ', '.join(f'{getattr(episode, why)} {_why(why)}' for why in GIVEN_UP
                             if getattr(episode, why))
        LOGGER.log(logging.WARNING if episode.given_up else logging.INFO,
                   'answers DDS dropped (of %s): %d left the node on a later offer (up to %.1f '
                   's late), %d given up%s', ', '.join(sorted(episode.services)), episode.late,
                   episode.latest, episode.given_up, f' ({given_up})' if given_up else '')


def retry_the_node_services(node) -> AnswerRetry:
    """Make the services rclpy gave ``node`` (parameters, lifecycle) retry dropped answers.

    Returns their ``AnswerRetry``, to close when the node is destroyed.
    """
    retry = AnswerRetry()
    for service in node.services:
        retry.retry_dropped_answers(service)
    return retry
