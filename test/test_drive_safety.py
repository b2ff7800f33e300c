"""Every way out of the gateway stops its drives, on the bus, with the node as its own process.

The installed ``cbcan_node`` (or ``cbcan_lifecycle_node``) runs as a child process on a
udp_multicast bus of its own; the simulated CiA 402 drive (durand) lives in this process on
that bus, and a raw recorder here keeps every frame. This process plays the robot program:
``~/drive_command`` and ``~/node_<id>/target`` by rclpy, ``~/node_<id>/drive_state`` read.

What is asserted is what the gateway decides and what the drive did: the frames the gateway
sent (an SDO download to the controlword 0x6040, an RPDO carrying it, the consumer heartbeat
0x1016:1), their order against the signal or against a marker frame this process sent, and
the drive's own state and velocity. Nothing is proved by sleeping; the one test of absence
(no halt without a command timeout) watches for a bounded while.

Frames to the drive: RPDO1 0x200 + id carries the controlword (with the target position and
the mode), RPDO2 0x300 + id the target velocity and torque, SDO requests go to 0x600 + id.
"""

import signal
import struct
import threading
import time

import can
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
import pytest
from std_msgs.msg import Float64

from cbcan_ros.core.drives import cia402
from cbcan_ros.msg import DriveState
from cbcan_ros.ros.drives import STATE_QOS
from cbcan_ros.ros.node import SHUTDOWN_LIMIT
from cbcan_ros.simulation.durand.drive import DurandDrive
from cbcan_ros.simulation.durand.drive_objects import QUICK_STOP_OPTION
from cbcan_ros.simulation.durand.drive_pdos import default_drive_pdos
from cbcan_ros.simulation.durand.drive_pdos import drive_pdos as layout_pdos
from cbcan_ros.simulation.durand.scheduler import shared_scheduler
from cbcan_ros.simulation.simulated_drives import LAYOUTS
from cbcan_ros.srv import DriveCommand, NmtCommand

from conftest import wait_until
from node_process import (
    arguments,
    BusRecorder,
    call,
    namespace,
    private_bus,
    service_client,
    START_TIMEOUT,
    StateWatcher,
    STOP_TIMEOUT,
)

NODE = 7
CSP, CSV = 8, 9
VELOCITY = 1500  # counts/s: the target the drive moves at (joint scale 1)
ANSWER = 15.0  # ceiling for what a quiet machine does within a fraction of a second
COMMAND_TIMEOUT = 10.0  # the drive_command timeout the tests ask for: far above a transition
OWN_ID = 100  # the gateway's heartbeat node id
LOCAL_CONTROL = 0x08000021
INACTIVE = 0x08000022
MARKER = 0x7F0  # no CANopen service uses it: this process's marks in the recording

RPDO1, RPDO2 = 0x200 + NODE, 0x300 + NODE
RPDOS = {0x200 + NODE, 0x300 + NODE, 0x400 + NODE, 0x500 + NODE}
SDO_REQUEST, SDO_RESPONSE = 0x600 + NODE, 0x580 + NODE
CONTROLWORD = 0x6040
CONSUMER_HEARTBEAT = 0x1016
HALT = 1 << 8
QUICK_STOP, DISABLE_VOLTAGE = 0x0002, 0x0000
STOPPED = ('QUICK_STOP_ACTIVE', 'SWITCH_ON_DISABLED')

PDOS = default_drive_pdos()  # the simulated drive's own, as make run has them
# The drives watch the gateway by default; unless a test says otherwise, with a consumer
# time that a busy test machine's pauses do not reach.
CONSUMER_TIME = 3.0


# Reading the frames.

def is_download(message) -> bool:
    """Return whether ``message`` is an SDO download request to the drive (any kind)."""
    return (message.arbitration_id == SDO_REQUEST and len(message.data) > 0
            and message.data[0] >> 5 in (0, 1, 6))  # segment, initiate, block


def expedited_download(message):
    """Return (index, subindex, value) of an expedited SDO download to the drive, else None."""
    data = bytes(message.data)
    if message.arbitration_id != SDO_REQUEST or len(data) != 8 or data[0] & 0xE3 != 0x23:
        return None
    index, subindex = struct.unpack_from('<HB', data, 1)
    size = 4 - (data[0] >> 2 & 3)
    return index, subindex, int.from_bytes(data[4:4 + size], 'little')


def controlword_of(message):
    """Return the controlword a frame to the drive carries (RPDO1 or SDO download), else None."""
    if message.arbitration_id == RPDO1 and len(message.data) >= 2:
        return struct.unpack_from('<H', bytes(message.data))[0]
    written = expedited_download(message)
    if written and written[:2] == (CONTROLWORD, 0):
        return written[2]
    return None


def velocity_of(message):
    """Return the velocity actual value in the drive's TPDO2, else None."""
    if message.arbitration_id == 0x280 + NODE and len(message.data) == 8:
        return struct.unpack_from('<i', bytes(message.data), 4)[0]
    return None


def heartbeats_left_out(frames) -> list:
    """Return ``frames`` without the heartbeats (0x701..0x77F) that come every period."""
    return [m for m in frames if not 0x700 <= m.arbitration_id < 0x780]


def shown(frames, count: int = 40) -> str:
    """Return the last ``count`` frames as 'id#data' text, for failure messages."""
    return ' '.join(f'{m.arbitration_id:03X}#{bytes(m.data).hex()}' for m in frames[-count:])


