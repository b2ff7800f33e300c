"""Program download (CiA 302-3) under attack: cancels, faults, odd files and shutdowns.

Red-team guards of ``~/program_download`` (issue 38). Each test acts as a user would (the
action, the CLI's client, the installed node in a process of its own) against durand's
simulated bootloader and checks what went on the bus, what the goal was answered and what the
gateway shows. Where a test must act in a given phase it waits for that phase's feedback and
for the device to have taken that phase's command (a long ``clear_time``/``flash_time`` or a
device that never comes back keeps the phase open): no race with the transfer's speed.
"""

import os
import signal
import subprocess
import threading
import zlib

from action_msgs.msg import GoalStatus, GoalStatusArray
from diagnostic_msgs.msg import DiagnosticStatus
from durand.services.sdo.server import SDODomainAbort
import pytest
from rclpy.action import ActionClient
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from test_boot_configuration import bus_file, Frames, state_of
from test_diagnostics import DiagnosticsRecorder
from test_drives import CSV
from test_drives import NODE as DRIVE
from test_drives import Rig as DriveRig
from test_program_download import (
    aborts,
    booted,
    held_bootloader,
    Hold,
    LOCAL_CONTROL,
    NODE,
    OTHER,
    Rig,
    SMALL,
    WAIT,
)

from cbcan_ros.action import ProgramDownload
from cbcan_ros.core.boot.plan import PlanError
from cbcan_ros.simulation.durand.bootloader import (
    ABORT_DEVICE_STATE,
    BootloaderDevice,
    CLEAR,
    PROGRAM_CONTROL,
    START,
    STOP,
)
from cbcan_ros.simulation.durand.device import DurandDevice

from conftest import Harness, new_channel, wait_for_future, wait_until
import faulty_bus
from faulty_bus import FaultController
from node_process import (
    arguments,
    BusRecorder,
    executable,
    namespace,
    private_bus,
    START_TIMEOUT,
    StateWatcher,
    STOP_TIMEOUT,
)

faulty_bus.register()

THIRD = 14  # a second device with a bootloader
SDO_REQUEST = 0x600


@pytest.fixture
def rig(ros_context, start_durand, tmp_path):
    """Return ``rig(device={options}, **parameters)`` (test_program_download's), closed after."""
    made = []

    def factory(**options):
        made.append(Rig(start_durand, tmp_path, **options))
        return made[-1]
    yield factory
    for each in made:
        each.close()


def requests_to(frames, node_id: int, since: int = 0):
    """Return the SDO requests the gateway sent to ``node_id`` from frame ``since`` on."""
    return [frame for frame in frames[since:] if frame.arbitration_id == SDO_REQUEST + node_id]


def control_writes(frames, node_id: int, since: int = 0):
    """Return the values written to 0x1F51:1 (expedited download requests) from ``since`` on."""
    return [frame.data[4] for frame in requests_to(frames, node_id, since)
            if frame.data[0] >> 5 == 1 and frame.data[1:4] == bytes([0x51, 0x1F, 1])]


def image_writes(frames, node_id: int, since: int = 0):
    """Return the initiations of a download of 0x1F50:1 (segmented or block) from ``since``."""
    return [frame for frame in requests_to(frames, node_id, since)
            if frame.data[0] >> 5 in (1, 6) and frame.data[1:4] == bytes([0x50, 0x1F, 1])]


def phase_seen(feedback, phase: str) -> bool:
    """Return whether a feedback of ``phase`` arrived."""
    return any(message.phase == phase for message in feedback)


def programming(setup) -> bool:
    """Return whether the last ``~/node_states`` shows NODE being programmed."""
    return any(n.node_id == NODE and n.programming for n in setup.gateway.states[-1].nodes)


# Cancel in each phase: the goal ends CANCELED, its message names the phase and what the
# device holds, and no command or image goes to the device after the cancel.

@pytest.mark.parametrize('phase, device, parameters, reached, left', [
    ('CLEARING', dict(clear_time=60.0), {}, lambda device: device.cleared,
     'stopped and perhaps cleared, not started'),
    ('FLASHING', dict(flash_time=60.0), {}, lambda device: True,
     'written, flashing not confirmed, not started'),
    ('STARTING', dict(comes_back=False), {'program_download.start_timeout': 60.0},
     lambda device: device.starts == 1, 'its start was not seen'),
])
def test_a_cancel_in_a_waiting_phase_ends_it_and_sends_no_command_after(
        rig, phase, device, parameters, reached, left):
    setup = rig(device=device, **parameters)
    goal, feedback = setup.send(node_id=NODE, file=setup.image(3000))
    wait_until(lambda: phase_seen(feedback, phase) and reached(setup.device), WAIT,
               f'the download in {phase}')
    commands = {'STARTING': [STOP, CLEAR, START]}.get(phase, [STOP, CLEAR])
    wait_until(lambda: control_writes(setup.frames.snapshot(), NODE) == commands, WAIT,
               f'the commands so far read back: {commands}')
    starts = setup.device.starts
    since = len(setup.frames.snapshot())
    wait_for_future(goal.cancel_goal_async(), WAIT)
    result, status = setup.result(goal)
    assert not result.success and status == GoalStatus.STATUS_CANCELED, result.message
    assert result.message.startswith(f'{phase} failed: cancelled by the caller'), result.message
    assert left in result.message, result.message
    frames = setup.frames.snapshot()
    assert not control_writes(frames, NODE, since), 'a program control command after the cancel'
    assert not image_writes(frames, NODE, since), 'an image after the cancel'
    assert setup.device.starts == starts
    # The cancelled run is gone: not shown, and no longer refusing the device.
    wait_until(lambda: not programming(setup), WAIT, 'node states showing the download over')
    assert setup.core.program.refusal(NODE) is None


