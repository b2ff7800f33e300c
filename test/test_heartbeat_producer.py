"""The gateway's own heartbeat: what drives watching it (their 0x1016 consumer) see on the bus.

The producer's schedule and states against a stand-in for the bus supervisor; the gateway in
this process (its own dictionary, diagnostics); the installed ``cbcan_node`` and
``cbcan_lifecycle_node`` as separate processes on udp_multicast, whose frames a raw bus in
this process records: beats at about the period, PRE_OPERATIONAL while the managed node is
inactive, none once the node is gone; and a node id a device also has, refused at start.

Timing is asserted with wide margins only (a third of the beats a window should hold): a busy
machine delays beats, and how punctual they are is the producer's grid, checked exactly on
its own.
"""

import signal
import struct
import subprocess
import threading
import time
import uuid

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
import pytest
from rclpy.node import Node
from test_diagnostics import DiagnosticsRecorder, OK, values

from cbcan_ros.core.bus import BusDown
from cbcan_ros.core.heartbeat_producer import HeartbeatProducer, next_beat
from cbcan_ros.ros.config import NodeParameters
from cbcan_ros.ros.parameter_checks import ConfigurationError
from cbcan_ros.simulation.durand.drive import DurandDrive
from cbcan_ros.srv import SdoWrite

from conftest import wait_until
from node_process import (
    arguments,
    BusRecorder,
    call,
    executable,
    namespace,
    private_bus,
    service_client,
    START_TIMEOUT,
    StateWatcher,
)

OPERATIONAL, PRE_OPERATIONAL = b'\x05', b'\x7f'
OWN_ID = 100                 # the gateway's heartbeat node id in these tests
OWN_COB_ID = 0x700 + OWN_ID
PERIOD = 0.05                # seconds
WINDOW = 2.0                 # seconds over which beats are counted
EXPECTED = WINDOW / PERIOD   # beats a window holds on a quiet machine
ANSWER = 10.0                # ceiling for what a quiet machine does within a fraction of a second


# The schedule, exactly.

def test_beats_stay_on_a_fixed_grid_however_late_each_goes_out():
    # Every beat leaves up to 90 % of a period late: beat k is still due at k periods, so
    # lateness never adds up (sleeping a period after each send would drift by the sum).
    start, period, beat, sent = 1000.0, 0.1, 0, []
    for k in range(1000):
        due = start + beat * period
        sent.append(beat)
        beat = next_beat(beat, start, period, due + 0.009 * (k % 11))  # 0 to 0.09 s
    assert sent == list(range(1000))
    assert start + beat * period == pytest.approx(start + 100.0)


def test_beats_missed_by_a_stall_are_skipped_not_sent_in_a_burst():
    # Beat 1 went out 3.5 periods late: beats 2 and 3 are past, the next is beat 4, due at
    # 0.4 s, not three beats at once (a consumer would read those as a node that is fine).
    assert next_beat(1, 0.0, 0.1, 0.35) == 4
    assert next_beat(0, 0.0, 0.1, 0.0) == 1
    assert next_beat(5, 0.0, 0.1, 0.52) == 6  # on time


class FakeSupervisor:
    """Takes frames as the bus supervisor does, and fails them while ``down`` is set."""

    def __init__(self):
        self.frames = []
        self.down = False
        self._lock = threading.Lock()

    def send(self, message) -> None:
        """Take ``message``, or raise BusDown as the supervisor does while the bus is down."""
        if self.down:
            raise BusDown('the CAN bus is down: unplugged by the test')
        with self._lock:
            self.frames.append((message.arbitration_id, bytes(message.data)))

    def count(self) -> int:
        """Return how many frames were taken."""
        with self._lock:
            return len(self.frames)


def test_the_producer_beats_its_state_pauses_while_the_bus_is_down_and_stops():
    bus = FakeSupervisor()
    producer = HeartbeatProducer(bus, 9, 0.02)
    producer.start()
    try:
        wait_until(lambda: bus.count() >= 5, ANSWER, 'five beats')
        assert set(bus.frames) == {(0x709, OPERATIONAL)}
        producer.set_operational(False)
        wait_until(lambda: bus.frames[-1] == (0x709, PRE_OPERATIONAL), ANSWER, 'a 0x7F beat')
        bus.down = True
        wait_until(lambda: producer.status().failed >= 3, ANSWER, 'beats failing')
        sent = bus.count()
        bus.down = False
        wait_until(lambda: bus.count() >= sent + 3, ANSWER, 'beats again once the bus is back')
        producer.set_operational(True)
        wait_until(lambda: bus.frames[-1] == (0x709, OPERATIONAL), ANSWER, 'a 0x05 beat')
    finally:
        producer.stop()
    sent = bus.count()
    assert producer.status().sent == sent
    time.sleep(10 * 0.02)
    assert bus.count() == sent, 'a beat after stop() returned'