class Recorder(BusRecorder):
    """Every frame on the bus, and marks: frames this process sent to split the recording.

    Frames arrive in the order they were sent, so a frame recorded after a mark was sent
    after this process sent the mark.
    """

    def __init__(self, group: str, port: int):
        super().__init__(group, port)
        self._marks = 0

    def messages(self, since: int = 0) -> list:
        """Return the frames recorded from position ``since`` on."""
        return [message for _, message in self.frames[since:]]

    def mark(self) -> int:
        """Send a marker frame; return its position in the recording, once recorded.

        Sent again each second it is not recorded: a datagram is lost when the recorder's
        socket overflows, as under a flood of frames on a loaded machine.
        """
        self._marks += 1
        data = self._marks.to_bytes(4, 'little')
        since = len(self.frames)
        sent = [0.0]

        def position():
            if time.monotonic() - sent[0] >= 1.0:
                self.send(MARKER, data)
                sent[0] = time.monotonic()
            for number, (_, message) in enumerate(list(self.frames)[since:], since):
                if message.arbitration_id == MARKER and bytes(message.data) == data:
                    return number + 1  # +1: 0 would read as "not yet"
            return None
        return wait_until(position, ANSWER, 'the marker frame recorded') - 1

    def send(self, can_id: int, data: bytes) -> None:
        """Send a frame on the bus, as another device or master would."""
        self._bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))

    def first(self, condition, what: str, since: int = 0, timeout: float = ANSWER) -> int:
        """Wait for a frame ``condition(message)`` from ``since`` on; return its position."""
        def found():
            for number, (_, message) in enumerate(list(self.frames)[since:], since):
                if condition(message):
                    return number + 1
            return None
        try:
            return wait_until(found, timeout, what) - 1
        except AssertionError:
            # Heartbeats left out: they would fill the frames shown.
            frames = heartbeats_left_out(self.messages(since))
            raise AssertionError(f'{what} not seen (the recording socket dropped '
                                 f'{self.dropped()} datagrams); the last frames but '
                                 f'heartbeats: {shown(frames, 120)}') from None


class Targets:
    """A robot program's target stream on ``~/node_<id>/target``, every 20 ms, in a thread."""

    PERIOD = 0.02

    def __init__(self, publisher, value: float):
        self._publisher = publisher
        self.value = value
        self.published = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            self._publisher.publish(Float64(data=float(self.value)))
            self.published += 1
            self._stop.wait(self.PERIOD)

    def stop(self) -> None:
        """Stop publishing."""
        self._stop.set()
        self._thread.join()


