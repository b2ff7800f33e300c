"""Program download (CiA 302-3): ``~/program_download`` against a simulated bootloader.

The device is durand's (an independent stack) with a bootloader (``BootloaderDevice``): it
stores the image as it arrives, flashes for a while, reports 0x1F57, resets into the new
program and identifies it by the CRC-32 of the image (0x1F56). What the tests read is what
the device holds and the frames on the bus. Where a test must act while the image is on its
way, it holds the download at a segment boundary (``Hold``) until the gateway tells it to
end: no race with the transfer's speed, no sleeps.
"""

import os
import signal
import struct
import threading
import zlib

from action_msgs.msg import GoalStatus
from diagnostic_msgs.msg import DiagnosticStatus
import pytest
from rclpy.action import ActionClient
from test_boot_configuration import bus_file, Frames, state_of
from test_diagnostics import DiagnosticsRecorder
from test_drives import CSV
from test_drives import NODE as DRIVE
from test_drives import Rig as DriveRig

from cbcan_ros.action import ProgramDownload
from cbcan_ros.ros.cli import build_parser, Client, run
from cbcan_ros.ros.client import GatewayClient, RequestFailed
from cbcan_ros.simulation.durand.bootloader import BootloaderDevice
from cbcan_ros.simulation.durand.device import DurandDevice

from conftest import Harness, new_channel, wait_for_future, wait_until
from node_process import (
    arguments,
    BusRecorder,
    namespace,
    private_bus,
    START_TIMEOUT,
    StateWatcher,
    STOP_TIMEOUT,
)

NODE = 12
OTHER = 13
WAIT = 20.0
SMALL = 20 * 1024  # bytes: images of a few round trips of blocks
NOT_STORED = 0x08000020
LOCAL_CONTROL = 0x08000021
BLOCK_ACKNOWLEDGED = b'\xa2'  # the device's answer to a block of the download
PHASES = ['STOPPING', 'CLEARING', 'DOWNLOADING', 'FLASHING', 'STARTING', 'CHECKING']


class Rig:
    """A gateway, a device with a bootloader, a plain device, and an action client."""

    def __init__(self, start_durand, tmp_path, device=None, **parameters):
        channel = new_channel()
        self.tmp_path = tmp_path
        self.frames = Frames(channel)
        self.device = start_durand(NODE, kind=BootloaderDevice, channel=channel,
                                   **(device or {}))
        self.other = start_durand(OTHER, kind=DurandDevice, channel=channel)
        self.gateway = Harness({'can.channel': channel, 'simulation.devices': None,
                                'nodes': [NODE, OTHER], **parameters})
        self.core = self.gateway.node.gateway
        self.action = ActionClient(self.gateway.client_node, ProgramDownload,
                                   '/cbcan/program_download')
        assert self.action.wait_for_server(timeout_sec=WAIT)
        wait_until(lambda: all(self.core.monitor.status(n).detected for n in (NODE, OTHER)),
                   WAIT, 'both devices heard')

    def image(self, size: int = SMALL, name: str = 'firmware.bin') -> str:
        """Write an image of ``size`` random bytes; return its path."""
        path = self.tmp_path / name
        path.write_bytes(os.urandom(size))
        return str(path)

    def send(self, **fields):
        """Send a goal; return (its handle, the feedback list filled as it arrives)."""
        feedback = []
        goal = wait_for_future(self.action.send_goal_async(
            ProgramDownload.Goal(**fields),
            feedback_callback=lambda message: feedback.append(message.feedback)), WAIT)
        assert goal.accepted
        return goal, feedback

    def result(self, goal):
        """Return (the result, its status) of a goal."""
        answer = wait_for_future(goal.get_result_async(), WAIT)
        return answer.result, answer.status

    def run(self, **fields):
        """Run a goal to its end; return (result, status, feedback)."""
        goal, feedback = self.send(**fields)
        result, status = self.result(goal)
        return result, status, feedback

    def frames_sent(self) -> list:
        """Return the frames on the bus, once the reader has every one sent before this call.

        The reader is a thread of its own that may lag on a loaded machine: a read of the
        other device through the gateway, its request recorded, marks where the gateway's
        earlier frames are all in.
        """
        since = len(self.frames.snapshot())
        assert self.gateway.call('sdo_read', node_id=OTHER, index=0x1000, subindex=0).success
        wait_until(lambda: any(frame.arbitration_id == 0x600 + OTHER
                               for frame in self.frames.snapshot()[since:]), WAIT,
                   'the marker read on the bus')
        return self.frames.snapshot()

    def close(self) -> None:
        """Stop the gateway and the frame reader."""
        self.action.destroy()
        self.gateway.close()
        self.frames.close()