def test_a_silence_longer_than_the_watchers_is_told_once_before_the_next_beat():
    # The drives watching the heartbeat stopped by themselves: the gateway must know before
    # it sends anything after the silence, and see it as silent until it is told.
    bus = FakeSupervisor()
    producer = HeartbeatProducer(bus, 9, 0.02)
    told = []

    def on_silence(seconds: float) -> None:
        told.append((seconds, bus.count(), producer.silent_too_long()))
    producer.watch_silence(0.1, on_silence)
    producer.start()
    try:
        wait_until(lambda: bus.count() >= 3, ANSWER, 'beats')
        assert producer.silent_too_long() is None
        bus.down = True  # no beat goes out: the watchers see silence
        wait_until(lambda: producer.silent_too_long() is not None, ANSWER, 'a long silence')
        sent = bus.count()
        bus.down = False
        wait_until(lambda: bus.count() > sent, ANSWER, 'beats again')
        wait_until(lambda: bus.count() > sent + 3, ANSWER, 'more beats')
    finally:
        producer.stop()
    assert len(told) == 1, told  # once a silence, however many beats failed in it
    seconds, beats_before, still_silent = told[0]
    assert seconds > 0.1 and beats_before == sent and still_silent is not None


def test_beat_now_sends_a_beat_at_once_between_those_of_a_long_period():
    # A drive told to watch the gateway watches from the first beat it hears: one goes out
    # at once, not a period later (here a period no test outlasts).
    bus = FakeSupervisor()
    producer = HeartbeatProducer(bus, 9, 3600.0)
    producer.start()
    try:
        wait_until(lambda: bus.count() == 1, ANSWER, 'the first beat, at start')
        for beats in (2, 3):
            producer.beat_now()
            wait_until(lambda count=beats: bus.count() == count, ANSWER, f'beat {beats}')
    finally:
        producer.stop()
    assert set(bus.frames) == {(0x709, OPERATIONAL)}


def test_node_id_0_sends_nothing():
    bus = FakeSupervisor()
    producer = HeartbeatProducer(bus, 0, 0.01)
    producer.start()
    time.sleep(0.1)
    producer.stop()
    assert not bus.frames and not producer.producing


# The gateway in this process.

def test_the_gateway_beats_shows_its_period_as_0x1017_and_in_diagnostics(make_gateway):
    gateway = make_gateway(heartbeat__node_id=OWN_ID, heartbeat__period=PERIOD,
                           diagnostics_period=0.1)
    recorder = DiagnosticsRecorder(gateway.client_node)
    raw = gateway.raw_bus()
    try:
        deadline = time.monotonic() + ANSWER
        while time.monotonic() < deadline:
            frame = raw.recv(0.1)
            if frame is not None and frame.arbitration_id == OWN_COB_ID:
                break
        else:
            raise AssertionError('no heartbeat of the gateway on its bus')
        assert bytes(frame.data) == OPERATIONAL
    finally:
        raw.shutdown()
    answer = gateway.call('sdo_read', node_id=0, index=0x1017, subindex=0)
    assert answer.success and bytes(answer.data) == (50).to_bytes(2, 'little')  # ms
    bus = recorder.wait_for('cbcan: CAN bus', OK,
                            where=lambda v: int(v.get('Own heartbeats sent', 0)) > 0)
    assert values(bus)['Own heartbeat'] == f'node {OWN_ID} every 50 ms, OPERATIONAL'


# The installed nodes as processes.

def heartbeats(recorder: BusRecorder, since: float = 0.0) -> list:
    """Return (arrival time, data) of every beat of the gateway recorded from ``since`` on."""
    return [(stamp, bytes(message.data)) for stamp, message in list(recorder.frames)
            if message.arbitration_id == OWN_COB_ID and stamp >= since]


def count_beats(recorder: BusRecorder, state: bytes) -> None:
    """Count the beats over WINDOW: about one per period, each with ``state``."""
    start = time.monotonic()
    time.sleep(WINDOW)
    beats = [(stamp, data) for stamp, data in heartbeats(recorder, start)
             if stamp < start + WINDOW]
    assert EXPECTED / 3 <= len(beats) <= 2 * EXPECTED + 5, \
        f'{len(beats)} beats in {WINDOW} s, about {EXPECTED:.0f} expected'
    assert {data for _, data in beats} == {state}


