"""Drives run as ROS joints: commands, targets, joint states, moves, faults, bad input.

Each test starts a gateway with one simulated CiA 402 drive (durand) on a bus of its own and
works it as a robot program would: ``~/drive_command``, ``~/node_<id>/target``,
``~/joint_commands``, ``~/joint_states``, ``~/node_<id>/drive_state`` and the ``~/move``
action. What the drive did is read from the drive itself; conditions are waited for with
generous ceilings, never proved by sleeping.
"""

import asyncio
import contextlib
import logging
import math
import struct
import threading

from action_msgs.msg import GoalStatus, GoalStatusArray
import pytest
from rclpy.action import ActionClient
from rclpy.qos import qos_profile_action_status_default
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64

from cbcan_ros.action import DriveMove
from cbcan_ros.core.drives import commands as drive_commands
from cbcan_ros.core.nmt import OPERATIONAL
from cbcan_ros.msg import DriveState
from cbcan_ros.ros.drives import STATE_QOS
from cbcan_ros.ros.service_qos import ACTION_RESULT_KEPT, ACTION_SERVICES_QOS
from cbcan_ros.simulation.durand.drive import DurandDrive
from cbcan_ros.simulation.durand.drive_objects import (
    HOMING_METHOD,
    PROFILE_ACCELERATION,
    PROFILE_VELOCITY,
    QUICK_STOP_OPTION,
)
from cbcan_ros.simulation.durand.drive_pdos import default_drive_pdos

from conftest import Harness, new_channel, wait_for_future, wait_until

NODE = 7
JOINT = 'shoulder'
SCALE = 1000.0  # counts per rad, counts/s per rad/s
PP, PV, HOMING, CSP, CSV, CST = 1, 3, 6, 8, 9, 10
WAIT = 15.0
LOCAL_CONTROL = 0x08000021

PDOS = default_drive_pdos()  # the simulated drive's own, as make run has them


class Rig:
    """A gateway, its drive, and a robot program's view: topics, services, the action."""

    def __init__(self, start_durand, pdos=PDOS, before_gateway=None, **parameters):
        channel = new_channel()
        self.drive = start_durand(NODE, kind=DurandDrive, channel=channel, pdos=pdos)
        wait_until(lambda: self.drive.running, WAIT, 'the drive receiving')
        if before_gateway is not None:
            before_gateway(self.drive)
        # The drive watches the gateway's heartbeat (as by default), with a consumer time
        # that a busy test machine's pauses do not reach.
        self.gateway = Harness({'can.channel': channel, 'simulation.devices': None,
                                'drives.nodes': [NODE], f'node_{NODE}.joint': JOINT,
                                f'node_{NODE}.position_scale': SCALE,
                                f'node_{NODE}.velocity_scale': SCALE,
                                'drives.command_timeout': 0.0, 'drives.consumer_time': 3.0,
                                **parameters})
        node = self.gateway.client_node
        self._lock = threading.Lock()
        self.states, self.joint_states = [], []
        node.create_subscription(DriveState, f'/cbcan/node_{NODE}/drive_state',
                                 lambda m: self._keep(self.states, m), STATE_QOS)
        node.create_subscription(JointState, '/cbcan/joint_states',
                                 lambda m: self._keep(self.joint_states, m), 10)
        self.target = node.create_publisher(Float64, f'/cbcan/node_{NODE}/target', 10)
        self.commands = node.create_publisher(JointState, '/cbcan/joint_commands', 10)
        self.mover = ActionClient(node, DriveMove, '/cbcan/move')
        if not parameters.get('read_only'):  # PDOs flow in OPERATIONAL; else SDO reads
            assert self.gateway.call('nmt_command', node_id=NODE, command=1).success
        wait_until(lambda: self.latest_state() not in (None, 'UNKNOWN'), WAIT,
                   'the drive state published')

    def _keep(self, kept: list, message) -> None:
        with self._lock:
            kept.append(message)

    def latest_state(self):
        """Return the state of the latest drive_state message, None before one."""
        with self._lock:
            return self.states[-1].state if self.states else None

    def command(self, command: str, mode: int = 0, **fields):
        """Call ~/drive_command; return the response."""
        return self.gateway.call('drive_command', node_id=fields.pop('node_id', NODE),
                                 command=command, mode=mode, **fields)

    def enable(self, mode: int):
        """Enable in ``mode``; it must succeed (within WAIT, not the 2 s default).

        A mode change by SDO alone (the ``sdo_only`` layout) takes some twenty round trips:
        a loaded test machine once took more than 2 s for one.
        """
        response = self.command('enable', mode, timeout=WAIT)
        assert response.success, response.message
        return response

    def close(self):
        """Stop the gateway."""
        self.gateway.close()


@contextlib.contextmanager
def joints_enabled(start_durand, joints: dict):
    """Yield (gateway, drives by node id, its ``joint_commands`` publisher): several joints.

    ``joints``: node id: (joint name, mode), each a simulated drive enabled in its mode, at
    SCALE in position and velocity; the command timeout off.
    """
    channel = new_channel()
    drives = {node_id: start_durand(node_id, kind=DurandDrive, channel=channel,
                                    pdos=default_drive_pdos()) for node_id in joints}
    parameters = {'can.channel': channel, 'simulation.devices': None,
                  'drives.nodes': list(joints), 'drives.command_timeout': 0.0,
                  'drives.consumer_time': 3.0}
    for node_id, (joint, _) in joints.items():
        parameters.update({f'node_{node_id}.joint': joint,
                           f'node_{node_id}.position_scale': SCALE,
                           f'node_{node_id}.velocity_scale': SCALE})
    gateway = Harness(parameters)
    try:
        commands = gateway.client_node.create_publisher(JointState, '/cbcan/joint_commands',
                                                        10)
        for node_id, (_, mode) in joints.items():
            assert gateway.call('nmt_command', node_id=node_id, command=1).success
            wait_until(lambda node_id=node_id, mode=mode: gateway.call(
                'drive_command', node_id=node_id, command='enable', mode=mode).success,
                WAIT, f'drive {node_id} enabled')
        yield gateway, drives, commands
    finally:
        gateway.close()


