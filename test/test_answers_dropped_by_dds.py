"""An answer DDS drops because it has not matched its caller yet is offered again.

rmw_fastrtps drops an answer whose caller's answer reader it has not matched within 100 ms,
which a caller's first call right after discovery meets on a loaded machine; rclpy reports it
only as a warning. The node offers that answer again until the reader matches, for up to
``RETRY_WINDOW``, spacing its offers (each one to a caller still unmatched holds the whole
process 100 ms), and says in one line per episode what became of them.
"""

import logging
import re
import threading
import time
import warnings

from rcl_interfaces.srv import GetParameters
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from cbcan_ros.ros import answer_retry
from cbcan_ros.ros.answer_retry import AnswerRetry
from cbcan_ros.srv import NmtState, SdoRead

from conftest import wait_until
from node_process import arguments, call, namespace, service_client

# rclpy's words when rmw reports a timeout (rclpy/src/rclpy/service.cpp).
DROPPED = 'failed to send response (timeout): client will not receive response'


class _Service:
    srv_name = '/test/sdo_read'


class _Middleware:
    """rclpy's ``send_response`` where DDS drops the first ``drops`` answers, as rmw does."""

    def __init__(self, drops: int, blocks: float = 0.0):
        self.drops = drops
        self.blocks = blocks  # rmw's wait for the match, with the GIL held
        self.delivered = []
        self.offers = []  # when each offer was made (monotonic)
        self.offered = []  # which answer each offer was

    def send_response(self, response, header) -> None:
        self.offers.append(time.monotonic())
        self.offered.append(response)
        if len(self.offers) <= self.drops:
            time.sleep(self.blocks)
            warnings.warn(DROPPED, RuntimeWarning, stacklevel=1)
        else:
            self.delivered.append((response, header))


def never_matching(monkeypatch, window: float):
    """Return (middleware, retry, answer): a service whose callers DDS never matches."""
    monkeypatch.setattr(answer_retry, 'RETRY_WINDOW', window)
    middleware = _Middleware(drops=10 ** 6)
    retry = AnswerRetry()
    return middleware, retry, retry.sender(_Service(), middleware.send_response)


def lines(caplog, text: str) -> list:
    """Return the log lines containing ``text``."""
    return [r.getMessage() for r in caplog.records if text in r.getMessage()]


def test_a_dropped_answer_is_offered_again_until_it_leaves_once(caplog):
    middleware = _Middleware(drops=3)
    retry = AnswerRetry()
    answer = retry.sender(_Service(), middleware.send_response)
    with warnings.catch_warnings(record=True) as shown, caplog.at_level(logging.INFO):
        warnings.simplefilter('once')  # a filter put first must not hide the drops
        answer('the answer', 'its header')
        wait_until(lambda: middleware.delivered, 10.0, 'the dropped answer sent again')
        wait_until(lambda: lines(caplog, 'left the node'), 10.0, 'the episode logged')
        retry.close()
    assert middleware.delivered == [('the answer', 'its header')]
    assert len(middleware.offers) == 4
    assert not [w for w in shown if DROPPED in str(w.message)], 'the drop is handled, not shown'
    assert len(lines(caplog, 'DDS dropped an answer of /test/sdo_read')) == 1, caplog.text
    summary = lines(caplog, 'answers DDS dropped (of /test/sdo_read): 1 left the node')
    assert len(summary) == 1 and '0 given up' in summary[0], caplog.text


def test_an_answer_still_dropped_when_its_window_ends_is_given_up_after_few_offers(
        caplog, monkeypatch):
    middleware, retry, answer = never_matching(monkeypatch, 2.0)
    with caplog.at_level(logging.INFO):
        answer('the answer', 'its header')
        wait_until(lambda: not retry.waiting, 10.0, 'the answer given up')
        offers = len(middleware.offers)
        retry.close()
    assert len(middleware.offers) == offers, 'nothing is offered once given up'
    # Offers 0.1, 0.2, 0.4, 0.8 s apart, at least DROPPED_PAUSE after a drop: 6 at most in
    # 2 s, where one every 0.1 s would make 20.
    assert 3 <= offers <= 6 and not middleware.delivered, middleware.offers
    assert len(lines(caplog, 'an answer of /test/sdo_read was given up')) == 1, caplog.text
    summary = lines(caplog, '1 given up (1 whose callers never matched within 2 s)')
    assert len(summary) == 1 and summary[0].startswith('answers DDS dropped'), caplog.text


