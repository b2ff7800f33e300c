"""Stops and moves hold on layouts and timings that tried to undo or misplace them.

Found by attacking the drive support from outside: a frame of an earlier write waiting for
SYNC must not undo a later enable, halt or quick stop (an RPDO synchronous beside
event-driven ones); a move halted by its timeout and then cancelled or replaced gets its one
answer; a relative move counts from the set-point the drive holds; the software limits are
never skipped for a read that failed once; a drive whose heartbeat consumer could not be
written is not enabled; a short ``~/joint_commands`` array is never given to the wrong joint.
"""

from dataclasses import replace
import struct

from action_msgs.msg import GoalStatus
import pytest
from sensor_msgs.msg import JointState
from test_drive_layouts import move
import test_drives
from test_drives import CSP, CSV, NODE, PP, WAIT, watch

from cbcan_ros.action import DriveMove
from cbcan_ros.simulation.durand.drive import DurandDrive
from cbcan_ros.simulation.durand.drive_objects import (
    CONSUMER_HEARTBEAT,
    PROFILE_ACCELERATION,
    QUICK_STOP_OPTION,
    SOFTWARE_POSITION_LIMIT,
)
from cbcan_ros.simulation.durand.drive_pdos import drive_pdos

from conftest import Harness, new_channel, wait_for_future, wait_until

rig = test_drives.rig  # a gateway with one simulated drive (a fixture)
SYNC = 0x80


def mixed():
    """Return the vendor layout with RPDO 4 (controlword, target velocity) synchronous."""
    return tuple(replace(pdo, transmission_type=1) if (pdo.kind, pdo.number) == ('rpdo', 4)
                 else pdo for pdo in drive_pdos('vendor'))


def two_syncs_pass(axis) -> None:
    """Return once two SYNCs went by on the bus: what waited for one has been applied."""
    bus, frames = axis.gateway.raw_bus(), []
    try:
        watch(bus, frames, lambda seen: sum(m.arbitration_id == SYNC for m in seen) >= 2,
              'two SYNCs')
    finally:
        bus.shutdown()


def enabled_on_mixed_rpdos(rig):
    axis = rig(pdos=mixed(), **{'sync.period': 0.1})
    gateway = axis.gateway.node.gateway
    wait_until(lambda: 4 in gateway.pdo.mappings(NODE)[1], WAIT, 'RPDO 4 read')
    axis.enable(CSV)
    two_syncs_pass(axis)  # the enable's hold frame, waiting for SYNC, came after its steps
    assert axis.drive.drive_state == 'OPERATION_ENABLED'
    assert gateway.drives.target(NODE, 1000).success
    wait_until(lambda: axis.drive.velocity == 1000, WAIT, 'the drive at 1000 counts/s')
    return axis, gateway


def test_a_halt_is_not_undone_by_a_target_frame_waiting_for_sync(rig):
    axis, gateway = enabled_on_mixed_rpdos(rig)
    assert gateway.drives.target(NODE, 900).success  # waits for the next SYNC in RPDO 4
    halted = axis.command('halt', timeout=WAIT)  # the halt goes at once in RPDO 1
    assert halted.success, halted.message
    two_syncs_pass(axis)
    assert axis.drive.velocity == 0 and axis.drive.statusword & 0x100


def test_a_quick_stop_is_not_undone_by_a_target_frame_waiting_for_sync(rig):
    axis, gateway = enabled_on_mixed_rpdos(rig)
    axis.drive.set_value(QUICK_STOP_OPTION, 0, struct.pack('<h', 6))  # stays in quick stop
    assert gateway.drives.target(NODE, 900).success
    stopped = axis.command('quick_stop', timeout=WAIT)
    assert stopped.success, stopped.message
    two_syncs_pass(axis)
    assert axis.drive.drive_state == 'QUICK_STOP_ACTIVE' and axis.drive.velocity == 0


def goal(axis, **fields):
    """Send a ~/move goal; return its handle, accepted."""
    assert axis.mover.wait_for_server(timeout_sec=10.0)
    handle = wait_for_future(axis.mover.send_goal_async(DriveMove.Goal(node_id=NODE,
                                                                         **fields)), WAIT)
    assert handle.accepted
    return handle