class Hold:
    """Holds the gateway's download of the image at a segment boundary past ``at`` bytes.

    Once there, ``reached`` is set, and the download goes on only when the gateway tells it
    to end (cancel, shutdown), or after :meth:`release`.
    """

    def __init__(self, rig: Rig, at: int):
        self.reached = threading.Event()
        self._released = threading.Event()
        service = rig.core.program
        stream = service._sdo_stream

        def held(access, answer_within, written):
            def each(position: int, block: bool):
                reason = written(position, block)
                if position >= at and not self.reached.is_set():
                    self.reached.set()
                    reason = wait_until(lambda: written(position, block)
                                        or self._released.is_set(),
                                        WAIT, 'the download told to end, or released')
                    reason = reason if isinstance(reason, str) else None
                return reason
            return stream(access, answer_within, each)
        service._sdo_stream = held

    def release(self) -> None:
        """Let the download go on."""
        self._released.set()


@pytest.fixture
def rig(ros_context, start_durand, tmp_path):
    """Return ``rig(device={options}, **parameters)``, closed after the test."""
    made = []

    def factory(**options):
        made.append(Rig(start_durand, tmp_path, **options))
        return made[-1]
    yield factory
    for each in made:
        each.close()


def sdo_writes(frames, node_id: int):
    """Return the SDO download and block download frames sent to a node (no block running)."""
    return [frame for frame in frames
            if frame.arbitration_id == 0x600 + node_id and frame.data[0] >> 5 in (1, 6)]


def aborts(frames, node_id: int):
    """Return the abort codes the gateway sent to a node."""
    return [struct.unpack_from('<I', frame.data, 4)[0] for frame in frames
            if frame.arbitration_id == 0x600 + node_id and frame.data[0] == 0x80]


def test_an_image_is_stored_byte_for_byte_started_and_identified(rig):
    setup = rig()
    path = setup.image()
    expected = zlib.crc32(open(path, 'rb').read())
    result, status, feedback = setup.run(node_id=NODE, file=path,
                                         expected_software_id=expected)
    assert result.success and status == GoalStatus.STATUS_SUCCEEDED, result.message
    assert bytes(setup.device.image) == open(path, 'rb').read()
    assert result.software_id == expected and result.abort_code == 0, result
    assert setup.device.starts == 1 and setup.device.program_running
    assert 'started, software id' in result.message, result.message
    assert 'block transfer' in result.message, result.message
    phases = [message.phase for message in feedback]
    assert [p for n, p in enumerate(phases) if p not in phases[:n]] == PHASES, phases
    downloading = [m for m in feedback if m.phase == 'DOWNLOADING']
    assert downloading[-1].bytes_sent == downloading[-1].bytes_total == SMALL
    assert downloading[-1].bytes_per_second > 0


def test_without_start_the_program_is_written_and_left_stopped(rig):
    setup = rig()
    path = setup.image(300)
    result, status, _ = setup.run(node_id=NODE, file=path, start=False)
    assert result.success, result.message
    assert bytes(setup.device.image) == open(path, 'rb').read()
    assert setup.device.starts == 0 and not setup.device.program_running
    assert 'not started (start: false)' in result.message, result.message


