"""Enabling never starts a motion: the drive enters OPERATION_ENABLED holding its axis.

The installed ``cbcan_node`` runs as a child process on a udp_multicast bus of its own; the
simulated CiA 402 drive (durand) lives in this process (``test_drive_safety``'s rig). Targets
left in the drive from before (another master, an earlier run, a power-on default) must not
be what the drive takes when it enters OPERATION_ENABLED: the gateway sets the target of the
mode that holds the axis (velocity 0, torque the hold torque, position the actual one) before
or with the controlword that enables it, on every PDO layout real drives ship, with
synchronous RPDOs too, from every state enable starts in.
"""

from dataclasses import replace
import itertools
import struct
import threading

import pytest
from std_msgs.msg import Float64
from test_drive_layouts import writes_on_the_bus
import test_drive_safety
from test_drive_safety import ANSWER, DriveRig, NODE, RPDOS, shown, VELOCITY, velocity_in_units

from cbcan_ros.core.pdo.sync import SYNC_COB_ID
from cbcan_ros.simulation.cia402_states import State
from cbcan_ros.simulation.durand.drive_objects import PROFILE_ACCELERATION
from cbcan_ros.simulation.durand.drive_pdos import default_drive_pdos
from cbcan_ros.simulation.durand.drive_pdos import drive_pdos as layout_pdos
from cbcan_ros.simulation.simulated_drives import LAYOUTS
from cbcan_ros.srv import SdoWrite

from conftest import wait_until
from node_process import call

PP, PV, PT, CSP, CSV, CST = 1, 3, 4, 8, 9, 10
MODE, CONTROLWORD = 0x6060, 0x6040
TARGET_POSITION, TARGET_VELOCITY, TARGET_TORQUE = 0x607A, 0x60FF, 0x6071
TARGET_OF_MODE = {PP: TARGET_POSITION, CSP: TARGET_POSITION, PV: TARGET_VELOCITY,
                  CSV: TARGET_VELOCITY, PT: TARGET_TORQUE, CST: TARGET_TORQUE}
SDO_REQUEST = 0x600 + NODE


def synchronous(layout: str) -> tuple:
    """Return ``layout`` with every RPDO synchronous (type 1)."""
    if layout == 'combined':
        return default_drive_pdos(transmission_type=1)
    return tuple(replace(pdo, transmission_type=1) if pdo.kind == 'rpdo' and pdo.enabled
                 else pdo for pdo in layout_pdos(layout))


rig = test_drive_safety.rig  # the node as a child process, the drive here (a fixture)


def entries_to_operation_enabled(drive) -> list:
    """Record the drive's mode and targets each time it enters OPERATION_ENABLED."""
    seen = []
    enter = drive._enter

    def entering(state) -> None:
        if state is State.OPERATION_ENABLED:
            read = drive._read
            seen.append({'mode': read(MODE), 'position': read(0x6064), **{
                index: read(index) for index in (TARGET_POSITION, TARGET_VELOCITY,
                                                 TARGET_TORQUE)}})
        enter(state)
    drive._enter = entering
    return seen


def halt_releases(drive) -> list:
    """Record the drive's velocity each time its halt is released (at its first cycle)."""
    released, halted = [], [False]
    move = drive._move

    def moving(elapsed: float) -> None:
        if halted[0] and not drive._halted:
            released.append(drive._velocity)
        halted[0] = drive._halted
        move(elapsed)
    drive._move = moving
    return released


def leave_stale_targets(drive) -> None:
    """Put targets in the drive as another master would have left them."""
    position = drive.position
    drive.set_value(TARGET_VELOCITY, 0, struct.pack('<i', 5000))
    drive.set_value(TARGET_TORQUE, 0, struct.pack('<h', 77))
    drive.set_value(TARGET_POSITION, 0, struct.pack('<i', position + 5000))


# The controlword of the first step of an enable from each state it starts in.
FIRST_STEP = {'SWITCH_ON_DISABLED': 0x06, 'READY_TO_SWITCH_ON': 0x07, 'SWITCHED_ON': 0x0F,
              'fault reset': 0x06}


