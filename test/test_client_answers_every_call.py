"""The Python client (cbcan_ros.ros.client) gets every answer, right, in each of its forms.

Against the installed cbcan_node in a process of its own, with simulated devices 2..9 on a
virtual bus inside it: bursts of 200 concurrent calls from threads (blocking form) and from
coroutines on the caller's executor (awaitable form), a blocking call inside a callback of
the caller's executor, and the errors a caller sees.
"""

import re
import threading
import uuid

import pytest
import rclpy
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor

from cbcan_ros.core.values import decode_value, encode
from cbcan_ros.ros.client import GatewayClient, GatewayUnavailable, Read, RequestFailed, Write

from conftest import new_channel, Spinning, wait_until
from node_process import NodeProcess, START_TIMEOUT

# One worker runs the module, so its gateway starts once.
pytestmark = pytest.mark.xdist_group('python_client')

DEVICES = list(range(2, 10))
BURST = 200
DEVICE_TYPE = 0x00020192  # 0x1000 of every simulated device
ANSWER_WAIT = 60.0  # a burst on a busy 2-core machine; a lost answer never comes at all


def device_value(node_id: int) -> int:
    """Return the value the tests write to 0x2002 of a device: one of its own."""
    return 0x11110000 + node_id


@pytest.fixture(scope='module')
def gateway():
    """Start cbcan_node once for the module; yield (its name, the process)."""
    namespace = f'/client{uuid.uuid4().hex[:8]}'
    process = NodeProcess(['-r', f'__ns:={namespace}',
                           '-p', f'can.channel:={new_channel()}',
                           '-p', f'simulation.devices:={DEVICES}',
                           '-p', 'sdo.timeout:=10.0'])
    yield f'{namespace}/cbcan', process
    process.close()


@pytest.fixture
def node():
    """Yield a node of the caller that nothing spins."""
    made = rclpy.create_node(f'client_test_{uuid.uuid4().hex[:8]}')
    yield made
    made.destroy_node()


@pytest.fixture
def client(gateway, node):
    """Yield a client of the gateway with each device's own value in its 0x2002."""
    with GatewayClient(node, gateway[0], wait=START_TIMEOUT) as made:
        try:
            results = made.batch([Write(device, 0x2002, 0, device_value(device), 'u32')
                                  for device in DEVICES])
        except GatewayUnavailable as error:
            raise AssertionError(f'{error}\ncbcan_node output:\n{gateway[1].output()}') \
                from None
        assert all(result.success for result in results), results
        yield made


def burst_call(number: int):
    """Return (device, index, expected value) of call ``number`` of a burst."""
    device = DEVICES[number % len(DEVICES)]
    if number % 2:
        return device, 0x2002, device_value(device)
    return device, 0x1000, DEVICE_TYPE