def test_a_cancel_after_the_download_ended_is_rejected_and_the_result_stays(rig):
    setup = rig()
    goal, _ = setup.send(node_id=NODE, file=setup.image(2000))
    result, status = setup.result(goal)
    assert result.success and status == GoalStatus.STATUS_SUCCEEDED, result.message
    response = wait_for_future(goal.cancel_goal_async(), WAIT)
    assert not response.goals_canceling, 'a finished goal was accepted for cancelling'
    assert setup.device.starts == 1


# Devices that misbehave.

class StopRefusingDevice(BootloaderDevice):
    """A bootloader that refuses to stop its program (0x1F51:1 = 0 answered with an abort)."""

    def _control(self, command: int) -> None:
        if command == STOP:
            raise SDODomainAbort(ABORT_DEVICE_STATE, (PROGRAM_CONTROL, 1))
        super()._control(command)


class ClearRefusingDevice(BootloaderDevice):
    """A bootloader that refuses to clear the program (0x1F51:1 = 3 answered with an abort)."""

    def _control(self, command: int) -> None:
        if command == CLEAR:
            raise SDODomainAbort(ABORT_DEVICE_STATE, (PROGRAM_CONTROL, 1))
        super()._control(command)


class UnansweredStopDevice(BootloaderDevice):
    """A bootloader that restarts when stopped before it answers the stop."""

    def _control(self, command: int) -> None:
        if command == STOP and self.program_running:
            self._network.muted = True  # its answer is lost in the restart
        super()._control(command)


def bootloaders_of(kind, start_durand):
    """Return a ``start_durand`` that starts ``kind`` where a rig asks for a bootloader."""
    def start(node_id, **options):
        if options.get('kind') is BootloaderDevice:
            options['kind'] = kind
        return start_durand(node_id, **options)
    return start


def test_a_device_that_refuses_the_stop_gets_no_clear_and_no_image(
        ros_context, start_durand, tmp_path):
    setup = Rig(bootloaders_of(StopRefusingDevice, start_durand), tmp_path)
    try:
        before = bytes(setup.device.image)
        result, status, _ = setup.run(node_id=NODE, file=setup.image(2000))
        assert not result.success and status == GoalStatus.STATUS_ABORTED
        assert result.message.startswith('STOPPING failed'), result.message
        assert 'perhaps stopped' in result.message, result.message
        assert result.abort_code == ABORT_DEVICE_STATE, result
        frames = setup.frames_sent()
        assert control_writes(frames, NODE) == [STOP], 'a command after the refused stop'
        assert not image_writes(frames, NODE)
        assert bytes(setup.device.image) == before and setup.device.program_running
    finally:
        setup.close()


def test_a_device_that_restarts_when_stopped_is_cleared_once_its_boot_up_came(rig):
    # Many bootloaders restart when the program is stopped; a clear sent meanwhile is lost.
    setup = rig(device=dict(restarts_on_stop=0.3),
                **{'program_download.restart_timeout': 5.0})
    path = setup.image(2000)
    result, status, _ = setup.run(node_id=NODE, file=path)
    assert result.success and status == GoalStatus.STATUS_SUCCEEDED, result.message
    assert bytes(setup.device.image) == open(path, 'rb').read()
    frames = setup.frames_sent()
    assert control_writes(frames, NODE) == [STOP, CLEAR, START], 'each command once'
    boot_ups = [at for at, frame in enumerate(frames)
                if frame.arbitration_id == 0x700 + NODE and bytes(frame.data) == b'\x00']
    clear = next(at for at, frame in enumerate(frames)
                 if frame.arbitration_id == 0x600 + NODE and bytes(frame.data[:5])
                 == bytes([0x2F, 0x51, 0x1F, 1, CLEAR]))
    assert any(at < clear for at in boot_ups), 'the clear went before the restart ended'


def test_a_device_that_restarts_when_stopped_fails_in_clearing_naming_the_parameter(rig):
    setup = rig(device=dict(restarts_on_stop=0.3), **{'program_download.flash_timeout': 1.0})
    result, status, _ = setup.run(node_id=NODE, file=setup.image(2000))
    assert not result.success and status == GoalStatus.STATUS_ABORTED
    assert result.message.startswith('CLEARING failed'), result.message
    assert 'the device restarted after the stop' in result.message, result.message
    assert 'program_download.restart_timeout' in result.message, result.message
    assert not image_writes(setup.frames_sent(), NODE)


def test_a_restart_timeout_for_a_device_that_does_not_restart_fails_in_stopping(rig):
    setup = rig(**{'program_download.restart_timeout': 0.5})
    before = bytes(setup.device.image)
    result, status, _ = setup.run(node_id=NODE, file=setup.image(2000))
    assert not result.success and status == GoalStatus.STATUS_ABORTED
    assert result.message.startswith('STOPPING failed: no boot-up message within 0.5 s '
                                     'after writing 0 to 0x1F51:1 (parameter '
                                     'program_download.restart_timeout)'), result.message
    assert 'perhaps stopped' in result.message, result.message
    assert control_writes(setup.frames_sent(), NODE) == [STOP], 'a command after the stop'
    assert bytes(setup.device.image) == before


def test_a_device_in_its_bootloader_already_is_not_waited_for_to_restart(rig):
    # Red team: after a failed download left the device in its bootloader, the next one,
    # with restart_timeout set as the failure told, waited for a restart that never came.
    setup = rig(device=dict(restarts_on_stop=0.3),
                **{'program_download.restart_timeout': 60.0})
    setup.device.program_running = False  # 0x1F51:1 reads 0
    path = setup.image(2000)
    result, status, _ = setup.run(node_id=NODE, file=path)
    assert result.success and status == GoalStatus.STATUS_SUCCEEDED, result.message
    assert bytes(setup.device.image) == open(path, 'rb').read()