def bring_to(axis: DriveRig, start: str, with_sync: bool) -> None:
    """Bring the disabled drive to the state ``start`` that an enable starts from.

    ``with_sync``: the gateway produces SYNC.
    """
    if start == 'fault reset':
        axis.drive.inject_fault(0x2310)
        wait_until(lambda: axis.latest().state == 'FAULT', ANSWER, 'drive_state FAULT')
        reset = axis.command('fault_reset')
        assert reset.success, reset.message
        return
    words = {'READY_TO_SWITCH_ON': [0x06], 'SWITCHED_ON': [0x06, 0x07]}.get(start, [])
    if words and with_sync:
        # The gateway's disable goes again after the next SYNC and is applied at the one
        # after (``PdoService.carry``): another master's steps before that would be undone.
        since = axis.recorder.mark()
        for _ in range(2):
            since = axis.recorder.first(lambda m: m.arbitration_id == SYNC_COB_ID, 'a SYNC',
                                        since) + 1
    for word in words:  # another master's steps
        axis.drive.set_value(CONTROLWORD, 0, struct.pack('<H', word))
    if words:
        wait_until(lambda: axis.latest().state == start, ANSWER, f'drive_state {start}')


VARIANTS = [(layout, False) for layout in LAYOUTS] + [('combined', True), ('vendor', True)]


@pytest.mark.parametrize('layout, sync', VARIANTS,
                         ids=[f'{name}{"-sync" if sync else ""}' for name, sync in VARIANTS])
def test_enable_holds_the_axis_whatever_targets_the_drive_was_left_with(rig, layout, sync):
    parameters = ['-p', 'drives.command_timeout:=0.0']
    with_sync = sync or layout == 'ros2_canopen'  # its TPDOs are synchronous
    if with_sync:
        parameters += ['-p', 'sync.period:=0.01']
    axis = rig(*parameters, pdos=synchronous(layout) if sync else layout_pdos(layout))
    axis.wait_state('SWITCH_ON_DISABLED')
    axis.nmt_start()
    entries = entries_to_operation_enabled(axis.drive)
    starts = itertools.cycle(['SWITCH_ON_DISABLED', 'READY_TO_SWITCH_ON', 'SWITCHED_ON',
                              'fault reset'])
    # Each mode twice: from another mode, then in that mode already.
    for mode, start in zip([PV, PV, CST, CST, CSP, CSP, PP, PP, CSV, CSV, PT, PT], starts,
                           strict=False):
        leave_stale_targets(axis.drive)
        bring_to(axis, start, with_sync)
        since, count = axis.recorder.mark(), len(entries)
        enabled = axis.command('enable', mode)
        axis.recorder.mark()
        assert enabled.success, enabled.message
        entry = entries[count]
        index = TARGET_OF_MODE[mode]
        holding = entry['position'] if index == TARGET_POSITION else 0
        frames = axis.recorder.messages(since)
        assert (entry['mode'], entry[index]) == (mode, holding), (
            f'enable {mode} from {start}: the drive entered OPERATION_ENABLED with {entry}; '
            f'frames: {shown(frames)}')
        # On the bus: the holding target in the first step's write or before it, never after
        # its controlword (the frames of a write in order, the controlword's last).
        writes = writes_on_the_bus(frames, layout)
        step = next(number for number, values in enumerate(writes)
                    if values.get(CONTROLWORD) == FIRST_STEP[start])
        assert any(values.get(index) == holding for values in writes[:step + 1]), (
            f'enable {mode} from {start}: the first step went before the holding target; '
            f'writes: {writes}')
        assert axis.command('disable').success