@pytest.mark.parametrize('goal, named', [
    (dict(file='missing.bin'), 'cannot be read'),
    (dict(file='empty.bin'), 'is empty'),
    (dict(file=''), 'file is empty'),
    (dict(program=0), 'program 0 is out of range'),
    (dict(node_id=0), 'node_id 0 is out of range'),
    (dict(node_id=40), 'not heard'),
    (dict(node_id=OTHER), 'has no 0x1F51:1'),
])
def test_bad_goals_are_refused_before_anything_is_written(rig, goal, named):
    setup = rig()
    (setup.tmp_path / 'empty.bin').write_bytes(b'')
    fields = {'node_id': NODE, 'file': setup.image(100), **goal}
    if fields['file'] and not fields['file'].startswith('/'):
        fields['file'] = str(setup.tmp_path / fields['file'])
    before = bytes(setup.device.image)
    result, status, feedback = setup.run(**fields)
    assert not result.success and status == GoalStatus.STATUS_ABORTED
    assert named in result.message and 'nothing was sent' in result.message, result.message
    assert not feedback, 'a refused goal has no phase'
    assert bytes(setup.device.image) == before and setup.device.program_running
    assert not sdo_writes(setup.frames.snapshot(), goal.get('node_id', NODE))


def test_a_device_that_aborts_mid_image_fails_the_download_with_its_abort_code(rig):
    setup = rig(device=dict(abort_at=5000))
    result, status, _ = setup.run(node_id=NODE, file=setup.image())
    assert not result.success and status == GoalStatus.STATUS_ABORTED
    assert result.abort_code == NOT_STORED, result
    assert result.message.startswith('DOWNLOADING failed'), result.message
    assert 'cleared and partly written, not started: download again' in result.message
    assert not setup.device.program_running and setup.device.starts == 0


def test_a_device_that_resets_mid_image_ends_the_download_at_its_boot_up(rig):
    # Once a defect: the rest of the image reached the restarted device, which answered
    # what it took for unknown commands with aborts; the result named one of those (an
    # abort of 0000:00), and a boot reading the device next could take another for its
    # own answer.
    setup = rig(device=dict(reset_at=20000))
    result, status, _ = setup.run(node_id=NODE, file=setup.image(size=64 * 1024))
    assert not result.success and status == GoalStatus.STATUS_ABORTED
    assert result.message.startswith('DOWNLOADING failed: the device reset (it sent its '
                                     'boot-up message) at byte'), result.message
    assert 'download again' in result.message, result.message
    assert len(setup.device.image) < 64 * 1024, 'the image was not sent on to its end'


def test_a_flash_error_fails_the_download_with_the_flash_status(rig):
    setup = rig(device=dict(flash_error=5))
    result, _, _ = setup.run(node_id=NODE, file=setup.image())
    assert not result.success
    assert result.flash_status == 5 << 1, result
    assert result.message.startswith('FLASHING failed'), result.message
    assert 'flash write error' in result.message, result.message
    assert setup.device.starts == 0


def test_a_device_that_never_comes_back_fails_after_the_start_timeout(rig):
    setup = rig(device=dict(comes_back=False), **{'program_download.start_timeout': 1.0})
    result, _, _ = setup.run(node_id=NODE, file=setup.image())
    assert not result.success
    assert result.message.startswith('STARTING failed: no boot-up message within 1 s'), \
        result.message
    assert 'its start was not seen' in result.message, result.message
    assert setup.device.starts == 1


def test_another_software_id_than_expected_fails_the_check(rig):
    setup = rig()
    result, _, _ = setup.run(node_id=NODE, file=setup.image(), expected_software_id=7)
    assert not result.success
    assert result.message.startswith('CHECKING failed'), result.message
    assert result.software_id == setup.device.software_id != 7


def test_a_cancel_aborts_between_segments_and_says_what_the_device_holds(rig):
    setup = rig()
    hold = Hold(setup, 3000)
    goal, _ = setup.send(node_id=NODE, file=setup.image())
    assert hold.reached.wait(WAIT)
    wait_for_future(goal.cancel_goal_async(), WAIT)
    result, status = setup.result(goal)
    assert not result.success and status == GoalStatus.STATUS_CANCELED, result.message
    assert 'cancelled by the caller' in result.message, result.message
    assert 'partly written, not started: download again' in result.message
    assert result.abort_code == LOCAL_CONTROL
    wait_until(lambda: LOCAL_CONTROL in aborts(setup.frames.snapshot(), NODE), WAIT,
               'the abort on the bus')
    assert 3000 <= len(setup.device.image) < SMALL
    assert not setup.device.program_running


