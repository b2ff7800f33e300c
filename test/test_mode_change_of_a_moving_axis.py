"""A mode change of a moving axis brings it to a stand first, and holds it there in the new mode.

The new mode's holding target (in CSP the position) is read once the axis stands: read while
it moves, it is where the axis was, and the drive entering CSP runs back to it. No target of
the old mode is taken as one of the new while the mode changes; a change that fails leaves
the axis halted in its old mode, and only a fresh enable (which holds it where it stands)
goes on. The installed ``cbcan_node`` runs as a child process, the simulated drive in this
process (``test_drive_safety``'s rig). That no target is taken while the mode changes is
tested in ``test_drives``, whose gateway runs in this process.
"""

import struct
import threading
from typing import Callable

import pytest
from rclpy.action import ActionClient
import test_drive_safety
from test_drive_safety import ANSWER, COMMAND_TIMEOUT, DriveRig, NODE, VELOCITY, velocity_in_units
from test_enable_holds_the_axis import halt_releases, synchronous

from cbcan_ros.action import DriveMove
from cbcan_ros.core.drives.commands import STILL_SPAN
from cbcan_ros.simulation.cia402_states import State
from cbcan_ros.simulation.durand.device import DurandDevice
from cbcan_ros.simulation.durand.drive_objects import PROFILE_ACCELERATION
from cbcan_ros.simulation.durand.drive_pdos import drive_pdos as layout_pdos

from conftest import wait_for_future, wait_until

PP, PV, CSP, CSV = 1, 3, 8, 9
MODE, TARGET_POSITION, CONTROLWORD, POSITION_WINDOW = 0x6060, 0x607A, 0x6040, 0x6067
TARGET_VELOCITY = 0x60FF
QUICK_STOP_OPTION = 0x605A
# A braking ramp that takes 1.5 s from the rig's VELOCITY (1500 counts/s): longer than the
# half second the gateway once waited before it went on, moving.
LONG_RAMP = 1000
# The simulated drive's position window (0x6067), counts: an axis moving less than this in
# STILL_SPAN stands, for the gateway (a velocity read may jitter around 0 for good).
WINDOW = 10


rig = test_drive_safety.rig  # the node as a child process, the drive here (a fixture)


def moving_in_csv(rig, layout: str, ramp: int = 0, window: int = WINDOW) -> DriveRig:
    """Return a rig whose axis runs in CSV at VELOCITY with no stream.

    ``layout``: one of ``simulated_drives.LAYOUTS``, with ``-sync`` its RPDOs synchronous
    and the gateway producing SYNC; ``ramp``: its 0x6083 (the simulated drive brakes a halt
    with it); ``window``: its 0x6067.
    """
    name, sync = layout.removesuffix('-sync'), layout.endswith('-sync')
    axis = rig('-p', 'drives.command_timeout:=0.0',
               *(('-p', 'sync.period:=0.01') if sync else ()),
               pdos=synchronous(name) if sync else layout_pdos(name))
    axis.drive.set_value(POSITION_WINDOW, 0, struct.pack('<I', window))
    axis.enable_moving()
    axis.stop_streams()  # 0x60FF holds VELOCITY: the axis runs on
    if ramp:
        axis.drive.set_value(PROFILE_ACCELERATION, 0, struct.pack('<I', ramp))
    return axis


def speeds_of(drive) -> list:
    """Record the drive's speed (|velocity|) at each of its cycles from now on."""
    speeds = []
    move = drive._move

    def moving(elapsed: float) -> None:
        move(elapsed)
        speeds.append(abs(drive._velocity))
    drive._move = moving
    return speeds


def never_faster(speeds: list) -> None:
    """Fail if the axis sped up between two cycles (braking, it only slows)."""
    faster = [(a, b) for a, b in zip(speeds, speeds[1:], strict=False) if b > a + 1]
    assert not faster, f'the axis sped up again: {faster[:5]}'


