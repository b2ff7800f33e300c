"""Red-team regressions, third pass: EventsExecutor, the shared interface, the managed node.

Each test starts the installed ``cbcan_node`` or ``cbcan_lifecycle_node`` as a separate
process (test/node_process.py) and meets it as a robot does: rclpy clients and subscribers in
this process or in child processes, signals, lifecycle transitions, frames on the bus.
"""

import os
import signal
import subprocess
import sys
import threading
import time

import can
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rcl_interfaces.msg import Parameter as ParameterMessage
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from test_process_faults import BusRecorder, namespace, StateWatcher

from cbcan_ros.msg import NodeStates, SdoAccess
from cbcan_ros.ros.interface import NODE_STATES_QOS
from cbcan_ros.srv import RegisterMailbox, SdoBatch, SdoRead, SdoWrite

from conftest import HEAVY, new_channel, wait_for_future, wait_until
from node_process import random_bus, service_client, START_TIMEOUT

pytestmark = HEAVY

LIVE = (2, 3)            # simulated devices inside the node's process
SILENT = range(10, 30)   # node ids nobody answers
CALL_TIMEOUT = 30.0      # far beyond each test: only shutdown or cleanup answers these calls
BUSY = 0x060A0023
DEVICE_TYPE = [0x0192, 0x0002]  # 0x1000 of the simulated devices, as two words

ME3CAN_MULTI_READ = 0x0008
ME3CAN_MULTI_READ_OK = 0x0009
END_OF_LIST = 0xFFFF


def me3can_multi_read(node_ids) -> list:
    """Return a Mitsubishi ME3CAN1-L multi SDO read block: 0x1000:00 of each node in turn."""
    block = [0] * 67
    block[0] = ME3CAN_MULTI_READ
    for number, node_id in enumerate(node_ids):
        block[1 + 8 * number:5 + 8 * number] = [node_id, 0x1000, 0, 4]
    if len(node_ids) < 8:
        block[1 + 8 * len(node_ids)] = END_OF_LIST
    return block


def arguments(name: str, *more: str) -> list:
    """Return the node's command line arguments for the node name ``/<namespace>/cbcan``."""
    return ['-r', f'__ns:={name.rsplit("/", 1)[0]}', *more]


def unanswered(calls) -> int:
    """Return how many of the rclpy futures have no answer."""
    return sum(not future.done() for future in calls)


def answered_within(calls, timeout: float, what: str, gateway) -> None:
    """Fail, with the node's output, unless every call has its answer within ``timeout``."""
    try:
        wait_until(lambda: not unanswered(calls), timeout, what)
    except AssertionError:
        raise AssertionError(f'{unanswered(calls)} of {len(calls)} calls never answered '
                             f'({what}); node output:\n{gateway.output()[-4000:]}') from None


def cpu_seconds(pid: int) -> float:
    """Return the user + system CPU time a process used so far."""
    fields = open(f'/proc/{pid}/stat').read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


# Shutdown: "SIGINT/SIGTERM answers every waiting call and exits 0 within about 2 s".