def test_a_move_halted_by_its_timeout_and_then_cancelled_or_replaced_is_answered(rig):
    axis = rig()
    axis.drive.set_value(PROFILE_ACCELERATION, 0, struct.pack('<I', 1000))  # 1 s to stand
    axis.enable(PP)
    for ending in ('cancel', 'new goal'):
        seen = len(axis.states)
        first = goal(axis, position=100.0, velocity=1.0, timeout=0.3)
        wait_until(lambda seen=seen: any(m.halted for m in axis.states[seen:]), WAIT,
                   'halted by the timeout')
        if ending == 'cancel':
            wait_for_future(first.cancel_goal_async(), WAIT)
        else:
            second = goal(axis, position=0.0, velocity=50.0)
        result = wait_for_future(first.get_result_async(), WAIT)
        assert not result.result.success
        assert result.result.message.startswith('timed out after 0.3 s'), result.result.message
        if ending == 'new goal':
            done = wait_for_future(second.get_result_async(), WAIT).result
            assert done.success, done.message


def test_a_relative_move_counts_from_the_set_point_the_drive_holds(rig):
    # A move cancelled on its way leaves its set-point in the drive; "relative" counts from
    # there (CiA 402's default), not from where the axis stopped.
    axis = rig()
    axis.enable(PP)
    first = goal(axis, position=5.0, velocity=1.0)
    wait_until(lambda: axis.drive.position > 200, WAIT, 'the move under way')
    wait_for_future(first.cancel_goal_async(), WAIT)
    assert wait_for_future(first.get_result_async(), WAIT).status == GoalStatus.STATUS_CANCELED
    stopped = axis.drive.position
    assert stopped < 5000
    result = move(axis, -4.0, relative=True).result  # 5 - 4 = 1 rad, not stopped - 4000
    assert result.success, result.message
    assert axis.drive.position == 1000


def test_the_software_limits_are_checked_though_their_first_read_failed(rig):
    axis = rig(**{'sdo.timeout': 0.3})
    axis.drive.set_value(SOFTWARE_POSITION_LIMIT, 1, struct.pack('<i', -5000))
    axis.drive.set_value(SOFTWARE_POSITION_LIMIT, 2, struct.pack('<i', 5000))
    reads = []

    def busy_once():  # the drive fails its first read of 0x607D:2 (busy, a timeout...)
        reads.append(1)
        if len(reads) == 1:
            raise RuntimeError('busy')
        return 5000
    axis.drive.node.object_dictionary.set_read_callback(SOFTWARE_POSITION_LIMIT, 2, busy_once)
    axis.enable(PP)
    first = move(axis, 1.0).result
    assert not first.success and 'could not be read' in first.message, first.message
    assert axis.drive.position == 0  # nothing was sent
    outside = move(axis, 9.0).result
    assert not outside.success and 'outside its software position limits' in outside.message
    assert move(axis, 4.0).result.success


def test_a_drive_whose_heartbeat_consumer_cannot_be_written_is_not_enabled(rig):
    # The drive objects may be written, 0x1016 may not: a least-privilege write rule.
    axis = rig(**{'sdo.write_allow': ['*:0x6000-0x67FF']})
    answer = axis.command('enable', CSV)
    assert not answer.success
    assert '0x1016:1' in answer.message and 'nothing was sent' in answer.message
    assert axis.drive.drive_state == 'SWITCH_ON_DISABLED'
    assert axis.drive.value(CONSUMER_HEARTBEAT, 1) == bytes(4)


def test_a_short_joint_commands_array_naming_another_devices_joint_is_not_guessed(rig, caplog):
    axis = rig()
    axis.enable(CSV)
    # wrist (no drive of this gateway) and the shoulder take velocity, gripper position:
    # which velocity is the shoulder's cannot be told from the gateway's drives alone.
    message = JointState(name=['wrist', test_drives.JOINT, 'gripper'], velocity=[2.0, 0.3],
                         position=[0.05])

    def refused():
        axis.commands.publish(message)  # again until the subscription matched
        return 'which value is whose cannot be told' in caplog.text
    wait_until(refused, WAIT, 'the message refused, in the log')
    assert axis.drive.velocity == 0
    line = next(r.getMessage() for r in caplog.records if 'cannot be told' in r.getMessage())
    assert '3 joints and has 1 position, 2 velocity, 0 effort values' in line, line


def test_a_joint_named_twice_in_joint_commands_gets_neither_value(rig, caplog):
    # Each value would go out in a frame of its own, and the drive would take whichever
    # came last before its SYNC.
    axis = rig()
    axis.enable(CSV)
    message = JointState(name=[test_drives.JOINT, test_drives.JOINT], velocity=[2.0, 0.3])

    def refused():
        axis.commands.publish(message)  # again until the subscription matched
        return 'is named more than once' in caplog.text
    wait_until(refused, WAIT, 'the message refused, in the log')
    assert axis.drive.velocity == 0
    axis.commands.publish(JointState(name=[test_drives.JOINT], velocity=[0.5]))
    wait_until(lambda: axis.drive.velocity == 500, WAIT, 'a later message taken')