def test_a_burst_of_blocking_reads_from_threads_gets_every_answer_right(client):
    answers = [None] * BURST
    start = threading.Barrier(BURST)

    def call(number: int) -> None:
        device, index, _expected = burst_call(number)
        start.wait()
        try:
            answers[number] = client.read(device, index, type='u32')
        except Exception as error:  # noqa: BLE001 - reported by the assertion below
            answers[number] = error

    threads = [threading.Thread(target=call, args=(number,)) for number in range(BURST)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(ANSWER_WAIT)
    assert not any(thread.is_alive() for thread in threads), 'calls still waiting'
    wrong = [(number, burst_call(number), answer) for number, answer in enumerate(answers)
             if answer != burst_call(number)[2]]
    assert wrong == [], wrong


@pytest.mark.parametrize('executor_type', [SingleThreadedExecutor, MultiThreadedExecutor])
def test_a_burst_of_awaited_reads_on_the_callers_executor_gets_every_answer_right(
        client, node, executor_type):
    executor = executor_type()
    executor.add_node(node)

    async def call(number: int):
        device, index, _expected = burst_call(number)
        return await client.read_async(device, index, type='u32')

    tasks = [executor.create_task(call, number) for number in range(BURST)]
    spinning = Spinning(executor)
    try:
        wait_until(lambda: all(task.done() for task in tasks), ANSWER_WAIT,
                   f'{BURST} awaited reads to finish')
    finally:
        spinning.stop()
    wrong = [(number, burst_call(number), task.exception() or task.result())
             for number, task in enumerate(tasks)
             if task.exception() or task.result() != burst_call(number)[2]]
    assert wrong == [], wrong


def test_a_blocking_call_inside_a_callback_of_the_callers_executor_is_answered(client, node):
    answers = []

    def on_timer() -> None:
        if not answers:
            answers.append(client.read(5, 0x2002, type='u32'))
            answers.append(client.states())

    node.create_timer(0.01, on_timer)
    executor = SingleThreadedExecutor()  # one thread: a call waiting on it would never end
    executor.add_node(node)
    spinning = Spinning(executor)
    try:
        wait_until(lambda: len(answers) == 2, ANSWER_WAIT, 'the calls in the timer callback')
    finally:
        spinning.stop()
    assert answers[0] == device_value(5)
    assert set(DEVICES) <= set(answers[1]), answers[1]


def test_subscribed_node_states_arrive_on_the_callers_executor(client, node):
    seen = []
    client.subscribe_states(lambda message: seen.append(
        (threading.current_thread(), {state.node_id for state in message.nodes})))
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinning = Spinning(executor)
    try:
        wait_until(lambda: any(set(DEVICES) <= nodes for _thread, nodes in seen),
                   ANSWER_WAIT, f'node states listing devices {DEVICES} (seen {seen})')
    finally:
        spinning.stop()
    assert {thread for thread, _nodes in seen} == {spinning.thread}


def test_a_refusal_raises_with_the_abort_code_and_a_batch_answers_every_access(client):
    with pytest.raises(RequestFailed) as refused:
        client.read(5, 0x6000)
    assert refused.value.abort_code == 0x06020000, refused.value
    assert 'node 5 object 0x6000:00' in str(refused.value), refused.value
    assert refused.value.response.success is False

    results = client.batch([Read(3, 0x6000), Read(3, 0x2002, type='u32'),
                            Read(3, 0x2002, type='u16'), Write(3, 0x2001, 0, b'\x34\x12'),
                            Read(3, 0x2001, type='u16')])
    assert [(result.success, result.abort_code) for result in results] == [
        (False, 0x06020000), (True, 0), (False, 0), (True, 0), (True, 0)], results
    assert results[1].value == device_value(3)
    assert 'type u16 takes 2 bytes, the answer has 4' in results[2].message, results[2]
    assert results[4].value == 0x1234

    with pytest.raises(ValueError, match="'70000' does not fit u16"):
        client.write(5, 0x2001, 0, 70000, type='u16')
    with pytest.raises(RequestFailed, match='command 99 is not an NMT command'):
        client.nmt(5, 99)


def test_a_value_that_does_not_fit_is_refused_before_anything_is_sent(node):
    with GatewayClient(node, f'/nobody{uuid.uuid4().hex[:8]}/cbcan', wait=0.2) as nowhere:
        with pytest.raises(ValueError, match='does not fit u8'):
            nowhere.write(5, 0x2001, 0, 256, type='u8')  # no GatewayUnavailable: not called
        with pytest.raises(GatewayUnavailable, match='no gateway at /nobody'):
            nowhere.read(5, 0x1000)


def test_closing_the_client_answers_the_calls_still_waiting(node):
    nowhere = GatewayClient(node, f'/nobody{uuid.uuid4().hex[:8]}/cbcan', wait=ANSWER_WAIT)
    answers = []

    def call() -> None:
        try:
            nowhere.read(5, 0x1000)
        except GatewayUnavailable as error:
            answers.append(str(error))

    caller = threading.Thread(target=call)
    caller.start()
    wait_until(lambda: nowhere._watches, 5.0, 'the call to wait for the gateway')
    nowhere.close()
    caller.join(5.0)  # far less than the call's wait
    assert answers == ['the client is closed'], answers


@pytest.mark.parametrize('value, value_type, data, read_back', [
    (-2, 'i32', b'\xfe\xff\xff\xff', -2),
    (0x1234, 'u16', b'\x34\x12', 0x1234),
    ('0x1234', 'u16', b'\x34\x12', 0x1234),  # text as cbcan_cli takes it
    (-0.1, 'f32', b'\xcd\xcc\xcc\xbd', -0.1),
    (2, 'f64', b'\x00\x00\x00\x00\x00\x00\x00\x40', 2.0),
    ('robot', 'str', b'robot', 'robot'),
    (b'\x78\x56', 'hex', b'\x78\x56', b'\x78\x56'),
    ('78 56', 'hex', b'\x78\x56', b'\x78\x56'),
])
def test_python_values_are_written_and_read_as_their_type(value, value_type, data, read_back):
    assert encode(value, value_type) == data
    assert decode_value(data, value_type) == read_back


@pytest.mark.parametrize('value, value_type, says', [
    (256, 'u8', "'256' does not fit u8: allowed 0..255"),
    (1.5, 'u8', 'type u8 does not take float 1.5'),
    (True, 'u8', 'type u8 does not take bool True'),
    (5, 'str', 'type str does not take int 5'),
    (b'', 'hex', 'the value is empty'),
    (5, 'u17', "'u17' is not a value type: allowed u8"),
])
def test_a_python_value_of_the_wrong_kind_is_refused_naming_it(value, value_type, says):
    with pytest.raises(ValueError, match=re.escape(says)):
        encode(value, value_type)