def test_signal_during_a_burst_answers_every_caller_and_sends_no_write_twice(
        start_node, client_node):
    # 3,000 reads, writes and batches, most for silent devices, SIGINT while the node is still
    # taking the burst in. A defect found by this pass: requests that had reached the node but
    # that the executor had not taken yet when it stopped were never answered: those callers
    # wait for ever (about 500 of 3,000 here). Nothing drains the services before they go.
    group, port = random_bus()
    recorder = BusRecorder(group, port)
    name = f'{namespace()}/cbcan'
    try:
        gateway = start_node(arguments(name, '-p', 'can.interface:=udp_multicast',
                                       '-p', f'can.channel:={group}'), port)
        read = service_client(client_node, SdoRead, f'{name}/sdo_read', gateway)
        write = service_client(client_node, SdoWrite, f'{name}/sdo_write', gateway)
        batch = service_client(client_node, SdoBatch, f'{name}/sdo_batch', gateway)
        calls = []
        for number in range(3000):
            node_id = SILENT[number % len(SILENT)]
            kind = number % 3
            if kind == 0:
                calls.append(read.call_async(SdoRead.Request(
                    node_id=node_id, index=0x1000, timeout=CALL_TIMEOUT)))
            elif kind == 1:  # the call number in the data: each write is one frame's data
                calls.append(write.call_async(SdoWrite.Request(
                    node_id=node_id, index=0x2002, data=list(number.to_bytes(4, 'little')),
                    timeout=CALL_TIMEOUT)))
            else:
                calls.append(batch.call_async(SdoBatch.Request(accesses=[
                    SdoAccess(node_id=node_id, index=0x1000),
                    SdoAccess(node_id=node_id, index=0x2003, write=True,
                              data=list(number.to_bytes(4, 'little')))],
                    timeout=CALL_TIMEOUT)))
        wait_until(lambda: any(call.done() for call in calls), 10.0, 'the first answer')
        signalled = time.monotonic()
        gateway.process.send_signal(signal.SIGINT)
        status = gateway.wait(5.0)
        exited = time.monotonic() - signalled
        answered_within(calls, 2.0, 'after SIGINT in the middle of a burst', gateway)
        time.sleep(0.2)  # let frames still in flight reach the recorder
    finally:
        recorder.close()
    output = gateway.output()
    assert status == 0 and exited < 2.0, (status, exited, output[-3000:])
    assert 'Traceback' not in output, output
    sdo_requests = [(t, m) for t, m in recorder.frames if 0x600 < m.arbitration_id < 0x680]
    after = [m.data.hex() for t, m in sdo_requests if t > signalled and m.data[0] != 0x80]
    assert after == [], f'requests sent after the signal: {after[:10]}'
    writes = [bytes(m.data[4:8]) for _, m in sdo_requests if m.data[0] & 0xE0 == 0x20]
    assert len(writes) == len(set(writes)), 'a write went out twice'


def mailbox_backlog(start_node, client_node):
    """Start a node and send it 2,000 ME3CAN multi-reads of 8 blocks; return at the first answer.

    The mailbox loop needs seconds for them: a shutdown meets a long backlog.
    """
    name = f'{namespace()}/cbcan'
    gateway = start_node(arguments(name, '-p', f'can.channel:={new_channel()}',
                                   '-p', f'simulation.devices:={list(LIVE)}'))
    mailbox = service_client(client_node, RegisterMailbox, f'{name}/plc_mailbox', gateway)
    calls = [mailbox.call_async(RegisterMailbox.Request(
        format='me3can', registers=me3can_multi_read([LIVE[number % 2]] * 8)))
        for number in range(2000)]
    wait_until(lambda: any(call.done() for call in calls), 15.0, 'the first mailbox answer')
    return gateway, calls


def test_signal_with_a_mailbox_backlog_answers_every_mailbox_call(start_node, client_node):
    # 2,000 ME3CAN multi-reads of 8 blocks (the mailbox loop needs seconds for them), SIGINT
    # at the first answer. A defect found by this pass: shutdown waits ANSWER_GRACE for the
    # calls, then CoroutineRunner.close() stops the loop with mailbox tasks still on it.
    # Their callers are never answered, the node prints one "Task was destroyed but it is
    # pending!" (with a task dump) per lost call, and destroy_node then waits ANSWER_GRACE a
    # second time for the calls that can no longer end: exit after about 3 s.
    gateway, calls = mailbox_backlog(start_node, client_node)
    signalled = time.monotonic()
    gateway.process.send_signal(signal.SIGINT)
    status = gateway.wait(5.0)
    exited = time.monotonic() - signalled
    output = gateway.output()
    assert 'Task was destroyed but it is pending' not in output, output[-3000:]
    # Every one of the 2,000 requests is taken and answered during shutdown: a second more
    # than the 2 s of an ordinary shutdown, for a test suite sharing 2 cores between workers.
    assert status == 0 and exited < 3.0, (status, exited, output[-3000:])
    # The answers left the node before it exited; this client takes its time to read 2,000.
    answered_within(calls, 10.0, 'mailbox calls after SIGINT', gateway)