@pytest.fixture
def rig(ros_context, start_durand):
    """Return ``rig(**parameters)``: a gateway with one simulated drive, closed after."""
    made = []

    def factory(**options):
        made.append(Rig(start_durand, **options))
        return made[-1]
    yield factory
    for each in made:
        each.close()


def test_enable_answers_once_the_drive_is_operation_enabled_in_the_mode(rig):
    axis = rig()
    response = axis.enable(CSV)
    assert (response.state, response.mode) == ('OPERATION_ENABLED', CSV)
    assert axis.drive.drive_state == 'OPERATION_ENABLED'
    assert response.statusword & 0x6F == 0x27
    wait_until(lambda: axis.latest_state() == 'OPERATION_ENABLED', WAIT, 'drive_state')


def test_a_velocity_target_moves_the_drive_in_joint_units(rig):
    axis = rig()
    axis.enable(CSV)
    axis.target.publish(Float64(data=1.5))
    wait_until(lambda: axis.drive.velocity == 1500, WAIT, 'the drive at 1500 counts/s')
    wait_until(lambda: axis.joint_states and axis.joint_states[-1].velocity[0] == 1.5, WAIT,
               'joint_states showing 1.5 rad/s')
    assert axis.joint_states[-1].name == [JOINT]


def test_joint_commands_by_name_reach_the_drive(rig):
    axis = rig()
    axis.enable(CSP)
    start = axis.drive.position
    axis.commands.publish(JointState(name=[JOINT], position=[start / SCALE + 0.25]))
    wait_until(lambda: axis.drive.position == start + 250, WAIT, 'the drive 250 counts on')


def test_a_fault_shows_its_error_and_refuses_enable_until_reset(rig):
    axis = rig()
    axis.enable(CSV)
    axis.drive.inject_fault(0x2310)
    wait_until(lambda: axis.latest_state() == 'FAULT', WAIT, 'drive_state FAULT')
    assert axis.states[-1].error_code == 0x2310  # from its EMCY, before 0x603F is read
    assert 'over-current' in axis.states[-1].error
    refused = axis.command('enable', CSV)
    assert not refused.success and '0x2310' in refused.message
    assert axis.drive.drive_state == 'FAULT'
    reset = axis.command('fault_reset')
    assert reset.success, reset.message
    assert reset.state == 'SWITCH_ON_DISABLED'
    axis.enable(CSV)


def test_a_move_succeeds_on_target_reached_at_the_goal(rig):
    axis = rig()
    axis.enable(PP)
    assert axis.mover.wait_for_server(timeout_sec=10.0)
    goal = wait_for_future(axis.mover.send_goal_async(
        DriveMove.Goal(node_id=NODE, position=2.0, velocity=20.0)), WAIT)
    assert goal.accepted
    result = wait_for_future(goal.get_result_async(), WAIT).result
    assert result.success, result.message
    assert axis.drive.position == 2000
    assert math.isclose(result.position, 2.0)


@pytest.mark.parametrize('fields, named', [
    (dict(command='spin'), 'command'),
    (dict(command='enable', mode=2), 'mode 2'),
    (dict(command='enable', node_id=9), 'not a drive'),
    (dict(command='set_mode'), 'set_mode needs a mode'),
    (dict(command='halt'), 'enable first'),
    (dict(command='enable', timeout=-1.0), 'timeout'),
])
def test_bad_requests_are_refused_naming_the_field(rig, fields, named):
    axis = rig()
    command = fields.pop('command')
    response = axis.command(command, **fields)
    assert not response.success
    assert named in response.message and 'nothing was sent' in response.message
    assert axis.drive.drive_state == 'SWITCH_ON_DISABLED'


def test_read_only_refuses_every_command(rig):
    axis = rig(read_only=True)
    response = axis.command('enable', CSV)
    assert not response.success and response.abort_code == LOCAL_CONTROL
    assert axis.drive.drive_state == 'SWITCH_ON_DISABLED'


@pytest.mark.parametrize('sets_bit_10', [True, False], ids=['bit_10', 'no_bit_10'])
def test_halt_stops_the_axis_and_resume_lets_targets_through_again(rig, sets_bit_10):
    # CiA 402 leaves statusword bit 10 to the vendor in the cyclic modes. Once a defect: a
    # halt in CSV waited for it, and a drive that never sets it there got "timed out".
    axis = rig()
    axis.drive.cyclic_target_reached = sets_bit_10
    axis.enable(CSV)
    axis.target.publish(Float64(data=1.0))
    wait_until(lambda: axis.drive.velocity == 1000, WAIT, 'the drive at 1000 counts/s')
    halted = axis.command('halt', timeout=WAIT)
    assert halted.success, halted.message
    assert axis.drive.velocity == 0
    assert bool(axis.drive.statusword & 0x400) == sets_bit_10
    refused = axis.gateway.node.gateway.drives.target(NODE, 500.0)
    assert not refused.success and 'resume' in refused.message
    assert axis.command('resume').success
    axis.target.publish(Float64(data=0.5))
    wait_until(lambda: axis.drive.velocity == 500, WAIT, 'the drive at 500 counts/s')