class DriveRig:
    """A gateway process with drive NODE, the drive in this process, the bus recorded."""

    def __init__(self, start_node, client_node, start_durand, *parameters: str,
                 program: str = 'cbcan_node', pdos=PDOS):
        self.group, self.port = private_bus()
        self._pdos = pdos
        self.recorder = Recorder(self.group, self.port)
        self._start_durand = start_durand
        self.drive = self.start_drive()
        self.name = f'{namespace()}/cbcan'
        self.client_node = client_node
        self.node = start_node(arguments(
            self.name, '-p', 'can.interface:=udp_multicast', '-p', f'can.channel:={self.group}',
            '-p', f'drives.nodes:=[{NODE}]', '-p', f'drives.consumer_time:={CONSUMER_TIME}',
            *parameters), self.port, program)
        self._lock = threading.Lock()
        self.states = []
        self.node_states = StateWatcher(client_node, self.name)
        client_node.create_subscription(DriveState, f'{self.name}/node_{NODE}/drive_state',
                                        self._keep, STATE_QOS)
        self.publisher = client_node.create_publisher(
            Float64, f'{self.name}/node_{NODE}/target', 10)
        self._clients = {}
        self._streams = []

    def start_drive(self) -> DurandDrive:
        """Start a drive NODE on the bus (a new one boots, as after power-on)."""
        drive = self._start_durand(NODE, kind=DurandDrive, interface='udp_multicast',
                                   channel=self.group, bus_options={'port': self.port},
                                   pdos=self._pdos)
        wait_until(lambda: drive.running, ANSWER, 'the drive receiving')
        return drive

    def _keep(self, message) -> None:
        with self._lock:
            self.states.append(message)

    def latest(self):
        """Return the latest DriveState message, None before one."""
        with self._lock:
            return self.states[-1] if self.states else None

    def wait_state(self, state: str, since: int = 0, timeout: float = START_TIMEOUT) -> None:
        """Wait for a drive_state message with ``state`` (among those from ``since`` on).

        ``state`` '*' is any state but UNKNOWN: the drive heard.
        """
        def seen():
            with self._lock:
                return any(m.state == state or (state == '*' and m.state != 'UNKNOWN')
                           for m in self.states[since:])
        try:
            wait_until(seen, timeout, f'drive_state {state}')
        except AssertionError:
            latest = self.latest()
            raise AssertionError(f'drive_state {state} not published within {timeout} s '
                                 f'(latest: {latest and latest.state}):\n'
                                 f'{self.node.output()[-3000:]}') from None

    def drive_reaches(self, condition, what: str) -> None:
        """Wait for ``condition(drive)``; fail saying where the drive stands then."""
        try:
            wait_until(lambda: condition(self.drive), ANSWER, what)
        except AssertionError:
            latest = self.latest()
            raise AssertionError(
                f'{what} not within {ANSWER} s: the drive is {self.drive.drive_state} at '
                f'velocity {self.drive.velocity}; drive_state says '
                f'{latest and (latest.state, "halted" if latest.halted else "not halted")}'
            ) from None

    def client(self, service_type, service: str):
        """Return (creating once) a client of the node's ``service``."""
        if service not in self._clients:
            self._clients[service] = service_client(self.client_node, service_type,
                                                    f'{self.name}/{service}', self.node)
        return self._clients[service]

    def command(self, command: str, mode: int = 0, timeout: float = COMMAND_TIMEOUT):
        """Call ``~/drive_command``; return the response."""
        return call(self.client(DriveCommand, 'drive_command'), DriveCommand.Request(
            node_id=NODE, command=command, mode=mode, timeout=timeout), command, self.node,
            timeout + ANSWER)

    def nmt_start(self) -> None:
        """Start the drive (NMT): its PDOs flow only in OPERATIONAL."""
        answer = call(self.client(NmtCommand, 'nmt_command'), NmtCommand.Request(
            node_id=NODE, command=1), 'nmt start', self.node)
        assert answer.success, answer.message
        wait_until(lambda: self.drive.state == 5, ANSWER, 'the drive OPERATIONAL')
        # The gateway uses the drive's PDOs once its heartbeat says OPERATIONAL, up to a
        # heartbeat period after the drive is: a command before that goes by SDO, at once.
        wait_until(lambda: self.node_states.latest().get(NODE) == 'OPERATIONAL', ANSWER,
                   'the gateway hearing the drive OPERATIONAL')

    def stream(self, value: float = VELOCITY) -> Targets:
        """Publish ``value`` as the drive's target every 20 ms until the test ends."""
        wait_until(lambda: self.publisher.get_subscription_count() > 0, START_TIMEOUT,
                   'the node subscribed to the target topic')
        targets = Targets(self.publisher, value)
        self._streams.append(targets)
        return targets

    def enable_moving(self, timeout: float = COMMAND_TIMEOUT) -> Targets:
        """Start the drive, enable it in CSV and stream VELOCITY; return once it moves.

        It waits first for the drive_state that shows the gateway has read the drive: until
        then an enable is refused. ``timeout``: the enable's.
        """
        self.wait_state('SWITCH_ON_DISABLED')
        self.nmt_start()
        enabled = self.command('enable', CSV, timeout)
        assert enabled.success, enabled.message
        assert self.drive.drive_state == 'OPERATION_ENABLED'
        targets = self.stream()
        self.drive_reaches(lambda drive: drive.velocity == VELOCITY,
                           f'the drive moving at {VELOCITY}')
        return targets

    def stop_streams(self) -> None:
        """Stop every target stream."""
        for targets in self._streams:
            targets.stop()
        self._streams = []

    def target_refused(self, text: str) -> None:
        """Wait for the node's log line that a target was refused, saying ``text``.

        The node logs the first refusal of each kind: the proof a target reached it.
        """
        line = f'node_{NODE}/target: {text}'
        wait_until(lambda: line in self.node.output(), ANSWER,
                   f'{line!r} in the log:\n{self.node.output()[-3000:]}')

    def close(self) -> None:
        """Stop the target streams and the recorder (the fixtures stop node and drive)."""
        self.stop_streams()
        self.recorder.close()


@pytest.fixture
def rig(start_durand, start_node, client_node):
    """Return ``rig(*parameters, program=..., pdos=...)``: a DriveRig, closed after the test."""
    # The drive set up first is stopped last: the node's exit stops a live drive (one
    # already gone would keep its shutdown waiting for the stop's confirmation, a second).
    made = []

    def factory(*parameters: str, program: str = 'cbcan_node', pdos=PDOS) -> DriveRig:
        made.append(DriveRig(start_node, client_node, start_durand, *parameters,
                             program=program, pdos=pdos))
        return made[-1]
    yield factory
    for each in made:
        each.close()


def velocity_in_units(drive: DurandDrive, counts_per_unit: int) -> None:
    """Have ``drive`` show its velocity (0x606C) in units of ``counts_per_unit`` counts/s.

    As a drive whose velocity is in rpm and its position in an encoder's counts: a coarse
    unit reads 0 while the axis still moves.
    """
    publish = drive._publish

    def in_units() -> None:
        publish()
        drive.node.object_dictionary.write(0x606C, 0, round(drive._velocity / counts_per_unit))
    drive._publish = in_units


def standing_still(drive: DurandDrive) -> bool:
    """Return whether the drive is stopped: quick stop or power stage off, velocity 0."""
    return drive.drive_state in STOPPED and drive.velocity == 0


def stop_with(rig: DriveRig, signum) -> float:
    """Send ``signum`` to the node; return the time it was sent, once it exited cleanly."""
    signalled = time.monotonic()
    rig.node.process.send_signal(signum)
    status = rig.node.wait(STOP_TIMEOUT)
    exited = time.monotonic() - signalled
    output = rig.node.output()
    assert status == 0, f'exit status {status}:\n{output[-3000:]}'
    assert exited < SHUTDOWN_LIMIT, f'exited after {exited:.1f} s:\n{output[-3000:]}'
    assert 'Traceback' not in output, output[-3000:]
    return signalled


def stop_frame_after(rig: DriveRig, word: int, since: int) -> int:
    """Wait for the SDO download of ``word`` to 0x6040 from ``since`` on and the drive's answer.

    Return the request's position in the recording.
    """
    request = rig.recorder.first(lambda m: expedited_download(m) == (CONTROLWORD, 0, word),
                                 f'an SDO download of 0x{word:04X} to 0x6040', since)
    # The drive took it (scs 3: download confirmed).
    rig.recorder.first(lambda m: m.arbitration_id == SDO_RESPONSE
                       and bytes(m.data[:4]) == b'\x60\x40\x60\x00',
                       'the drive confirming the download to 0x6040', request)
    return request