def test_second_signal_during_a_slow_shutdown_exits_at_once(start_node, client_node):
    # The first SIGINT starts the orderly shutdown of a node with a mailbox backlog; the
    # impatient second one must end the process at once (status 128 + 2), whatever the
    # first is waiting for.
    gateway, calls = mailbox_backlog(start_node, client_node)
    gateway.process.send_signal(signal.SIGINT)
    wait_until(lambda: 'shutting down' in gateway.output() or gateway.process.poll() is not None,
               2.0, 'the first signal taken')
    if gateway.process.poll() is None:
        again = time.monotonic()
        gateway.process.send_signal(signal.SIGINT)
        status = gateway.wait(2.0)
        assert time.monotonic() - again < 0.5, gateway.output()[-2000:]
        assert status in (0, 128 + signal.SIGINT), gateway.output()[-2000:]
    assert 'Traceback' not in gateway.output()


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
    sent = time.monotonic()
    calls = [read.call_async(SdoRead.Request(node_id=silent, index=0x1000, timeout=2.0))
             for _ in range(300)]
    # One request on the bus and sdo.queue_limit behind it wait; the rest are busy at once.
    wait_until(lambda: sum(call.done() for call in calls) >= 300 - 65, 1.5,
               f'the busy answers ({sum(call.done() for call in calls)} so far)')
    busy = [call.result() for call in calls if call.done()]
    assert all(answer.abort_code == BUSY for answer in busy), {a.message for a in busy}
    assert 64 <= unanswered(calls) <= 65
    # While they wait, another device answers at once and the topic goes on.
    published = len(states._messages)
    for _ in range(20):
        answer = wait_for_future(read.call_async(SdoRead.Request(node_id=LIVE[0],
                                                                  index=0x1000)), 0.5)
        assert answer.success and list(answer.data) == [0x92, 0x01, 0x02, 0x00]
    wait_until(lambda: len(states._messages) >= published + 3, 1.0,
               'node_states going on while calls wait')
    assert 64 <= unanswered(calls) <= 65
    answered_within(calls, 3.0, 'the waiting calls, at their timeout', gateway)
    assert time.monotonic() - sent < 2.0 + 1.0
    timed_out = [call.result() for call in calls if call.result().abort_code != BUSY]
    assert {answer.abort_code for answer in timed_out} == {0x05040000}


def test_many_concurrent_mailbox_chains_read_the_right_values(start_node, client_node):
    # 60 ME3CAN multi-reads of 8 blocks at once, alternating two devices: every block of
    # every call reads back 0x1000 of its node (no busy answer: 60 < sdo.queue_limit).
    name = f'{namespace()}/cbcan'
    gateway = start_node(arguments(name, '-p', f'can.channel:={new_channel()}',
                                   '-p', f'simulation.devices:={list(LIVE)}'))
    mailbox = service_client(client_node, RegisterMailbox, f'{name}/plc_mailbox', gateway)
    blocks = [me3can_multi_read([LIVE[(number + block) % 2] for block in range(8)])
              for number in range(60)]
    calls = [mailbox.call_async(RegisterMailbox.Request(format='me3can', registers=block))
             for block in blocks]
    answered_within(calls, 10.0, 'the mailbox chains', gateway)
    for block, call in zip(blocks, calls, strict=True):
        answer = call.result()
        registers = list(answer.registers)
        assert registers[0] == ME3CAN_MULTI_READ_OK, answer.message
        for number in range(8):
            offset = 1 + 8 * number
            assert registers[offset:offset + 3] == block[offset:offset + 3]
            assert registers[offset + 3:offset + 8] == [4, *DEVICE_TYPE, 0, 0]