def entering_csp(drive) -> list:
    """Record (velocity, target - position) at the drive's first cycle in CSP."""
    entering = []
    move = drive._move

    def moving(elapsed: float) -> None:
        if drive._read(MODE) == CSP and not entering:
            entering.append((drive._velocity, drive._read(TARGET_POSITION) - drive._position))
        move(elapsed)
    drive._move = moving
    return entering


def mover(axis: DriveRig):
    """Return ``goal(position, velocity=500)``: send a ``~/move`` goal, return its handle."""
    client = ActionClient(axis.client_node, DriveMove, f'{axis.name}/move')
    assert client.wait_for_server(timeout_sec=ANSWER)

    def goal(position: float, velocity: float = 500.0):
        handle = wait_for_future(client.send_goal_async(DriveMove.Goal(
            node_id=NODE, position=position, velocity=velocity)), ANSWER)
        assert handle.accepted
        return handle
    return goal


def during_the_braking(axis: DriveRig, first: tuple, then: Callable):
    """Call ``first`` (command, mode); once the axis brakes for it, ``then()``.

    Return their answers and the axis's velocity as ``then`` returned.
    """
    answers = []
    thread = threading.Thread(target=lambda: answers.append(axis.command(*first)))
    thread.start()
    try:
        axis.drive_reaches(lambda drive: abs(drive.velocity) < 1400, 'the axis braking')
        later = then()
        velocity = axis.drive.velocity
    finally:
        thread.join()
    return answers[0], later, velocity


# Once a defect (a red team's): a mode change of an axis moving in CSV read where it stood by
# SDO, then sent that as the CSP target and the mode: the axis had moved on meanwhile (270 ms
# once, on a busy machine), and the drive entering CSP ran back to where it had been. Then,
# with the axis halted first, a braking ramp longer than half a second was cut short: the
# drive entered CSP at two thirds of its speed (9 of 9 runs); and with a wide position window
# (0x6067 100000), an axis at nearly full speed moved less than it in 0.1 s and passed as
# standing (12 of 12).
@pytest.mark.parametrize('ramp, window', [(0, WINDOW), (LONG_RAMP, WINDOW), (LONG_RAMP, 100000)],
                         ids=['at-once', 'long-ramp', 'long-ramp-wide-window'])
@pytest.mark.parametrize('layout', ['combined', 'vendor', 'vendor-sync'])
@pytest.mark.parametrize('command', ['enable', 'set_mode'])
def test_a_mode_change_of_a_moving_axis_holds_it_where_it_stood(rig, layout, command, ramp,
                                                                 window):
    axis = moving_in_csv(rig, layout, ramp, window)
    entering = entering_csp(axis.drive)
    answer = axis.command(command, CSP)
    assert answer.success, answer.message
    assert (answer.state, answer.mode) == ('OPERATION_ENABLED', CSP)
    wait_until(lambda: entering, ANSWER, 'a cycle of the drive in CSP')
    velocity, behind = entering[0]
    assert abs(velocity) <= WINDOW / STILL_SPAN and abs(behind) <= WINDOW, (
        f'the axis entered CSP at velocity {velocity}, its target {behind:+.1f} from where '
        f'it stood')
    wait_until(lambda: not axis.latest().halted, ANSWER, 'drive_state not halted')
    start = axis.drive.position
    axis.stream(start + 100.0)  # CSP targets are taken: the axis follows them
    axis.drive_reaches(lambda drive: drive.position == start + 100, 'the axis at its target')