def nothing_to_the_drive_after(rig: DriveRig, position: int, what: str) -> None:
    """Assert no RPDO and no SDO download reached the drive after ``position``.

    Uploads may go on (a managed node deactivated still reads what no TPDO brings).
    """
    sent = [m for m in rig.recorder.messages(position + 1)
            if m.arbitration_id in RPDOS or is_download(m)]
    assert not sent, f'frames commanding the drive after {what}: {shown(sent)}'


# 1. Signals.

@pytest.mark.parametrize('signum, layout', [
    (signal.SIGINT, 'combined'), (signal.SIGTERM, 'combined'), (signal.SIGINT, 'vendor'),
    (signal.SIGINT, 'ros2_canopen'), (signal.SIGINT, 'sdo_only')],
    ids=['SIGINT', 'SIGTERM', 'SIGINT-vendor', 'SIGINT-ros2_canopen', 'SIGINT-sdo_only'])
def test_a_signal_quick_stops_an_enabled_drive_before_the_node_exits(rig, signum, layout):
    # The robot program keeps streaming targets through the signal, as a controller does.
    axis = rig('-p', 'drives.command_timeout:=0.0', pdos=layout_pdos(layout))
    axis.enable_moving()
    before = axis.recorder.mark()
    signalled = stop_with(axis, signum)
    axis.stop_streams()
    request = stop_frame_after(axis, QUICK_STOP, before)
    assert axis.recorder.frames[request][0] > signalled, 'the quick stop came before the signal'
    axis.drive_reaches(standing_still, 'the drive stopped')
    axis.recorder.mark()  # every frame the node sent is recorded before this
    nothing_to_the_drive_after(axis, request, 'the quick stop')


# Once a defect: the quick stop went out after the PDO service had stopped taking TPDOs, so
# the statusword that showed it was never taken, and the last drive_state a robot program
# got from the node that had gone said OPERATION_ENABLED. With synchronous TPDOs the
# statusword comes at a SYNC after the stop; without TPDOs (sdo_only, or synchronous ones
# while the gateway produces no SYNC) only a read brings it, and the feedback cycle's polls
# have ended.
@pytest.mark.parametrize('layout, sync', [
    ('combined', ()), ('ros2_canopen', ('-p', 'sync.period:=0.01')), ('sdo_only', ())],
    ids=['combined', 'ros2_canopen-sync', 'sdo_only'])
def test_after_a_signal_the_last_drive_state_shows_the_stop(rig, layout, sync):
    axis = rig('-p', 'drives.command_timeout:=0.0', *sync, pdos=layout_pdos(layout))
    axis.enable_moving()
    axis.wait_state('OPERATION_ENABLED')
    stop_with(axis, signal.SIGINT)
    axis.stop_streams()
    axis.drive_reaches(standing_still, 'the drive stopped')
    try:
        wait_until(lambda: axis.latest().state in STOPPED, ANSWER,
                   'the last drive_state showing the stop')
    except AssertionError:
        with axis._lock:
            seen = [message.state for message in axis.states[-5:]]
        raise AssertionError(f'the node exited; the drive is {axis.drive.drive_state}, its '
                             f'last drive_state messages said {seen}:\n'
                             f'{axis.node.output()[-3000:]}') from None


def test_on_shutdown_disable_switches_the_power_stage_off(rig):
    axis = rig('-p', 'drives.command_timeout:=0.0', '-p', 'drives.on_shutdown:=disable')
    axis.enable_moving()
    before = axis.recorder.mark()
    stop_with(axis, signal.SIGINT)
    axis.stop_streams()
    request = stop_frame_after(axis, DISABLE_VOLTAGE, before)
    axis.drive_reaches(lambda drive: drive.drive_state == 'SWITCH_ON_DISABLED',
                       'the drive SWITCH_ON_DISABLED')
    axis.recorder.mark()
    nothing_to_the_drive_after(axis, request, 'the disable')
    assert axis.drive.velocity == 0


def test_on_shutdown_none_sends_nothing_to_the_controlword(rig):
    axis = rig('-p', 'drives.command_timeout:=0.0', '-p', 'drives.on_shutdown:=none')
    targets = axis.enable_moving()
    targets.stop()  # the last targets reach the node before the signal
    before = axis.recorder.mark()
    stop_with(axis, signal.SIGINT)
    axis.recorder.mark()  # every frame the node sent is recorded before this
    written = [m for m in axis.recorder.messages(before) if controlword_of(m) is not None]
    assert not written, f'controlwords at shutdown with on_shutdown none: {shown(written)}'
    # Left as it is: nothing stopped it (it has no consumer heartbeat to watch).
    assert axis.drive.drive_state == 'OPERATION_ENABLED'
    assert axis.drive.velocity == VELOCITY


# 2. The command timeout.

def halts(message) -> bool:
    """Return whether ``message`` carries a controlword with the halt bit to the drive."""
    word = controlword_of(message)
    return word is not None and bool(word & HALT)