def test_a_clear_refused_after_the_restart_says_nothing_of_a_restart(
        ros_context, start_durand, tmp_path):
    # Red team: any failed clear after the awaited restart named restart_timeout, although
    # it was set and the device had answered the clear.
    setup = Rig(bootloaders_of(ClearRefusingDevice, start_durand), tmp_path,
                device=dict(restarts_on_stop=0.3),
                **{'program_download.restart_timeout': 5.0})
    try:
        result, _, _ = setup.run(node_id=NODE, file=setup.image(2000))
        assert not result.success and result.abort_code == ABORT_DEVICE_STATE, result
        assert result.message.startswith('CLEARING failed'), result.message
        assert 'restart' not in result.message.split('; the device is left')[0], \
            result.message
    finally:
        setup.close()


def test_a_device_that_restarts_without_answering_the_stop_names_the_parameter(
        ros_context, start_durand, tmp_path):
    start = bootloaders_of(UnansweredStopDevice, start_durand)
    setup = Rig(start, tmp_path, device=dict(restarts_on_stop=0.3))
    try:
        result, _, _ = setup.run(node_id=NODE, file=setup.image(2000))
        assert not result.success
        assert result.message.startswith('STOPPING failed'), result.message
        assert 'program_download.restart_timeout' in result.message, result.message
    finally:
        setup.close()
    # With the parameter, its boot-up is the answer.
    setup = Rig(start, tmp_path, device=dict(restarts_on_stop=0.3),
                **{'program_download.restart_timeout': 5.0})
    try:
        result, status, _ = setup.run(node_id=NODE, file=setup.image(2000))
        assert result.success and status == GoalStatus.STATUS_SUCCEEDED, result.message
        assert control_writes(setup.frames_sent(), NODE) == [STOP, CLEAR, START]
    finally:
        setup.close()


def test_a_boot_download_of_a_device_restarting_when_stopped_logs_the_parameter(
        ros_context, start_durand, tmp_path, caplog):
    # Red team: the boot's download waited the whole flash timeout, then the boot-up it held
    # began a boot that succeeded: the failure and its cure showed nowhere.
    gateway, unit, image = booted(start_durand, tmp_path, device=dict(restarts_on_stop=0.3),
                                  **{'program_download.flash_timeout': 1.0})
    try:
        wait_until(lambda: any('program_download.restart_timeout' in record.getMessage()
                               for record in caplog.records), WAIT,
                   'the failed download logged, naming the parameter')
        wait_until(lambda: bytes(unit.image) == image, WAIT, 'the image stored by a later boot')
    finally:
        gateway.close()


def test_a_device_that_resets_mid_image_fails_the_download_once_and_is_not_started(rig):
    setup = rig(**{'sdo.timeout': 0.5})
    hold = Hold(setup, 3000)
    goal, _ = setup.send(node_id=NODE, file=setup.image())
    assert hold.reached.wait(WAIT)
    setup.device.stop()  # the device disappears mid-image, as a power cut would
    hold.release()
    result, status = setup.result(goal)
    assert not result.success and status == GoalStatus.STATUS_ABORTED, result.message
    assert result.message.startswith('DOWNLOADING failed'), result.message
    assert 'partly written, not started' in result.message, result.message
    assert not control_writes(setup.frames.snapshot(), NODE)[2:], 'a start after the failure'


# Requests that are odd, several at once, and other callers.

@pytest.mark.parametrize('goal, named', [
    (dict(node_id=128), 'node_id 128 is out of range'),
    (dict(program=255), 'program 255 is out of range'),
    (dict(program=2), 'has no 0x1F51:2'),
    (dict(file='DIRECTORY'), 'Is a directory'),
    (dict(file='/dev/null'), 'not a regular file'),
    (dict(expected_software_id=0xFFFFFFFF, node_id=OTHER), 'has no 0x1F51:1'),
])
def test_more_bad_goals_are_refused_naming_the_field_before_anything_is_written(
        rig, goal, named):
    setup = rig()
    fields = {'node_id': NODE, 'file': setup.image(100), **goal}
    if fields['file'] == 'DIRECTORY':
        fields['file'] = str(setup.tmp_path)
    result, status, feedback = setup.run(**fields)
    assert not result.success and status == GoalStatus.STATUS_ABORTED
    assert named in result.message and 'nothing was sent' in result.message, result.message
    assert not feedback, 'a refused goal has no phase'
    frames = setup.frames.snapshot()
    assert not control_writes(frames, NODE) and not image_writes(frames, NODE)
    assert setup.device.program_running


def test_two_goals_for_one_device_sent_together_run_one_download(rig):
    setup = rig()
    hold = Hold(setup, 3000)  # the first download stays under way until both are answered
    path = setup.image()
    goals = [setup.action.send_goal_async(ProgramDownload.Goal(node_id=NODE, file=path))
             for _ in range(2)]
    answers = [wait_for_future(goal, WAIT).get_result_async() for goal in goals]
    assert hold.reached.wait(WAIT)
    wait_until(lambda: any(answer.done() for answer in answers), WAIT, 'one goal answered')
    hold.release()
    results = [wait_for_future(answer, WAIT).result for answer in answers]
    assert sorted(r.success for r in results) == [False, True], [r.message for r in results]
    refused = next(r for r in results if not r.success)
    assert 'being programmed already' in refused.message, refused.message
    assert 'nothing was sent' in refused.message, refused.message
    frames = setup.frames_sent()
    assert control_writes(frames, NODE) == [STOP, CLEAR, START]
    assert len(image_writes(frames, NODE)) == 1
    assert setup.device.starts == 1


