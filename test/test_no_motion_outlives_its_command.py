"""No motion outlives the command, goal or stream it belonged to.

A motion that ended (a cancelled or timed-out move, a silent publisher) is never brought back
to life, and a drive a failed command leaves running stays watched. The gateway and one
simulated drive in this process (``test_drives``' rig), a robot program's view of it:
``~/drive_command``, ``~/move``, ``~/node_<id>/target``. Each defect was found by a red team
from outside the node; the message of each assert says what a user met.
"""

import math
import struct
import threading

import pytest
from std_msgs.msg import Float64
import test_drives
from test_drives import CSP, CSV, move_under_way, NODE, PP, PV, SCALE, WAIT

from cbcan_ros.action import DriveMove
from cbcan_ros.simulation.durand.device import DurandDevice
from cbcan_ros.simulation.durand.drive_objects import PROFILE_ACCELERATION
from cbcan_ros.simulation.durand.drive_pdos import drive_pdos as layout_pdos

from conftest import wait_for_future, wait_until

TARGET_POSITION, TARGET_VELOCITY, PROFILE_VELOCITY = 0x607A, 0x60FF, 0x6081
HALT = 0x100
# An SDO upload request of the velocity actual value (0x606C): the first thing an enable in
# another mode asks of a moving axis, before it halts it.
VELOCITY_READ = bytes([0x40, 0x6C, 0x60])

rig = test_drives.rig  # a gateway with one simulated drive (a fixture)


def unanswered_writes(monkeypatch, lost) -> threading.Event:
    """Have the simulated drive drop the SDO writes ``lost(index, value)`` picks, once armed.

    Return the event that arms it. As a drive that never gets the frame: nothing is applied,
    nothing answered, and the write fails at its SDO timeout.
    """
    armed = threading.Event()

    def on_sdo_frame(device, handler, cob_id, data):
        data = bytes(data)
        expedited_write = data[0] & 0xE3 == 0x23
        if not (armed.is_set() and expedited_write and lost(
                int.from_bytes(data[1:3], 'little'), int.from_bytes(data[4:8], 'little'))):
            answer_sdo(device, handler, cob_id, data)
    answer_sdo = DurandDevice._on_sdo_frame
    monkeypatch.setattr(DurandDevice, '_on_sdo_frame', on_sdo_frame)
    return armed


def the_halt(index: int, value: int) -> bool:
    """Pick the controlword writes with the halt bit."""
    return index == 0x6040 and bool(value & HALT)


def csv_ignoring_the_halt_bit(rig, **parameters):
    """Return a drive run by SDO alone, enabled in CSV at 1000 counts/s, ignoring bit 8."""
    axis = rig(pdos=layout_pdos('sdo_only'), **parameters)
    axis.drive.halts_in_cyclic_modes = False
    axis.enable(CSV)
    axis.target.publish(Float64(data=1.0))
    wait_until(lambda: axis.drive.velocity == 1000, WAIT, 'the drive at 1000 counts/s')
    return axis


def test_an_enable_that_fails_before_it_halts_a_streaming_axis_leaves_it_to_the_command_timeout(
        rig, monkeypatch):
    # Once a defect (a red team's, 12 of 13 tries): an enable in another mode whose time ran
    # out before it halted the axis left the drive marked as needing a fresh enable. Its
    # stream's last velocity then ran on after the publisher stopped: the command timeout
    # skips such a drive, and a halt was refused ("needs a fresh enable").
    unanswered = threading.Event()  # set: the drive leaves its velocity read unanswered

    def on_sdo_frame(device, handler, cob_id, data):
        if not (unanswered.is_set() and bytes(data[:3]) == VELOCITY_READ):
            answer_sdo(device, handler, cob_id, data)
    answer_sdo = DurandDevice._on_sdo_frame
    monkeypatch.setattr(DurandDevice, '_on_sdo_frame', on_sdo_frame)
    axis = rig(**{'drives.command_timeout': 0.5})
    axis.enable(CSV)
    stopped = threading.Event()

    def stream() -> None:  # a controller's targets, every 20 ms, until it stops
        while not stopped.wait(0.02):
            axis.target.publish(Float64(data=1.0))
    publisher = threading.Thread(target=stream)
    publisher.start()
    try:
        wait_until(lambda: axis.drive.velocity == 1000, WAIT, 'the drive at 1000 counts/s')
        unanswered.set()
        answer = axis.command('enable', CSP, timeout=0.3)
    finally:
        stopped.set()
        publisher.join()
        unanswered.clear()
    assert not answer.success and answer.message.startswith('timed out'), answer.message
    assert not axis.drive._controlword & HALT, 'the enable halted the axis: nothing to test'
    wait_until(lambda: axis.drive.velocity == 0 and axis.drive._controlword & HALT, WAIT,
               'the axis halted by the command timeout once its publisher stopped')
    halted = axis.command('halt', timeout=WAIT)
    assert halted.success, halted.message