# Once a defect (a red team's): a set_mode that timed out while the axis braked left it
# halted in its old mode, and the answer told neither that nor how to go on; the resume the
# target refusals suggested released the halt, and the axis ran up to its old velocity again.
# A second set_mode then answered success with the axis still halted.
def test_a_mode_change_that_times_out_leaves_the_axis_halted_and_only_enable_goes_on(rig):
    axis = moving_in_csv(rig, 'combined', LONG_RAMP)
    answer = axis.command('set_mode', CSP, timeout=0.2)
    assert not answer.success
    assert 'halted for the mode change' in answer.message, answer.message
    assert 'call enable' in answer.message, answer.message
    assert answer.mode == CSV
    resumed = axis.command('resume')
    assert not resumed.success and 'enable' in resumed.message, resumed.message
    axis.drive_reaches(lambda drive: drive.velocity == 0, 'the axis braked to a stand')
    assert axis.drive._read(MODE) == CSV
    again = axis.command('set_mode', CSP)
    assert again.success, again.message
    assert 'takes targets after an enable' in again.message, again.message
    wait_until(lambda: not axis.latest().halted, ANSWER, 'drive_state not halted')
    axis.drive_reaches(lambda drive: drive._read(MODE) == CSP and drive.velocity == 0,
                       'the axis standing in CSP')
    stood = axis.drive.position
    enabled = axis.command('enable', CSP)
    assert enabled.success, enabled.message
    axis.drive_reaches(lambda drive: drive.velocity == 0, 'the axis standing')
    assert abs(axis.drive.position - stood) <= WINDOW


def test_a_set_mode_of_a_standing_axis_does_not_halt_it(rig):
    axis = rig('-p', 'drives.command_timeout:=0.0', pdos=layout_pdos('combined'))
    axis.wait_state('SWITCH_ON_DISABLED')
    axis.nmt_start()
    assert axis.command('enable', PV).success
    since = axis.recorder.mark()
    answer = axis.command('set_mode', CSV)
    assert answer.success, answer.message
    words = [struct.unpack_from('<H', m.data)[0] for m in axis.recorder.messages(since)
             if m.arbitration_id == 0x200 + NODE]
    assert not any(word & 0x100 for word in words), [hex(word) for word in words]



# Once a defect (a red team's): a homing from a moving mode that timed out while the axis
# braked left it halted in that mode, and a resume ran it up to its old velocity again.
def test_a_homing_that_times_out_while_the_axis_brakes_needs_a_fresh_enable(rig):
    axis = moving_in_csv(rig, 'combined', LONG_RAMP)
    answer = axis.command('home', timeout=0.3)
    assert not answer.success
    assert 'halted for the mode change' in answer.message, answer.message
    # The timeout's own halt was confirmed (the drive needed an enable only after it).
    assert 'halted at position' in answer.message, answer.message
    resumed = axis.command('resume')
    assert not resumed.success and 'enable' in resumed.message, resumed.message
    axis.drive_reaches(lambda drive: drive.velocity == 0, 'the axis braked to a stand')


# Once a defect (a red team's): a drive that quick-stopped by itself (its input) while it
# braked for a set_mode was enabled again by the set_mode's own frames once it stood
# (transition 16), and set_mode answered success with the drive in QUICK_STOP_ACTIVE.
def test_a_drive_that_stops_by_itself_during_a_mode_change_ends_it_and_stays_stopped(rig):
    axis = moving_in_csv(rig, 'combined', LONG_RAMP)
    axis.drive.set_value(QUICK_STOP_OPTION, 0, struct.pack('<h', 6))  # stays in quick stop
    enabled_again = []
    enter = axis.drive._enter

    def entering(state) -> None:
        if state is State.OPERATION_ENABLED:
            enabled_again.append(state)
        enter(state)
    axis.drive._enter = entering
    its_input = threading.Timer(0.4, lambda: axis.drive.set_value(
        CONTROLWORD, 0, struct.pack('<H', 0x02)))
    its_input.start()
    try:
        answer = axis.command('set_mode', CSP)
    finally:
        its_input.join()
    assert not answer.success
    assert 'left OPERATION_ENABLED' in answer.message, answer.message
    axis.drive_reaches(lambda drive: drive.velocity == 0, 'the axis at a stand')
    assert axis.drive.drive_state == 'QUICK_STOP_ACTIVE' and not enabled_again