def silent_after(recorder: BusRecorder, what: str) -> None:
    """Assert no beat arrives once those already on their way have arrived."""
    time.sleep(10 * PERIOD)  # what was sent before is received by now
    before = len(heartbeats(recorder))
    time.sleep(20 * PERIOD)
    assert len(heartbeats(recorder)) == before, f'beats after {what}'


def wait_for_beat(recorder: BusRecorder, state: bytes, since: float, what: str) -> float:
    """Wait for a beat with ``state`` arriving from ``since`` on; return its arrival time."""
    beats = wait_until(lambda: [stamp for stamp, data in heartbeats(recorder, since)
                                if data == state], START_TIMEOUT, what)
    return beats[0]


@pytest.fixture
def recorded_bus():
    """Yield (group, port, recorder): a private udp_multicast bus and all frames on it."""
    group, port = private_bus()
    recorder = BusRecorder(group, port)
    yield group, port, recorder
    recorder.close()


def test_the_node_beats_as_operational_and_falls_silent_when_it_exits(
        start_node, client_node, recorded_bus):
    group, port, recorder = recorded_bus
    name = f'{namespace()}/cbcan'
    node = start_node(arguments(name, '-p', 'can.interface:=udp_multicast',
                                '-p', f'can.channel:={group}', '-p', 'simulation.devices:=[2]',
                                '-p', f'heartbeat.node_id:={OWN_ID}',
                                '-p', f'heartbeat.period:={PERIOD}',
                                '-p', 'state_publish_period:=0.2'), port)
    states = StateWatcher(client_node, name)
    wait_for_beat(recorder, OPERATIONAL, 0.0, f'the first beat:\n{node.output()}')
    count_beats(recorder, OPERATIONAL)
    # udp_multicast hands the gateway its own beats back: it does not list itself as a node.
    wait_until(lambda: 2 in states.latest(), ANSWER, f'device 2 on node_states: {node.output()}')
    assert OWN_ID not in states.latest()
    node.stop()
    assert node.process.returncode == 0, node.output()
    silent_after(recorder, 'the node exited')


def test_the_managed_node_beats_pre_operational_while_inactive(
        start_node, client_node, recorded_bus):
    group, port, recorder = recorded_bus
    name = f'{namespace()}/cbcan'
    node = start_node(arguments(name, '-p', 'can.interface:=udp_multicast',
                                '-p', f'can.channel:={group}', '-p', 'simulation.devices:=[2]',
                                '-p', f'heartbeat.node_id:={OWN_ID}',
                                '-p', f'heartbeat.period:={PERIOD}'),
                      port, 'cbcan_lifecycle_node')
    change_state = service_client(client_node, ChangeState, f'{name}/change_state', node)

    def transition(transition_id: int) -> float:
        request = ChangeState.Request(transition=Transition(id=transition_id))
        assert call(change_state, request, f'transition {transition_id}', node).success
        return time.monotonic()

    time.sleep(10 * PERIOD)
    assert not heartbeats(recorder), 'beats while unconfigured (there is no gateway yet)'
    transition(Transition.TRANSITION_CONFIGURE)
    wait_for_beat(recorder, PRE_OPERATIONAL, 0.0, 'a 0x7F beat once configured')
    assert {data for _, data in heartbeats(recorder)} == {PRE_OPERATIONAL}, \
        'a configured, inactive node said OPERATIONAL'
    for _ in range(2):
        activated = transition(Transition.TRANSITION_ACTIVATE)
        first = wait_for_beat(recorder, OPERATIONAL, activated, '0x05 once active')
        count_beats(recorder, OPERATIONAL)
        assert {data for stamp, data in heartbeats(recorder, first)} == {OPERATIONAL}
        deactivated = transition(Transition.TRANSITION_DEACTIVATE)
        first = wait_for_beat(recorder, PRE_OPERATIONAL, deactivated, '0x7F once inactive')
        count_beats(recorder, PRE_OPERATIONAL)
        assert {data for stamp, data in heartbeats(recorder, first)} == {PRE_OPERATIONAL}
    transition(Transition.TRANSITION_CLEANUP)
    silent_after(recorder, 'cleanup')
    node.stop()
    assert node.process.returncode == 0, node.output()