def test_a_streaming_drive_without_targets_is_halted_and_the_next_target_resumes_it(rig):
    axis = rig(**{'drives.command_timeout': 0.3})
    axis.enable(CSV)
    axis.target.publish(Float64(data=1.0))
    wait_until(lambda: axis.drive.velocity == 1000, WAIT, 'the drive at 1000 counts/s')
    wait_until(lambda: axis.states[-1].halted, WAIT, 'drive_state halted')
    wait_until(lambda: axis.drive.velocity == 0, WAIT, 'the halted drive standing')
    assert axis.drive.statusword & 0x100  # the drive shows the halt itself
    axis.target.publish(Float64(data=0.7))
    wait_until(lambda: axis.drive.velocity == 700, WAIT, 'the drive moving again')


def test_a_resumed_drive_left_without_targets_is_halted_again(rig):
    # resume's release is delayed on its way (a busy machine) while the command timeout
    # runs out. Once a defect: resume built its controlword first, the timeout halted in
    # between, and the late release undid that halt while drive_state still said halted;
    # no later timeout came, and the drive ran on with nobody sending targets.
    axis = rig(**{'drives.command_timeout': 0.3})
    drives = axis.gateway.node.gateway.drives
    axis.enable(CSV)
    axis.target.publish(Float64(data=1.0))
    wait_until(lambda: axis.drive.velocity == 1000, WAIT, 'the drive at 1000 counts/s')
    wait_until(lambda: axis.drive.statusword & 0x100 and axis.drive.velocity == 0, WAIT,
               'the drive halted by the command timeout, standing')
    send, halts = drives.send, drives.command_timeouts(NODE)

    def delayed(*args, **options):  # until the timeout halts again, if it can meanwhile
        with contextlib.suppress(AssertionError):
            wait_until(lambda: drives.command_timeouts(NODE) > halts, 2.0, 'a timeout halt')
        return send(*args, **options)
    bus, frames = axis.gateway.raw_bus(), []
    try:
        drives.send = delayed
        resumed = axis.command('resume', timeout=WAIT)  # longer than the delay it meets
        drives.send = send
        assert resumed.success, resumed.message
        watch(bus, frames, released_then_halted, 'the release, then a halt, in RPDO 1')
    finally:
        bus.shutdown()
    wait_until(lambda: axis.drive.statusword & 0x100 and axis.drive.velocity == 0, WAIT,
               'the resumed drive halted again, standing')
    wait_until(lambda: axis.states[-1].halted, WAIT, 'drive_state halted')


def released_then_halted(frames: list) -> bool:
    """Return whether RPDO 1 carried a controlword without the halt bit, then one with it."""
    words = [struct.unpack_from('<H', m.data)[0] for m in frames
             if m.arbitration_id == 0x200 + NODE]
    release = next((n for n, word in enumerate(words) if not word & 0x100), None)
    return release is not None and any(word & 0x100 for word in words[release:])


def test_a_target_sent_just_as_the_command_timeout_halts_cannot_undo_the_halt(rig):
    # In CSP the target position goes in RPDO 1 with the controlword. The caller's thread is
    # preempted between building that frame (controlword: run) and sending it, for longer
    # than the command timeout. Once a defect: the halt went out meanwhile and the late frame
    # undid it; the caller fell silent, drive_state said halted, and the drive ran on.
    axis = rig(**{'drives.command_timeout': 0.3})
    gateway = axis.gateway.node.gateway
    wait_until(lambda: gateway.monitor.status(NODE).state == OPERATIONAL
               and 1 in gateway.pdo.mappings(NODE)[1], WAIT,
               'the drive heard OPERATIONAL, its RPDO 1 read: targets go in it')
    axis.enable(CSP)
    send, caller, other_sent = gateway.pdo._send, threading.get_ident(), threading.Event()

    def preempted(mapping, frame, **options):
        if threading.get_ident() == caller:
            other_sent.wait(1.0)  # the halt, if it can go before this frame
        result = send(mapping, frame, **options)
        if threading.get_ident() != caller:
            other_sent.set()
        return result
    gateway.pdo._send = preempted
    assert gateway.drives.target(NODE, 100).success  # then silence
    wait_until(lambda: axis.states[-1].halted, WAIT, 'drive_state halted')
    wait_until(lambda: axis.drive.statusword & 0x100, WAIT, 'the drive halted, as shown')


def enabled_in_csp_with_sync(rig):
    """Return (rig, gateway): the drive's PDOs synchronous, SYNC every 0.5 s, enabled in CSP.

    Its quick stop option (0x605A) keeps it in QUICK_STOP_ACTIVE, from where a controlword
    that enables operation runs it again (transition 16).
    """
    axis = rig(pdos=default_drive_pdos(1), **{'sync.period': 0.5})
    axis.drive.set_value(QUICK_STOP_OPTION, 0, struct.pack('<h', 6))
    gateway = axis.gateway.node.gateway
    wait_until(lambda: 1 in gateway.pdo.mappings(NODE)[1], WAIT, "the drive's RPDO 1 read")
    # Its PDOs are used once its heartbeat says OPERATIONAL (before: SDO, and no RPDO 1 frame
    # for a stop to be undone by; seen once on a busy machine).
    wait_until(lambda: gateway.monitor.operational(NODE), WAIT,
               'the drive heard OPERATIONAL')
    assert axis.command('enable', CSP, timeout=WAIT).success
    return axis, gateway