# Once a defect: the gateway kept the mode it had last written itself (or read when it first
# heard the drive) as the value of 0x6060 its frames carry. After the mode was changed
# another way (its own sdo_write, another master, a tool), enable found the drive in the
# mode asked for, sent no mode, and the RPDO that maps the controlword next to 0x6060 put the
# old mode back with the first step: the drive entered OPERATION_ENABLED in CSV at the
# velocity its last stream had left in 0x60FF, and ran; enable answered success "in CSV".
@pytest.mark.parametrize('layout', ['combined', 'ros2_canopen'])
@pytest.mark.parametrize('by', ['sdo_write', 'another master'])
def test_enable_in_the_mode_set_another_way_keeps_that_mode_and_starts_no_motion(rig, layout,
                                                                                 by):
    axis = rig('-p', 'drives.command_timeout:=0.0', '-p', 'sync.period:=0.01',
               pdos=layout_pdos(layout))
    axis.enable_moving()  # CSV at VELOCITY: 0x60FF holds it from now on
    # The gateway writes by RPDO once it has heard the drive OPERATIONAL.
    axis.recorder.first(lambda m: m.arbitration_id in RPDOS, 'a target in an RPDO')
    axis.stop_streams()
    assert axis.command('disable').success
    axis.drive_reaches(lambda drive: drive.velocity == 0, 'the disabled drive standing')
    if by == 'sdo_write':
        written = call(axis.client(SdoWrite, 'sdo_write'), SdoWrite.Request(
            node_id=NODE, index=MODE, subindex=0, data=list(struct.pack('<b', PP))),
            'sdo_write 0x6060', axis.node)
        assert written.success, written.message
    else:  # an expedited SDO download of one byte from another client on the bus
        axis.recorder.send(SDO_REQUEST, struct.pack('<BHBb3x', 0x2F, MODE, 0, PP))
    wait_until(lambda: axis.latest().mode == PP, ANSWER, 'drive_state showing PP')
    assert axis.drive._read(TARGET_VELOCITY) == VELOCITY  # left from the stream
    entries = entries_to_operation_enabled(axis.drive)
    since = axis.recorder.mark()
    enabled = axis.command('enable', PP)
    axis.recorder.mark()
    assert enabled.success, enabled.message
    assert [(entry['mode'], entry[TARGET_VELOCITY]) for entry in entries] == [(PP, VELOCITY)], (
        f'the drive entered OPERATION_ENABLED with {entries}, answered {enabled.message!r}; '
        f'frames: {shown(axis.recorder.messages(since))}')
    assert enabled.mode == PP
    assert axis.drive.velocity == 0


# Once a defect: before a mode change, the holding target goes in a write of its own, and in
# an RPDO that maps the controlword too (make run's RPDO 1, every RPDO of the vendor layout)
# that write repeats the controlword the gateway commanded last: "enable operation", from
# before the drive stopped by itself. The drive took it as transition 16 and was
# OPERATION_ENABLED again in CSV, running at the velocity the stream had left in 0x60FF,
# before the mode change came; enable answered success in CSP, set_mode in CSP.
@pytest.mark.parametrize('layout', ['combined', 'vendor'])
@pytest.mark.parametrize('command', ['enable', 'set_mode'])
def test_a_mode_change_of_a_drive_that_quick_stopped_by_itself_starts_no_motion(rig, layout,
                                                                                command):
    # The drive stops by itself (its quick-stop input) while streaming in CSV and stays in
    # QUICK_STOP_ACTIVE (0x605A 6), where a controlword "enable operation" takes it back to
    # OPERATION_ENABLED (CiA 402 transition 16) in the mode it is in, on the target it holds.
    axis = rig('-p', 'drives.command_timeout:=0.0', pdos=layout_pdos(layout))
    axis.drive.set_value(0x605A, 0, struct.pack('<h', 6))
    axis.enable_moving()
    axis.recorder.first(lambda m: m.arbitration_id in RPDOS, 'a target in an RPDO')
    axis.stop_streams()

    def stopped_by_itself() -> bool:
        if axis.drive.drive_state == 'OPERATION_ENABLED':  # again, by a target still coming
            axis.drive.set_value(CONTROLWORD, 0, struct.pack('<H', 0x02))  # its quick stop
        return (axis.drive.drive_state == axis.latest().state == 'QUICK_STOP_ACTIVE'
                and axis.drive.velocity == 0)
    wait_until(stopped_by_itself, ANSWER, 'the drive standing in QUICK_STOP_ACTIVE, shown')
    entries = entries_to_operation_enabled(axis.drive)
    since = axis.recorder.mark()
    answer = axis.command(command, CSP)
    axis.recorder.mark()
    assert answer.success, answer.message
    expected = [(CSP, 0)] if command == 'enable' else []
    assert [(entry['mode'], entry[TARGET_POSITION] - entry['position'])
            for entry in entries] == expected, (
        f'the drive entered OPERATION_ENABLED with {entries}, answered {answer.message!r}; '
        f'frames: {shown(axis.recorder.messages(since))}')
    if command == 'set_mode':
        assert axis.drive.drive_state == 'QUICK_STOP_ACTIVE'