# A client process killed with kill -9 in the middle of its burst.

KILLED_CLIENT = """
import sys
import rclpy
from cbcan_ros.ros.interface import SERVICE_QOS
from cbcan_ros.srv import SdoRead
rclpy.init()
node = rclpy.create_node('doomed_client')
client = node.create_client(SdoRead, sys.argv[1], qos_profile=SERVICE_QOS)
assert client.wait_for_service(timeout_sec=15.0)
first = client.call_async(SdoRead.Request(node_id=0, index=0x1000))
rclpy.spin_until_future_complete(node, first, timeout_sec=10.0)
calls = [client.call_async(SdoRead.Request(node_id=10 + n % 20, index=0x1000, timeout=1.0))
         for n in range(1500)]
print('sent', flush=True)
sys.stdin.read()
"""


def test_a_client_killed_mid_burst_leaves_the_others_served(start_node, client_node):
    name = f'{namespace()}/cbcan'
    gateway = start_node(arguments(name, '-p', f'can.channel:={new_channel()}',
                                   '-p', f'simulation.devices:={list(LIVE)}'))
    read = service_client(client_node, SdoRead, f'{name}/sdo_read', gateway)
    doomed = subprocess.Popen([sys.executable, '-c', KILLED_CLIENT, f'{name}/sdo_read'],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert doomed.stdout.readline().strip() == 'sent'
    finally:
        doomed.kill()
        doomed.wait(START_TIMEOUT)
        doomed.stdin.close()
        doomed.stdout.close()
    # Its 1,500 calls end (busy or timeout) and are answered to nobody; ours go on, also
    # after its calls' answers have all been sent into the void.
    for round_ in range(3):
        calls = [read.call_async(SdoRead.Request(node_id=LIVE[n % 2], index=0x1000,
                                                 timeout=2.0)) for n in range(100)]
        answered_within(calls, 3.0, f'round {round_ + 1} after the client was killed',
                        gateway)
        assert all(call.result().success for call in calls), \
            {call.result().message for call in calls}
        time.sleep(0.5)
    assert gateway.process.poll() is None, gateway.output()
    assert 'Traceback' not in gateway.output()


# node_states from the thread that sees the change, with a full bus of 127 nodes.

OTHERS = [1, *range(3, 128)]  # node 2 is a simulated device that answers SDO


def test_all_nodes_changing_state_at_once_does_not_stall_sdo(start_node, client_node):
    # 126 nodes heartbeat every 0.2 s; then all change state at once, as after "NMT start
    # all". A defect found by this pass: each change publishes a 127-node message (about
    # 2 ms of Python) from the bus's receive thread, so the receive thread spends about a
    # quarter of a second publishing ~126 messages, and the SDO answer of an unrelated
    # healthy device waits behind them: 230..530 ms here instead of 2 ms, some reads time
    # out (sdo.timeout 0.5 s). Publishing the latest picture from a thread of its own,
    # coalescing changes, measured 40..125 ms on this loaded machine.
    group, port = random_bus()
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
        wait_until(lambda: len(states.latest()) == 127, 10.0, 'all 127 nodes on the topic')
        slowest, failures = [], []
        for state, expected in ((0x05, 'OPERATIONAL'), (0x7F, 'PRE_OPERATIONAL')):
            time.sleep(0.3)
            heartbeat['state'] = state
            changed = time.monotonic()
            latencies = []
            while time.monotonic() - changed < 0.6:
                started = time.monotonic()
                answer = wait_for_future(read.call_async(SdoRead.Request(
                    node_id=2, index=0x1000)), 5.0)
                latencies.append(time.monotonic() - started)
                failures.extend([answer.message] if not answer.success else [])
            slowest.append(max(latencies))
            # The last message is the latest picture, and a late subscriber gets it at once.
            wait_until(lambda e=expected: all(states.latest().get(i) == e for i in OTHERS), 3.0,
                       f'every node {expected} on the topic')
            late = []
            client_node.create_subscription(NodeStates, f'{name}/node_states', late.append,
                                            NODE_STATES_QOS)
            wait_until(lambda late=late: late, 3.0, 'the current picture for a late subscriber')
            assert {n.node_id: n.state_name for n in late[0].nodes if n.node_id != 2} == \
                {i: expected for i in OTHERS}
        stamps = [(m.stamp.sec, m.stamp.nanosec) for m in states._messages]
        assert stamps == sorted(stamps), 'node_states published out of order'
    finally:
        running.clear()
        producer.join()
        bus.shutdown()
    assert not failures and max(slowest) < 0.2, (
        f'an SDO read of a healthy device took up to {max(slowest) * 1000:.0f} ms while 126 '
        f'nodes changed state (about 2 ms otherwise); {len(failures)} failed: {failures[:1]}')


def test_idle_nodes_do_not_spin(start_node, client_node):
    # EventsExecutor.spin() was reported to busy-wait; both nodes idle near 0 % of a core.
    plain_name = f'{namespace()}/cbcan'
    plain = start_node(arguments(plain_name, '-p', f'can.channel:={new_channel()}'))
    managed_name = f'{namespace()}/cbcan'
    managed = start_node(arguments(managed_name, '-p', f'can.channel:={new_channel()}'),
                         program='cbcan_lifecycle_node')
    service_client(client_node, SdoRead, f'{plain_name}/sdo_read', plain)
    change_state = service_client(client_node, ChangeState, f'{managed_name}/change_state',
                                  managed)
    for transition in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE):
        assert wait_for_future(change_state.call_async(ChangeState.Request(
            transition=Transition(id=transition))), 10.0).success
    time.sleep(0.5)
    before = {p: cpu_seconds(p.process.pid) for p in (plain, managed)}
    time.sleep(2.0)
    used = {p: (cpu_seconds(p.process.pid) - before[p]) / 2.0 for p in (plain, managed)}
    assert used[plain] < 0.05 and used[managed] < 0.05, \
        f'idle CPU: cbcan_node {used[plain]:.0%}, cbcan_lifecycle_node {used[managed]:.0%}'