def watch(bus, frames: list, condition, what: str):
    """Collect ``bus``'s frames into ``frames`` until ``condition(frames)``; return that.

    A timeout names the last frames seen: a rare miss then says what the bus carried.
    """
    def seen():
        message = bus.recv(0.1)
        if message is not None:
            frames.append(message)
        return condition(frames)
    try:
        return wait_until(seen, WAIT, what)
    except AssertionError as error:
        carried = ' '.join(f'{m.arbitration_id:03X}#{bytes(m.data).hex()}' for m in frames[-40:])
        raise AssertionError(f'{error}; the last frames: {carried or "none"}') from None


def two_syncs_after_the_stop(frames: list) -> bool:
    """Return whether two SYNCs followed the SDO write of the controlword."""
    stop = next((n for n, m in enumerate(frames) if m.arbitration_id == 0x600 + NODE
                 and bytes(m.data[1:4]) == bytes([0x40, 0x60, 0])), None)
    return stop is not None and sum(m.arbitration_id == 0x80 for m in frames[stop:]) >= 2


def last_controlword_in_rpdo1(frames: list) -> int:
    """Return the controlword of the last RPDO 1 frame: the one the drive keeps for SYNC."""
    return struct.unpack_from('<H', [m for m in frames if m.arbitration_id == 0x200 + NODE][-1]
                              .data)[0]


def target_frame_sent(frames: list) -> bool:
    """Return whether RPDO 1 went out with the target position 100 (after a SYNC)."""
    return any(m.arbitration_id == 0x200 + NODE and struct.unpack_from('<i', m.data, 2)[0] == 100
               for m in frames)


@pytest.mark.parametrize('sent', [False, True], ids=['waiting', 'kept by the drive'])
def test_a_stop_by_sdo_is_not_undone_by_a_target_frame_for_the_next_sync(rig, sent):
    # With SYNC a CSP target goes in RPDO 1 (controlword, target position, mode) right after
    # a SYNC, and the drive keeps it to apply at the next one; deactivating the node stops
    # the drive by SDO at once. Once a defect: the frame, waiting in the gateway or kept by
    # the drive, carried the controlword that ran the drive, and that SYNC ran it again.
    axis, gateway = enabled_in_csp_with_sync(rig)
    bus, frames = axis.gateway.raw_bus(), []
    try:
        assert gateway.drives.target(NODE, 100).success
        if sent:
            watch(bus, frames, target_frame_sent, 'the target frame sent after a SYNC')
        gateway.drives.pause('deactivated')
        watch(bus, frames, two_syncs_after_the_stop, 'two SYNCs after the stop')
    finally:
        bus.shutdown()
    assert last_controlword_in_rpdo1(frames) == 0x0002
    assert axis.drive.drive_state == 'QUICK_STOP_ACTIVE'


def test_at_shutdown_the_frame_the_drive_keeps_for_the_sync_carries_the_stop(rig):
    # The gateway's shutdown stops the drives by SDO after its PDO service has stopped, and
    # SYNC goes on until after that. Once a defect: the frame the drive kept still said run.
    axis, gateway = enabled_in_csp_with_sync(rig)
    bus, frames = axis.gateway.raw_bus(), []
    try:
        assert gateway.drives.target(NODE, 100).success
        watch(bus, frames, target_frame_sent, 'the target frame sent after a SYNC')
        gateway.stop()
        # A virtual bus hands each frame to the others as it is sent: all are queued here.
        frames.extend(iter(lambda: bus.recv(0), None))
    finally:
        bus.shutdown()
    assert last_controlword_in_rpdo1(frames) == 0x0002


def test_a_halted_drive_stopped_at_shutdown_is_no_longer_shown_halted(rig):
    # Red team: after a halt, the shutdown's quick stop left drive_state showing the drive
    # halted in SWITCH_ON_DISABLED, though the stop's controlword has no halt bit.
    axis = rig()
    axis.enable(CSV)
    assert axis.command('halt').success
    axis.gateway.node.gateway.drives._stop_motion('shutting down (a test)')
    wait_until(lambda: axis.latest_state() in ('QUICK_STOP_ACTIVE', 'SWITCH_ON_DISABLED'),
               WAIT, 'the drive shown stopped')
    with axis._lock:
        assert not axis.states[-1].halted


def test_enable_on_a_halted_drive_releases_the_halt_and_targets_move_it_again(rig):
    # enable where resume was meant: the drive is already enabled, so no step of the power
    # state machine goes out. Once a defect: the halt bit stayed in the controlword, and
    # targets were answered "sent" while the drive stood.
    axis = rig()
    axis.enable(CSV)
    assert axis.command('halt').success
    axis.enable(CSV)
    axis.target.publish(Float64(data=0.5))
    wait_until(lambda: axis.drive.velocity == 500, WAIT, 'the drive at 500 counts/s')


def test_position_targets_in_pp_are_new_set_points_applied_at_once(rig):
    axis = rig()
    axis.enable(PP)
    for goal in (0.5, 1.0, 0.25):
        axis.target.publish(Float64(data=goal))
    wait_until(lambda: axis.drive.position == 250 and axis.states[-1].target_reached, WAIT,
               'the drive at the last set-point')


def test_homing_answers_when_the_drive_shows_homing_attained(rig):
    axis = rig()
    axis.enable(CSV)
    homed = axis.command('home')
    assert homed.success, homed.message
    assert (homed.mode, homed.statusword & 0x1400) == (HOMING, 0x1400)