def test_silence_halts_a_streaming_drive_and_a_new_target_resumes_it(rig):
    axis = rig('-p', 'drives.command_timeout:=0.3')
    before = axis.recorder.mark()
    targets = axis.enable_moving()
    targets.stop()  # then silence
    halt = axis.recorder.first(halts, 'a controlword with the halt bit (8)', before)
    assert controlword_of(axis.recorder.messages()[halt]) & 0x8F == 0x0F, \
        'the halt did not keep operation enabled'
    axis.drive_reaches(lambda drive: drive.velocity == 0, 'the halted drive standing')
    assert axis.drive.drive_state == 'OPERATION_ENABLED'
    wait_until(lambda: axis.latest().halted, ANSWER, 'drive_state showing halted')
    # A new target: the halt bit goes, the drive moves at the new target.
    resumed = axis.stream(VELOCITY + 500)
    release = axis.recorder.first(lambda m: controlword_of(m) is not None
                                  and not controlword_of(m) & HALT,
                                  'a controlword without the halt bit', halt)
    axis.recorder.first(lambda m: velocity_of(m) == VELOCITY + 500,
                        f'the drive moving at {VELOCITY + 500} again', release)
    wait_until(lambda: not axis.latest().halted, ANSWER, 'drive_state no longer halted')
    resumed.stop()


def test_command_timeout_0_never_halts(rig):
    axis = rig('-p', 'drives.command_timeout:=0.0')
    targets = axis.enable_moving()
    targets.stop()
    start = axis.recorder.mark()
    time.sleep(1.5)  # a test of absence: five times the timeout of the test above
    axis.recorder.mark()
    halted = [m for m in axis.recorder.messages(start) if halts(m)]
    assert not halted, f'halted without a command timeout: {shown(halted)}'
    assert axis.drive.velocity == VELOCITY
    assert not axis.latest().halted


def test_a_drive_in_pre_operational_is_still_halted_when_targets_stop(rig):
    # A drive leaves OPERATIONAL while it moves: another tool's NMT command here; a drive
    # also goes there by itself on a communication error (CiA 301, 0x1029 default). Its
    # power stage runs on, but it takes no RPDO in PRE_OPERATIONAL (its heartbeat says so).
    # Once a defect (before 573df06): the command timeout's halt went in RPDO1 all the same,
    # the drive never got it and ran on at its last velocity, while drive_state said halted.
    axis = rig('-p', 'drives.command_timeout:=0.3')
    targets = axis.enable_moving()
    axis.recorder.send(0x000, bytes([0x80, NODE]))  # enter PRE_OPERATIONAL
    wait_until(lambda: axis.drive.state == 127, ANSWER, 'the drive PRE_OPERATIONAL')
    targets.stop()
    axis.drive_reaches(lambda drive: drive.velocity == 0, 'the drive halted')


def test_a_drive_stopped_by_nmt_is_not_shown_halted_and_is_halted_once_started(rig):
    # Another tool's NMT stop while the drive moves: in STOPPED it takes neither PDO nor SDO,
    # and this drive (as many) runs on. Once a defect (red team): the command timeout's halt
    # failed by SDO, drive_state said halted all the same, and it was never tried again, so
    # the drive ran on after NMT start too.
    axis = rig('-p', 'drives.command_timeout:=0.3')
    targets = axis.enable_moving()
    axis.recorder.send(0x000, bytes([0x02, NODE]))  # NMT stop
    wait_until(lambda: axis.drive.state == 4, ANSWER, 'the drive STOPPED')
    published = len(axis.states)
    targets.stop()
    wait_until(lambda: 'the command timeout could not halt it' in axis.node.output(),
               ANSWER + 5.0, 'the log line that the halt failed')
    wait_until(lambda: not axis.latest().halted, ANSWER, 'drive_state no longer halted')
    assert any(m.halted for m in axis.states[published:]), 'the halt was never tried'
    assert axis.drive.velocity == VELOCITY, 'the STOPPED drive took a frame'
    started = axis.recorder.mark()
    axis.recorder.send(0x000, bytes([0x01, NODE]))  # NMT start, by the other tool
    axis.recorder.first(halts, 'the halt sent once the drive is OPERATIONAL', started)
    axis.drive_reaches(lambda drive: drive.velocity == 0, 'the drive halted')
    wait_until(lambda: axis.latest().halted, ANSWER, 'drive_state showing halted')


@pytest.mark.parametrize('node_id', [NODE, 0])
def test_an_nmt_stop_that_would_cut_off_an_enabled_drive_is_refused(rig, node_id):
    # STOPPED, a drive takes neither PDO nor SDO, and this one (as many) runs on.
    axis = rig()
    targets = axis.enable_moving()
    before = axis.recorder.mark()
    answer = call(axis.client(NmtCommand, 'nmt_command'), NmtCommand.Request(
        node_id=node_id, command=2), 'nmt stop', axis.node)
    assert not answer.success and answer.abort_code == INACTIVE, answer
    assert f'drive {NODE} is OPERATION_ENABLED' in answer.message, answer.message
    answer = call(axis.client(NmtCommand, 'nmt_command'), NmtCommand.Request(
        node_id=node_id, command=1), 'nmt start', axis.node)
    assert answer.success, answer.message
    axis.recorder.mark()
    nmt = [m for m in axis.recorder.messages(before) if m.arbitration_id == 0]
    assert [bytes(m.data) for m in nmt] == [bytes([1, node_id])], shown(nmt)
    assert axis.drive.velocity == VELOCITY and axis.drive.state == 5
    targets.stop()
    disabled = axis.command('disable')
    assert disabled.success, disabled.message
    answer = call(axis.client(NmtCommand, 'nmt_command'), NmtCommand.Request(
        node_id=node_id, command=2), 'nmt stop', axis.node)
    assert answer.success, f'refused once the drive was disabled: {answer.message}'