def test_joint_commands_for_a_drive_not_heard_say_so(rig, caplog):
    axis = rig(**{'heartbeat.timeout': 1.0})
    axis.enable(CSV)
    axis.drive.stop()  # silent, as when its cable is pulled
    wait_until(lambda: axis.latest_state() == 'UNKNOWN', WAIT, 'the drive shown UNKNOWN')

    def refused():
        axis.commands.publish(JointState(name=[test_drives.JOINT], velocity=[0.3]))
        return 'is not heard (UNKNOWN)' in caplog.text
    wait_until(refused, WAIT, 'the target refused as not heard, in the log')


@pytest.mark.parametrize('what', ['move', 'home'])
def test_a_move_or_homing_on_a_drive_without_that_mode_is_refused_before_anything_is_sent(
        ros_context, start_durand, what):
    # 0x6502 lists CSV alone: neither profile position (a move) nor homing.
    channel = new_channel()
    drive = start_durand(NODE, kind=DurandDrive, channel=channel,
                         pdos=drive_pdos('combined'), modes=(CSV,))
    wait_until(lambda: drive.running, WAIT, 'the drive receiving')
    gateway = Harness({'can.channel': channel, 'simulation.devices': None,
                       'drives.nodes': [NODE], 'drives.consumer_time': 3.0})
    try:
        assert gateway.call('nmt_command', node_id=NODE, command=1).success
        wait_until(lambda: gateway.call('drive_command', node_id=NODE, command='enable',
                                        mode=CSV).success, WAIT, 'the drive enabled in CSV')
        if what == 'move':
            future, _cancel = gateway.node.gateway.drives.move(NODE, 1000)
            refused, missing = future.result(WAIT), 'profile position'
        else:  # answered at once, not after homing's 60 s default timeout
            refused = gateway.call('drive_command', node_id=NODE, command='home', wait=WAIT)
            missing = 'homing'
        assert not refused.success
        assert f'does not support {missing}' in refused.message, refused.message
        assert 'nothing was sent' in refused.message
        assert drive.value(0x6060, 0) == struct.pack('<b', CSV)
        assert drive.drive_state == 'OPERATION_ENABLED'
    finally:
        gateway.close()


def test_a_relative_move_after_another_mode_counts_from_where_the_axis_stands(rig):
    # The last move's set-point is no base once the axis was moved in another mode.
    axis = rig()
    axis.enable(PP)
    assert move(axis, 2.0).result.success
    axis.enable(CSP)
    axis.target.publish(test_drives.Float64(data=0.5))
    wait_until(lambda: axis.drive.position == 500, WAIT, 'the drive at 500 counts (CSP)')
    result = move(axis, 1.0, relative=True).result
    assert result.success, result.message
    assert axis.drive.position == 1500


def test_a_target_alone_sends_no_other_frame_again(rig):
    # RPDOs 1-3 synchronous, RPDO 4 (controlword, target velocity) event-driven: a target
    # changes no controlword, so the synchronous frames are not sent again (they would go
    # out at once, between SYNCs, and repeat whatever they held).
    pdos = tuple(replace(pdo, transmission_type=1)
                 if pdo.kind == 'rpdo' and pdo.number != 4 else pdo
                 for pdo in drive_pdos('vendor'))
    axis = rig(pdos=pdos, **{'sync.period': 0.1})
    gateway = axis.gateway.node.gateway
    wait_until(lambda: 4 in gateway.pdo.mappings(NODE)[1], WAIT, 'RPDO 4 read')
    axis.enable(CSV)
    two_syncs_pass(axis)
    bus, frames = axis.gateway.raw_bus(), []
    try:
        assert gateway.drives.target(NODE, 700).success
        watch(bus, frames, lambda seen: sum(m.arbitration_id == SYNC for m in seen) >= 2,
              'two SYNCs after the target')
    finally:
        bus.shutdown()
    wait_until(lambda: axis.drive.velocity == 700, WAIT, 'the drive at 700 counts/s')
    sent = {m.arbitration_id for m in frames} & {0x200 + NODE, 0x300 + NODE, 0x400 + NODE}
    assert not sent, f'RPDOs sent again for a target alone: {sorted(map(hex, sent))}'