# Once a defect (a red team's): a homing replaced just after the drive showed homing attained
# answered only "replaced", though the homing had set the drive's position.
@pytest.mark.parametrize('ended_by', ['replaced', 'timed out'])
def test_a_homing_ended_after_the_drive_homed_says_its_position_was_set(rig, ended_by):
    axis = rig()
    axis.enable(CSV)
    commands = axis.gateway.node.gateway.drives._commands
    homed_here = commands._homed_here
    attained = threading.Event()

    async def held_up(drive) -> str:  # the answer's checks, held until a newer command
        attained.set()
        await asyncio.sleep(60.0)
        return await homed_here(drive)
    commands._homed_here = held_up
    answers = []
    timeout = 3.0 if ended_by == 'timed out' else 0.0
    homing = threading.Thread(
        target=lambda: answers.append(axis.command('home', timeout=timeout)))
    homing.start()
    try:
        assert attained.wait(WAIT), 'the drive never showed homing attained'
        if ended_by == 'replaced':
            assert axis.command('disable').success
    finally:
        homing.join()
    assert not answers[0].success
    assert ended_by in answers[0].message, answers[0].message
    assert 'homing attained' in answers[0].message, answers[0].message
    assert 'home position' in answers[0].message, answers[0].message


def test_a_homing_replaced_on_its_way_home_says_nothing_of_a_home_position(rig):
    axis = rig()
    axis.enable(CSV)
    axis.drive.set_value(HOMING_METHOD, 0, struct.pack('<b', 1))  # travels, not home here
    axis.drive.set_value(PROFILE_VELOCITY, 0, struct.pack('<I', 1))  # at 1 count/s
    axis.target.publish(Float64(data=1.0))
    wait_until(lambda: axis.drive.position > 100, WAIT, 'the axis away from home')
    answers = []
    homing = threading.Thread(target=lambda: answers.append(axis.command('home')))
    homing.start()
    try:
        wait_until(lambda: axis.drive._read(0x6060) == HOMING and axis.drive.velocity == -1,
                   WAIT, 'the drive on its way home')
        assert axis.command('disable').success
    finally:
        homing.join()
    assert 'replaced' in answers[0].message, answers[0].message
    assert 'homing attained' not in answers[0].message, answers[0].message


# Once a race (read in the code): an enable replacing a set_mode left the drive enabled for
# the loop turns before the enable's own first step, so a halt or move checked then was taken
# (and replaced the enable), where one checked a moment later was refused.
def test_a_halt_as_an_enable_replaces_a_set_mode_is_refused_as_one_during_the_enable(rig):
    axis = rig()
    axis.enable(CSV)
    axis.drive.set_value(PROFILE_ACCELERATION, 0, struct.pack('<I', 1000))  # brakes in 1 s
    axis.target.publish(Float64(data=1.0))
    wait_until(lambda: axis.drive.velocity == 1000, WAIT, 'the drive at 1000 counts/s')
    commands = axis.gateway.node.gateway.drives._commands
    mapping_known = commands._mapping_known
    entered, go_on = threading.Event(), threading.Event()

    async def held(drive) -> None:  # the enable's first wait, held while the halt is checked
        entered.set()
        while not go_on.is_set():
            await asyncio.sleep(0.01)
        await mapping_known(drive)
    answers = {}
    changing = threading.Thread(
        target=lambda: answers.update(set_mode=axis.command('set_mode', CSP)))
    changing.start()
    enabling = threading.Thread(
        target=lambda: answers.update(enable=axis.command('enable', CSP, timeout=WAIT)))
    try:
        wait_until(lambda: axis.drive.velocity < 1000, WAIT, 'the axis braking for set_mode')
        commands._mapping_known = held
        enabling.start()
        assert entered.wait(WAIT), 'the enable never began'
        halted = axis.command('halt')
    finally:
        go_on.set()
        changing.join()
        if enabling.is_alive():
            enabling.join()
    assert not halted.success and 'being enabled' in halted.message, halted.message
    assert 'replaced' in answers['set_mode'].message, answers['set_mode'].message
    assert answers['enable'].success, answers['enable'].message


def test_set_mode_holds_the_axis_and_answers_in_the_new_mode(rig):
    axis = rig()
    axis.enable(CSV)
    axis.target.publish(Float64(data=1.0))
    wait_until(lambda: axis.drive.velocity == 1000, WAIT, 'the drive at 1000 counts/s')
    changed = axis.command('set_mode', CST)
    assert changed.success and changed.mode == CST, changed.message
    wait_until(lambda: axis.drive.velocity == 0, WAIT, 'zero torque: the axis at rest')


# Once a defect (a red team's): targets streamed in the old mode while set_mode ran were
# refused only while the axis was halted for it; from the release to the answer (two SYNCs
# and a read, with synchronous RPDOs), the drive took them as the new mode's: a velocity as a
# CSP position, a position as a PP set-point that then replaced the set_mode.
@pytest.mark.parametrize('mode', [CSP, PP])
def test_no_target_is_taken_while_the_mode_changes(rig, mode):
    axis = rig(**{'drives.command_timeout': 0.0})
    axis.enable(CSV)
    axis.target.publish(Float64(data=1.0))
    wait_until(lambda: axis.drive.velocity == 1000, WAIT, 'the drive at 1000 counts/s')
    service = axis.gateway.node.gateway.drives
    commands = service._commands
    release = commands._release_held
    taken = []

    async def releasing(drive, mode, held) -> None:
        await release(drive, mode, held)
        taken.append(service.target(NODE, 12345))  # a target arriving then
    commands._release_held = releasing
    answer = axis.command('set_mode', mode)
    assert answer.success, answer.message
    assert [result.success for result in taken] == [False]
    assert 'changing its mode' in taken[0].message, taken[0].message
    after = service.target(NODE, axis.drive.position)
    assert after.success, after.message