def test_a_resume_after_a_cancelled_move_holds_the_axis_where_it_stands(rig):
    # Once a defect (a red team's, 6 of 6): the resume released the halt alone, and the
    # drive went on to the cancelled goal's set-point with no goal, timeout or result
    # watching it.
    axis = rig()
    goal = move_under_way(axis)  # towards 500 rad
    wait_for_future(goal.cancel_goal_async(), WAIT)
    stopped = wait_for_future(goal.get_result_async(), WAIT).result.position
    resumed = axis.command('resume', timeout=WAIT)
    assert resumed.success, resumed.message
    assert 'held where it stands' in resumed.message, resumed.message
    held = struct.unpack('<i', axis.drive.value(TARGET_POSITION))[0]
    assert abs(held - stopped * SCALE) <= 10, f'the drive heads for {held}, not {stopped}'
    assert not axis.drive._controlword & HALT, 'still halted'
    wait_until(lambda: axis.drive.statusword & 0x400 and axis.drive.velocity == 0, WAIT,
               'the drive at its set-point, standing')
    assert math.isclose(axis.drive.position / SCALE, stopped, abs_tol=0.01)
    assert wait_for_future(axis.mover.send_goal_async(DriveMove.Goal(
        node_id=NODE, position=stopped + 0.5, velocity=20.0)), WAIT).accepted


def test_a_resume_after_the_command_timeout_in_pv_keeps_the_axis_standing(rig):
    # Once a defect (a red team's, 4 of 4): the halt set bit 8 only, leaving the dead
    # publisher's velocity in 0x60FF, and resume ran the axis at it until the next timeout.
    axis = rig(**{'drives.command_timeout': 0.3})
    axis.enable(PV)
    axis.target.publish(Float64(data=1.0))
    wait_until(lambda: axis.drive.velocity == 1000, WAIT, 'the drive at 1000 counts/s')
    wait_until(lambda: axis.drive.velocity == 0 and axis.drive._controlword & HALT, WAIT,
               'the drive halted by the command timeout, standing')
    assert axis.drive.value(TARGET_VELOCITY) == struct.pack('<i', 0)
    resumed = axis.command('resume', timeout=WAIT)
    assert resumed.success, resumed.message
    assert axis.drive.value(TARGET_VELOCITY) == struct.pack('<i', 0)
    axis.target.publish(Float64(data=0.5))
    wait_until(lambda: axis.drive.velocity == 500, WAIT, 'a new target moving it again')


def test_pp_set_points_on_the_topic_run_at_the_configured_profile_velocity(rig):
    # Once a defect (a red team's, 3 of 3): after a fast move, set-points on the target
    # topic ran at that move's velocity, 20 times the drive's configured one here.
    axis = rig()
    configured = axis.drive.value(PROFILE_VELOCITY)
    axis.enable(PP)
    assert wait_for_future(wait_for_future(axis.mover.send_goal_async(DriveMove.Goal(
        node_id=NODE, position=1.0, velocity=20.0)), WAIT).get_result_async(),
        WAIT).result.success
    assert axis.drive.value(PROFILE_VELOCITY) == struct.pack('<I', 20_000)
    axis.target.publish(Float64(data=1.01))
    wait_until(lambda: axis.drive.position == 1010, WAIT, 'the set-point reached')
    assert axis.drive.value(PROFILE_VELOCITY) == configured


def test_a_goal_refused_before_anything_is_sent_says_where_the_drive_stands(rig):
    # Once a defect (a red team's): such results said position 0.0 wherever the axis stood.
    axis = rig()
    axis.enable(PP)
    assert wait_for_future(wait_for_future(axis.mover.send_goal_async(DriveMove.Goal(
        node_id=NODE, position=1.5, velocity=20.0)), WAIT).get_result_async(),
        WAIT).result.success
    for goal, says in ((DriveMove.Goal(node_id=NODE, position=math.nan), 'finite'),
                       (DriveMove.Goal(node_id=NODE, position=2.0, velocity=-1.0), 'velocity'),
                       (DriveMove.Goal(node_id=NODE, position=2.0, velocity=1e-9), 'below')):
        result = wait_for_future(wait_for_future(axis.mover.send_goal_async(goal), WAIT)
                                 .get_result_async(), WAIT).result
        assert not result.success and says in result.message, result.message
        assert result.position == 1.5, (result.position, result.message)
    result = wait_for_future(wait_for_future(axis.mover.send_goal_async(DriveMove.Goal(
        node_id=NODE + 1, position=1.0)), WAIT).get_result_async(), WAIT).result
    assert not result.success and 'not a drive' in result.message, result.message
    assert math.isnan(result.position)