def test_offers_to_callers_still_unmatched_are_spaced_whatever_their_number(monkeypatch):
    middleware, retry, answer = never_matching(monkeypatch, 1.5)
    for number in range(8):
        answer(f'answer {number}', number)
    first_offers = len(middleware.offers)
    wait_until(lambda: not retry.waiting, 30.0, 'every answer given up')
    retry.close()
    again = middleware.offers[first_offers:]
    gaps = [later - earlier for earlier, later in zip(again, again[1:], strict=False)]
    assert gaps and min(gaps) >= answer_retry.DROPPED_PAUSE - 0.05, gaps


def test_close_gives_up_what_is_kept_after_at_most_one_offer_in_progress(
        caplog, monkeypatch):
    middleware, retry, answer = never_matching(monkeypatch, 60.0)
    with caplog.at_level(logging.INFO):
        for number in range(answer_retry.MOST_KEPT + 5):
            answer(f'answer {number}', number)
        assert retry.waiting == answer_retry.MOST_KEPT, 'at most MOST_KEPT are kept'
        middleware.blocks = 0.1  # from now on each offer waits for the match, as rmw does
        began = time.monotonic()
        retry.close()
        closing = time.monotonic() - began
        offers = len(middleware.offers)
        answer('an answer during shutdown', 'its header')
    assert closing < 2.0, f'close took {closing:.1f} s'  # a round of 100 offers: 10 s
    assert len(middleware.offers) == offers + 1, 'an answer after close is tried once, not kept'
    assert not retry.waiting
    most = answer_retry.MOST_KEPT
    summary = lines(caplog, f'{most + 5} given up (5 beyond the {most} kept, {most} at shutdown)')
    assert len(summary) == 1, caplog.text
    assert len(lines(caplog, '1 given up (1 at shutdown)')) == 1, caplog.text


def test_a_new_dropped_answer_is_offered_before_those_offered_many_times(monkeypatch):
    middleware, retry, answer = never_matching(monkeypatch, 60.0)
    for number in range(5):  # a caller that never matches, calling again and again
        answer(f'unmatched {number}', number)
    wait_until(lambda: len(middleware.offers) >= 5 + 3 * 5, 30.0, 'each offered again thrice')
    answer('new', 'its header')
    new_drop = len(middleware.offered)
    wait_until(lambda: middleware.offered.count('new') >= 2, 30.0, 'the new answer offered again')
    retry.close()
    assert middleware.offered[new_drop] == 'new', middleware.offered[new_drop - 1:]


def test_an_answer_that_cannot_be_offered_again_is_given_up_and_the_others_go_on(caplog):
    calls = []

    def send(response, header):
        calls.append(response)
        if calls.count(response) == 1:
            warnings.warn(DROPPED, RuntimeWarning, stacklevel=1)
        elif response == 'broken':
            raise RuntimeError('the service went away')
    retry = AnswerRetry()
    answer = retry.sender(_Service(), send)
    with caplog.at_level(logging.INFO):
        answer('broken', 1)
        wait_until(lambda: calls.count('broken') == 2, 10.0, 'the broken answer offered again')
        answer('fine', 2)
        wait_until(lambda: calls.count('fine') == 2, 10.0, 'a later answer offered again')
        wait_until(lambda: not retry.waiting, 10.0, 'nothing kept')
        retry.close()
    assert calls.count('broken') == 2, 'given up, not offered for ever'
    assert len(lines(caplog, 'could not be offered again')) == 1, caplog.text
    assert lines(caplog, '1 that could not be sent'), caplog.text