# Once a defect (a red team's): the drive's velocity threshold (0x606F) was read before the
# halt; a drive that never answered that read got its halt a second late (the SDO timeout),
# and a set_mode with a shorter timeout never halted it at all: it ran on at full speed.
def test_a_drive_slow_to_answer_a_setting_is_halted_at_once_for_a_mode_change(rig,
                                                                              monkeypatch):
    unanswered = bytes([0x40, 0x6F, 0x60])  # an SDO upload request of 0x606F

    def on_sdo_frame(device, handler, cob_id, data):
        if bytes(data[:3]) != unanswered:
            answer_sdo(device, handler, cob_id, data)
    answer_sdo = DurandDevice._on_sdo_frame
    monkeypatch.setattr(DurandDevice, '_on_sdo_frame', on_sdo_frame)
    axis = moving_in_csv(rig, 'combined', LONG_RAMP)
    answer = axis.command('set_mode', CSP, timeout=0.3)
    assert not answer.success
    assert 'halted for the mode change' in answer.message, answer.message
    assert axis.drive._controlword & 0x100, 'no halt reached the drive'
    axis.drive_reaches(lambda drive: drive.velocity == 0, 'the axis braked to a stand')


# Once a defect (a red team's): a resume while a homing braked for its mode change, or while
# the halt of that homing's timeout braked, released the halt in the old mode: the axis ran
# up to its old velocity again, and, marked as needing an enable a moment later, was then
# refused a halt and skipped by the command timeout (8 of 8).
def test_a_resume_while_the_axis_brakes_for_a_mode_change_is_refused(rig):
    axis = moving_in_csv(rig, 'combined', LONG_RAMP)
    speeds = speeds_of(axis.drive)
    homing = []
    thread = threading.Thread(target=lambda: homing.append(axis.command('home', timeout=0.3)))
    thread.start()
    try:
        resumes = []
        for below in (1400, 600):  # braking for the change, then for the timeout's halt
            axis.drive_reaches(lambda drive, below=below: abs(drive.velocity) < below,
                               f'the axis braking below {below} counts/s')
            resumes.append(axis.command('resume'))
    finally:
        thread.join()
    assert [answer.success for answer in resumes] == [False, False], resumes
    assert all('halted for a mode change' in answer.message for answer in resumes), resumes
    answer, = homing
    assert not answer.success and 'halted at position' in answer.message, answer.message
    axis.drive_reaches(lambda drive: drive.velocity == 0, 'the axis at a stand')
    never_faster(speeds)
    assert not axis.command('resume').success


# Once a defect (a red team's): a halt while a homing braked for its mode change replaced
# the homing and named the halt its own; a resume later was then accepted and ran the axis
# up to its old velocity again (6 of 6).
def test_a_halt_while_the_axis_brakes_for_a_mode_change_keeps_it_from_a_resume(rig):
    axis = moving_in_csv(rig, 'combined', LONG_RAMP)
    answer, halted, _ = during_the_braking(axis, ('home',), lambda: axis.command('halt'))
    assert not answer.success, answer.message
    # Once a defect (a red team's): the homing, replaced, marked the drive as needing an
    # enable after the halt had begun, and the halt failed with "it left OPERATION_ENABLED,
    # or was stopped", which had not happened (6 of 6).
    assert halted.success and 'halted for the mode change' in halted.message, halted.message
    axis.drive_reaches(lambda drive: drive.velocity == 0, 'the axis at a stand')
    resumed = axis.command('resume')
    assert not resumed.success, resumed.message
    assert axis.drive.velocity == 0 and axis.drive._read(MODE) == CSV


# Once a defect (a red team's): a move sent while another braked for its mode change
# replaced it, and the replaced move then marked the drive as needing an enable: the new move
# failed with "it left OPERATION_ENABLED, or was stopped", which had not happened. The new
# move takes over the braking, and goes on in profile position from where the axis stands.
def test_a_move_while_another_brakes_for_its_mode_change_takes_over_and_arrives(rig):
    axis = moving_in_csv(rig, 'combined', LONG_RAMP)
    goal = mover(axis)
    first = goal(axis.drive.position + 100000.0)
    axis.drive_reaches(lambda drive: abs(drive.velocity) < 1400, 'the axis braking')
    second = goal(axis.drive.position + 1500.0)  # ahead: braking takes about 1000 counts
    replaced = wait_for_future(first.get_result_async(), COMMAND_TIMEOUT).result
    assert not replaced.success and 'replaced' in replaced.message, replaced.message
    assert 'held there' not in replaced.message, replaced.message
    done = wait_for_future(second.get_result_async(), COMMAND_TIMEOUT + ANSWER).result
    assert done.success, done.message
    assert axis.drive._read(MODE) == PP and axis.drive.velocity == 0
    assert abs(done.position - axis.drive._read(TARGET_POSITION)) <= WINDOW