# The managed node, driven as launch systems and people at a shell do.

class Managed:
    """A ``cbcan_lifecycle_node`` process with simulated device 2, and its lifecycle clients."""

    def __init__(self, start_node, client_node, *parameters: str):
        self.name = f'{namespace()}/cbcan'
        self.client_node = client_node
        self.node = start_node(arguments(self.name, '-p', f'can.channel:={new_channel()}',
                                         '-p', 'simulation.devices:=[2]', *parameters),
                               program='cbcan_lifecycle_node')
        self._change_state = self.client(ChangeState, 'change_state')
        self._get_state = self.client(GetState, 'get_state')

    def client(self, service_type, service: str):
        """Return a client of the node's ``service``."""
        return service_client(self.client_node, service_type, f'{self.name}/{service}',
                              self.node)

    def transition_async(self, transition: int):
        """Request a transition; return the rclpy future of its answer."""
        return self._change_state.call_async(ChangeState.Request(
            transition=Transition(id=transition)))

    def transition(self, transition: int) -> bool:
        """Make a transition; return whether it succeeded."""
        try:
            return wait_for_future(self.transition_async(transition), 3.0).success
        except AssertionError:
            raise AssertionError(f'transition {transition} unanswered (exit status '
                                 f'{self.node.process.poll()}):\n{self.node.output()}') from None

    def state(self) -> str:
        """Return the label of the node's lifecycle state."""
        return wait_for_future(self._get_state.call_async(GetState.Request()),
                               5.0).current_state.label