# 3. The gateway's heartbeat, watched by the drive.

CONSUMER_MS = 1500


def consumer_write(message) -> bool:
    """Return whether ``message`` writes (OWN_ID << 16) | CONSUMER_MS to the drive's 0x1016:1."""
    return expedited_download(message) == (CONSUMER_HEARTBEAT, 1, OWN_ID << 16 | CONSUMER_MS)


@pytest.mark.parametrize('layout', LAYOUTS)
def test_the_drive_watches_the_gateway_and_stops_by_itself_when_it_is_killed(rig, layout):
    # Beats a second apart: a consumer watches from the first beat it hears, so the gateway
    # sends one right after each write of 0x1016:1, and a kill right after the enable, before
    # the next beat on the grid, still stops the drive.
    axis = rig('-p', f'heartbeat.node_id:={OWN_ID}', '-p', 'heartbeat.period:=1.0',
               '-p', f'drives.consumer_time:={CONSUMER_MS / 1000}',
               '-p', 'drives.command_timeout:=0.0', pdos=layout_pdos(layout))
    axis.wait_state('SWITCH_ON_DISABLED')
    axis.recorder.first(consumer_write, 'the consumer heartbeat written to 0x1016:1')
    entry = struct.pack('<I', OWN_ID << 16 | CONSUMER_MS)
    wait_until(lambda: axis.drive.value(CONSUMER_HEARTBEAT, 1) == entry, ANSWER,
               'the drive holding 0x1016:1 = 0x006405DC')
    # After a boot the drive has its default (no consumer): the gateway writes it again.
    booted, shown = axis.recorder.mark(), len(axis.states)
    answer = call(axis.client(NmtCommand, 'nmt_command'), NmtCommand.Request(
        node_id=NODE, command=129), 'nmt reset node', axis.node)
    assert answer.success, answer.message
    axis.recorder.first(lambda m: m.arbitration_id == 0x700 + NODE and bytes(m.data) == b'\0',
                        'the drive booting', booted)
    axis.recorder.first(consumer_write, '0x1016:1 written again after the boot', booted)
    wait_until(lambda: axis.drive.value(CONSUMER_HEARTBEAT, 1) == entry, ANSWER,
               'the drive holding 0x1016:1 again')
    # The gateway's re-read ends just after that write: UNKNOWN until then, and enable
    # refused. drive_state tells its end (in order): the drive shown again after UNKNOWN.
    axis.wait_state('UNKNOWN', shown)
    wait_until(lambda: axis.latest().state == 'SWITCH_ON_DISABLED', ANSWER,
               'the drive shown again, read afresh after its boot')
    axis.enable_moving()
    killed = axis.recorder.mark()
    axis.node.process.send_signal(signal.SIGKILL)  # no shutdown code runs
    axis.node.process.wait(ANSWER)
    try:
        axis.drive_reaches(standing_still, 'the drive stopped by itself')
    except AssertionError as error:
        # What the drive's consumer saw: heartbeats of the gateway's id still on the bus
        # (someone else's), or none and no consumer timer running.
        heard = [message for message in axis.recorder.messages(killed)
                 if message.arbitration_id == 0x700 + OWN_ID]
        raise AssertionError(f'{error}; heartbeats of node {OWN_ID} after the kill: '
                             f'{len(heard)}; durand timers pending: '
                             f'{shared_scheduler().pending()}') from None


def statewords_since(axis, since: int) -> list:
    """Return the states the drive's TPDO 1 statuswords showed since mark ``since``."""
    return [cia402.state_of(struct.unpack_from('<H', bytes(m.data))[0])
            for m in axis.recorder.messages(since) if m.arbitration_id == 0x180 + NODE]


@pytest.mark.parametrize('rpdos', ['event-driven', 'synchronous'])
def test_a_gateway_held_up_longer_than_the_drive_watches_it_does_not_run_it_again(rig, rpdos):
    # Red team: a drive that stays in QUICK_STOP_ACTIVE (0x605A = 6, where enable operation
    # is transition 16) stopped by itself while the gateway was frozen for 1.5 s, and ran
    # again within 10 ms of the gateway going on: a message's frames from before the freeze,
    # the command timeout's halt (0x010F), the targets queued meanwhile, and with
    # synchronous RPDOs the frame the drive held for the first SYNC after it.
    synchronous = rpdos == 'synchronous'
    axis = rig('-p', f'heartbeat.node_id:={OWN_ID}', '-p', 'heartbeat.period:=0.2',
               '-p', 'drives.consumer_time:=1.0', '-p', 'drives.command_timeout:=0.5',
               *(('-p', 'sync.period:=0.05') if synchronous else ()),
               pdos=default_drive_pdos(1 if synchronous else 0))
    axis.drive.set_value(QUICK_STOP_OPTION, 0, struct.pack('<h', 6))
    if synchronous:  # CSP: each target's frame (RPDO 1) carries the controlword
        axis.wait_state('SWITCH_ON_DISABLED')
        axis.nmt_start()
        enabled = axis.command('enable', CSP)
        assert enabled.success, enabled.message
        axis.stream(axis.drive.position)
        axis.recorder.first(lambda m: m.arbitration_id == RPDO1, 'targets in RPDO 1',
                            axis.recorder.mark())
        # Frozen right after a frame, which the drive holds for the SYNC 50 ms later.
        axis.recorder.first(lambda m: m.arbitration_id == RPDO1, 'a target in RPDO 1',
                            axis.recorder.mark())
    else:
        axis.enable_moving()
    frozen = axis.recorder.mark()
    axis.node.process.send_signal(signal.SIGSTOP)
    try:
        axis.drive_reaches(lambda drive: drive.drive_state == 'QUICK_STOP_ACTIVE',
                           'the drive stopped by itself')
    finally:
        resumed = axis.recorder.mark()
        axis.node.process.send_signal(signal.SIGCONT)
    # The targets kept coming all the while: refused once the drive needs a fresh enable.
    wait_until(lambda: 'and needs a fresh enable' in axis.node.output(), ANSWER,
               f'a target refused, in the log:\n{axis.node.output()[-3000:]}')
    axis.recorder.mark()
    enabling = [m for m in axis.recorder.messages(frozen) if controlword_of(m) is not None
                and controlword_of(m) & 0x8F == 0x0F]  # enable operation, halted or not
    assert not enabling, f'frames that enable after the stall: {shown(enabling)}'
    states = statewords_since(axis, resumed)
    assert 'OPERATION_ENABLED' not in states, f'the drive ran again: {states}'
    assert axis.drive.drive_state == 'QUICK_STOP_ACTIVE'
    assert axis.node.output().count('was silent for') == 1, axis.node.output()[-3000:]