def test_a_drop_on_one_thread_is_not_taken_for_another_threads_answer():
    dropping, sent_meanwhile = threading.Event(), threading.Event()

    def dropped_send(response, header):
        warnings.warn(DROPPED, RuntimeWarning, stacklevel=1)
        dropping.set()
        sent_meanwhile.wait(10.0)
    delivered = []
    retry = AnswerRetry()
    first = retry.sender(_Service(), dropped_send)
    second = retry.sender(_Service(), lambda response, header: delivered.append(response))
    worker = threading.Thread(target=first, args=('dropped', 1))
    worker.start()
    assert dropping.wait(10.0)
    second('delivered', 2)  # while the first send is still inside the middleware
    sent_meanwhile.set()
    worker.join(10.0)
    assert retry.waiting == 1, 'the dropped answer is kept'
    retry.close()
    assert delivered == ['delivered'], 'the other answer left once and was not kept'


def test_a_drop_raised_as_an_error_by_a_warning_filter_is_still_a_drop():
    def send_under_an_error_filter(response, header):
        # What Python makes of rclpy ignoring that its warning raised.
        raise SystemError('returned a result with an exception set') from RuntimeWarning(
            DROPPED)
    retry = AnswerRetry()
    retry.sender(_Service(), send_under_an_error_filter)('the answer', 1)
    assert retry.waiting == 1
    retry.close()


SUMMARY = re.compile(r'answers DDS dropped \(of ([^)]*)\): (\d+) left the node .*, (\d+) given up')


def test_the_node_offers_again_what_rmw_really_dropped_and_answers_others_meanwhile(
        start_node, client_node):
    """Offer again the answers rmw_fastrtps really drops, of every kind of service.

    rmw_fastrtps drops every answer to a caller whose answer reader it can never match, as it
    does to one not matched yet (this one asks for TRANSIENT_LOCAL answers, the services offer
    VOLATILE): the node keeps offering them, answers everyone else meanwhile, and says what
    it gave up.
    """
    name = f'{namespace()}/cbcan'
    gateway = start_node(arguments(name, '-p', 'can.interface:=virtual',
                                   '-p', 'simulation.devices:=[2]', '-p', 'nodes:=[2]'))
    unmatched = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
    lost = [client_node.create_client(kind, f'{name}/{service}', qos_profile=unmatched)
            for kind, service in ((NmtState, 'nmt_state'), (SdoRead, 'sdo_read'),
                                  (GetParameters, 'get_parameters'))]
    read = service_client(client_node, SdoRead, f'{name}/sdo_read', gateway)

    def read_by_a_matched_caller() -> None:
        answer = call(read, SdoRead.Request(node_id=2, index=0x1000, subindex=0, max_size=4),
                      'a read by a matched caller', gateway)
        assert answer.success, answer.message
    # wait_for_service would wait for ever for the lost callers (their answer readers never
    # match), and a request written before the node's VOLATILE request reader matched its
    # writer is never delivered. The node discovers this process's endpoints in the order
    # they were made: once it answered a caller made after the lost ones, it has matched
    # their request writers too.
    read_by_a_matched_caller()
    lost[0].call_async(NmtState.Request(node_id=2))
    lost[1].call_async(SdoRead.Request(node_id=2, index=0x1000, subindex=0, max_size=4))
    lost[2].call_async(GetParameters.Request(names=['nodes']))
    for _ in range(3):
        read_by_a_matched_caller()

    def given_up():
        found = [SUMMARY.search(line) for line in gateway.output().splitlines()]
        return [match for match in found if match]
    wait_until(lambda: sum(int(match[3]) for match in given_up()) >= 3,
               answer_retry.RETRY_WINDOW + 50.0, f'the lost answers given up:\n'
               f'{gateway.output()}')
    output = gateway.output()
    named = ', '.join(match[1] for match in given_up())
    for service in ('~/nmt_state', '~/sdo_read', 'get_parameters'):
        assert service in named, output
    assert 'never matched within 10 s' in output, output
    assert 'failed to send response' not in output, output
