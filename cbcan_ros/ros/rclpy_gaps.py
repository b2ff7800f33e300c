"""Everything the gateway adds to rclpy 7.1.6 (Jazzy), in one place, to be offered upstream.

Each function here reaches into rclpy where it offers no public way, and each gap is listed
in docs/library_gaps.md:

1. A service cannot answer later, from another thread (rclcpp has deferred responses):
   :func:`intercept_responses` replaces the service's own ``send_response``, which rclpy's
   executors (the default ones and ``EventsExecutor``) call with the request's header.
2. Requests still waiting in a service's reader when the executor stops are never answered:
   :func:`drain` takes them as the executors do and hands them to the callback.
3. ``LifecycleNode`` raises for a transition the current state does not have (rclcpp answers
   ``success: false``), which ends the executor: :func:`refuse_unavailable_transitions`.
4. A parameter no node declares is silently ignored, and there is no public list of the
   values a node was given: :func:`parameter_overrides`.
5. A service cannot tell whether its callers acknowledged its answers (a publisher has
   ``wait_for_all_acked``; rmw has nothing for services), so shutdown cannot wait for exactly
   that: it keeps the services a fixed ``interface.ANSWER_LINGER`` after the last answer.
6. An answer the middleware dropped (rmw_fastrtps gives up on a caller whose answer reader
   it has not matched yet) is reported only as a ``RuntimeWarning``, and the default warning
   filter shows it once per process: :func:`send_or_report_dropped` says whether an answer left.
7. An action client takes one feedback message a wake and handles a result taken with it
   first, then forgets the goal's feedback callback: feedback the server sent before its
   result, still waiting when the result is taken (a busy client), is lost.
   :class:`FeedbackFirstActionClient` hands the goal all of it before its result.
8. Every publisher and subscription gets event handlers by default (the warnings of an
   endpoint with incompatible QoS or type), which are waitables: destroyed while
   ``EventsExecutor`` spins (a managed node's cleanup or shutdown), an event that came in
   between ended the process with a segmentation fault.
   :func:`without_default_event_handlers` makes a node's without them.
9. ``EventsExecutor.wake()`` does not end a ``spin_once(timeout)`` waiting for work: a node
   stopping its spin loop waited out the timeout (up to a second) at every exit.
   :func:`end_spin_once` wakes it with a timer due at once.
"""

import re
import threading
from typing import Callable, Dict
import warnings

from rclpy.action import ActionClient
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.exceptions import InvalidHandle
from rclpy.lifecycle import LifecycleNode
from rclpy.node import Node
from rclpy.parameter import Parameter


def intercept_responses(service, send_when_ready: Callable) -> Callable:
    """Make ``service`` call ``send_when_ready(response, header)`` to answer a request.

    Returns rclpy's own ``send_response(response, header)``, to send the answer with later.
    """
    send = service.send_response
    service.send_response = send_when_ready
    return send


# rclpy's text when rcl_send_response returns RCL_RET_TIMEOUT (rclpy/src/rclpy/service.cpp).
_DROPPED = 'failed to send response (timeout)'
_DROPPED_PATTERN = re.escape(_DROPPED)
_sending = threading.local()
_hook_lock = threading.Lock()
_watching = [None, None]  # the hook and the filter last put in place


def watch_for_dropped_answers() -> None:
    """Make the warning rclpy raises for a dropped answer reach :func:`send_or_report_dropped`.

    The warning is raised in C and shown through ``warnings._showwarnmsg``, which a test
    runner's ``catch_warnings`` leaves in place. The first filter shows it every time: the
    default shows it once per place, and another filter put first might hide it or make it
    an error. The filter is the process's: unwrapped services' drops are shown every time.
    """
    filters = warnings.filters
    if (warnings._showwarnmsg is _watching[0] and filters
            and filters[0] is _watching[1]):
        return  # both still in place (every answer asks): no lock, no pattern
    with _hook_lock:
        show = warnings._showwarnmsg
        if not getattr(show, 'reports_dropped_answers', False):
            def show_or_report(message):
                if (getattr(_sending, 'watching', False)
                        and issubclass(message.category, RuntimeWarning)
                        and str(message.message).startswith(_DROPPED)):
                    _sending.dropped = True
                    return
                show(message)
            show_or_report.reports_dropped_answers = True
            warnings._showwarnmsg = show_or_report
        first = warnings.filters[0] if warnings.filters else None
        if not (first and first[0] == 'always'
                and getattr(first[1], 'pattern', first[1]) == _DROPPED_PATTERN):
            warnings.filterwarnings('always', message=_DROPPED_PATTERN,
                                    category=RuntimeWarning)
        _watching[:] = [warnings._showwarnmsg, warnings.filters[0]]