def test_a_set_mode_that_could_not_halt_the_axis_leaves_it_to_the_command_timeout(rig):
    # The drive took no halt (its controlword write failed): set_mode fails, and the axis,
    # running on its last target, must stay what it was, enabled, so that the command
    # timeout halts it once no target comes (it watches no drive that needs an enable).
    axis = rig(**{'drives.command_timeout': 0.5})
    axis.enable(CSV)
    axis.target.publish(Float64(data=1.0))
    wait_until(lambda: axis.drive.velocity == 1000, WAIT, 'the drive at 1000 counts/s')
    commands = axis.gateway.node.gateway.drives._commands
    send = commands._send

    async def refusing_the_halt(drive, values, halt=None, stopping=None):
        if halt == 'mode change':
            raise drive_commands.DriveFailed(f'node {NODE}: the halt was refused (test)')
        return await send(drive, values, halt, stopping)
    commands._send = refusing_the_halt
    answer = axis.command('set_mode', CSP)
    assert not answer.success and 'the halt was refused' in answer.message, answer.message
    wait_until(lambda: axis.drive.velocity == 0, WAIT, 'the command timeout halting the axis')


def move_under_way(axis):
    """Enable in PP and move towards 500 rad at 2 rad/s; return the goal once moving."""
    axis.enable(PP)
    assert axis.mover.wait_for_server(timeout_sec=10.0)
    feedback = []
    goal = wait_for_future(axis.mover.send_goal_async(
        DriveMove.Goal(node_id=NODE, position=500.0, velocity=2.0),
        feedback_callback=feedback.append), WAIT)
    # Cancelled once under way: a cancel before the first step would halt it at 0.
    wait_until(lambda: feedback and feedback[-1].feedback.position > 0, WAIT,
               'move feedback with the drive under way')
    return goal


def test_a_move_ends_with_an_answer_when_the_drive_leaves_operation_enabled_by_itself(rig):
    # Once a defect: the move waited for target reached from a drive no longer enabled, and
    # the goal was never answered.
    axis = rig()
    goal = move_under_way(axis)
    axis.drive.set_value(0x6040, 0, 0x0002)  # the drive's own quick-stop input, say
    result = wait_for_future(goal.get_result_async(), WAIT).result
    assert not result.success, result.message
    assert 'needs a fresh enable' in result.message, result.message
    assert 'left OPERATION_ENABLED, or was stopped, during the command' in result.message, \
        result.message
    refused = axis.command('halt')
    assert not refused.success and 'enable' in refused.message, refused.message


def test_a_halt_that_finds_the_drive_stopped_by_itself_sends_nothing_that_enables_it(rig):
    # The drive quick-stops itself between the halt's check and its send. Once a defect: the
    # halt's controlword (enable operation with bit 8) went out all the same, and the drive
    # took transition 16 out of QUICK_STOP_ACTIVE: the gateway re-enabled it.
    axis = rig()
    axis.drive.set_value(QUICK_STOP_OPTION, 0, struct.pack('<h', 6))  # stays quick-stopped
    axis.enable(CSV)
    drives = axis.gateway.node.gateway.drives
    send = drives.send

    def stopped_first(*args, **options):
        axis.drive.set_value(0x6040, 0, 0x0002)  # its own quick-stop input, say
        wait_until(lambda: drives.status(NODE).state == 'QUICK_STOP_ACTIVE', WAIT,
                   'the gateway seeing the drive quick-stopped')
        return send(*args, **options)
    drives.send = stopped_first
    halted = axis.command('halt')
    drives.send = send
    assert not halted.success and 'needs a fresh enable' in halted.message, halted.message
    assert halted.message.startswith(f'node {NODE} is QUICK_STOP_ACTIVE'), halted.message
    assert axis.drive.drive_state == 'QUICK_STOP_ACTIVE'
    # Nothing was sent, so nothing shows it halted (it once did, and said so until enabled).
    assert not drives.status(NODE).halted


def test_cancelling_a_move_halts_the_drive_and_answers_where_it_stopped(rig):
    axis = rig()
    goal = move_under_way(axis)
    wait_for_future(goal.cancel_goal_async(), WAIT)
    result = wait_for_future(goal.get_result_async(), WAIT).result
    assert not result.success and 'cancelled' in result.message
    assert axis.drive.velocity == 0
    assert 0 < result.position < 500.0
    assert math.isclose(result.position, axis.drive.position / SCALE)


def test_enable_on_a_drive_halted_on_its_way_keeps_it_where_it_stopped(rig):
    # enable where resume was meant, after a cancelled move: the halt is released and the
    # axis stays. Once a defect (f39d984): the halt was released alone, and the drive went
    # on to the set-point it had been halted on its way to.
    axis = rig()
    goal = move_under_way(axis)
    wait_for_future(goal.cancel_goal_async(), WAIT)
    stopped = wait_for_future(goal.get_result_async(), WAIT).result.position
    axis.enable(PP)
    wait_until(lambda: axis.drive.statusword & 0x400 and axis.drive.velocity == 0, WAIT,
               'the drive at a set-point, standing')
    assert not axis.drive.statusword & 0x100, 'still halted'
    assert math.isclose(axis.drive.position / SCALE, stopped)


