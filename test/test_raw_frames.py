"""Raw CAN frames beside CANopen: what a program on the bus and a ROS program see of each other.

The other side is never the gateway: a python-can bus opened by this test (another program
on the same wires) sends frames the gateway must publish on ``~/from_can_bus``, and receives
the frames ROS programs send through ``~/to_can_bus`` and ``~/send_frames``. The gateway runs
in this process on a private virtual bus (with simulated devices 2, 3 and 5), on the
fault-injecting bus for an adapter pulled mid-call, and as the installed node in its own
process on udp_multicast, which hands every sender its own frames back.
"""

import logging
import os
import subprocess
import threading
import time
import uuid

import can
from can_msgs.msg import Frame
from diagnostic_msgs.msg import DiagnosticStatus
import pytest
from rclpy.node import Node
from test_diagnostics import DiagnosticsRecorder

from cbcan_ros.msg import CanFrame, LssIdentity, Pdo
from cbcan_ros.ros.config import NodeParameters
from cbcan_ros.ros.parameter_checks import ConfigurationError
from cbcan_ros.ros.pdo import PDO_QOS
from cbcan_ros.ros.raw_frames import RAW_QOS
from cbcan_ros.srv import SdoRead, SendFrames

from conftest import new_channel, wait_for_future, wait_until
import faulty_bus
from faulty_bus import FaultController
from node_process import (
    BusRecorder,
    call,
    executable,
    private_bus,
    service_client,
    START_TIMEOUT,
    StateWatcher,
)

faulty_bus.register()

RAW_LOGGER = 'cbcan_ros.core.raw.frames'
# Ids no CANopen service of the gateway uses: the raw devices of these tests.
RAW_IDS = range(0x7F0, 0x7FF)  # 0x7F0..0x7FE
EXTENDED = 0x18FF0000
RAW_FILTERS = ['7F0:7F0', f'{EXTENDED:08X}:1FFF0000']
# What only a defect makes slow (a quiet machine needs milliseconds): seeing frames, answers.
PROMPT = 30.0
RECOVERY = 20.0


def key(frame) -> tuple:
    """Return what a frame is, alike for python-can frames and ROS messages."""
    if isinstance(frame, can.Message):
        return (frame.arbitration_id, frame.is_extended_id, frame.is_remote_frame,
                frame.is_error_frame, frame.dlc, bytes(frame.data) if not
                frame.is_remote_frame else b'')
    return (frame.id, frame.is_extended, frame.is_rtr, frame.is_error, frame.dlc,
            bytes(frame.data[:frame.dlc]) if not frame.is_rtr else b'')


def raw_message(frame_id: int, data: bytes = b'', extended: bool = False,
                remote: bool = False, dlc: int = 0) -> can.Message:
    if remote:
        return can.Message(arbitration_id=frame_id, is_extended_id=extended,
                           is_remote_frame=True, dlc=dlc)
    return can.Message(arbitration_id=frame_id, is_extended_id=extended, data=data)


def can_frame(frame_id: int, data: bytes = b'', extended: bool = False, remote: bool = False,
              dlc=None, message_type=CanFrame):
    """Return a CanFrame (or can_msgs Frame) with ``data`` padded to its 8 bytes."""
    return message_type(id=frame_id, is_extended=extended, is_rtr=remote,
                        dlc=len(data) if dlc is None else dlc,
                        data=list(data.ljust(8, b'\0')))


class FrameRecorder:
    """The frames a subscriber of ``~/from_can_bus`` gets, in order of arrival."""

    def __init__(self, node, topic: str):
        self._lock = threading.Lock()
        self._frames = []
        node.create_subscription(Frame, topic, self._keep, RAW_QOS)

    def _keep(self, message) -> None:
        with self._lock:
            self._frames.append(message)

    @property
    def frames(self) -> list:
        """Return every frame received so far."""
        with self._lock:
            return list(self._frames)

    def keys(self, ids=None) -> list:
        """Return the keys of the frames received so far, of ``ids`` only if given."""
        return [key(frame) for frame in self.frames if ids is None or frame.id in ids]

    def wait_for(self, expected: list, ids, timeout: float = PROMPT) -> None:
        """Wait until the frames of ``ids`` received are ``expected`` (in that order)."""
        wait_until(lambda: len(self.keys(ids)) >= len(expected), timeout,
                   f'{len(expected)} frames on from_can_bus (got {len(self.keys(ids))})')
        assert self.keys(ids) == expected