# Once a defect (a red team's finding, read in the code): an enable of an axis still braking
# from a halt waited half a second, then held it at the position read then and released the
# halt. A drive that ramps its halt in CSP stopped short of the ramp's end, at speed, and ran
# back to that position. Then, for a few hours, a velocity (0x606C) that read 0 counted as
# standing: a drive without 0x606F whose velocity unit is coarse (rpm against an encoder's
# counts) was released at 907-965 counts/s (a red team's, 3 of 3).
@pytest.mark.parametrize('velocity_unit', [1, 2000], ids=['counts', 'coarse'])
def test_an_enable_of_an_axis_braking_from_a_halt_releases_it_standing(rig, velocity_unit):
    axis = rig('-p', 'drives.command_timeout:=0.0', pdos=layout_pdos('combined'))
    drive = axis.drive
    velocity_in_units(drive, velocity_unit)
    axis.wait_state('SWITCH_ON_DISABLED')
    axis.nmt_start()
    assert axis.command('enable', CSP).success
    wait_until(lambda: axis.publisher.get_subscription_count() > 0, ANSWER, 'a subscriber')
    drive.set_value(PROFILE_ACCELERATION, 0, struct.pack('<I', 1000))  # 1.5 s from VELOCITY
    released = halt_releases(drive)
    stop = threading.Event()

    def run_ahead() -> None:  # CSP set-points VELOCITY counts/s ahead, until halted
        position = float(drive.position)
        while not stop.wait(0.01):
            position += VELOCITY * 0.01
            axis.publisher.publish(Float64(data=position))
    streaming = threading.Thread(target=run_ahead)
    streaming.start()
    halting = []
    try:
        axis.drive_reaches(lambda drive: drive._velocity > 1000, 'the axis running in CSP')
        halter = threading.Thread(target=lambda: halting.append(axis.command('halt')))
        halter.start()
        axis.drive_reaches(lambda drive: drive._halted and abs(drive._velocity) < 1000,
                           'the axis braking')
        stop.set()
        enabled = axis.command('enable', CSP)
        halter.join()
    finally:
        stop.set()
        streaming.join()
    assert enabled.success, enabled.message
    wait_until(lambda: released, ANSWER, "the drive's first cycle with the halt released")
    assert abs(released[0]) <= 100, f'released at velocity {released[0]}'


# Red team 17 (R17-3): a halt sent while an enable waits for a braking axis to stand was
# refused with "needs a fresh enable: call drive_command enable first", the enable being the
# very request under way. It is refused still (the enable takes the drive over), saying so.
def test_a_halt_while_an_enable_waits_for_the_axis_says_an_enable_is_under_way(rig):
    axis = rig('-p', 'drives.command_timeout:=0.0', pdos=layout_pdos('combined'))
    drive = axis.drive
    axis.wait_state('SWITCH_ON_DISABLED')
    axis.nmt_start()
    assert axis.command('enable', CSV).success
    wait_until(lambda: axis.publisher.get_subscription_count() > 0, ANSWER, 'a subscriber')
    drive.set_value(PROFILE_ACCELERATION, 0, struct.pack('<I', 1000))  # 1.5 s from VELOCITY
    axis.publisher.publish(Float64(data=float(VELOCITY)))
    axis.drive_reaches(lambda drive: drive._velocity == VELOCITY, 'the axis running in CSV')
    answers = {}
    halter = threading.Thread(target=lambda: answers.update(halt=axis.command('halt')))
    halter.start()
    axis.drive_reaches(lambda drive: drive._halted and drive._velocity < VELOCITY,
                       'the axis braking')
    enabler = threading.Thread(target=lambda: answers.update(enable=axis.command('enable')))
    enabler.start()
    wait_until(lambda: 'halt' in answers, ANSWER, 'the halt replaced by the enable')
    refused = axis.command('halt')
    braking = drive._velocity
    enabler.join()
    halter.join()
    assert braking > 0, 'the axis stood before the second halt: nothing tested'
    assert not refused.success and 'is being enabled' in refused.message, refused.message
    assert answers['enable'].success, answers['enable'].message
    halted = axis.command('halt')
    assert halted.success, halted.message