@pytest.mark.parametrize('command, mode', [('enable', CSP), ('halt', 0)])
def test_a_command_whose_time_runs_out_during_its_halt_still_sends_the_stopping_target(
        rig, monkeypatch, command, mode):
    # Once a defect (a red team's, 8 of 8 with a drive slow to take a halt): the halt and
    # the target that stops a drive ignoring it are two writes, and a command whose time
    # ran out between them never sent the second. The axis ran on, shown halted (a halt) or
    # needing an enable (an enable), so neither the command timeout nor a halt stopped it.
    armed = unanswered_writes(monkeypatch, the_halt)
    axis = csv_ignoring_the_halt_bit(rig)
    armed.set()
    answer = axis.command(command, mode, timeout=0.3)
    assert not answer.success and answer.message.startswith('timed out'), answer.message
    wait_until(lambda: axis.drive.velocity == 0, WAIT,
               'the axis stopped by the stopping target that follows the halt')
    assert axis.drive.value(0x60FF) == struct.pack('<i', 0)


@pytest.mark.parametrize('command', ['enable', 'set_mode'])
def test_a_mode_change_that_failed_after_writing_the_new_mode_needs_a_fresh_enable(
        rig, monkeypatch, command):
    # Once a defect (red teams', 5 of 5 and 6 of 6): such an enable or set_mode gave the
    # drive back "enabled" in the new mode, and the controller's stream of velocity 0 for
    # the old mode went to it as position 0: the axis jumped thousands of counts.
    armed = unanswered_writes(monkeypatch, lambda index, _value: index == 0x6060)
    axis = rig(pdos=layout_pdos('sdo_only'))
    axis.enable(CSV)
    axis.target.publish(Float64(data=0.0))
    armed.set()
    answer = axis.command(command, CSP, timeout=WAIT)
    assert not answer.success, answer.message
    assert 'the new mode was written: the drive needs a fresh enable' in answer.message, \
        answer.message
    refused = axis.gateway.node.gateway.drives.target(NODE, 0.0)
    assert not refused.success and 'needs a fresh enable' in refused.message, refused.message


def test_a_resume_in_pp_waits_for_the_axis_to_stand_before_it_holds_it(rig):
    # Once a defect (a red team's, 5 of 5): resume set the new set-point where a braking axis
    # happened to be, cutting its ramp short (a real drive overshoots and comes back).
    axis = rig()
    axis.drive.set_value(PROFILE_ACCELERATION, 0, struct.pack('<I', 600))  # 3.3 s to stand
    goal = move_under_way(axis)  # at 2000 counts/s
    speeds = []
    take = axis.drive._take_set_point

    def taken(controlword):
        speeds.append(axis.drive.velocity)
        take(controlword)
    axis.drive._take_set_point = taken
    wait_for_future(goal.cancel_goal_async(), WAIT)
    cancelled = wait_for_future(goal.get_result_async(), WAIT).result
    assert 'the halt was not confirmed' in cancelled.message, cancelled.message
    assert axis.drive.velocity != 0, 'stood already: nothing to test'
    resumed = axis.command('resume', timeout=WAIT)
    assert resumed.success, resumed.message
    assert speeds == [0], f'the set-point came at velocities {speeds}'


def test_a_command_after_one_that_ended_before_its_mode_showed_writes_its_own_mode(
        rig, monkeypatch):
    # Once a defect (a red team's, 10 of 10): a set_mode to CSP replaced by an enable in CSV
    # while its mode write was on its way. The enable saw the drive still show CSV and sent
    # no mode; the CSP write landed after it, and the drive ran in CSP while the gateway
    # answered CSV (a stream of velocity 0 then went to it as position 0).
    sent, landed = threading.Event(), threading.Event()

    def on_sdo_frame(device, handler, cob_id, data):
        data = bytes(data)
        if data[0] & 0xE3 == 0x23 and data[1:3] == bytes([0x60, 0x60]) and data[4] == CSP:
            sent.set()
            # The write of CSP reaches the drive late (a busy drive, a SYNC to wait for).
            def late():
                answer_sdo(device, handler, cob_id, data)
                landed.set()
            threading.Timer(0.5, late).start()
            return
        answer_sdo(device, handler, cob_id, data)
    answer_sdo = DurandDevice._on_sdo_frame
    monkeypatch.setattr(DurandDevice, '_on_sdo_frame', on_sdo_frame)
    axis = rig(pdos=layout_pdos('sdo_only'))
    axis.enable(CSV)
    axis.target.publish(Float64(data=0.0))
    wait_until(lambda: axis.drive.velocity == 0, WAIT, 'the axis standing in CSV')
    changing = threading.Thread(target=lambda: axis.command('set_mode', CSP, timeout=WAIT))
    changing.start()
    try:
        wait_until(sent.is_set, WAIT, "the set_mode's write of CSP on its way")
        assert not landed.is_set()
        enabled = axis.command('enable', CSV, timeout=WAIT)
    finally:
        changing.join()
    assert enabled.success, enabled.message
    wait_until(landed.is_set, WAIT, 'the late write of CSP taken by the drive')
    wait_until(lambda: axis.drive.value(0x6060) == bytes([CSV]), WAIT,
               'the drive in CSV, as the enable answered')