def received_from(bus: can.BusABC, ids, count: int, timeout: float = PROMPT) -> list:
    """Return the next ``count`` frames of ``ids`` another program receives, in order."""
    frames = []
    deadline = time.monotonic() + timeout
    while len(frames) < count and time.monotonic() < deadline:
        message = bus.recv(0.1)
        if message is not None and message.arbitration_id in ids:
            frames.append(message)
    return frames


def subscribed(gateway_node: Node, topic: str) -> None:
    """Wait until the gateway's publisher of ``topic`` sees a subscriber."""
    wait_until(lambda: gateway_node.count_subscribers(topic) > 0, PROMPT,
               f'a subscriber of {topic}')


def mixed_frames(count: int) -> list:
    """Return frames of every kind the raw devices send: standard, extended, remote, 0-8 bytes."""
    frames = []
    for number in range(count):
        data = bytes((number + i) & 0xFF for i in range(number % 9))
        if number % 7 == 3:
            frames.append(raw_message(RAW_IDS[number % len(RAW_IDS)], remote=True,
                                      dlc=number % 9))
        elif number % 3:
            frames.append(raw_message(RAW_IDS[number % len(RAW_IDS)], data))
        else:
            frames.append(raw_message(EXTENDED | number, data, extended=True))
    return frames


def assert_in_bus_order_each_once(published: list, sent: list) -> None:
    """Assert that ``published`` holds frames of ``sent`` (unique), each once, in its order."""
    place = {frame: number for number, frame in enumerate(sent)}
    places = [place[frame] for frame in published]
    assert places == sorted(set(places)), 'frames published out of order or twice'



class Stream:
    """Another program's extended frames, ``burst`` at a time, ``pause`` between, until stopped."""

    def __init__(self, bus, id_mask: int, burst: int, pause: float):
        self.frames = []  # their keys, in the order sent
        self._sending = threading.Event()
        self._sending.set()
        self._thread = threading.Thread(target=self._send, args=(bus, id_mask, burst, pause),
                                        daemon=True)
        self._thread.start()

    def _send(self, bus, id_mask: int, burst: int, pause: float) -> None:
        number = 0
        while self._sending.is_set():
            frame = raw_message(EXTENDED | number & id_mask, number.to_bytes(4, 'little'),
                                extended=True)
            bus.send(frame)
            self.frames.append(key(frame))
            number += 1
            if number % burst == 0:
                time.sleep(pause)

    def stop(self) -> None:
        """Stop sending (again is harmless); return once the last frame went out."""
        self._sending.clear()
        self._thread.join()

def test_frames_another_program_sends_are_published_once_in_bus_order(make_gateway):
    gateway = make_gateway(raw__filters=RAW_FILTERS)
    recorder = FrameRecorder(gateway.client_node, '/cbcan/from_can_bus')
    subscribed(gateway.node, '/cbcan/from_can_bus')
    other = gateway.raw_bus()
    try:
        frames = mixed_frames(600)
        # Frames the filters do not take: CANopen's (0x185) and other raw ids.
        ignored = [raw_message(0x185, b'\x01'), raw_message(0x123, b'\x02'),
                   raw_message(0x18FE0001, b'\x03', extended=True),
                   raw_message(0x7F1, b'\x04', extended=True)]
        before = time.time()
        for number, frame in enumerate(frames):
            other.send(frame)
            if number % 150 == 0:
                for frame in ignored:
                    other.send(frame)
        recorder.wait_for([key(frame) for frame in frames], None)
        after = time.time()
    finally:
        other.shutdown()
    stamps = [frame.header.stamp.sec + frame.header.stamp.nanosec * 1e-9
              for frame in recorder.frames]
    assert before - 0.01 <= min(stamps) and max(stamps) <= after + 0.01, (before, after)
    assert stamps == sorted(stamps)
    assert {frame.header.frame_id for frame in recorder.frames} == {gateway.channel}