def send_or_report_dropped(send: Callable, response, header) -> bool:
    """Answer with rclpy's ``send_response(response, header)``; return False if it was dropped.

    Dropped means the middleware did not take the answer (rmw returned a timeout), so the
    same answer may be offered again; any other failure raises as rclpy raises it.
    """
    watch_for_dropped_answers()
    _sending.dropped = False
    _sending.watching = True
    try:
        send(response, header)
    except SystemError as error:
        # An "error" filter put first by another thread meanwhile: rclpy ignores that its
        # warning raised, and Python reports the exception left set as a SystemError.
        cause = error.__cause__ or error.__context__
        if not (isinstance(cause, RuntimeWarning) and str(cause).startswith(_DROPPED)):
            raise
        return False
    finally:
        _sending.watching = False
    return not _sending.dropped


def drain(service) -> int:
    """Hand each request still waiting in ``service`` (never taken) to its callback, once.

    Return how many there were.

    Called once the executor takes no more requests (shutdown) or is busy taking the service
    away (cleanup): without it those callers would wait for ever. The request is taken as
    rclpy's executors take it (``service.handle.service_take_request``).
    """
    taken = 0
    while True:
        try:
            with service.handle:
                request, header = service.handle.service_take_request(
                    service.srv_type.Request)
        except InvalidHandle:
            return taken
        if header is None:
            return taken
        taken += 1
        service.send_response(service.callback(request, service.srv_type.Response()), header)


def refuse_unavailable_transitions(node: LifecycleNode) -> None:
    """Answer a transition the current state does not have ``success: false``, logged."""
    change_state = node._service_change_state.callback
    machine = node._state_machine

    def checked(request, response):
        transition = request.transition
        available = {described[0] for described in machine.available_transitions}
        if not transition.label and transition.id not in available:
            node.get_logger().warning(
                f'transition {transition.id} refused: state {machine.current_state[1]} '
                f'has no such transition')
            response.success = False
            return response
        return change_state(request, response)

    node._service_change_state.callback = checked


def without_default_event_handlers(node: Node) -> None:
    """Create ``node``'s publishers and subscriptions from now on without event handlers.

    Those given ``event_callbacks`` of their own keep them.
    """
    create_publisher, create_subscription = node.create_publisher, node.create_subscription

    def publisher(*args, event_callbacks=None, **kwargs):
        return create_publisher(*args, event_callbacks=event_callbacks or
                                PublisherEventCallbacks(use_default_callbacks=False), **kwargs)

    def subscription(*args, event_callbacks=None, **kwargs):
        return create_subscription(*args, event_callbacks=event_callbacks or
                                   SubscriptionEventCallbacks(use_default_callbacks=False),
                                   **kwargs)

    node.create_publisher, node.create_subscription = publisher, subscription


def end_spin_once(node: Node) -> None:
    """Have a ``spin_once`` of ``node``'s executor that waits for work return now.

    A timer due at once, cancelled by its one call: ``EventsExecutor`` takes no guard
    conditions, and its ``wake()`` leaves a ``spin_once`` waiting out its timeout.
    """
    def once() -> None:
        timer.cancel()
    timer = node.create_timer(0.0, once)


def parameter_overrides(node: Node) -> Dict[str, Parameter]:
    """Return the parameter values ``node`` was given (-p, parameter files), declared or not."""
    return getattr(node, '_parameter_overrides', {})


class FeedbackFirstActionClient(ActionClient):
    """An ``ActionClient`` that calls a goal's feedback callback before its result is set.

    With a result, every feedback message waiting in the reader is taken too, and all are
    handed over, in order, before the result; rclpy's own would drop them.
    """

    def take_data(self):
        """Take what rclpy takes, and with a result every feedback message waiting."""
        data = super().take_data()
        feedback = [data.pop('feedback')] if 'feedback' in data else []
        if feedback or 'result' in data:
            while True:
                message = self._client_handle.take_feedback(
                    self._action_type.Impl.FeedbackMessage)
                if message is None:
                    break
                feedback.append(message)
        if feedback:
            data['feedback_messages'] = feedback
        return data

    async def execute(self, taken_data):
        """Hand over the feedback taken, then the rest as rclpy does."""
        for message in taken_data.pop('feedback_messages', ()):
            await super().execute({'feedback': message})
        await super().execute(taken_data)