def test_a_transition_the_state_does_not_have_is_refused_not_fatal(start_node, client_node):
    # A defect found by this pass: configure sent twice (a second launch manager, a script,
    # `ros2 service call .../change_state` by hand) makes rclpy's LifecycleNode raise
    # RCLError "Transition is not registered" inside the change_state callback. The exception
    # ends the executor thread, so the node shuts down (exit status 0, a traceback on its
    # output) and the caller is never answered. rclcpp answers success: false instead.
    managed = Managed(start_node, client_node)
    assert managed.transition(Transition.TRANSITION_CONFIGURE)
    assert not managed.transition(Transition.TRANSITION_CONFIGURE)
    assert not managed.transition(Transition.TRANSITION_DEACTIVATE)
    assert managed.node.process.poll() is None, managed.node.output()
    assert managed.state() == 'inactive'
    assert managed.transition(Transition.TRANSITION_ACTIVATE)
    read = managed.client(SdoRead, 'sdo_read')
    answer = wait_for_future(read.call_async(SdoRead.Request(node_id=2, index=0x1000)), 5.0)
    assert answer.success, answer.message
    # Shutdown from active answers the calls waiting for a silent device; finalized, the
    # node refuses every further transition and still ends cleanly on SIGINT.
    waiting = [read.call_async(SdoRead.Request(node_id=SILENT[0], index=0x1000,
                                               timeout=CALL_TIMEOUT)) for _ in range(5)]
    assert wait_for_future(read.call_async(SdoRead.Request(node_id=2, index=0x1000)),
                           5.0).success
    assert managed.transition(Transition.TRANSITION_ACTIVE_SHUTDOWN)
    answered_within(waiting, 2.0, 'calls waiting at the shutdown transition', managed.node)
    assert all('shutting down' in call.result().message for call in waiting)
    assert managed.state() == 'finalized'
    assert not managed.transition(Transition.TRANSITION_CONFIGURE)
    managed.node.process.send_signal(signal.SIGINT)
    assert managed.node.wait(2.0) == 0
    assert 'Traceback' not in managed.node.output()


def test_a_failed_configure_says_why_and_leaves_nothing_behind(start_node, client_node):
    # A defect found by this pass: a configure that fails for another reason than a
    # ValueError (here: the simulated devices' EDS file does not exist) fails without a word
    # in the log (rclpy swallows the exception), and the log handler GatewayInterface added
    # stays on the package logger: from then on every core log line appears twice.
    managed = Managed(start_node, client_node, '-p', 'simulation.eds:=/nonexistent/dev.eds')
    assert not managed.transition(Transition.TRANSITION_CONFIGURE)
    assert managed.state() == 'unconfigured'
    wait_until(lambda: 'simulation.eds' in managed.node.output()
               or '/nonexistent/dev.eds' in managed.node.output(), 3.0,
               f'the reason of the failed configure in the log:\n{managed.node.output()}')
    fixed = ParameterMessage(name='simulation.eds', value=ParameterValue(
        type=ParameterType.PARAMETER_STRING, string_value=''))
    set_parameters = managed.client(SetParameters, 'set_parameters')
    result = wait_for_future(set_parameters.call_async(SetParameters.Request(
        parameters=[fixed])), 5.0)
    assert result.results[0].successful, result.results[0].reason
    assert managed.transition(Transition.TRANSITION_CONFIGURE)
    assert managed.transition(Transition.TRANSITION_CLEANUP)
    wait_until(lambda: 'is closed' in managed.node.output(), 3.0, 'the bus closed')
    output = managed.node.output()
    assert output.count('is open') == 1 and output.count('is closed') == 1, output


