"""An answer DDS drops because it has not matched its caller yet is offered again.

rmw_fastrtps drops an answer whose caller's answer reader it has not matched within 100 ms,
which a caller's first call right after discovery meets on a loaded machine; rclpy reports it
only as a warning. The node offers that answer again until the reader matches, for up to
``RETRY_WINDOW``, and says in one line what became of it.
"""

import logging
import threading
import warnings

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

    def __init__(self, drops: int):
        self.drops = drops
        self.delivered = []
        self.offers = 0
        self.changed = threading.Event()

    def send_response(self, response, header) -> None:
        self.offers += 1
        if self.offers <= self.drops:
            warnings.warn(DROPPED, RuntimeWarning, stacklevel=1)
        else:
            self.delivered.append((response, header))
        self.changed.set()


def test_a_dropped_answer_is_offered_again_until_it_leaves_once(caplog):
    middleware = _Middleware(drops=3)
    retry = AnswerRetry()
    answer = retry.sender(_Service(), middleware.send_response)
    with warnings.catch_warnings(record=True) as shown, caplog.at_level(logging.INFO):
        warnings.simplefilter('once')  # a filter put first must not hide the drops
        answer('the answer', 'its header')
        wait_until(lambda: middleware.delivered, 10.0, 'the dropped answer sent again')
        retry.close()
    assert middleware.delivered == [('the answer', 'its header')]
    assert middleware.offers == 4
    assert not [w for w in shown if DROPPED in str(w.message)], 'the drop is handled, not shown'
    late = [r.getMessage() for r in caplog.records if 'late' in r.getMessage()]
    assert len(late) == 1 and '/test/sdo_read' in late[0], caplog.text


def test_an_answer_still_dropped_when_its_window_ends_is_given_up_in_one_line(
        caplog, monkeypatch):
    monkeypatch.setattr(answer_retry, 'RETRY_WINDOW', 0.5)
    middleware = _Middleware(drops=10 ** 6)
    retry = AnswerRetry()
    answer = retry.sender(_Service(), middleware.send_response)
    with caplog.at_level(logging.INFO):
        answer('the answer', 'its header')
        wait_until(lambda: not retry.waiting, 10.0, 'the answer given up')
        offers = middleware.offers
        retry.close()
    assert middleware.offers == offers, 'nothing is offered once given up'
    assert offers > 2 and not middleware.delivered
    lines = [r.getMessage() for r in caplog.records if 'never reached' in r.getMessage()]
    assert len(lines) == 1 and '/test/sdo_read' in lines[0], caplog.text


def test_an_answer_offered_when_the_services_go_is_given_up_in_one_line(caplog):
    middleware = _Middleware(drops=10 ** 6)
    retry = AnswerRetry()
    answer = retry.sender(_Service(), middleware.send_response)
    with caplog.at_level(logging.INFO):
        answer('the answer', 'its header')
        retry.close()
        offers = middleware.offers
        answer('an answer during shutdown', 'its header')
    assert middleware.offers == offers + 1, 'an answer after close is tried once, not kept'
    assert not retry.waiting
    assert len([r for r in caplog.records if 'went away' in r.getMessage()]) == 1, caplog.text
    assert len([r for r in caplog.records if 'during shutdown' in r.getMessage()]) == 1


def test_the_node_offers_again_what_rmw_really_dropped_and_answers_others_meanwhile(
        start_node, client_node):
    """Offer again and again the answers rmw_fastrtps really drops.

    rmw_fastrtps drops every answer to a caller whose answer reader it can never match, as it
    does to one not matched yet (this one asks for TRANSIENT_LOCAL answers, the services offer
    VOLATILE): the node keeps offering them, answers everyone else meanwhile, and says once
    per answer when it gives up.
    """
    name = f'{namespace()}/cbcan'
    gateway = start_node(arguments(name, '-p', 'can.interface:=virtual',
                                   '-p', 'simulation.devices:=[2]', '-p', 'nodes:=[2]'))
    unmatched = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
    lost_state = client_node.create_client(NmtState, f'{name}/nmt_state', qos_profile=unmatched)
    lost_read = client_node.create_client(SdoRead, f'{name}/sdo_read', qos_profile=unmatched)
    read = service_client(client_node, SdoRead, f'{name}/sdo_read', gateway)
    # Their requests are kept (TRANSIENT_LOCAL) until their writers match the node's readers;
    # wait_for_service would wait for ever, for the answer readers never match.
    lost_state.call_async(NmtState.Request(node_id=2))
    lost_read.call_async(SdoRead.Request(node_id=2, index=0x1000, subindex=0, max_size=4))

    for _ in range(3):  # while the lost answers are offered again
        answer = call(read, SdoRead.Request(node_id=2, index=0x1000, subindex=0, max_size=4),
                      'a read by a matched caller', gateway)
        assert answer.success, answer.message
    wait_until(lambda: gateway.output().count('never reached its caller') >= 2,
               answer_retry.RETRY_WINDOW + 50.0, f'both lost answers given up:\n'
               f'{gateway.output()}')
    output = gateway.output()
    assert 'an answer of ~/nmt_state never reached' in output, output
    assert 'an answer of ~/sdo_read never reached' in output, output
    assert 'failed to send response' not in output, output