def test_two_devices_are_programmed_at_once(ros_context, start_durand, tmp_path):
    channel = new_channel()
    devices = {node_id: start_durand(node_id, kind=BootloaderDevice, channel=channel)
               for node_id in (NODE, THIRD)}
    gateway = Harness({'can.channel': channel, 'simulation.devices': None,
                       'nodes': [NODE, THIRD]})
    action = ActionClient(gateway.client_node, ProgramDownload, '/cbcan/program_download')
    try:
        assert action.wait_for_server(timeout_sec=WAIT)
        wait_until(lambda: all(gateway.node.gateway.monitor.status(n).detected
                               for n in devices), WAIT, 'both devices heard')
        images = {node_id: os.urandom(SMALL) for node_id in devices}
        goals = {}
        for node_id, image in images.items():
            path = tmp_path / f'{node_id}.bin'
            path.write_bytes(image)
            goals[node_id] = action.send_goal_async(ProgramDownload.Goal(
                node_id=node_id, file=str(path), expected_software_id=zlib.crc32(image)))
        for node_id, goal in goals.items():
            handle = wait_for_future(goal, WAIT)
            result = wait_for_future(handle.get_result_async(), WAIT).result
            assert result.success, result.message
            assert bytes(devices[node_id].image) == images[node_id]
            assert devices[node_id].starts == 1
    finally:
        action.destroy()
        gateway.close()


def test_another_callers_sdo_to_the_device_being_programmed_gets_one_answer(rig):
    setup = rig()
    hold = Hold(setup, 3000)
    goal, _ = setup.send(node_id=NODE, file=setup.image())
    assert hold.reached.wait(WAIT)
    read = setup.gateway.call_async('sdo_read', node_id=NODE, index=0x1000, subindex=0)
    hold.release()
    result, _ = setup.result(goal)
    got = wait_for_future(read, WAIT)
    assert result.success, result.message
    # Queued behind the image (answered or timed out there), answered once either way.
    assert got.success or got.message, got
    assert control_writes(setup.frames_sent(), NODE) == [0, 3, 1]


# The bus, the file and the process.

def test_a_bus_that_goes_down_mid_image_ends_the_download_saying_so(
        ros_context, start_durand, tmp_path):
    channel = new_channel()
    faults = FaultController.get(channel)
    setup = Rig.__new__(Rig)
    setup.tmp_path = tmp_path
    setup.frames = Frames(channel)
    setup.device = start_durand(NODE, kind=BootloaderDevice, channel=channel)
    setup.other = start_durand(OTHER, kind=DurandDevice, channel=channel)
    setup.gateway = Harness({'can.interface': 'faulty', 'can.channel': channel,
                             'simulation.devices': None, 'nodes': [NODE, OTHER]})
    setup.core = setup.gateway.node.gateway
    setup.action = ActionClient(setup.gateway.client_node, ProgramDownload,
                                '/cbcan/program_download')
    try:
        assert setup.action.wait_for_server(timeout_sec=WAIT)
        wait_until(lambda: setup.core.monitor.status(NODE).detected, WAIT, 'the device heard')
        hold = Hold(setup, 3000)
        goal, _ = setup.send(node_id=NODE, file=setup.image())
        assert hold.reached.wait(WAIT)
        faults.fail_receive('adapter unplugged')
        faults.fail_send('adapter unplugged')
        wait_until(lambda: not setup.core.bus_status.up, WAIT, 'the bus down')
        hold.release()
        result, _ = setup.result(goal)
        assert not result.success
        assert result.message.startswith('DOWNLOADING failed'), result.message
        assert 'partly written, not started' in result.message, result.message
        assert 'the device ended the download' not in result.message, \
            f'the bus going down is blamed on the device: {result.message}'
    finally:
        faults.clear()
        setup.close()


def test_a_file_changed_after_the_goal_does_not_change_the_image(rig):
    setup = rig()
    hold = Hold(setup, 3000)
    path = setup.image()
    image = open(path, 'rb').read()
    goal, _ = setup.send(node_id=NODE, file=path, expected_software_id=zlib.crc32(image))
    assert hold.reached.wait(WAIT)
    os.remove(path)
    hold.release()
    result, _ = setup.result(goal)
    assert result.success, result.message
    assert bytes(setup.device.image) == image


def test_a_fifo_as_file_is_refused_and_the_goal_answered(rig):
    setup = rig()
    fifo = setup.tmp_path / 'firmware.fifo'
    os.mkfifo(fifo)
    try:
        goal, _ = setup.send(node_id=NODE, file=str(fifo))
        wait_for_future(goal.cancel_goal_async(), WAIT)
        answer = goal.get_result_async()
        finished = threading.Event()
        answer.add_done_callback(lambda _: finished.set())
        assert finished.wait(5.0) or answer.done(), 'the goal was not answered'
        assert not answer.result().result.success
        # ~/node_states is published on its own cycle, so the cleared flag comes a little later.
        wait_until(lambda: not programming(setup), WAIT, 'node states without programming')
    finally:
        # Let the stuck open() return (EOF), so the gateway can close.
        descriptor = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK) if _has_reader(fifo) else None
        if descriptor is not None:
            os.close(descriptor)


def _has_reader(fifo) -> bool:
    try:
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
    except OSError:
        return False
    return True


# At boot.

def test_a_boot_with_the_matching_software_version_downloads_nothing(
        ros_context, start_durand, tmp_path):
    channel = new_channel()
    unit = start_durand(NODE, kind=BootloaderDevice, channel=channel)
    (tmp_path / 'new.bin').write_bytes(os.urandom(SMALL))
    path = bus_file(tmp_path, f"""\
        master:
          node_id: 1
          boot_timeout: 2000
        nodes:
          arm_io:
            node_id: {NODE}
            dcf: device.eds
            software_file: new.bin
            software_version: 0x{unit.software_id:08X}
        """)
    frames = Frames(channel)
    gateway = Harness({'can.channel': channel, 'simulation.devices': None,
                       'bus_config': path, 'program_download.at_boot': True})
    try:
        state = wait_until(lambda: (s := state_of(gateway, NODE)).boots >= 1 and s, WAIT,
                           'the boot of the device ended')
        assert state.state == 'BOOTED', state
        assert 'software updated' not in state.message, state.message
        assert not control_writes(frames.snapshot(), NODE)
        assert not image_writes(frames.snapshot(), NODE)
        assert unit.starts == 0
    finally:
        gateway.close()
        frames.close()