def test_cleanup_answers_every_call_that_reached_the_node(start_node, client_node):
    # Calls wait for a silent device; cleanup is requested while callers keep calling. A
    # defect found by this pass: the requests that arrive while the transition runs (the
    # executor is busy with it) are never answered once cleanup destroys the services (the
    # node logs one "could not be sent (InvalidHandle ...)"). Only a call sent in the last
    # moment, as the service goes, may go unanswered (ROS cannot deliver it anywhere).
    managed = Managed(start_node, client_node)
    assert managed.transition(Transition.TRANSITION_CONFIGURE)
    assert managed.transition(Transition.TRANSITION_ACTIVATE)
    read = managed.client(SdoRead, 'sdo_read')
    waiting = [read.call_async(SdoRead.Request(node_id=SILENT[0], index=0x1000,
                                               timeout=CALL_TIMEOUT)) for _ in range(20)]
    assert wait_for_future(read.call_async(SdoRead.Request(node_id=2, index=0x1000)),
                           5.0).success
    assert managed.transition(Transition.TRANSITION_DEACTIVATE)
    cleanup = managed.transition_async(Transition.TRANSITION_CLEANUP)
    racing = []
    deadline = time.monotonic() + 10.0
    while not cleanup.done() and time.monotonic() < deadline:
        racing.append((time.monotonic(), read.call_async(SdoRead.Request(
            node_id=2, index=0x1000))))
        time.sleep(0.001)
    cleaned = time.monotonic()
    assert cleanup.done() and cleanup.result().success, managed.node.output()
    answered_within(waiting, 2.0, 'the calls waiting when cleanup began', managed.node)
    assert all('shutting down' in call.result().message for call in waiting)
    # Calls sent well before cleanup's answer arrived reached the node before it destroyed
    # its services (the transition holds the executor far longer than that).
    reached = [call for sent, call in racing if sent < cleaned - 0.05]
    answered_within(reached, 2.0, f'calls sent during cleanup ({len(racing)} in all)',
                    managed.node)


def test_deactivate_cleanup_and_signals_in_every_state(start_node, client_node):
    managed = Managed(start_node, client_node, '-p', 'sdo.timeout:=1.0')
    assert managed.transition(Transition.TRANSITION_CONFIGURE)
    assert managed.transition(Transition.TRANSITION_ACTIVATE)
    read = managed.client(SdoRead, 'sdo_read')
    # Calls under way when the node is deactivated get their real answer (a timeout).
    waiting = [read.call_async(SdoRead.Request(node_id=SILENT[0], index=0x1000))
               for _ in range(3)]
    assert wait_for_future(read.call_async(SdoRead.Request(node_id=2, index=0x1000)),
                           5.0).success
    assert managed.transition(Transition.TRANSITION_DEACTIVATE)
    answered_within(waiting, 4.0, 'calls under way at deactivate', managed.node)
    assert [call.result().abort_code for call in waiting] == [0x05040000] * 3
    # Cleanup closes the bus, configure opens it again; SIGINT while inactive with calls
    # waiting answers them and exits 0 at once.
    assert managed.transition(Transition.TRANSITION_CLEANUP)
    assert managed.transition(Transition.TRANSITION_CONFIGURE)
    assert managed.transition(Transition.TRANSITION_ACTIVATE)
    waiting = [read.call_async(SdoRead.Request(node_id=SILENT[0], index=0x1000,
                                               timeout=CALL_TIMEOUT)) for _ in range(5)]
    assert wait_for_future(read.call_async(SdoRead.Request(node_id=2, index=0x1000)),
                           5.0).success
    assert managed.transition(Transition.TRANSITION_DEACTIVATE)
    signalled = time.monotonic()
    managed.node.process.send_signal(signal.SIGINT)
    answered_within(waiting, 2.0, 'calls waiting at SIGINT while inactive', managed.node)
    assert all('shutting down' in call.result().message for call in waiting)
    assert managed.node.wait(2.0) == 0
    assert time.monotonic() - signalled < 2.0
    output = managed.node.output()
    assert output.count('is open') == 2 and output.count('is closed') == 2, output
    assert 'Traceback' not in output

    # SIGINT while unconfigured.
    unconfigured = Managed(start_node, client_node)
    signalled = time.monotonic()
    unconfigured.node.process.send_signal(signal.SIGINT)
    assert unconfigured.node.wait(2.0) == 0
    assert time.monotonic() - signalled < 2.0
    assert 'Traceback' not in unconfigured.node.output()