def test_frames_sent_by_service_and_topic_reach_another_program_in_order(make_gateway):
    gateway = make_gateway(raw__send_allow=RAW_FILTERS)
    other = gateway.raw_bus()
    try:
        frames = [can_frame(RAW_IDS[n % len(RAW_IDS)], bytes([n] * (n % 9)))
                  for n in range(40)]
        frames += [can_frame(EXTENDED | 0xAB, b'\x01\x02', extended=True),
                   can_frame(0x7F2, remote=True, dlc=4)]
        answer = gateway.call('send_frames', frames=frames)
        assert answer.success and answer.sent == len(frames), answer.message
        got = received_from(other, set(RAW_IDS) | {EXTENDED | 0xAB}, len(frames))
        assert [key(frame) for frame in got] == [key(frame) for frame in frames]

        publisher = gateway.client_node.create_publisher(Frame, '/cbcan/to_can_bus', RAW_QOS)
        wait_until(lambda: publisher.get_subscription_count() > 0, PROMPT,
                   'the gateway subscribed to to_can_bus')
        topic_frames = [can_frame(0x7F0 + n % 8, bytes([n, n]), message_type=Frame)
                        for n in range(100)]
        for frame in topic_frames:
            publisher.publish(frame)
        got = received_from(other, set(RAW_IDS), len(topic_frames))
        assert [key(frame) for frame in got] == [key(frame) for frame in topic_frames]
    finally:
        other.shutdown()


def test_canopen_goes_on_undisturbed_while_raw_frames_flow_both_ways(make_gateway,
                                                                     start_durand):
    gateway = make_gateway(raw__filters=RAW_FILTERS, raw__send_allow=['7F0:7F0'],
                           pdo__nodes=[5], lss__probe_timeout=0.15)
    # A new device without node id, to be given one by LSS meanwhile.
    identity = (0x319, 0x51, 0x10000, 0x77)
    newcomer = start_durand(255, channel=gateway.channel, lss=True, identity=identity)
    recorder = FrameRecorder(gateway.client_node, '/cbcan/from_can_bus')
    pdos = []
    gateway.client_node.create_subscription(Pdo, '/cbcan/node_5/rpdo', pdos.append, PDO_QOS)
    subscribed(gateway.node, '/cbcan/from_can_bus')
    gateway.wait_for_states({5: 'PRE_OPERATIONAL'})
    other = gateway.raw_bus()
    # Another program's frames, about 500 a second, for as long as CANopen is exercised.
    stream = Stream(other, 0xFFFF, burst=5, pause=0.01)
    streamed = stream.frames
    try:
        wait_until(lambda: len(recorder.frames) > 20, PROMPT, 'streamed frames published')
        assert gateway.call('nmt_command', node_id=5, command=1).success
        configured = gateway.call('lss_configure', node_id=20, identity=LssIdentity(
            vendor_id=identity[0], product_code=identity[1], revision=identity[2],
            serial=identity[3]))
        assert configured.success, configured.message
        for number in range(20):
            read = gateway.call('sdo_read', node_id=5, index=0x1000, subindex=0)
            assert read.success, read.message
            sent = gateway.call('send_frames', frames=[can_frame(0x7F0, bytes([number]))])
            assert sent.success, sent.message
        wait_until(lambda: len(pdos) >= 3, PROMPT, "node 5's PDOs")
        gateway.wait_for_states({5: 'OPERATIONAL', 20: 'PRE_OPERATIONAL'})
        stream.stop()
        got = received_from(other, {0x7F0}, 20)
        wait_until(lambda: recorder.keys()[-1:] == streamed[-1:], PROMPT,
                   'the last streamed frame published')
    finally:
        stream.stop()
        other.shutdown()
    assert newcomer.node_id == 20
    assert [frame.data[0] for frame in got] == list(range(20))
    published = recorder.keys()
    assert_in_bus_order_each_once(published, streamed)
    # Every one was handed to the publisher: none dropped by the gateway. (Whether a subscriber
    # that falls far behind gets each is DDS's; the burst of 600 above proves none is lost
    # within the publisher's history, and make bench counts them at 5,000 frames/s.)
    statistics = gateway.node.gateway.raw.statistics()
    assert (statistics.received, statistics.lost) == (len(streamed), 0)


