"""Bursts, overload and killed clients: every caller gets its one answer, and the rest go on.

Each test starts the installed ``cbcan_node`` as a separate process (test/node_process.py)
and calls it as a robot's software does, from rclpy clients in this process or in child
processes that are killed midway. All of them load both cores by themselves (``HEAVY``).
"""

import subprocess
import sys
import threading
import time

import can
from test_shutdown import answered_within, me3can_multi_read, unanswered

from cbcan_ros.msg import NodeStates
from cbcan_ros.ros.interface import NODE_STATES_QOS
from cbcan_ros.srv import RegisterMailbox, SdoRead

from conftest import HEAVY, new_channel, wait_for_future, wait_until
from node_process import (
    arguments,
    namespace,
    private_bus,
    service_client,
    START_TIMEOUT,
    StateWatcher,
)

pytestmark = HEAVY

LIVE = (2, 3)            # simulated devices inside the node's process
SILENT = range(10, 30)   # node ids nobody answers
BUSY = 0x060A0023
TIMEOUT = 0x05040000
DEVICE_TYPE = [0x0192, 0x0002]  # 0x1000 of the simulated devices, as two words
ME3CAN_MULTI_READ_OK = 0x0009
# Ceiling for answers a quiet machine gives within a fraction of a second.
ANSWER = 10.0


# "Every request gets exactly one answer, within its timeout".

def test_burst_of_waiting_calls_is_answered_within_its_timeout(start_node, client_node):
    # 1,000 reads of 16 silent nodes (62 each, under sdo.queue_limit 64), timeout 2 s. Once
    # a defect: answers came up to 8 s after the call, because rclpy's executor resumed
    # every waiting coroutine on each wake; answers now leave from the gateway's threads.
    calls, timeout, silent = 1000, 2.0, range(10, 26)
    name = f'{namespace()}/cbcan'
    gateway = start_node(arguments(name, '-p', f'can.channel:={new_channel()}'))
    sdo_read = service_client(client_node, SdoRead, f'{name}/sdo_read', gateway)
    answered = {}
    sent = []
    for number in range(calls):
        future = sdo_read.call_async(SdoRead.Request(
            node_id=silent[number % len(silent)], index=0x1000, subindex=0, timeout=timeout))
        future.add_done_callback(
            lambda _, n=number: answered.setdefault(n, time.monotonic()))
        sent.append((time.monotonic(), future))
    # Node 0 is the gateway itself, answered at once; the node takes a client's requests in
    # the order sent, so by this answer it had taken every call above and started its timeout.
    taken = wait_for_future(sdo_read.call_async(SdoRead.Request(node_id=0, index=0x1000)),
                            3 * ANSWER)
    assert taken.success, taken.message
    all_taken = time.monotonic()
    try:
        wait_until(lambda: all(f.done() for _, f in sent), 3 * ANSWER,
                   'an answer to every call')
    except AssertionError:
        waiting = [n for n, (_, future) in enumerate(sent) if not future.done()]
        raise AssertionError(f'{len(waiting)} of {calls} calls unanswered {3 * ANSWER:g} s '
                             f'after the node had taken them all (calls {waiting[:20]}); the '
                             f"node's output:\n{gateway.output()[-6000:]}") from None
    # Each answer is due at its timeout after it was taken; a busy machine may add a few
    # seconds (2.4 s measured with both cores overloaded), less than the defect's 6 s.
    allowed = all_taken + timeout + 4.0
    # (a done-callback rclpy skipped, a known race, leaves its call out of the count)
    late = [answered[n] - allowed for n in range(calls) if n in answered]
    assert max(late) <= 0, (f'{sum(t > 0 for t in late)} of {calls} answers more than '
                            f'{timeout + 4.0:.1f} s after the node had taken them all; the '
                            f'last {max(late):.2f} s later than that')


# A client in a process of its own: one answered call, so its response reader is matched to
# the node's response writer, then argv[2] calls to silent nodes left in flight, then it
# waits to be killed.
CLIENT = """
import sys
import rclpy
from cbcan_ros.ros.interface import SERVICE_QOS
from cbcan_ros.srv import SdoRead
rclpy.init()
node = rclpy.create_node('doomed_client')
client = node.create_client(SdoRead, sys.argv[1], qos_profile=SERVICE_QOS)
assert client.wait_for_service(timeout_sec=60.0)
future = client.call_async(SdoRead.Request(node_id=0, index=0x1000))
rclpy.spin_until_future_complete(node, future, timeout_sec=30.0)
print('answered' if future.done() else 'no answer', flush=True)
calls = [client.call_async(SdoRead.Request(node_id=10 + n % 20, index=0x1000, timeout=1.0))
         for n in range(int(sys.argv[2]))]
print('sent', flush=True)
sys.stdin.read()
"""