def test_while_a_download_runs_other_devices_are_served_and_it_shows_as_programming(rig):
    # The download is held at a segment boundary, so "while" is a fact, not a race.
    setup = rig(diagnostics_period=0.1)
    diagnostics = DiagnosticsRecorder(setup.gateway.client_node)
    hold = Hold(setup, 3000)
    goal, _ = setup.send(node_id=NODE, file=setup.image())
    assert hold.reached.wait(WAIT)
    read = setup.gateway.call('sdo_read', node_id=OTHER, index=0x1000, subindex=0)
    assert read.success, read.message
    second, _, _ = setup.run(node_id=NODE, file=setup.image(name='other.bin'))
    assert not second.success and 'being programmed already' in second.message
    wait_until(lambda: any(n.node_id == NODE and n.programming
                           for n in setup.gateway.states[-1].nodes), WAIT,
               'node states showing the device being programmed')
    status = diagnostics.wait_for(f'cbcan: node {NODE}', DiagnosticStatus.WARN, WAIT,
                                  lambda shown: shown.get('Program download') == 'DOWNLOADING')
    assert 'being programmed (DOWNLOADING' in status.message, status.message
    hold.release()
    result, _ = setup.result(goal)
    assert result.success, result.message
    wait_until(lambda: not any(n.programming for n in setup.gateway.states[-1].nodes), WAIT,
               'node states showing the download over')


def test_shutdown_during_a_download_aborts_it_and_answers_the_goal(rig):
    setup = rig()
    hold = Hold(setup, 3000)
    goal, _ = setup.send(node_id=NODE, file=setup.image())
    assert hold.reached.wait(WAIT)
    stopping = threading.Thread(target=setup.gateway.node.shut_down_gateway)
    stopping.start()
    result, _ = setup.result(goal)
    stopping.join(WAIT)
    assert not result.success
    assert 'the gateway is shutting down' in result.message, result.message
    assert 'partly written' in result.message, result.message
    assert aborts(setup.frames.snapshot(), NODE), 'no abort on the bus'
    assert setup.device.starts == 0


def test_an_enabled_drive_is_refused_before_anything_is_written(ros_context, start_durand,
                                                                 tmp_path):
    axis = DriveRig(start_durand)
    try:
        axis.enable(CSV)
        action = ActionClient(axis.gateway.client_node, ProgramDownload,
                              '/cbcan/program_download')
        assert action.wait_for_server(timeout_sec=WAIT)
        path = tmp_path / 'drive.bin'
        path.write_bytes(b'new drive firmware')
        goal = wait_for_future(action.send_goal_async(
            ProgramDownload.Goal(node_id=DRIVE, file=str(path))), WAIT)
        result = wait_for_future(goal.get_result_async(), WAIT).result
        assert not result.success
        assert 'OPERATION_ENABLED: disable it first' in result.message, result.message
        assert axis.drive.drive_state == 'OPERATION_ENABLED'
        action.destroy()
    finally:
        axis.close()


def test_the_cli_shows_each_phase_and_the_bar_and_prints_the_software_id(rig, capsys):
    setup = rig()
    path = setup.image()
    client = Client('/cbcan', WAIT)
    try:
        status = run(client, build_parser().parse_args(
            ['program-download', str(NODE), path, '--expect',
             f'0x{zlib.crc32(open(path, "rb").read()):08X}']))
        out, err = capsys.readouterr()
        assert status == 0, err
        assert out.splitlines()[0] == 'STOPPING', out
        assert '[##############################] 100.0 %' in out, out
        assert f'started, software id 0x{setup.device.software_id:08X}' in out, out
        status = run(client, build_parser().parse_args(
            ['program-download', str(NODE), path, '--expect', '7']))
        out, err = capsys.readouterr()
        assert status == 1 and 'error: node 12 program download: CHECKING failed' in err, err
    finally:
        client.close()