def test_a_boot_with_at_boot_off_sends_no_program_command(ros_context, start_durand,
                                                          tmp_path):
    gateway, unit, _ = booted(start_durand, tmp_path, at_boot=False)
    try:
        state = wait_until(lambda: (s := state_of(gateway, NODE)).boots >= 1 and s, WAIT,
                           'the boot of the device ended')
        assert state.state == 'FAILED' and state.error_status == 'H', state
        assert unit.starts == 0 and unit.program_running
        assert bytes(unit.image) == b'firmware 1.0'
    finally:
        gateway.close()


def test_a_shutdown_during_flashing_answers_the_goal_and_sends_no_start(rig):
    setup = rig(device=dict(flash_time=60.0))
    goal, feedback = setup.send(node_id=NODE, file=setup.image(3000))
    wait_until(lambda: phase_seen(feedback, 'FLASHING'), WAIT, 'the download in FLASHING')
    since = len(setup.frames.snapshot())
    stopping = threading.Thread(target=setup.gateway.node.shut_down_gateway)
    stopping.start()
    result, _ = setup.result(goal)
    stopping.join(WAIT)
    assert not result.success
    assert result.message.startswith('FLASHING failed: the gateway is shutting down'), \
        result.message
    assert not control_writes(setup.frames.snapshot(), NODE, since)
    assert setup.device.starts == 0
    assert LOCAL_CONTROL not in aborts(setup.frames.snapshot(), NODE)


class HeldChecks:
    """Holds the download's first SDO request (the checks, before anything is written).

    ``reached`` is set once the download asks; it goes on after :meth:`release`.
    """

    def __init__(self, service):
        self.reached = threading.Event()
        self._released = threading.Event()
        batch = service._sdo_batch

        def held(accesses, timeout, stop=None):
            if not self.reached.is_set():
                self.reached.set()
                self._released.wait(WAIT)
            return batch(accesses, timeout, stop)
        service._sdo_batch = held

    def release(self) -> None:
        """Let the checks go on."""
        self._released.set()


def test_a_cancel_during_the_checks_writes_nothing_and_says_so(rig):
    setup = rig()
    checks = HeldChecks(setup.core.program)
    goal, feedback = setup.send(node_id=NODE, file=setup.image(2000))
    try:
        assert checks.reached.wait(WAIT)
        response = wait_for_future(goal.cancel_goal_async(), WAIT)
        assert response.goals_canceling, 'the cancel of a running download was rejected'
    finally:
        checks.release()
    result, status = setup.result(goal)
    # CANCELED, as a cancel in any other phase: the CLI then says "cancelled", not "error".
    assert not result.success and status == GoalStatus.STATUS_CANCELED, result.message
    assert 'cancelled by the caller' in result.message, result.message
    assert 'nothing was sent' in result.message, result.message
    frames = setup.frames.snapshot()
    assert not control_writes(frames, NODE) and not image_writes(frames, NODE)
    assert not feedback and setup.device.program_running


def test_a_drive_being_programmed_cannot_be_enabled(ros_context, start_durand, tmp_path):
    axis = DriveRig(start_durand)
    action = ActionClient(axis.gateway.client_node, ProgramDownload,
                          '/cbcan/program_download')
    checks = HeldChecks(axis.gateway.node.gateway.program)
    try:
        assert action.wait_for_server(timeout_sec=WAIT)
        path = tmp_path / 'drive.bin'
        path.write_bytes(b'new drive firmware')
        goal = wait_for_future(action.send_goal_async(
            ProgramDownload.Goal(node_id=DRIVE, file=str(path))), WAIT)
        assert checks.reached.wait(WAIT)
        refused = axis.command('enable', CSV)
        assert not refused.success and 'being programmed' in refused.message, refused.message
        assert axis.drive.drive_state != 'OPERATION_ENABLED'
        checks.release()
        result = wait_for_future(goal.get_result_async(), WAIT).result
        assert not result.success and 'has no 0x1F51:1' in result.message, result.message
        axis.enable(CSV)  # the download over, the drive may be enabled again
    finally:
        checks.release()
        action.destroy()
        axis.close()


def test_ctrl_c_in_the_cli_cancels_the_download_with_an_abort_and_exits_130(
        start_node, start_durand, client_node, tmp_path):
    group, port = private_bus()
    device, holding, released = held_bootloader(start_durand, group, port)
    recorder = BusRecorder(group, port)
    name = f'{namespace()}/cbcan'
    gateway = start_node(arguments(name, '-p', 'can.interface:=udp_multicast',
                                   '-p', f'can.channel:={group}', '-p', f'nodes:=[{NODE}]',
                                   '-p', 'sdo.timeout:=10.0'), port)
    path = tmp_path / 'firmware.bin'
    path.write_bytes(os.urandom(SMALL))
    out, err = tmp_path / 'out.txt', tmp_path / 'err.txt'
    statuses = set()
    client_node.create_subscription(
        GoalStatusArray, f'{name}/program_download/_action/status',
        lambda array: statuses.update(s.status for s in array.status_list),
        QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                   reliability=ReliabilityPolicy.RELIABLE))
    cli = None
    try:
        StateWatcher(client_node, name).wait_for({NODE: 'PRE_OPERATIONAL'}, START_TIMEOUT)
        with open(out, 'w') as stdout, open(err, 'w') as stderr:
            cli = subprocess.Popen([executable('cbcan_cli'), '--gateway', name,
                                    'program-download', str(NODE), str(path)],
                                   stdout=stdout, stderr=stderr, text=True)
        assert holding.wait(START_TIMEOUT), gateway.output()
        cli.send_signal(signal.SIGINT)
        # Once the gateway took the cancel (the goal shows CANCELING), the device goes on:
        # the download ends at its next block.
        wait_until(lambda: GoalStatus.STATUS_CANCELING in statuses, START_TIMEOUT,
                   'the goal CANCELING')
        released.set()
        status = cli.wait(START_TIMEOUT)
    finally:
        released.set()
        if cli is not None and cli.poll() is None:
            cli.kill()
            cli.wait()
        recorder.close()
    printed, errors = out.read_text(), err.read_text()
    assert status == 130, (status, printed, errors, gateway.output())
    assert printed.splitlines()[:3] == ['STOPPING', 'CLEARING', 'DOWNLOADING'], printed
    assert 'cancelled: node 12 program download: DOWNLOADING failed: cancelled by the caller' \
        in errors, errors
    assert 'abort code 0x08000021' in errors, errors
    requests = [message for _, message in recorder.frames
                if message.arbitration_id == SDO_REQUEST + NODE]
    aborted = [n for n, message in enumerate(requests) if message.data[0] == 0x80]
    assert aborted, 'no abort on the bus'
    assert not [m for m in requests[aborted[0] + 1:] if m.data[0] >> 5 in (1, 6)], \
        'a write after the abort'
    assert device.starts == 0 and not device.program_running