# Once a defect (a red team's): a set_mode replaced by a set_mode during the braking gave the
# drive back enabled, late, in the middle of the newer one, which had marked it. A target
# every millisecond slipped in as that released the axis; the newer set_mode then answered
# "it takes targets after an enable", so the command timeout no longer watched the axis, and
# halt and resume were refused: the axis ran on at that target (4 of 4).
def test_a_set_mode_replacing_one_under_way_gives_the_drive_back_still_watched(rig):
    axis = rig('-p', 'drives.command_timeout:=0.5', pdos=layout_pdos('combined'))
    stream = axis.enable_moving()
    stream.PERIOD = 0.001  # a target every millisecond: one taken mid-change would show
    axis.drive.set_value(PROFILE_ACCELERATION, 0, struct.pack('<I', LONG_RAMP))
    first, second, _ = during_the_braking(axis, ('set_mode', CSP),
                                            lambda: axis.command('set_mode', CSV))
    assert not first.success and 'replaced' in first.message, first.message
    assert second.success and 'enable' not in second.message, second.message
    axis.drive_reaches(lambda drive: drive.velocity == VELOCITY, 'the stream followed again')
    axis.stop_streams()
    axis.drive_reaches(lambda drive: drive.velocity == 0, 'the command timeout halting it')


# Once a defect (a red team's): a set_mode to the mode the axis was braking in, for a
# set_mode it replaced, answered at once that the axis was held there, while it still ran
# at 1200 counts/s.
def test_a_set_mode_to_the_mode_it_brakes_in_answers_once_the_axis_stands(rig):
    axis = moving_in_csv(rig, 'combined', LONG_RAMP)
    _, second, velocity = during_the_braking(axis, ('set_mode', CSP),
                                            lambda: axis.command('set_mode', CSV))
    assert second.success and 'held' not in second.message, second.message
    assert abs(velocity) <= WINDOW / STILL_SPAN, f'answered at velocity {velocity}'
    assert axis.drive._read(MODE) == CSV
    wait_until(lambda: not axis.latest().halted, ANSWER, 'drive_state not halted')


# Once a defect (a red team's): a move replacing a homing that braked for its mode change,
# the axis still in profile position, released the halt at once: the axis went from +1300
# to -1000 counts/s within 0.2 s, with no stand between (4 of 4).
def test_a_move_replacing_a_homing_that_brakes_in_pp_releases_the_axis_standing(rig):
    axis = rig('-p', 'drives.command_timeout:=0.0', pdos=layout_pdos('combined'))
    axis.wait_state('SWITCH_ON_DISABLED')
    axis.nmt_start()
    assert axis.command('enable', PP).success
    axis.drive.set_value(PROFILE_ACCELERATION, 0, struct.pack('<I', LONG_RAMP))
    goal = mover(axis)
    first = goal(axis.drive.position + 100000.0, float(VELOCITY))
    axis.drive_reaches(lambda drive: abs(drive.velocity) == VELOCITY, 'the axis moving in PP')
    released = halt_releases(axis.drive)
    _, second, _ = during_the_braking(
        axis, ('home',), lambda: goal(axis.drive.position - 3000.0, 1000.0))
    assert not wait_for_future(first.get_result_async(), ANSWER).result.success
    done = wait_for_future(second.get_result_async(), COMMAND_TIMEOUT + ANSWER).result
    assert done.success, done.message
    assert released and abs(released[0]) <= WINDOW / STILL_SPAN, released