# 4. The drive's heartbeat lost.

def test_a_silent_drive_is_unknown_refuses_targets_and_needs_a_fresh_enable(rig):
    axis = rig('-p', 'drives.command_timeout:=0.0', '-p', 'heartbeat.timeout:=1.5')
    targets = axis.enable_moving()
    states_before = len(axis.states)
    axis.drive.stop()  # silent, as when its cable is pulled; the targets keep coming
    axis.wait_state('UNKNOWN', states_before)
    lost = axis.recorder.mark()
    axis.target_refused(f'node {NODE} is not heard')
    refused = axis.command('enable', CSV)
    assert not refused.success
    assert 'UNKNOWN' in refused.message and 'nothing was sent' in refused.message
    assert refused.state == 'UNKNOWN'
    axis.recorder.mark()
    # Uploads to a lost drive would be harmless; nothing may command it but the quick stop
    # the gateway sends in case it is alive and running (this one is gone).
    sent = [m for m in axis.recorder.messages(lost) if (m.arbitration_id in RPDOS
            or is_download(m)) and controlword_of(m) != QUICK_STOP]
    assert not sent, f'frames to the lost drive: {shown(sent)}'

    # It boots again (power back): SWITCH_ON_DISABLED, and targets refused until an enable.
    states_before = len(axis.states)
    axis.drive = axis.start_drive()
    axis.wait_state('SWITCH_ON_DISABLED', states_before)
    booted = axis.recorder.mark()
    axis.target_refused(f'node {NODE} is SWITCH_ON_DISABLED and needs a fresh enable')
    axis.recorder.mark()
    sent = [m for m in axis.recorder.messages(booted) if m.arbitration_id in RPDOS
            or is_download(m)]
    assert not sent, f'frames to the rebooted drive before an enable: {shown(sent)}'
    assert axis.drive.drive_state == 'SWITCH_ON_DISABLED'
    targets.stop()
    axis.stop_streams()
    axis.enable_moving()


def test_a_drive_that_stops_heartbeating_while_running_is_quick_stopped(rig):
    # Only its heartbeat stops (its producer time set to 0): the drive is alive, running, and
    # deaf to nothing. The gateway, which no longer takes its targets, stops it, and a
    # robot program's own quick_stop gets through too (by SDO: no statusword confirms it).
    axis = rig('-p', 'drives.command_timeout:=0.0', '-p', 'heartbeat.timeout:=0.6')
    targets = axis.enable_moving()
    states_before = len(axis.states)
    axis.drive.set_value(0x1017, 0, 0)
    axis.wait_state('UNKNOWN', states_before)
    targets.stop()
    axis.drive_reaches(standing_still, 'the drive stopped after its heartbeat was lost')
    stopped = axis.command('quick_stop')
    assert stopped.success and 'not heard' in stopped.message, stopped.message
    refused = axis.command('enable', CSV)
    assert not refused.success and 'nothing was sent' in refused.message


def test_a_drive_heard_again_without_a_boot_is_not_left_running(rig):
    # The drive's heartbeat pauses longer than heartbeat.timeout (a loose connector, a
    # stalled drive firmware) and comes back without a boot: the drive still runs in CSV at
    # its last velocity. The robot program now streams another target. Either the targets
    # reach the drive again, or the drive is stopped; it must not run on at a velocity
    # nobody commands.
    # Defect: the gateway refuses every target until a fresh enable (so the robot program
    # cannot even send 0), and the command timeout skips a drive that needs an enable, so
    # nothing ever halts it.
    axis = rig('-p', 'drives.command_timeout:=0.3', '-p', 'heartbeat.timeout:=0.6')
    targets = axis.enable_moving()
    states_before = len(axis.states)
    axis.drive.set_value(0x1017, 0, 0)  # its heartbeat pauses...
    axis.wait_state('UNKNOWN', states_before)
    states_before = len(axis.states)
    axis.drive.set_value(0x1017, 0, 200)  # ... and comes back, the drive never booted
    # Heard again: OPERATION_ENABLED as read, or already the stop that follows (the state
    # topic shows the newest state, and the stop may come before it is published).
    axis.wait_state('*', states_before)
    targets.value = VELOCITY + 500
    axis.drive_reaches(lambda drive: drive.velocity in (0, VELOCITY + 500),
                       f'the drive at the new target {VELOCITY + 500} or stopped')