def kill_a_client(service: str, in_flight: int = 0) -> None:
    """Run CLIENT against ``service`` with ``in_flight`` calls left open, then kill -9 it."""
    doomed = subprocess.Popen([sys.executable, '-c', CLIENT, service, str(in_flight)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert doomed.stdout.readline().strip() == 'answered'
        assert doomed.stdout.readline().strip() == 'sent'
    finally:
        doomed.kill()
        doomed.wait(START_TIMEOUT)
        doomed.stdin.close()
        doomed.stdout.close()


# More answers than the response writer of a KEEP_ALL service keeps unacknowledged (Fast DDS:
# resource_limits.max_samples 5000), sent in bursts that each must be answered long before
# the killed client's DDS lease (about 20 s) ends.
BURSTS = 11
BURST = 500


def test_a_killed_client_does_not_mute_the_service_for_the_others(start_node, client_node):
    # Once a defect: a client process killed (kill -9, a crash, a lost robot computer) stays
    # matched until its DDS lease runs out (about 20 s).
    # Its response reader never acknowledges, so a keep-all response writer kept every answer
    # to every caller; after 5000 of them each further answer failed to leave, unlogged, and
    # every other caller waited in vain until the lease ended.
    name = f'{namespace()}/cbcan'
    gateway = start_node(arguments(name, '-p', f'can.channel:={new_channel()}'))
    sdo_read = service_client(client_node, SdoRead, f'{name}/sdo_read', gateway)
    kill_a_client(f'{name}/sdo_read')

    request = SdoRead.Request(node_id=0, index=0x1018, subindex=2)
    for burst in range(BURSTS):
        calls = [sdo_read.call_async(request) for _ in range(BURST)]
        wait_until(lambda calls=calls: all(call.done() for call in calls), 8.0,
                   f'the answers of burst {burst + 1} of {BURSTS} ({BURST} calls) after a '
                   f'client was killed')
        assert all(call.result().success for call in calls)
    assert gateway.process.poll() is None, gateway.output()


# "Honest overload" and "a service call never blocks the executor".

def test_overload_is_answered_busy_at_once_while_other_devices_and_states_go_on(
        start_node, client_node):
    name = f'{namespace()}/cbcan'
    gateway = start_node(arguments(name, '-p', f'can.channel:={new_channel()}',
                                   '-p', f'simulation.devices:={list(LIVE)}',
                                   '-p', 'sdo.queue_limit:=64',
                                   '-p', 'state_publish_period:=0.1'))
    states = StateWatcher(client_node, name)
    read = service_client(client_node, SdoRead, f'{name}/sdo_read', gateway)
    silent = SILENT[0]
    # The waiting calls' timeout: what follows takes a fraction of a second on a quiet
    # machine and must all happen while they still wait.
    timeout = 6.0
    calls = [read.call_async(SdoRead.Request(node_id=silent, index=0x1000, timeout=timeout))
             for _ in range(300)]
    # One request on the bus and sdo.queue_limit behind it wait; the rest are busy at once
    # (long before any of them could time out).
    wait_until(lambda: sum(call.done() for call in calls) >= 300 - 65, timeout / 2,
               f'the busy answers ({sum(call.done() for call in calls)} so far)')
    busy = [call.result() for call in calls if call.done()]
    assert all(answer.abort_code == BUSY for answer in busy), {a.message for a in busy}
    assert 64 <= unanswered(calls) <= 65
    # While they wait, another device answers at once and the topic goes on.
    published = len(states.messages)
    for _ in range(20):
        answer = wait_for_future(read.call_async(SdoRead.Request(node_id=LIVE[0],
                                                                  index=0x1000)), 1.0)
        assert answer.success and list(answer.data) == [0x92, 0x01, 0x02, 0x00]
    wait_until(lambda: len(states.messages) >= published + 3, 2.0,
               'node_states going on while calls wait')
    assert 64 <= unanswered(calls) <= 65
    answered_within(calls, timeout + ANSWER, 'the waiting calls, at their timeout', gateway)
    timed_out = [call.result() for call in calls if call.result().abort_code != BUSY]
    assert {answer.abort_code for answer in timed_out} == {TIMEOUT}


def test_many_concurrent_mailbox_chains_read_the_right_values(start_node, client_node):
    # 60 ME3CAN multi-reads of 8 blocks at once, alternating two devices: every block of
    # every call reads back 0x1000 of its node (no busy answer: 60 < sdo.queue_limit).
    name = f'{namespace()}/cbcan'
    # 240 reads wait for each device at the start: sdo.timeout (queueing included) leaves
    # room for a busy machine to work through them.
    gateway = start_node(arguments(name, '-p', f'can.channel:={new_channel()}',
                                   '-p', f'simulation.devices:={list(LIVE)}',
                                   '-p', 'sdo.timeout:=20.0'))
    mailbox = service_client(client_node, RegisterMailbox, f'{name}/plc_mailbox', gateway)
    blocks = [me3can_multi_read([LIVE[(number + block) % 2] for block in range(8)])
              for number in range(60)]
    calls = [mailbox.call_async(RegisterMailbox.Request(format='me3can', registers=block))
             for block in blocks]
    answered_within(calls, 3 * ANSWER, 'the mailbox chains', gateway)
    for block, call in zip(blocks, calls, strict=True):
        answer = call.result()
        registers = list(answer.registers)
        assert registers[0] == ME3CAN_MULTI_READ_OK, answer.message
        for number in range(8):
            offset = 1 + 8 * number
            assert registers[offset:offset + 3] == block[offset:offset + 3]
            assert registers[offset + 3:offset + 8] == [4, *DEVICE_TYPE, 0, 0]


# A client process killed with kill -9 in the middle of its burst.

def test_a_client_killed_mid_burst_leaves_the_others_served(start_node, client_node):
    name = f'{namespace()}/cbcan'
    gateway = start_node(arguments(name, '-p', f'can.channel:={new_channel()}',
                                   '-p', f'simulation.devices:={list(LIVE)}'))
    read = service_client(client_node, SdoRead, f'{name}/sdo_read', gateway)
    kill_a_client(f'{name}/sdo_read', in_flight=1500)
    # Its 1,500 calls end (busy or timeout) and are answered to nobody; ours go on, also
    # after its calls' answers have all been sent into the void.
    for round_ in range(3):
        calls = [read.call_async(SdoRead.Request(node_id=LIVE[n % 2], index=0x1000,
                                                 timeout=ANSWER)) for n in range(100)]
        answered_within(calls, 2 * ANSWER, f'round {round_ + 1} after the client was killed',
                        gateway)
        assert all(call.result().success for call in calls), \
            {call.result().message for call in calls}
        time.sleep(0.5)
    assert gateway.process.poll() is None, gateway.output()
    assert 'Traceback' not in gateway.output()


# node_states with a full bus of 127 nodes.

OTHERS = [1, *range(3, 128)]  # node 2 is a simulated device that answers SDO


def test_all_nodes_changing_state_at_once_does_not_stall_sdo(start_node, client_node):
    # 126 nodes heartbeat every 0.2 s; then all change state at once, as after "NMT start
    # all". Once a defect: each change publishes a 127-node message (about
    # 2 ms of Python) from the bus's receive thread, so the receive thread spends about a
    # quarter of a second publishing ~126 messages, and the SDO answer of an unrelated
    # healthy device waits behind them: 230..530 ms here instead of 2 ms, some reads time
    # out (sdo.timeout 0.5 s). Publishing the latest picture from a thread of its own,
    # coalescing changes, measured 40..125 ms on this loaded machine. How long a read takes
    # is a matter for `make bench`; here every read must succeed, with time to spare.
    group, port = private_bus()
    name = f'{namespace()}/cbcan'
    gateway = start_node(arguments(name, '-p', 'can.interface:=udp_multicast',
                                   '-p', f'can.channel:={group}',
                                   '-p', 'simulation.devices:=[2]',
                                   '-p', 'heartbeat.timeout:=2.0'), port)
    states = StateWatcher(client_node, name)
    read = service_client(client_node, SdoRead, f'{name}/sdo_read', gateway)
    bus = can.Bus(interface='udp_multicast', channel=group, port=port)
    heartbeat = {'state': 0x7F}
    running = threading.Event()
    running.set()

    def produce() -> None:
        while running.is_set():
            for node_id in OTHERS:
                bus.send(can.Message(arbitration_id=0x700 + node_id,
                                     data=[heartbeat['state']], is_extended_id=False))
            time.sleep(0.2)

    producer = threading.Thread(target=produce, daemon=True)
    producer.start()
    try:
        wait_until(lambda: len(states.latest()) == 127, 3 * ANSWER,
                   'all 127 nodes on the topic')
        failures = []
        for state, expected in ((0x05, 'OPERATIONAL'), (0x7F, 'PRE_OPERATIONAL')):
            time.sleep(0.3)
            heartbeat['state'] = state
            changed = time.monotonic()
            while time.monotonic() - changed < 0.6:
                answer = wait_for_future(read.call_async(SdoRead.Request(
                    node_id=2, index=0x1000, timeout=2.0)), ANSWER)
                failures.extend([answer.message] if not answer.success else [])
            # The last message is the latest picture, and a late subscriber gets it at once.
            wait_until(lambda e=expected: all(states.latest().get(i) == e for i in OTHERS),
                       ANSWER, f'every node {expected} on the topic')
            late = []
            client_node.create_subscription(NodeStates, f'{name}/node_states', late.append,
                                            NODE_STATES_QOS)
            wait_until(lambda late=late: late, ANSWER,
                       'the current picture for a late subscriber')
            assert {n.node_id: n.state_name for n in late[0].nodes if n.node_id != 2} == \
                {i: expected for i in OTHERS}
        stamps = [(m.stamp.sec, m.stamp.nanosec) for m in states.messages]
        assert stamps == sorted(stamps), 'node_states published out of order'
    finally:
        running.clear()
        producer.join()
        bus.shutdown()
    assert not failures, (f'{len(failures)} SDO reads of a healthy device failed while 126 '
                          f'nodes changed state: {failures[:1]}')
