"""A request whose time ran out while it waited for its device is answered, never sent.

docs/services.md: "timed out while waiting behind other requests to the same device: 0x05040000
... nothing was sent". Queued requests are timed out by one deadline thread, and that thread
also delivers their answers: the ROS layer sends each answer to its caller from the thread
that resolves it (``ros/deferred.py``, one send lock per service). When that thread is slow to
get to a request (a burst of requests timing out together, each answer sent to ROS in turn),
the device's worker must not take the request and put it on the bus after its deadline.
"""

import threading

import can

from cbcan_ros.core.gateway import Gateway, GatewayConfig

from conftest import new_channel, wait_until

SILENT = 9  # nothing on the bus answers this node id
TIMEOUT = 0x05040000


def test_a_request_whose_time_ran_out_in_the_queue_is_not_sent_when_its_turn_comes():
    """A user sees a read that timed out in the queue put on the bus anyway, and aborted.

    Three reads of a silent device: the first runs for 0.6 s; the second and third wait
    behind it with 0.2 s and 0.3 s. The second's answer is delivered slowly (its caller's
    done-callback takes its time, as a ROS answer waiting for the service's send lock does);
    the third's time runs out 0.3 s before the first's transfer ends. Expected: the third is
    answered 0x05040000 "nothing was sent" and only the first read's request is on the bus.
    Seen: the worker takes the third when the first ends and sends its request (and then an
    abort) although its time ran out long before.
    """
    channel = new_channel()
    bus = can.Bus(interface='virtual', channel=channel)
    gateway = Gateway(GatewayConfig(channel=channel))
    gateway.start()
    delivering = threading.Event()
    release = threading.Event()
    try:
        first = gateway.sdo_read(SILENT, 0x1000, 0, timeout=0.6)
        second = gateway.sdo_read(SILENT, 0x1000, 0, timeout=0.2)
        second.add_done_callback(lambda _: (delivering.set(), release.wait(10.0)))
        third = gateway.sdo_read(SILENT, 0x1000, 0, timeout=0.3)
        assert first.result(10.0).abort_code == TIMEOUT
        assert delivering.is_set()  # the second timed out in the queue, long before
        # The third is overdue now: a worker that answers it itself does so at once.
        try:
            wait_until(third.done, 2.0, 'the third read answered while the second is delivered')
        except AssertionError:
            pass  # only the deadline thread answers it: it will once released
        release.set()
        answer = third.result(10.0)
        requests = []
        while (message := bus.recv(0.2)) is not None:
            if message.arbitration_id == 0x600 + SILENT and message.data[0] != 0x80:
                requests.append(bytes(message.data).hex())
        seen = f'third answered {answer.message!r}; read requests on the bus: {requests}'
        assert answer.abort_code == TIMEOUT, seen
        assert 'nothing was sent' in answer.message and len(requests) == 1, seen
    finally:
        release.set()
        gateway.stop()
        bus.shutdown()