def test_a_new_move_right_after_a_cancel_answers_the_cancelled_one_and_runs(rig,
                                                                           monkeypatch):
    # Cancel, then a new goal at once: a common client pattern. The new goal comes while
    # the cancelled move waits for its halt (the drive decelerates for ten seconds here).
    # Once a defect: the cancelled goal never got its result and stayed CANCELING.
    monkeypatch.setattr(drive_commands, 'HALT_WAIT', WAIT)
    axis = rig()
    axis.drive.set_value(PROFILE_ACCELERATION, 0, struct.pack('<I', 200))
    first = move_under_way(axis)
    wait_for_future(first.cancel_goal_async(), WAIT)
    second = wait_for_future(axis.mover.send_goal_async(
        DriveMove.Goal(node_id=NODE, position=0.0, velocity=50.0)), WAIT)
    cancelled = wait_for_future(first.get_result_async(), WAIT)
    assert cancelled.status == GoalStatus.STATUS_CANCELED
    assert not cancelled.result.success
    assert 'cancelled' in cancelled.result.message and 'replaced' in cancelled.result.message
    done = wait_for_future(second.get_result_async(), WAIT).result
    assert done.success, done.message
    assert axis.drive.position == 0


def test_a_new_move_replaces_the_one_running(rig):
    axis = rig()
    axis.enable(PP)
    assert axis.mover.wait_for_server(timeout_sec=10.0)
    first = wait_for_future(axis.mover.send_goal_async(
        DriveMove.Goal(node_id=NODE, position=500.0, velocity=2.0)), WAIT)
    second = wait_for_future(axis.mover.send_goal_async(
        DriveMove.Goal(node_id=NODE, position=-0.5, velocity=50.0)), WAIT)
    replaced = wait_for_future(first.get_result_async(), WAIT).result
    done = wait_for_future(second.get_result_async(), WAIT).result
    assert not replaced.success and 'replaced' in replaced.message
    assert done.success, done.message
    assert axis.drive.position == -500  # below zero: decoded as the signed object it is


# Once a defect (a red team's): the action's goal, result and cancel services kept ROS's
# default 10 requests, so a burst of goals lost all but the first few (50 of 300 answered),
# each a goal never answered; the gateway's own services keep 4096.
def test_every_goal_of_a_burst_of_moves_is_answered_and_each_gets_its_result(rig):
    axis = rig()
    axis.enable(PP)
    mover = ActionClient(axis.gateway.client_node, DriveMove, '/cbcan/move',
                         **ACTION_SERVICES_QOS)  # the client keeps a burst's answers too
    assert mover.wait_for_server(timeout_sec=10.0)
    sent = [mover.send_goal_async(DriveMove.Goal(node_id=NODE, position=0.001 * n,
                                                 velocity=5.0)) for n in range(300)]
    wait_until(lambda: all(goal.done() for goal in sent), WAIT,
               'an answer to every goal of the burst')
    handles = [goal.result() for goal in sent]
    assert all(handle.accepted for handle in handles)
    results = [handle.get_result_async() for handle in handles]
    wait_until(lambda: all(result.done() for result in results), WAIT,
               'a result for every goal of the burst')
    last = results[-1].result().result
    assert last.success, last.message  # the newest ran to its end
    ended = [result.result().result for result in results[:-1]]
    # Each earlier one reached its position before the next came, or was replaced by it.
    assert all(result.success or 'replaced' in result.message for result in ended), [
        result.message for result in ended if not result.success
        and 'replaced' not in result.message][:3]


# Once a defect (a red team's): the move action kept every goal 900 s after it ended (rclpy's
# default) and listed each in every status message it published, so with goals sent a few a
# second every goal cost the executor more than the last (the node's CPU at 50 goals/s: 11 %
# of a core at first, 35 % after 90 s) until calls waited behind it for seconds.
def test_an_ended_move_is_kept_for_its_result_a_few_seconds_then_no_longer_listed(rig):
    axis = rig()  # not enabled: every move ends at once, refused
    statuses = []
    axis.gateway.client_node.create_subscription(
        GoalStatusArray, '/cbcan/move/_action/status', statuses.append,
        qos_profile_action_status_default)
    assert axis.mover.wait_for_server(timeout_sec=10.0)

    def ended_move():
        handle = wait_for_future(axis.mover.send_goal_async(
            DriveMove.Goal(node_id=NODE, position=0.5, velocity=1.0)), WAIT)
        result = wait_for_future(handle.get_result_async(), WAIT)
        assert not result.result.success and 'enable' in result.result.message
        return handle

    first = ended_move()
    # Asked for after the goal ended, its result is still there.
    again = wait_for_future(first.get_result_async(), WAIT)
    assert again.status == GoalStatus.STATUS_ABORTED and 'enable' in again.result.message

    def forgotten():
        asked = wait_for_future(first.get_result_async(), WAIT)
        return asked.status == GoalStatus.STATUS_UNKNOWN
    wait_until(forgotten, ACTION_RESULT_KEPT + WAIT, 'the ended move no longer kept')
    second = ended_move()
    wait_until(lambda: statuses and any(status.goal_info.goal_id.uuid.tobytes()
                                        == second.goal_id.uuid.tobytes()
                                        for status in statuses[-1].status_list),
               WAIT, 'a status message listing the new move')
    listed = [status.goal_info.goal_id.uuid.tobytes() for status in statuses[-1].status_list]
    assert first.goal_id.uuid.tobytes() not in listed