# 5. The managed node.

MANAGED = ('-p', f'heartbeat.node_id:={OWN_ID}', '-p', 'drives.command_timeout:=0.0',
           '-p', f'drives.consumer_time:={CONSUMER_MS / 1000}')


def managed_transition(axis: DriveRig, transition_id: int) -> None:
    """Make a lifecycle transition of the managed node; it must succeed."""
    request = ChangeState.Request(transition=Transition(id=transition_id))
    assert call(axis.client(ChangeState, 'change_state'), request,
                f'transition {transition_id}', axis.node).success


def configure_once_read(axis: DriveRig) -> None:
    """Configure the managed node; return once it is reading the drive (inactive still).

    It writes the consumer heartbeat (0x1016:1) while it reads a drive; the read ends a few
    SDO transfers later, which the drive_state published once active shows.
    """
    managed_transition(axis, Transition.TRANSITION_CONFIGURE)
    axis.recorder.first(consumer_write, 'the consumer heartbeat written to 0x1016:1',
                        timeout=START_TIMEOUT)


def test_deactivate_and_shutdown_of_the_managed_node_quick_stop_the_drive(rig):
    axis = rig(*MANAGED, program='cbcan_lifecycle_node')

    def transition(transition_id: int) -> None:
        managed_transition(axis, transition_id)

    configure_once_read(axis)
    transition(Transition.TRANSITION_ACTIVATE)
    axis.enable_moving()
    before = axis.recorder.mark()
    transition(Transition.TRANSITION_DEACTIVATE)
    request = stop_frame_after(axis, QUICK_STOP, before)
    axis.drive_reaches(standing_still, 'the drive stopped')
    refused = axis.command('enable', CSV)
    assert (refused.success, refused.abort_code) == (False, INACTIVE), refused.message
    axis.recorder.mark()
    nothing_to_the_drive_after(axis, request, 'the quick stop at deactivate')

    # Active again: the targets still streaming are refused until a fresh enable.
    transition(Transition.TRANSITION_ACTIVATE)
    axis.target_refused(f'node {NODE} is SWITCH_ON_DISABLED and needs a fresh enable')
    assert axis.drive.drive_state in STOPPED
    axis.stop_streams()
    enabled = axis.command('enable', CSV)
    assert enabled.success, enabled.message
    axis.stream()
    axis.drive_reaches(lambda drive: drive.velocity == VELOCITY, 'the drive moving again')
    before = axis.recorder.mark()
    transition(Transition.TRANSITION_ACTIVE_SHUTDOWN)
    request = stop_frame_after(axis, QUICK_STOP, before)
    axis.drive_reaches(standing_still, 'the drive stopped')
    axis.stop_streams()
    axis.recorder.mark()
    nothing_to_the_drive_after(axis, request, 'the quick stop at shutdown')


def test_the_managed_node_publishes_the_drive_state_once_active(rig):
    # The drive was read while the node was inactive (drive_state is not published then):
    # once active, a robot program subscribing to drive_state must learn the state.
    axis = rig(*MANAGED, program='cbcan_lifecycle_node')
    configure_once_read(axis)
    managed_transition(axis, Transition.TRANSITION_ACTIVATE)
    axis.wait_state('SWITCH_ON_DISABLED', timeout=ANSWER)


# 6. read_only.

COMMANDS = [('enable', CSV), ('disable', 0), ('quick_stop', 0), ('halt', 0), ('resume', 0),
            ('fault_reset', 0), ('set_mode', CSV), ('home', 0)]


def test_read_only_refuses_every_command_and_writes_nothing_even_at_shutdown(rig):
    axis = rig('-p', 'read_only:=true', '-p', f'heartbeat.node_id:={OWN_ID}',
               '-p', 'drives.consumer_time:=0.3')
    axis.wait_state('SWITCH_ON_DISABLED')
    for command, mode in COMMANDS:
        answer = axis.command(command, mode)
        assert not answer.success, command
        assert answer.abort_code == LOCAL_CONTROL, (command, answer.message)
        assert 'read-only' in answer.message and 'nothing was sent' in answer.message
    # Another master starts and enables the drive: the gateway sees it moving...
    axis.recorder.send(0x000, bytes([1, NODE]))
    wait_until(lambda: axis.drive.state == 5, ANSWER, 'the drive OPERATIONAL')
    for index, value in ((0x6060, CSV), (0x60FF, VELOCITY), (CONTROLWORD, 0x06),
                         (CONTROLWORD, 0x07), (CONTROLWORD, 0x0F)):
        axis.drive.set_value(index, 0, value)
    axis.wait_state('OPERATION_ENABLED')
    targets = axis.stream()
    axis.target_refused('the gateway is read-only')
    targets.stop()
    # ... and at shutdown leaves it to that master: a read-only gateway writes nothing.
    stop_with(axis, signal.SIGINT)
    axis.recorder.mark()
    written = [m for m in axis.recorder.messages() if m.arbitration_id in RPDOS
               or is_download(m)]
    assert not written, f'a read-only gateway wrote: {shown(written)}'
    nmt = [m for m in axis.recorder.messages() if m.arbitration_id == 0x000]
    assert [bytes(m.data) for m in nmt] == [bytes([1, NODE])], \
        f"NMT commands besides the other master's: {shown(nmt)}"
    assert axis.drive.drive_state == 'OPERATION_ENABLED'
    assert axis.drive.velocity == VELOCITY