# Once a defect (a red team's): an enable whose time ran out while the halted axis still
# braked (a ramp longer than the enable's default 2 s) answered only "timed out", though it
# leaves the axis halted and needing an enable; and the enable before waited at most half a
# second, then released the axis at speed (test_enable_holds_the_axis).
@pytest.mark.parametrize('mode', [CSV, CSP], ids=['its mode', 'another mode'])
def test_an_enable_that_times_out_while_the_axis_brakes_says_so_and_releases_nothing(rig, mode):
    axis = moving_in_csv(rig, 'combined', LONG_RAMP)
    speeds = speeds_of(axis.drive)
    halted, enabled, _ = during_the_braking(axis, ('halt',),
                                            lambda: axis.command('enable', mode, timeout=0.3))
    assert not enabled.success and 'still braking' in enabled.message, enabled.message
    assert 'replaced' in halted.message, halted.message  # by the enable
    never_faster(speeds)
    again = axis.command('enable', CSV)  # once the axis stands, by the judgement it has
    assert again.success, again.message
    axis.drive_reaches(lambda drive: drive.velocity == 0, 'the axis held at a stand')


# Once a wrong hint (seen in a CI run): an enable in another mode whose time ran out while
# the axis braked for the mode change told its caller to call enable, as it just had.
def test_an_enable_in_another_mode_that_times_out_while_the_axis_brakes_says_so(rig):
    axis = moving_in_csv(rig, 'combined', LONG_RAMP)
    enabled = axis.command('enable', CSP, timeout=0.3)
    assert not enabled.success
    assert 'still braking' in enabled.message, enabled.message
    assert 'call enable (in the mode wanted)' not in enabled.message, enabled.message
    assert enabled.mode == CSV and enabled.state == 'OPERATION_ENABLED'
    axis.drive_reaches(lambda drive: drive.velocity == 0, 'the axis braked to a stand')
    assert axis.drive._read(MODE) == CSV
    again = axis.command('enable', CSP)
    assert again.success, again.message


# Once a wrong hint (a red team's): after a set_mode timed out with the axis braking, an
# enable in the mode wanted that timed out too told its caller to call enable in the mode
# wanted, which it had just done, instead of that the axis was still braking.
def test_an_enable_after_a_set_mode_that_timed_out_says_the_axis_still_brakes(rig):
    axis = moving_in_csv(rig, 'combined', LONG_RAMP)
    changed = axis.command('set_mode', CSP, timeout=0.2)
    assert not changed.success and 'halted for the mode change' in changed.message, changed
    enabled = axis.command('enable', CSP, timeout=0.2)
    assert not enabled.success
    assert 'still braking' in enabled.message, enabled.message
    assert 'halted for the mode change' not in enabled.message, enabled.message
    axis.drive_reaches(lambda drive: drive.velocity == 0, 'the axis braked to a stand')
    again = axis.command('enable', CSP)
    assert again.success, again.message


# Once a defect (a red team's): before it halted anything, a mode change took a velocity
# (0x606C) that read 0 for a standing axis. A drive without 0x606F whose velocity unit is
# coarse (rpm against an encoder's counts) reads 0 while its axis still moves: a CSV axis at
# 800 counts/s, velocity in units of 2,000 counts/s, went to CSP unhalted (3 of 3).
def test_a_velocity_that_reads_0_in_coarse_units_is_not_taken_for_a_stand(rig):
    axis = moving_in_csv(rig, 'combined')
    drive = axis.drive
    velocity_in_units(drive, 2000)
    drive.set_value(TARGET_VELOCITY, 0, struct.pack('<i', 800))  # another master's target
    axis.drive_reaches(lambda drive: drive._velocity == 800, 'the axis at 800 counts/s')
    entering = entering_csp(drive)
    answer = axis.command('set_mode', CSP)
    assert answer.success, answer.message
    wait_until(lambda: entering, ANSWER, 'a cycle of the drive in CSP')
    velocity, behind = entering[0]
    assert abs(velocity) <= WINDOW / STILL_SPAN and abs(behind) <= WINDOW, (velocity, behind)