def test_the_python_client_reports_progress_and_raises_on_a_refusal(rig):
    setup = rig()
    path = setup.image()
    seen = []
    with GatewayClient(setup.gateway.client_node, '/cbcan', WAIT) as gateway:
        result = gateway.program_download(NODE, path, feedback=seen.append)
        assert result.software_id == setup.device.software_id
        assert seen and seen[-1].phase == 'CHECKING', seen
        with pytest.raises(RequestFailed, match='cannot be read'):
            gateway.program_download(NODE, path + '.missing')


def booted(start_durand, tmp_path, device=None, at_boot=True, plain=False, **parameters):
    """Start a gateway whose bus description gives NODE a software_file and its version.

    Returns (the gateway, the device, the new image's bytes).
    """
    channel = new_channel()
    image = os.urandom(SMALL)
    (tmp_path / 'new.bin').write_bytes(image)
    kind = DurandDevice if plain else BootloaderDevice
    unit = start_durand(NODE, kind=kind, channel=channel, **(device or {}))
    path = bus_file(tmp_path, f"""\
        master:
          node_id: 1
          boot_timeout: 2000
        nodes:
          arm_io:
            node_id: {NODE}
            dcf: device.eds
            software_file: new.bin
            software_version: 0x{zlib.crc32(image):08X}
        """)
    gateway = Harness({'can.channel': channel, 'simulation.devices': None,
                       'bus_config': path, 'program_download.at_boot': at_boot,
                       **parameters})
    return gateway, unit, image


def boot_of(gateway):
    """Return NODE's boot state once its first boot ended."""
    return wait_until(lambda: (state := state_of(gateway, NODE)).boots >= 1 and state, WAIT,
                      'the boot of the device ended')


def test_a_boot_downloads_the_software_file_when_the_version_differs(start_durand, tmp_path,
                                                                      ros_context):
    gateway, unit, image = booted(start_durand, tmp_path)
    try:
        state = boot_of(gateway)
        assert state.state == 'BOOTED', state
        assert 'software updated' in state.message, state.message
        assert bytes(unit.image) == image and unit.software_id == zlib.crc32(image)
    finally:
        gateway.close()


def test_a_boot_downloading_the_software_file_shows_the_device_as_being_programmed(
        start_durand, tmp_path, ros_context):
    # Once a defect: only ~/program_download's downloads were shown in node_states.
    gateway, unit, image = booted(start_durand, tmp_path, device=dict(flash_time=0.5))
    try:
        def shown_programming():
            with gateway._states_lock:
                return any(n.node_id == NODE and n.programming
                           for message in gateway.states for n in message.nodes)
        wait_until(shown_programming, WAIT, 'node_states showing the device being programmed')
        assert boot_of(gateway).state == 'BOOTED'
        wait_until(lambda: not any(n.programming for n in gateway.states[-1].nodes), WAIT,
                   'node_states showing the programming ended')
    finally:
        gateway.close()


@pytest.mark.parametrize('at_boot', [True, False], ids=['at_boot', 'not_at_boot'])
def test_a_download_the_next_boot_would_undo_is_refused_unless_it_is_the_software_version(
        start_durand, tmp_path, ros_context, at_boot):
    # Its next boot would download software_file over another program (at_boot) or leave
    # the device unstarted (error H): the goal would succeed and not last.
    gateway, unit, image = booted(start_durand, tmp_path, at_boot=at_boot)
    other = tmp_path / 'test_build.bin'
    other.write_bytes(os.urandom(SMALL))
    try:
        boot_of(gateway)
        held = bytes(unit.image)
        with GatewayClient(gateway.client_node, '/cbcan', WAIT) as client:
            for expected in (0, zlib.crc32(other.read_bytes())):
                with pytest.raises(RequestFailed) as refused:
                    client.program_download(NODE, str(other), expected_software_id=expected)
                assert f'software_version 0x{zlib.crc32(image):08X}' in str(refused.value)
                assert 'nothing was sent' in str(refused.value), refused.value
                assert bytes(unit.image) == held
            (tmp_path / 'same.bin').write_bytes(image)
            done = client.program_download(NODE, str(tmp_path / 'same.bin'),
                                           expected_software_id=zlib.crc32(image))
        assert done.software_id == zlib.crc32(image)
    finally:
        gateway.close()