def test_send_frames_refuses_a_whole_call_naming_the_frame_and_sends_none(make_gateway):
    gateway = make_gateway(raw__send_allow=['7F0:7F0', '0:0', '605:7FF'])
    other = gateway.raw_bus()
    good = [can_frame(0x7F1, b'\x01'), can_frame(0x7F2, b'\x02')]
    try:
        for bad, says in ((can_frame(0x602, b'\x40\x00\x10\x00'), 'frame 1 0x602: the '
                           'gateway uses this id for CANopen; only an entry of raw.send_allow '
                           'with the full mask naming it (602:7FF) opens it'),
                          (can_frame(0x800, b''), 'frame 1 0x800: id 0x800 is out of range'),
                          (can_frame(0x7F3, b'', dlc=9), 'frame 1 0x7F3: dlc 9'),
                          (CanFrame(id=0x7F3, is_error=True), 'frame 1 0x7F3: is_error'),
                          (can_frame(EXTENDED, b'', extended=True),
                           'frame 1 0x18FF0000 (extended): the id is not in parameter '
                           'raw.send_allow')):
            answer = gateway.call('send_frames', frames=[good[0], bad, good[1]])
            assert not answer.success and answer.sent == 0
            assert answer.message.startswith(says), answer.message
        # The one CANopen id named with the full mask is open; a marker shows the order.
        answer = gateway.call('send_frames', frames=[can_frame(0x605, b'\x40\x00\x10\x00'),
                                                     *good])
        assert answer.success and answer.sent == 3, answer.message
        got = received_from(other, {0x605, *RAW_IDS}, 3)
    finally:
        other.shutdown()
    assert [frame.arbitration_id for frame in got] == [0x605, 0x7F1, 0x7F2]


@pytest.mark.parametrize('parameters, says', [
    ({}, 'nothing may be sent: parameter raw.send_allow is empty'),
    ({'raw__send_allow': ['0:0'], 'read_only': True},
     'the gateway is read-only (parameter read_only)')], ids=['no send_allow', 'read_only'])
def test_nothing_is_sent_when_send_allow_is_empty_or_the_gateway_read_only(make_gateway,
                                                                         parameters, says):
    gateway = make_gateway(**parameters)
    answer = gateway.call('send_frames', frames=[can_frame(0x7F0, b'\x01')])
    assert not answer.success and answer.sent == 0 and says in answer.message, answer.message


def test_refusals_on_the_topic_are_logged_once_per_kind_and_counted(make_gateway, caplog):
    gateway = make_gateway(raw__send_allow=['7F0:7F0'], diagnostics_period=0.1)
    diagnostics = DiagnosticsRecorder(gateway.client_node)
    other = gateway.raw_bus()
    publisher = gateway.client_node.create_publisher(Frame, '/cbcan/to_can_bus', RAW_QOS)
    wait_until(lambda: publisher.get_subscription_count() > 0, PROMPT,
               'the gateway subscribed to to_can_bus')
    try:
        with caplog.at_level(logging.ERROR, logger=RAW_LOGGER):
            for frame in ([can_frame(0x123, b'\x01', message_type=Frame)] * 3 +
                          [can_frame(0x7F0, bytes(8), dlc=12, message_type=Frame)] * 2 +
                          [can_frame(0x7F1, b'\x09', message_type=Frame)]):
                publisher.publish(frame)
            got = received_from(other, set(RAW_IDS), 1)
    finally:
        other.shutdown()
    # Frames on a topic are taken in order: the good last one went out after the others.
    assert [frame.data[0] for frame in got] == [0x09]
    # Both counts at once: a frame is counted sent once its send returns, after it is on
    # the bus, so a status between shows the refusals without it.
    diagnostics.wait_for('cbcan: CAN bus', DiagnosticStatus.OK, where=lambda v: (
        v.get('Raw frames refused'), v.get('Raw frames sent')) == ('5', '1'))
    logged = [record.getMessage() for record in caplog.records if record.name == RAW_LOGGER]
    assert len(logged) == 2, logged
    assert 'to_can_bus: frame not sent: frame 0x123: the id is not in parameter ' \
           'raw.send_allow' in logged[0]
    assert 'dlc 12 is out of range' in logged[1]