class SlowDevice(BootloaderDevice):
    """A bootloader that holds its answer to the stop command, or to 0x1F56 once started.

    ``holding`` is set while it holds; it answers after ``release``.
    """

    def __init__(self, node_id: int, *args, hold: str = 'STOPPING', **options):
        super().__init__(node_id, *args, **options)
        self.hold = hold
        self.holding = threading.Event()
        self.released = threading.Event()

    def _build_dictionary(self, od) -> None:
        super()._build_dictionary(od)
        if self.hold == 'CHECKING':
            od.set_read_callback(0x1F56, 1, self._software_id_held)

    def _software_id_held(self) -> int:
        if self.starts:
            self.holding.set()
            self.released.wait(WAIT)
        return self.software_id

    def _control(self, command: int) -> None:
        if {'STOPPING': STOP, 'CLEARING': CLEAR}.get(self.hold) == command:
            self.holding.set()
            self.released.wait(WAIT)
        super()._control(command)


def slow_rig(start_durand, tmp_path, phase: str) -> Rig:
    """Return a Rig whose bootloader is a SlowDevice holding its answer in ``phase``."""
    def slow(node_id, kind=DurandDevice, **options):
        if kind is BootloaderDevice:
            return start_durand(node_id, kind=SlowDevice, hold=phase, **options)
        return start_durand(node_id, kind=kind, **options)
    return Rig(slow, tmp_path, **{'sdo.timeout': 10.0})


def test_a_cancel_while_the_device_holds_its_stop_answer_ends_in_stopping(
        ros_context, start_durand, tmp_path):
    phase, left = 'STOPPING', 'perhaps stopped'
    setup = slow_rig(start_durand, tmp_path, phase)
    try:
        goal, feedback = setup.send(node_id=NODE, file=setup.image(2000))
        assert setup.device.holding.wait(WAIT)
        wait_until(lambda: phase_seen(feedback, phase), WAIT, f'the feedback of {phase}')
        writes = [STOP]
        wait_until(lambda: control_writes(setup.frames.snapshot(), NODE) == writes, WAIT,
                   'the stop command read back')
        wait_for_future(goal.cancel_goal_async(), WAIT)
        setup.device.released.set()
        result, status = setup.result(goal)
        assert not result.success and status == GoalStatus.STATUS_CANCELED, result.message
        assert result.message.startswith(f'{phase} failed: cancelled by the caller'), \
            result.message
        assert left in result.message, result.message
        assert control_writes(setup.frames.snapshot(), NODE) == writes, \
            'a program control command after the cancel'
    finally:
        setup.device.released.set()
        setup.close()


def test_a_cancel_during_the_check_after_the_start_answers_what_the_device_runs(
        ros_context, start_durand, tmp_path):
    # Nothing is left to stop once the new program runs: the answer is the truth, not
    # "cancelled" (the goal may end SUCCEEDED after its cancel was accepted).
    setup = slow_rig(start_durand, tmp_path, 'CHECKING')
    try:
        goal, feedback = setup.send(node_id=NODE, file=setup.image(2000))
        assert setup.device.holding.wait(WAIT)
        wait_until(lambda: phase_seen(feedback, 'CHECKING'), WAIT, 'the feedback of CHECKING')
        wait_for_future(goal.cancel_goal_async(), WAIT)
        setup.device.released.set()
        result, status = setup.result(goal)
        assert setup.device.starts == 1 and setup.device.program_running
        if result.success:
            assert status == GoalStatus.STATUS_SUCCEEDED
            assert result.software_id == setup.device.software_id, result
        else:
            assert 'written and started' in result.message, result.message
        assert control_writes(setup.frames.snapshot(), NODE) == [0, 3, 1]
    finally:
        setup.device.released.set()
        setup.close()


def test_a_shutdown_while_the_device_holds_its_clear_answer_answers_the_goal_once(
        ros_context, start_durand, tmp_path):
    # The clear is waited for longer than the shutdown waits for downloads (STOP_WAIT): the
    # channel's close must end it, and nothing but an abort may follow.
    setup = slow_rig(start_durand, tmp_path, 'CLEARING')
    try:
        goal, _ = setup.send(node_id=NODE, file=setup.image(2000))
        assert setup.device.holding.wait(WAIT)
        wait_until(lambda: CLEAR in control_writes(setup.frames.snapshot(), NODE), WAIT,
                   'the clear command read back')
        since = len(setup.frames.snapshot())
        stopping = threading.Thread(target=setup.gateway.node.shut_down_gateway)
        stopping.start()
        result, _ = setup.result(goal)
        setup.device.released.set()
        stopping.join(WAIT)
        assert not result.success
        assert result.message.startswith('CLEARING failed'), result.message
        assert 'shutting down' in result.message, result.message
        assert 'stopped and perhaps cleared, not started' in result.message, result.message
        later = requests_to(setup.frames.snapshot(), NODE, since)
        assert all(frame.data[0] == 0x80 for frame in later), \
            [bytes(frame.data).hex() for frame in later]
        assert not image_writes(setup.frames.snapshot(), NODE)
    finally:
        setup.device.released.set()
        setup.close()