@pytest.mark.parametrize('letter, options, named', [
    ('H', dict(at_boot=False), 'program_download.at_boot'),
    ('G', dict(plain=True), '0x1F56:1 (software id) could not be read'),
    ('I', dict(device=dict(abort_at=3000)), 'DOWNLOADING failed'),
])
def test_a_boot_that_cannot_update_the_software_fails_with_its_letter(
        start_durand, tmp_path, ros_context, letter, options, named):
    gateway, unit, image = booted(start_durand, tmp_path, **options)
    try:
        state = boot_of(gateway)
        assert state.state == 'FAILED' and state.error_status == letter, state
        assert named in state.message, state.message
        assert unit.state == 127, 'a device whose boot failed is not started'
    finally:
        gateway.close()


def held_bootloader(start_durand, group: str, port: int):
    """Return (device, holding, released): a bootloader on udp_multicast ``group``/``port``.

    It holds its acknowledgement of the block that brings the image past 3,000 bytes
    (``holding`` set) until ``released`` is set, so whatever a test does next lands while the
    image is on its way.
    """
    device = start_durand(NODE, kind=BootloaderDevice, interface='udp_multicast',
                          channel=group, bus_options={'port': port})
    wait_until(lambda: device.running, WAIT, 'the device receiving')
    holding, released = threading.Event(), threading.Event()
    send = device._network.send

    def held(cob_id: int, data: bytes) -> None:
        if data[:1] == BLOCK_ACKNOWLEDGED and len(device.image) >= 3000 and \
                not released.is_set():
            holding.set()
            released.wait(WAIT)
        send(cob_id, data)
    device._network.send = held
    return device, holding, released


@pytest.mark.parametrize('stop', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_a_signal_during_a_download_aborts_it_answers_the_goal_and_sends_nothing_after(
        start_node, start_durand, client_node, tmp_path, stop):
    # The installed node in a process of its own, as users run it; the device in this one
    # holds its acknowledgement of a block, so the signal lands while the image is on its way.
    group, port = private_bus()
    device, holding, released = held_bootloader(start_durand, group, port)
    recorder = BusRecorder(group, port)
    name = f'{namespace()}/cbcan'
    gateway = start_node(arguments(name, '-p', 'can.interface:=udp_multicast',
                                   '-p', f'can.channel:={group}', '-p', f'nodes:=[{NODE}]',
                                   '-p', 'sdo.timeout:=10.0'), port)
    try:
        StateWatcher(client_node, name).wait_for({NODE: 'PRE_OPERATIONAL'}, START_TIMEOUT)
        action = ActionClient(client_node, ProgramDownload, f'{name}/program_download')
        assert action.wait_for_server(timeout_sec=START_TIMEOUT)
        path = tmp_path / 'firmware.bin'
        path.write_bytes(os.urandom(SMALL))
        goal = wait_for_future(action.send_goal_async(
            ProgramDownload.Goal(node_id=NODE, file=str(path))), START_TIMEOUT)
        answer = goal.get_result_async()
        assert holding.wait(START_TIMEOUT), gateway.output()
        gateway.process.send_signal(stop)
        assert gateway.wait(STOP_TIMEOUT) == 0, gateway.output()
        released.set()
        result = wait_for_future(answer, WAIT).result
    finally:
        released.set()
        recorder.close()
    assert not result.success
    assert 'DOWNLOADING failed: the gateway is shutting down' in result.message, result.message
    assert 'partly written, not started: download again' in result.message, result.message
    requests = [message for _, message in recorder.frames
                if message.arbitration_id == 0x600 + NODE]
    assert requests[-1].data[0] == 0x80, 'the last request to the device is not the abort'
    assert device.starts == 0
    assert device.starts == 0