@pytest.mark.parametrize('filters, published', [(['7F0:7F0', '#FFFFFFFF'], True),
                                                 (['7F0:7F0'], False)],
                         ids=['asked', 'not asked'])
def test_error_frames_are_published_only_when_the_filters_ask(make_gateway, filters,
                                                              published):
    gateway = make_gateway(raw__filters=filters)
    error = can.Message(is_error_frame=True, arbitration_id=0x04, dlc=8, data=bytes(8))
    marker = raw_message(0x7F0, b'\xAA')
    recorder = FrameRecorder(gateway.client_node, '/cbcan/from_can_bus')
    subscribed(gateway.node, '/cbcan/from_can_bus')
    other = gateway.raw_bus()
    try:
        other.send(error)
        other.send(marker)
        # The marker comes after the error frame: once it is here, so is the error frame.
        wait_until(lambda: any(not frame.is_error for frame in recorder.frames), PROMPT,
                   'the marker')
    finally:
        other.shutdown()
    assert recorder.keys() == ([key(error)] if published else []) + [key(marker)]


def test_an_inactive_gateway_neither_publishes_nor_sends_raw_frames(make_gateway):
    gateway = make_gateway(raw__filters=['7F0:7F0'], raw__send_allow=['7F0:7F0'])
    recorder = FrameRecorder(gateway.client_node, '/cbcan/from_can_bus')
    subscribed(gateway.node, '/cbcan/from_can_bus')
    other = gateway.raw_bus()
    try:
        gateway.node.interface.deactivate()  # what the managed node's deactivate does
        other.send(raw_message(0x7F1, b'\x01'))
        wait_until(lambda: gateway.node.gateway.raw.statistics().received == 1, PROMPT,
                   'the frame received while inactive')
        answer = gateway.call('send_frames', frames=[can_frame(0x7F2, b'\x02')])
        assert not answer.success and answer.sent == 0 and 'inactive' in answer.message
        gateway.node.interface.activate()
        other.send(raw_message(0x7F3, b'\x03'))
        recorder.wait_for([key(raw_message(0x7F3, b'\x03'))], None)
        assert gateway.call('send_frames', frames=[can_frame(0x7F4, b'\x04')]).success
        got = received_from(other, set(RAW_IDS), 1)
        assert [frame.arbitration_id for frame in got] == [0x7F4]
    finally:
        other.shutdown()