def test_after_a_gateway_killed_mid_image_a_new_gateway_programs_the_device(
        start_node, start_durand, client_node, tmp_path):
    # SIGKILL: no abort can go out; the device keeps a half-written block transfer. The next
    # gateway's download must still work (no answer waited for forever, the image whole).
    group, port = private_bus()
    device, holding, released = held_bootloader(start_durand, group, port)
    parameters = ('-p', 'can.interface:=udp_multicast', '-p', f'can.channel:={group}',
                  '-p', f'nodes:=[{NODE}]')
    path = tmp_path / 'firmware.bin'
    image = os.urandom(SMALL)
    path.write_bytes(image)
    first = f'{namespace()}/cbcan'
    gateway = start_node(arguments(first, *parameters), port)
    try:
        StateWatcher(client_node, first).wait_for({NODE: 'PRE_OPERATIONAL'}, START_TIMEOUT)
        action = ActionClient(client_node, ProgramDownload, f'{first}/program_download')
        assert action.wait_for_server(timeout_sec=START_TIMEOUT)
        action.send_goal_async(ProgramDownload.Goal(node_id=NODE, file=str(path)))
        assert holding.wait(START_TIMEOUT), gateway.output()
        gateway.process.kill()
        gateway.process.wait(STOP_TIMEOUT)
    finally:
        released.set()
    second = f'{namespace()}/cbcan'
    start_node(arguments(second, *parameters), port)
    StateWatcher(client_node, second).wait_for({NODE: 'PRE_OPERATIONAL'}, START_TIMEOUT)
    action = ActionClient(client_node, ProgramDownload, f'{second}/program_download')
    assert action.wait_for_server(timeout_sec=START_TIMEOUT)
    goal = wait_for_future(action.send_goal_async(ProgramDownload.Goal(
        node_id=NODE, file=str(path), expected_software_id=zlib.crc32(image))), START_TIMEOUT)
    result = wait_for_future(goal.get_result_async(), START_TIMEOUT).result
    assert result.success, result.message
    assert bytes(device.image) == image and device.starts == 1


def test_a_goal_for_a_device_whose_boot_is_downloading_is_refused_before_anything_is_sent(
        ros_context, start_durand, tmp_path):
    # The boot's own download (software_file, program_download.at_boot) is a download of
    # that device too: one per device, so a user's goal meanwhile must be refused.
    gateway, unit, image = booted(start_durand, tmp_path, device=dict(flash_time=60.0))
    action = ActionClient(gateway.client_node, ProgramDownload, '/cbcan/program_download')
    try:
        assert action.wait_for_server(timeout_sec=WAIT)
        wait_until(lambda: len(unit.image) == len(image) and unit._busy(), WAIT,
                   "the boot's download flashing")
        other = tmp_path / 'user.bin'
        other.write_bytes(os.urandom(1000))
        starts, running = unit.starts, unit.program_running
        goal = wait_for_future(action.send_goal_async(
            ProgramDownload.Goal(node_id=NODE, file=str(other))), WAIT)
        result = wait_for_future(goal.get_result_async(), WAIT).result
        assert not result.success
        assert 'nothing was sent' in result.message, \
            f"a download began during the boot's download: {result.message}"
        assert unit.starts == starts and unit.program_running == running
    finally:
        action.destroy()
        gateway.close()


@pytest.mark.parametrize('size', [1, 4, 7, 889])
def test_tiny_and_odd_sized_images_are_stored_byte_for_byte(rig, size):
    setup = rig()
    path = setup.image(size)
    image = open(path, 'rb').read()
    result, _, feedback = setup.run(node_id=NODE, file=path,
                                    expected_software_id=zlib.crc32(image))
    assert result.success, result.message
    assert bytes(setup.device.image) == image
    downloading = [m for m in feedback if m.phase == 'DOWNLOADING']
    assert downloading[-1].bytes_sent == downloading[-1].bytes_total == size


def test_after_a_cancel_diagnostics_and_node_states_no_longer_show_programming(rig):
    setup = rig(diagnostics_period=0.1)
    diagnostics = DiagnosticsRecorder(setup.gateway.client_node)
    hold = Hold(setup, 3000)
    goal, _ = setup.send(node_id=NODE, file=setup.image())
    assert hold.reached.wait(WAIT)
    diagnostics.wait_for(f'cbcan: node {NODE}', DiagnosticStatus.WARN, WAIT,
                         lambda shown: shown.get('Program download') == 'DOWNLOADING')
    wait_for_future(goal.cancel_goal_async(), WAIT)
    result, status = setup.result(goal)
    assert status == GoalStatus.STATUS_CANCELED, result.message
    wait_until(lambda: not programming(setup), WAIT, 'node states without programming')
    diagnostics.wait_for(f'cbcan: node {NODE}', DiagnosticStatus.OK, WAIT,
                         lambda shown: 'Program download' not in shown)


def test_a_bus_description_whose_software_file_is_a_fifo_is_refused_at_start(
        ros_context, start_durand, tmp_path):
    channel = new_channel()
    unit = start_durand(NODE, kind=BootloaderDevice, channel=channel)
    os.mkfifo(tmp_path / 'new.bin')
    path = bus_file(tmp_path, f"""\
        master:
          node_id: 1
          boot_timeout: 2000
        nodes:
          arm_io:
            node_id: {NODE}
            dcf: device.eds
            software_file: new.bin
            software_version: 0x{unit.software_id ^ 1:08X}
        """)
    with pytest.raises(PlanError, match='software_file: .* is not a readable file'):
        Harness({'can.channel': channel, 'simulation.devices': None, 'bus_config': path,
                 'program_download.at_boot': True})