def test_a_drive_watching_the_heartbeat_faults_when_the_gateway_dies(
        start_node, client_node, recorded_bus, start_durand):
    # What the heartbeat is for: the simulated CiA 402 drive's consumer (0x1016) watches the
    # gateway, its abort connection option (0x6007) is "fault"; the gateway's process is
    # killed (no shutdown code runs) and the drive stops by itself.
    group, port, recorder = recorded_bus
    drive_id, consumer_ms = 7, 1000  # 20 periods: a busy machine never looks like a loss
    drive = start_durand(drive_id, kind=DurandDrive, interface='udp_multicast', channel=group,
                         bus_options={'port': port})
    name = f'{namespace()}/cbcan'
    node = start_node(arguments(name, '-p', 'can.interface:=udp_multicast',
                                '-p', f'can.channel:={group}',
                                '-p', f'heartbeat.node_id:={OWN_ID}',
                                '-p', f'heartbeat.period:={PERIOD}'), port)
    sdo_write = service_client(client_node, SdoWrite, f'{name}/sdo_write', node)
    for index, subindex, data in (
            (0x6007, 0, struct.pack('<h', 1)),                              # fault signal
            (0x1016, 1, struct.pack('<I', OWN_ID << 16 | consumer_ms)),
            (0x6060, 0, struct.pack('<b', 9)),                              # CSV
            (0x6040, 0, struct.pack('<H', 0x06)), (0x6040, 0, struct.pack('<H', 0x07)),
            (0x6040, 0, struct.pack('<H', 0x0F))):
        answer = call(sdo_write, SdoWrite.Request(node_id=drive_id, index=index,
                                                  subindex=subindex, data=list(data)),
                      f'write 0x{index:04X}', node)
        assert answer.success, answer.message
    assert drive.drive_state == 'OPERATION_ENABLED'
    time.sleep(2 * consumer_ms / 1000)
    assert drive.drive_state == 'OPERATION_ENABLED', 'the drive lost a living gateway'
    node.process.send_signal(signal.SIGKILL)
    node.process.wait(ANSWER)
    wait_until(lambda: drive.drive_state == 'FAULT', ANSWER, 'the drive in FAULT')
    assert drive.value(0x603F) == struct.pack('<H', 0x8130)  # heartbeat error


# A node id a device has.

CLASHES = [('nodes', f'[3, {OWN_ID}]'), ('node_guarding', f'[{OWN_ID}]'),
           ('pdo.nodes', f'[{OWN_ID}]'), ('simulation.devices', f'[{OWN_ID}]')]


@pytest.mark.parametrize('parameter, node_ids', CLASHES, ids=[name for name, _ in CLASHES])
def test_a_node_id_a_device_has_is_refused_naming_both_parameters(parameter, node_ids):
    node = Node('cbcan', cli_args=[
        '--ros-args', '-p', 'can.interface:=virtual', '-p', f'can.channel:=hb-{uuid.uuid4()}',
        '-p', f'heartbeat.node_id:={OWN_ID}', '-p', f'{parameter}:={node_ids}'],
        use_global_arguments=False)
    try:
        with pytest.raises(ConfigurationError) as refused:
            NodeParameters(node).gateway_config()
    finally:
        node.destroy_node()
    assert str(refused.value).startswith(
        f'parameter heartbeat.node_id: {OWN_ID} is also a device in {parameter} ')
    assert '0x764' in str(refused.value)
    assert 'allowed: 0 (no heartbeat) or a node id no device on the bus uses' in \
        str(refused.value)


@pytest.mark.parametrize('given, says', [
    ('heartbeat.node_id:=128', 'parameter heartbeat.node_id: 128 is out of range'),
    ('heartbeat.period:=0.001', 'parameter heartbeat.period: 0.001 is out of range')])
def test_a_node_id_or_period_out_of_range_is_refused(given, says):
    node = Node('cbcan', cli_args=['--ros-args', '-p', given], use_global_arguments=False)
    try:
        with pytest.raises(ConfigurationError) as refused:
            NodeParameters(node)
    finally:
        node.destroy_node()
    assert says in str(refused.value)


def test_a_clashing_node_id_stops_the_installed_node():
    done = subprocess.run(
        [executable('cbcan_node'), '--ros-args', '-r', f'__ns:={namespace()}',
         '-p', 'can.interface:=virtual', '-p', f'can.channel:=hb-{uuid.uuid4()}',
         '-p', 'simulation.devices:=[2]', '-p', 'heartbeat.node_id:=2'],
        capture_output=True, text=True, timeout=START_TIMEOUT)
    output = done.stdout + done.stderr
    assert done.returncode not in (None, 0), output
    assert ('cbcan_node: cannot start: parameter heartbeat.node_id: 2 is also a device in '
            'simulation.devices ([2])') in output, output
    assert 'Traceback' not in output