def test_every_send_frames_call_gets_one_answer_when_the_adapter_is_pulled(make_gateway):
    channel = new_channel()
    faults = FaultController.get(channel)
    gateway = make_gateway(can__interface='faulty', can__channel=channel,
                           simulation__devices=None, raw__send_allow=['7F0:7F0'])
    calls, per_call = 60, 10
    futures = []
    for number in range(calls):
        if number == calls // 3:
            for future in futures:
                wait_for_future(future, PROMPT)
            faults.fail_send('adapter unplugged', after=per_call // 2)  # midway in the next
        futures.append(gateway.call_async('send_frames', frames=[
            can_frame(0x7F0, bytes([number, index])) for index in range(per_call)]))
    # An rclpy future holds one answer: every call has one once every future is done.
    answers = {number: wait_for_future(future, PROMPT) for number, future in enumerate(futures)}
    went_out = [bytes(frame.data) for frame in faults.sent if frame.arbitration_id == 0x7F0]
    for number, answer in answers.items():
        mine = [data for data in went_out if data[0] == number]
        assert mine == [bytes([number, index]) for index in range(answer.sent)], number
        assert answer.success == (answer.sent == per_call), (number, answer.message)
    first_failed = answers[calls // 3]
    assert not first_failed.success and first_failed.sent == per_call // 2
    assert 'adapter unplugged' in first_failed.message and \
        f'{per_call // 2} of {per_call} frames sent' in first_failed.message
    later = [answers[number] for number in range(calls // 3 + 1, calls)]
    assert all(not answer.success and answer.sent == 0 for answer in later)
    assert all('the CAN bus is down' in answer.message for answer in later)

    faults.clear()
    wait_until(lambda: gateway.call('send_frames', frames=[can_frame(0x7F0, b'\xFF')]).success,
               RECOVERY, 'sending again once the adapter is back')


@pytest.mark.parametrize('name, value, says', [
    ('raw.filters', "['0:0', '0x7F0:7F0']", "parameter raw.filters: ['0:0', '0x7F0:7F0'] "
                                            "holds a filter that does not parse: '0x7F0:7F0': "
                                            "id '0x7F0': hex without 0x"),
    ('raw.filters', "['1234:7FF']", "'1234:7FF': id '1234' has 4 digits"),
    ('raw.send_allow', "['#FFFFFFFF']", 'error frames cannot be sent'),
    ('raw.send_allow', "['0:0', 'j']", "'j': error frames cannot be sent"),
])
def test_a_filter_that_does_not_parse_stops_the_node_naming_it(name, value, says):
    node = Node('cbcan', cli_args=['--ros-args', '-p', 'can.interface:=virtual',
                                   '-p', f'can.channel:={new_channel()}', '-p',
                                   f'{name}:={value}'], use_global_arguments=False)
    try:
        with pytest.raises(ConfigurationError) as refused:
            NodeParameters(node).gateway_config()
    finally:
        node.destroy_node()
    assert says in str(refused.value)


def _without_can_msgs() -> dict:
    env = dict(os.environ)
    for name in ('PYTHONPATH', 'LD_LIBRARY_PATH', 'AMENT_PREFIX_PATH'):
        env[name] = os.pathsep.join(part for part in env.get(name, '').split(os.pathsep)
                                    if 'can_msgs' not in part)
    return env


def test_without_can_msgs_the_node_refuses_raw_topics_naming_what_to_install(start_node,
                                                                             client_node):
    env = _without_can_msgs()
    probe = subprocess.run([executable('python3'), '-c', 'import can_msgs'], env=env,
                           capture_output=True)
    assert probe.returncode != 0, 'can_msgs is importable without its paths: not a real test'
    done = subprocess.run([executable('cbcan_node'), '--ros-args', '-r',
                           f'__ns:=/raw{uuid.uuid4().hex[:8]}', '-p',
                           f'can.channel:={new_channel()}', '-p', "raw.filters:=['0:0']"],
                          env=env, capture_output=True, text=True, timeout=START_TIMEOUT)
    output = done.stdout + done.stderr
    assert done.returncode == 1 and 'Traceback' not in output, output
    assert "cbcan_node: cannot start: parameter raw.filters: ['0:0'] needs the ROS package " \
           'can_msgs' in output and 'sudo apt install ros-jazzy-can-msgs' in output, output

    # Without raw parameters the gateway needs no can_msgs: ~/send_frames answers, refusing.
    namespace = f'/raw{uuid.uuid4().hex[:8]}'
    previous = dict(os.environ)
    try:
        os.environ.clear()
        os.environ.update(env)
        node = start_node(['-r', f'__ns:={namespace}', '-p', f'can.channel:={new_channel()}'])
    finally:
        os.environ.clear()
        os.environ.update(previous)
    send = service_client(client_node, SendFrames, f'{namespace}/cbcan/send_frames', node)
    answer = call(send, SendFrames.Request(frames=[can_frame(0x7F0, b'\x01')]), 'send_frames',
                  node)
    assert not answer.success and 'raw.send_allow is empty' in answer.message


def test_the_installed_node_bridges_raw_frames_both_ways_while_canopen_goes_on(start_node,
                                                                              client_node):
    group, port = private_bus()
    namespace = f'/raw{uuid.uuid4().hex[:8]}'
    name = f'{namespace}/cbcan'
    node = start_node(['-r', f'__ns:={namespace}', '-p', 'can.interface:=udp_multicast',
                       '-p', f'can.channel:={group}', '-p', 'simulation.devices:=[5]',
                       '-p', 'nodes:=[5]', '-p', 'heartbeat.timeout:=2.0',
                       '-p', 'diagnostics_period:=0.2',
                       '-p', "raw.filters:=['0:0', '18FF0000:1FFF0000']",
                       '-p', "raw.send_allow:=['7F0:7F0', '18FF0000:1FFF0000']"], port)
    recorder = FrameRecorder(client_node, f'{name}/from_can_bus')
    diagnostics = DiagnosticsRecorder(client_node)
    states = StateWatcher(client_node, name)
    sdo_read = service_client(client_node, SdoRead, f'{name}/sdo_read', node)
    send = service_client(client_node, SendFrames, f'{name}/send_frames', node)
    states.wait_for({5: 'PRE_OPERATIONAL'}, START_TIMEOUT)
    wait_until(lambda: client_node.count_publishers(f'{name}/from_can_bus') > 0, PROMPT,
               'the from_can_bus publisher')
    # Another program: one bus to send, one recording every frame (its own echoed too).
    other = can.Bus(interface='udp_multicast', channel=group, port=port)
    seen = BusRecorder(group, port)
    # Its frames at about 500 a second, while CANopen and the ROS programs work.
    stream = Stream(other, 0x7FFF, burst=10, pause=0.02)
    streamed = stream.frames
    try:
        wait_until(lambda: len(recorder.frames) > 20, PROMPT, 'streamed frames published')
        for number in range(30):
            answer = call(sdo_read, SdoRead.Request(node_id=5, index=0x1000), 'sdo_read', node)
            assert answer.success, answer.message
            sent = call(send, SendFrames.Request(frames=[
                can_frame(0x7F0 + number % 8, bytes([number, 1])),
                can_frame(EXTENDED | 0xFFFF, bytes([number, 2]), extended=True)]),
                'send_frames', node)
            assert sent.success and sent.sent == 2, sent.message
        stream.stop()
        marker = raw_message(0x7FE, b'\xEE')
        other.send(marker)
        recorder.wait_for([key(marker)], {0x7FE})
        wait_until(lambda: len(mine(seen)) == 60, PROMPT, "the gateway's 60 frames on the bus")
    finally:
        stream.stop()
        other.shutdown()
        seen.close()
    assert [bytes(frame.data) for frame in mine(seen)] == [
        bytes([number, kind]) for number in range(30) for kind in (1, 2)]
    published = recorder.frames
    ids = {frame.id for frame in published}
    # The other program's frames in bus order, each once, from the first one published on
    # (a subscriber gets nothing before DDS has matched it).
    stream_keys = [key(frame) for frame in published if frame.is_extended and
                   frame.id != EXTENDED | 0xFFFF]
    assert_in_bus_order_each_once(stream_keys, streamed)
    assert stream_keys[-1] == streamed[-1]
    # The node handed every frame it took to its publisher (DDS delivers them or not).
    diagnostics.wait_for(f'{name}: CAN bus', DiagnosticStatus.OK, where=lambda v: int(
        v['Raw frames received']) >= len(streamed) and v['Raw frames lost'] == '0')
    # The device's SDO answers and heartbeats are published; the gateway's own frames (its
    # SDO requests, the raw frames it sent) never come back, though udp_multicast echoes them.
    # DDS may drop the few heartbeats sent during the stream (it dropped all of them once,
    # on a busy machine): the next ones come every period, so one is waited for.
    wait_until(lambda: 0x705 in {frame.id for frame in recorder.frames}, PROMPT,
               'a heartbeat of node 5 published')
    ids = {frame.id for frame in recorder.frames}
    assert 0x585 in ids
    assert 0x605 not in ids and not set(RAW_IDS[:8]) & ids and EXTENDED | 0xFFFF not in ids
    detected = next(number for number, message in enumerate(states.messages)
                    if message.nodes and message.nodes[0].state_name == 'PRE_OPERATIONAL')
    assert all(message.nodes[0].state_name == 'PRE_OPERATIONAL'
               for message in states.messages[detected:]), 'node 5 was lost meanwhile'


def mine(recorder: BusRecorder) -> list:
    """Return the frames the gateway sent for the ROS program, as the other program saw them."""
    return [frame for _, frame in recorder.frames
            if frame.arbitration_id in RAW_IDS[:8] or frame.arbitration_id == EXTENDED | 0xFFFF]