def test_a_boot_up_mid_download_starts_no_boot_into_the_device_being_programmed(
        ros_context, start_durand, tmp_path):
    # A boot-up heard while the device is being programmed (its watchdog reset it, or another
    # master's NMT): the boot of the bus description must not configure and start (NMT) a
    # device whose program is cleared and not yet started while the download owns it, nor
    # after that download failed, leaving the program not whole.
    path = bus_file(tmp_path, f"""\
        master:
          node_id: 1
          boot_timeout: 2000
        nodes:
          arm_io:
            node_id: {NODE}
            dcf: device.eds
        """)
    setup = Rig(start_durand, tmp_path, device=dict(flash_time=60.0),
                **{'bus_config': path, 'program_download.flash_timeout': 60.0})
    try:
        wait_until(lambda: state_of(setup.gateway, NODE).boots >= 1, WAIT, 'the first boot')
        boots = state_of(setup.gateway, NODE).boots
        goal, feedback = setup.send(node_id=NODE, file=setup.image(3000))
        wait_until(lambda: phase_seen(feedback, 'FLASHING'), WAIT, 'the download in FLASHING')
        since = len(setup.frames.snapshot())
        run = setup.core.program._runs[NODE]
        setup.frames.send(0x700 + NODE, b'\x00')  # a boot-up of the device
        wait_until(lambda: run.boot_ups, WAIT, 'the boot-up heard by the gateway')

        def flash_polls() -> list:
            return [frame for frame in setup.frames.snapshot()[since:]
                    if frame.arbitration_id == 0x600 + NODE
                    and bytes(frame.data[:4]) == bytes([0x40, 0x57, 0x1F, 1])]
        polled = len(flash_polls())
        wait_until(lambda: len(flash_polls()) > polled, WAIT, 'a poll of the flash after it')
        assert state_of(setup.gateway, NODE).boots == boots, 'booted while being programmed'
        wait_for_future(goal.cancel_goal_async(), WAIT)
        setup.result(goal)  # the download ended: the boot held for it runs now
        wait_until(lambda: state_of(setup.gateway, NODE).boots > boots, WAIT,
                   'the boot held for the download, once it ended')
        frames = setup.frames.snapshot()[since:]
        polls = [n for n, frame in enumerate(frames) if frame.arbitration_id == 0x600 + NODE
                 and bytes(frame.data[:4]) == bytes([0x40, 0x57, 0x1F, 1])]
        starts = [n for n, frame in enumerate(frames) if frame.arbitration_id == 0
                  and bytes(frame.data[:2]) == bytes([1, NODE])]
        assert polls, 'the flash status was not polled after the boot-up'
        assert not starts, 'NMT start of a device whose download was cancelled in FLASHING'
        # The program is not whole (flashing not confirmed): its boot says so, and waits for
        # a download that mends it.
        wait_until(lambda: state_of(setup.gateway, NODE).state == 'FAILED', WAIT,
                   'the held boot failed')
        failed = state_of(setup.gateway, NODE)
        assert failed.error_status == 'I', failed
        assert 'program download' in failed.message and 'FLASHING' in failed.message, failed
        assert 'not started' in failed.message, failed
    finally:
        setup.close()


class StartRefusingDevice(BootloaderDevice):
    """A bootloader that refuses to start the new program (0x1F51:1 = 1 aborted)."""

    def _control(self, command: int) -> None:
        if command == START:
            raise SDODomainAbort(ABORT_DEVICE_STATE, (PROGRAM_CONTROL, 1))
        super()._control(command)


def test_a_refused_start_fails_in_starting_with_the_devices_abort_code(
        ros_context, start_durand, tmp_path):
    def refusing(node_id, kind=DurandDevice, **options):
        kind = StartRefusingDevice if kind is BootloaderDevice else kind
        return start_durand(node_id, kind=kind, **options)
    setup = Rig(refusing, tmp_path)
    try:
        result, status, _ = setup.run(node_id=NODE, file=setup.image(2000))
        assert not result.success and status == GoalStatus.STATUS_ABORTED
        assert result.message.startswith('STARTING failed: writing 1 to 0x1F51:1 failed'), \
            result.message
        assert control_writes(setup.frames.snapshot(), NODE) == [STOP, CLEAR, START]
        assert result.abort_code == ABORT_DEVICE_STATE, result
    finally:
        setup.close()


def test_a_flash_busy_past_its_timeout_fails_in_flashing_and_sends_no_start(rig):
    setup = rig(device=dict(flash_time=120.0), **{'program_download.flash_timeout': 0.5})
    result, status, _ = setup.run(node_id=NODE, file=setup.image(2000))
    assert not result.success and status == GoalStatus.STATUS_ABORTED
    assert result.message.startswith('FLASHING failed: the flash was still busy'), \
        result.message
    assert 'program_download.flash_timeout' in result.message, result.message
    assert result.flash_status == 1, result
    assert control_writes(setup.frames.snapshot(), NODE) == [STOP, CLEAR]
    assert setup.device.starts == 0


class WithoutSoftwareId(BootloaderDevice):
    """A bootloader that answers every read of 0x1F56:1 with an abort (it has none)."""

    def _build_dictionary(self, od) -> None:
        super()._build_dictionary(od)

        def unreadable() -> int:
            raise RuntimeError('no software identification')
        od.set_read_callback(0x1F56, 1, unreadable)


def test_a_program_whose_id_cannot_be_read_is_not_said_to_run_id_0(
        ros_context, start_durand, tmp_path):
    def device(node_id, kind=DurandDevice, **options):
        return start_durand(node_id, kind=WithoutSoftwareId if kind is BootloaderDevice
                            else kind, **options)
    setup = Rig(device, tmp_path)
    try:
        result, status, _ = setup.run(node_id=NODE, file=setup.image())
        assert result.success and status == GoalStatus.STATUS_SUCCEEDED, result.message
        assert 'started, its software id not read (0x1F56:1: ' in result.message, \
            result.message
        assert result.software_id == 0
    finally:
        setup.close()