def test_nan_and_out_of_range_targets_are_refused_and_nothing_moves(rig):
    axis = rig()
    axis.enable(CSV)
    drives = axis.gateway.node.gateway.drives
    for value in (float('nan'), float('inf'), 2.0 ** 40):
        refused = drives.target(NODE, value)
        assert not refused.success and 'nothing was sent' in refused.message
    assert axis.drive.velocity == 0


def move_goal(axis, **fields):
    """Send a ~/move goal to the drive with ``fields``; return its result."""
    assert axis.mover.wait_for_server(timeout_sec=10.0)
    goal = wait_for_future(axis.mover.send_goal_async(DriveMove.Goal(node_id=NODE, **fields)),
                           WAIT)
    return wait_for_future(goal.get_result_async(), WAIT).result


def test_a_move_slower_than_a_count_per_second_or_backwards_is_refused(rig):
    # 0.0004 rad/s is 0.4 counts/s: rounded to 0 it would be the drive's profile velocity,
    # 25,000 times faster than asked. A negative velocity has no meaning for a move.
    axis = rig()
    axis.enable(PP)
    for velocity, said in ((0.0004, '0.4 counts/s at node_7.velocity_scale 1000: below the 1 '
                                    'count/s a drive takes'),
                           (0.0009, '0.9 counts/s'),  # not rounded up to twice as fast
                           (-5.0, 'velocity -5.0 must be 0')):
        result = move_goal(axis, position=2.0, velocity=velocity)
        assert not result.success
        assert said in result.message and 'nothing was sent' in result.message, result.message
    assert axis.drive.position == 0
    assert move_goal(axis, position=0.002, velocity=0.001).success  # 1 count/s


def test_an_int_given_for_a_float_field_is_refused_naming_the_number_meant(rig, caplog):
    # rclpy (Jazzy) sends a Python int in a float64 field as a tiny number: 5 arrives as
    # 5e-324, which as a timeout would end a command at once, and as a target drive the
    # axis to 0.
    caplog.set_level(logging.WARNING, logger='cbcan_ros.ros.drives')
    axis = rig()
    refused = axis.command('enable', PP, timeout=5)
    assert not refused.success
    assert 'timeout 5e-324 is what rclpy sends for a Python int' in refused.message
    assert axis.drive.drive_state == 'SWITCH_ON_DISABLED'
    axis.enable(PP)
    for field in ('position', 'velocity', 'timeout'):
        fields = {'position': 2.0, 'velocity': 1.0, field: 3}
        result = move_goal(axis, **fields)
        assert not result.success
        assert f'{field} 5e-324 is what rclpy sends' in result.message, result.message
    axis.enable(CSP)
    axis.target.publish(Float64(data=0.5))
    wait_until(lambda: axis.drive.position == 500, WAIT, 'the drive at 500 counts (CSP)')
    axis.target.publish(Float64(data=5))
    wait_until(lambda: 'target 5e-324 is what rclpy sends' in caplog.text, WAIT,
               'the int target refused, in the log')
    assert axis.drive.position == 500


def test_cancelling_a_replaced_goal_leaves_the_new_goal_running(rig):
    axis = rig()
    axis.enable(PP)
    assert axis.mover.wait_for_server(timeout_sec=10.0)
    old = wait_for_future(axis.mover.send_goal_async(
        DriveMove.Goal(node_id=NODE, position=50.0, velocity=2.0)), WAIT)
    new = wait_for_future(axis.mover.send_goal_async(
        DriveMove.Goal(node_id=NODE, position=-0.2, velocity=50.0)), WAIT)
    wait_for_future(old.cancel_goal_async(), WAIT)
    assert 'replaced' in wait_for_future(old.get_result_async(), WAIT).result.message
    done = wait_for_future(new.get_result_async(), WAIT).result
    assert done.success, done.message
    assert axis.drive.position == -200


def test_a_goal_that_overflows_the_drive_units_is_refused_naming_it(rig):
    axis = rig()
    axis.enable(PP)
    assert axis.mover.wait_for_server(timeout_sec=10.0)
    goal = wait_for_future(axis.mover.send_goal_async(
        DriveMove.Goal(node_id=NODE, position=1.7e306, velocity=1.0)), WAIT)
    result = wait_for_future(goal.get_result_async(), WAIT).result
    assert not result.success
    assert 'position' in result.message and 'nothing was sent' in result.message
    assert len(result.message) < 300
    assert axis.drive.velocity == 0


def test_a_refused_target_stream_is_logged_once_per_incident(rig, caplog):
    caplog.set_level(logging.WARNING, logger='cbcan_ros.ros.drives')
    axis = rig()

    def refusals() -> int:
        return sum('call drive_command enable first' in record.getMessage()
                   for record in caplog.records)

    def moving_at(velocity: float) -> None:
        # Targets are taken in order: once this one moves the drive, those before are done.
        axis.target.publish(Float64(data=velocity))
        wait_until(lambda: axis.drive.velocity == velocity * SCALE, WAIT, f'velocity {velocity}')

    axis.enable(CSV)
    moving_at(0.25)
    for incident in (1, 2):
        assert axis.command('disable').success
        for _ in range(5):
            axis.target.publish(Float64(data=0.5))  # refused: the drive is disabled
        wait_until(lambda count=incident: refusals() >= count, WAIT, f'refusal {incident} logged')
        axis.enable(CSV)
        moving_at(0.25 * (incident + 1))
        assert refusals() == incident, 'a stream of refused targets logged more than once'
