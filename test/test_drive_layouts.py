"""Every drive behaviour on every PDO layout real drives ship, the frames on the bus in order.

The simulated drive takes each layout of ``simulated_drives.LAYOUTS``: ``make run``'s combined
RPDO, the CiA 402 vendor default of EPOS2 or Faulhaber EDS files (the controlword in every
RPDO, the target position only in RPDO 3), ros2_canopen's example layout (the controlword in
RPDO 1, the target position in RPDO 2, synchronous TPDOs) and none at all (SDO). Each test
runs the drive as a robot program would and asserts what the drive did, and for the
set-point handshake what went on the bus: the target in the drive before the controlword's
rising bit 4, which the drive takes with the target it holds then.
"""

from dataclasses import replace
import struct
import threading

from action_msgs.msg import GoalStatus
from diagnostic_msgs.msg import DiagnosticArray
import pytest
from std_msgs.msg import Float64
import test_drives
from test_drives import CSP, CST, CSV, HOMING, NODE, PP, PV, SCALE, WAIT, watch

from cbcan_ros.action import DriveMove
from cbcan_ros.core.drives import cia402
from cbcan_ros.core.drives.service import DriveService
from cbcan_ros.core.nmt import OPERATIONAL
from cbcan_ros.core.pdo.service import REPLACED
from cbcan_ros.core.sdo.request_queue import resolved
from cbcan_ros.core.sdo.requests import SdoResult
from cbcan_ros.core.text import SHUTTING_DOWN
from cbcan_ros.simulation.durand.drive_objects import (
    HOME_OFFSET,
    MAX_TORQUE,
    PROFILE_VELOCITY,
    SOFTWARE_POSITION_LIMIT,
    TARGET_POSITION,
    TARGET_VELOCITY,
)
from cbcan_ros.simulation.durand.drive_pdos import drive_pdos as layout_pdos
from cbcan_ros.simulation.durand.drive_pdos import (
    EVENT_DRIVEN,
    MOTION,
    SYNCHRONOUS,
    TIMER_DRIVEN,
)
from cbcan_ros.simulation.durand.pdos import PdoConfig
from cbcan_ros.simulation.simulated_drives import LAYOUTS

from conftest import wait_for_future, wait_until
from node_process import ROOT

rig = test_drives.rig  # a gateway with one simulated drive (a fixture)
PT = 4  # profile torque
EXAMPLE_EDS = ROOT / 'config' / 'cia402_drive.eds'  # the vendor layout

# The mapping of each RPDO (COB-ID 0x200 + 0x100 * (n - 1) + node) in a layout.
RPDO_COB_IDS = {1: 0x200, 2: 0x300, 3: 0x400, 4: 0x500}
SDO_REQUEST = 0x600
SYNC = 0x80
EXPEDITED_DOWNLOAD = 0x20  # command specifier 1 of a client's SDO request
OK, WARN = b'\x00', b'\x01'  # diagnostic levels


def writes_on_the_bus(frames: list, layout: str) -> list:
    """Return the drive-object writes among ``frames``: one {index: value} per frame.

    RPDO frames are decoded by the layout's mapping, SDO downloads by their index.
    """
    rpdos = {RPDO_COB_IDS[config.number] + NODE: config.mapping
             for config in layout_pdos(layout) if config.kind == 'rpdo' and config.enabled}
    writes = []
    for message in frames:
        data = bytes(message.data)
        if message.arbitration_id in rpdos:
            values, offset = {}, 0
            for index, _subindex in rpdos[message.arbitration_id]:
                fmt = cia402.FORMATS[index]
                values[index] = struct.unpack_from(fmt, data, offset)[0]
                offset += struct.calcsize(fmt)
            writes.append(values)
        elif (message.arbitration_id == SDO_REQUEST + NODE and data[0] & 0xE0 == EXPEDITED_DOWNLOAD
              and struct.unpack_from('<H', data, 1)[0] in cia402.FORMATS):
            index = struct.unpack_from('<H', data, 1)[0]
            fmt = cia402.FORMATS[index]
            writes.append({index: struct.unpack_from(fmt, data, 4)[0]})
    return writes


def set_points_taken(writes: list) -> list:
    """Return, for each rising bit 4 of the controlword, the target position the drive held.

    Also returns how many frames carried each new controlword value.
    """
    held, taken, controlword = {}, [], 0
    for values in writes:
        held.update(values)
        word = values.get(cia402.CONTROLWORD, controlword)
        if word & cia402.NEW_SET_POINT and not controlword & cia402.NEW_SET_POINT:
            taken.append(held.get(TARGET_POSITION))
        controlword = word
    return taken


@pytest.fixture(params=list(LAYOUTS))
def layout(request):
    """Return the name of a simulated drive's PDO layout."""
    return request.param


def move(axis, position: float, relative: bool = False):
    """Run a ~/move goal to ``position`` (rad) at 20 rad/s; return its result."""
    assert axis.mover.wait_for_server(timeout_sec=10.0)
    goal = wait_for_future(axis.mover.send_goal_async(DriveMove.Goal(
        node_id=NODE, position=position, velocity=20.0, relative=relative)), WAIT)
    assert goal.accepted
    return wait_for_future(goal.get_result_async(), WAIT)


def test_a_move_reaches_its_target_and_the_drive_takes_each_set_point_with_it(rig, layout):
    axis = rig(pdos=layout_pdos(layout))
    axis.enable(PP)
    start = axis.drive.position
    bus, frames = axis.gateway.raw_bus(), []
    try:
        absolute = move(axis, start / SCALE + 3.0)
        assert absolute.status == GoalStatus.STATUS_SUCCEEDED
        assert absolute.result.success, absolute.result.message
        assert axis.drive.position == start + 3000
        relative = move(axis, -1.0, relative=True)
        assert relative.result.success, relative.result.message
        assert axis.drive.position == start + 2000
        watch(bus, frames, lambda seen: len(set_points_taken(
            writes_on_the_bus(seen, layout))) >= 2, 'both set-points on the bus')
    finally:
        bus.shutdown()
    # Each rising bit 4 found the move's own target in the drive: the absolute one, then
    # the relative one, sent as the absolute target it comes to.
    assert set_points_taken(writes_on_the_bus(frames, layout)) == [start + 3000, start + 2000]


def test_a_move_is_not_fooled_by_a_stale_target_left_in_the_drive(rig, layout):
    axis = rig(pdos=layout_pdos(layout))
    start = axis.drive.position
    # Another master (or a power-on default) left a set-point in 0x607A: the drive's own
    # start position, so a set-point taken with it reaches "target" without moving.
    axis.drive.set_value(TARGET_POSITION, 0, struct.pack('<i', start))
    axis.enable(PP)
    result = move(axis, start / SCALE + 3.0)
    assert result.result.success, result.result.message
    assert axis.drive.position == start + 3000
    assert result.result.position == pytest.approx(start / SCALE + 3.0)


def test_every_mode_enables_and_takes_its_targets(rig, layout):
    axis = rig(pdos=layout_pdos(layout))
    for mode in (PP, PV, HOMING, CSP, CSV, CST):
        response = axis.enable(mode)
        assert (response.state, response.mode) == ('OPERATION_ENABLED', mode)
    axis.enable(CSV)
    axis.target.publish(Float64(data=1.5))
    wait_until(lambda: axis.drive.velocity == 1500, WAIT, 'the drive at 1500 counts/s (CSV)')
    axis.enable(PV)
    axis.target.publish(Float64(data=-0.5))
    wait_until(lambda: axis.drive.velocity == -500, WAIT, 'the drive at -500 counts/s (PV)')
    assert axis.command('halt', timeout=WAIT).success
    axis.enable(CSP)
    start = axis.drive.position
    axis.target.publish(Float64(data=start / SCALE + 0.25))
    wait_until(lambda: axis.drive.position == start + 250, WAIT, 'the drive 250 counts on (CSP)')
    axis.enable(CST)
    axis.target.publish(Float64(data=3.0))
    wait_until(lambda: axis.drive.torque == 3, WAIT, 'the drive at torque 3 (CST)')
    assert axis.command('disable').state == 'SWITCH_ON_DISABLED'


def test_a_move_the_drive_finishes_away_from_its_target_fails_naming_both(rig):
    axis = rig()
    axis.enable(PP)
    start = axis.drive.position
    take = axis.drive._take_set_point

    def stale(controlword):
        # A drive that takes the set-point with the target it held before the frame.
        axis.drive.node.object_dictionary.write(TARGET_POSITION, 0, start)
        take(controlword)
    axis.drive._take_set_point = stale
    result = move(axis, start / SCALE + 3.0).result
    assert not result.success
    assert axis.drive.position == start
    assert f'at position {start}, not at the target {start + 3000}' in result.message
    assert '(0x607A) read back: ' in result.message


def test_a_stream_of_pp_targets_whose_last_set_point_is_missed_shows_it_in_diagnostics(rig):
    axis = rig()
    axis.enable(PP)
    start = axis.drive.position
    diagnostics = []
    axis.gateway.client_node.create_subscription(DiagnosticArray, '/diagnostics',
                                                 diagnostics.append, 10)

    def drive_item():
        for array in reversed(diagnostics[-3:]):
            for status in array.status:
                if status.name.endswith(f'drive {NODE}'):
                    return status
        return None
    take = axis.drive._take_set_point

    def stale(controlword):
        # A drive that takes the set-point with the target it held before the frame.
        axis.drive.node.object_dictionary.write(TARGET_POSITION, 0, start)
        take(controlword)
    axis.drive._take_set_point = stale
    for step in (1, 2, 3):  # a stream: only the last one is checked
        axis.target.publish(Float64(data=start / SCALE + step))

    def missed_last():
        # A loaded machine may deliver the three apart: each is then the last one in turn.
        item = drive_item()
        if item is None or item.level != WARN:
            return None
        shown = {pair.key: pair.value for pair in item.values}.get(
            'Last PP set-point streamed', '')
        return (item, shown) if f'target {start + 3000}' in shown else None
    missed, shown = wait_until(missed_last, WAIT, 'the missed last set-point on /diagnostics')
    assert f'at position {start}, not at the target {start + 3000}' in shown, shown
    assert 'the last PP set-point streamed was missed' in missed.message
    axis.drive._take_set_point = take  # the next stream arrives: shown again as OK
    axis.target.publish(Float64(data=start / SCALE + 1))
    wait_until(lambda: axis.drive.position == start + 1000, WAIT, 'the drive at its target')
    wait_until(lambda: drive_item() is not None and drive_item().level == OK, WAIT,
               'the drive OK on /diagnostics once a stream reached its last set-point')


def test_halt_resume_quick_stop_fault_reset_and_homing(rig, layout):
    axis = rig(pdos=layout_pdos(layout))
    axis.enable(CSV)
    axis.target.publish(Float64(data=1.0))
    wait_until(lambda: axis.drive.velocity == 1000, WAIT, 'the drive at 1000 counts/s')
    halted = axis.command('halt', timeout=WAIT)
    assert halted.success, halted.message
    assert axis.drive.velocity == 0
    assert axis.command('resume').success
    axis.target.publish(Float64(data=0.5))
    wait_until(lambda: axis.drive.velocity == 500, WAIT, 'the drive at 500 counts/s again')
    stopped = axis.command('quick_stop', timeout=WAIT)
    assert stopped.success, stopped.message
    wait_until(lambda: axis.drive.velocity == 0, WAIT, 'the quick-stopped drive standing')
    axis.enable(CSV)
    axis.drive.inject_fault(0x2310)
    wait_until(lambda: axis.latest_state() == 'FAULT', WAIT, 'drive_state FAULT')
    assert not axis.command('enable', CSV).success
    reset = axis.command('fault_reset')
    assert reset.success and reset.state == 'SWITCH_ON_DISABLED', reset.message
    axis.drive.set_value(HOME_OFFSET, 0, struct.pack('<i', 1234))
    axis.enable(PP)
    homed = axis.command('home', timeout=WAIT)
    assert homed.success, homed.message
    assert axis.drive.position == 1234


def test_the_command_timeout_halts_a_streaming_drive(rig, layout):
    axis = rig(pdos=layout_pdos(layout), **{'drives.command_timeout': 0.3})
    axis.enable(CSV)
    axis.target.publish(Float64(data=1.0))
    wait_until(lambda: axis.drive.velocity == 1000, WAIT, 'the drive at 1000 counts/s')
    wait_until(lambda: axis.drive.velocity == 0, WAIT, 'the drive halted without targets')
    wait_until(lambda: axis.states[-1].halted, WAIT, 'drive_state halted')
    axis.target.publish(Float64(data=0.7))
    wait_until(lambda: axis.drive.velocity == 700, WAIT, 'the drive moving again')


# The modes whose drives may ignore controlword bit 8, each with a target that moves the axis.
IN_THE_MODES_THAT_MAY_IGNORE_THE_HALT_BIT = pytest.mark.parametrize(
    'mode, target', [(CSV, 1.0), (CSP, None), (CST, 5.0), (PT, 5.0)],
    ids=['CSV', 'CSP', 'CST', 'PT'])


def drive_ignoring_the_halt_bit(rig, mode: int, command_timeout: float):
    """Return the rig with its drive ignoring bit 8 in the cyclic modes, enabled in ``mode``."""
    axis = rig(**{'drives.command_timeout': command_timeout})
    axis.drive.halts_in_cyclic_modes = False
    axis.enable(mode)
    return axis


@IN_THE_MODES_THAT_MAY_IGNORE_THE_HALT_BIT
def test_the_command_timeout_stops_a_drive_that_ignores_the_halt_bit(rig, mode, target):
    # Several vendors' drives ignore controlword bit 8 in the cyclic modes: the command
    # timeout sets the target that stops the axis too (CSP: where it stands).
    axis = drive_ignoring_the_halt_bit(rig, mode, 0.3)
    if mode == CSP:  # a stream that keeps the axis moving, then silence
        start = axis.drive.position
        for step in range(1, 6):
            axis.target.publish(Float64(data=(start + 100 * step) / SCALE))
        wait_until(lambda: axis.drive.position == start + 500, WAIT, 'the drive 500 on')
        wait_until(lambda: axis.states[-1].halted, WAIT, 'drive_state halted')
        assert axis.drive.position == start + 500
        return
    axis.target.publish(Float64(data=target))
    moving = (lambda: axis.drive.velocity == 1000) if mode == CSV else (
        lambda: axis.drive.torque == 5)
    wait_until(moving, WAIT, 'the drive following its target')
    wait_until(lambda: axis.states[-1].halted, WAIT, 'drive_state halted')
    wait_until(lambda: axis.drive.velocity == 0 and axis.drive.torque == 0, WAIT,
               'the drive stopped by its target though it ignores the halt bit')


@IN_THE_MODES_THAT_MAY_IGNORE_THE_HALT_BIT
def test_a_halt_command_stops_a_drive_that_ignores_the_halt_bit(rig, mode, target):
    # The same drives (bit 8 without function in the cyclic modes): the halt command sets
    # the stopping target too, and its answer waits for the axis to stand. No command
    # timeout: the halt alone must stop it.
    axis = drive_ignoring_the_halt_bit(rig, mode, 0.0)
    if mode == CSP:  # each target moves the axis on: the halt must leave it where it is
        start = axis.drive.position
        axis.target.publish(Float64(data=(start + 300) / SCALE))
        wait_until(lambda: axis.drive.position == start + 300, WAIT, 'the drive 300 on')
    else:
        axis.target.publish(Float64(data=target))
        wait_until((lambda: axis.drive.velocity == 1000) if mode == CSV else (
            lambda: axis.drive.torque == 5), WAIT, 'the drive following its target')
    halted = axis.command('halt')
    assert halted.success, halted.message
    assert axis.drive.velocity == 0 and axis.drive.torque == 0, (
        axis.drive.velocity, axis.drive.torque)
    if mode == CSP:
        assert axis.drive.position == start + 300
    assert axis.drive.drive_state == 'OPERATION_ENABLED'  # halted, not switched off


def test_a_drive_reset_to_its_factory_pdos_is_configured_from_its_eds_and_moves(rig):
    # The drive's own mapping has no PDO at all; the EDS of config/ maps the vendor layout,
    # written at every boot (pdo.configure).
    axis = rig(pdos=layout_pdos('sdo_only'), **{'pdo.configure': True,
                                                f'node_{NODE}.eds': str(EXAMPLE_EDS)})
    gateway = axis.gateway.node.gateway

    def boot():
        return next(state for state in gateway.boot.states() if state.node_id == NODE)
    # The gateway's start is a boot too, which writes the EDS's PDOs already: only a boot
    # counted after the reset is the reset's.
    wait_until(lambda: boot().state == 'BOOTED', WAIT, 'the boot at start ended')
    booted = boot().boots
    assert axis.gateway.call('nmt_command', node_id=NODE, command=129).success  # reset node

    def vendor_layout_read():
        rpdos = gateway.pdo.mappings(NODE)[1]
        return 3 in rpdos and rpdos[3].enabled and [
            entry.index for entry in rpdos[3].entries] == [cia402.CONTROLWORD, TARGET_POSITION]
    wait_until(vendor_layout_read, WAIT, "the EDS's RPDO 3 (controlword, target) read back")
    # The mapping is read within the boot, which ends a moment later: enable is refused
    # until it has (seen under load, the boot thread starved past the checks below).
    wait_until(lambda: boot().state == 'BOOTED' and boot().boots > booted, WAIT,
               'the boot of the drive after its reset ended')
    assert axis.gateway.call('nmt_command', node_id=NODE, command=1).success
    # The gateway's own state (UNKNOWN while it reads the drive again), not the last one
    # published, which may be from before the reset.
    wait_until(lambda: gateway.drives.status(NODE).state == 'SWITCH_ON_DISABLED'
               and gateway.monitor.status(NODE).state == OPERATIONAL, WAIT,
               'the drive read again, heard OPERATIONAL: its PDOs are used')
    axis.enable(PP)
    start = axis.drive.position
    bus, frames = axis.gateway.raw_bus(), []
    try:
        result = move(axis, start / SCALE + 2.0)
        assert result.result.success, result.result.message
        watch(bus, frames, lambda seen: set_points_taken(writes_on_the_bus(seen, 'vendor')),
              'the set-point on the bus')
    finally:
        bus.shutdown()
    assert axis.drive.position == start + 2000
    assert set_points_taken(writes_on_the_bus(frames, 'vendor')) == [start + 2000]
    assert any(m.arbitration_id == 0x400 + NODE for m in frames), 'no RPDO 3 sent'


def test_a_move_outside_the_software_position_limits_is_refused_before_anything_is_sent(rig):
    axis = rig()
    axis.drive.set_value(SOFTWARE_POSITION_LIMIT, 1, struct.pack('<i', -5000))
    axis.drive.set_value(SOFTWARE_POSITION_LIMIT, 2, struct.pack('<i', 5000))
    axis.enable(CSV)  # a move would change the mode to PP first
    result = move(axis, 6.0).result
    assert not result.success
    assert 'target 6000 is outside its software position limits -5000..5000' in result.message
    assert 'nothing was sent' in result.message
    assert axis.drive.value(0x6060, 0) == struct.pack('<b', CSV)
    assert move(axis, 4.0).result.success


def test_a_move_that_does_not_arrive_in_time_halts_the_drive_and_says_where(rig):
    axis = rig()
    axis.enable(PP)
    assert axis.mover.wait_for_server(timeout_sec=10.0)
    goal = wait_for_future(axis.mover.send_goal_async(DriveMove.Goal(
        node_id=NODE, position=100.0, velocity=1.0, timeout=0.5)), WAIT)
    result = wait_for_future(goal.get_result_async(), WAIT).result
    assert not result.success
    assert result.message.startswith('timed out after 0.5 s'), result.message
    assert 'halted at position' in result.message, result.message
    assert axis.drive.velocity == 0 and axis.drive.statusword & 0x100
    assert 0 < axis.drive.position < 100_000


def test_a_move_with_velocity_0_uses_the_drives_configured_profile_velocity(rig):
    axis = rig()
    configured = axis.drive.value(PROFILE_VELOCITY, 0)
    axis.enable(PP)
    assert move(axis, 1.0).result.success  # at 20 rad/s
    assert axis.drive.value(PROFILE_VELOCITY, 0) == struct.pack('<I', 20_000)
    assert axis.mover.wait_for_server(timeout_sec=10.0)
    goal = wait_for_future(axis.mover.send_goal_async(DriveMove.Goal(
        node_id=NODE, position=0.5)), WAIT)
    assert wait_for_future(goal.get_result_async(), WAIT).result.success
    assert axis.drive.value(PROFILE_VELOCITY, 0) == configured


def test_drive_settings_written_through_the_gateway_are_the_ones_a_move_uses(rig):
    # The profile velocity (0x6081) and the software position limits (0x607D) are read once;
    # written with the gateway's own sdo_write, the next move follows the new ones, and a
    # move at velocity 0 does not put back the profile velocity read before.
    axis = rig()
    axis.enable(PP)
    assert move(axis, 1.0).result.success  # reads the limits: none
    for index, subindex, data in ((PROFILE_VELOCITY, 0, struct.pack('<I', 7000)),
                                  (SOFTWARE_POSITION_LIMIT, 1, struct.pack('<i', -3000)),
                                  (SOFTWARE_POSITION_LIMIT, 2, struct.pack('<i', 3000))):
        written = axis.gateway.call('sdo_write', node_id=NODE, index=index,
                                    subindex=subindex, data=list(data))
        assert written.success, written.message
    assert axis.mover.wait_for_server(timeout_sec=10.0)
    goal = wait_for_future(axis.mover.send_goal_async(DriveMove.Goal(
        node_id=NODE, position=2.0)), WAIT)
    assert wait_for_future(goal.get_result_async(), WAIT).result.success
    assert axis.drive.value(PROFILE_VELOCITY, 0) == struct.pack('<I', 7000)
    beyond = move(axis, 4.0).result
    assert not beyond.success
    assert 'outside its software position limits -3000..3000' in beyond.message
    assert axis.drive.position == 2000


def test_enabling_in_a_torque_mode_holds_the_configured_torque(rig):
    # A gravity-loaded axis: 0.005 N·m at 1000 drive units per N·m holds it (5 units).
    axis = rig(**{f'node_{NODE}.hold_torque': 0.005, f'node_{NODE}.torque_scale': 1000.0,
                  'drives.command_timeout': 0.3})
    axis.enable(CST)
    wait_until(lambda: axis.drive.torque == 5, WAIT, 'the drive holding torque 5')
    axis.target.publish(Float64(data=0.02))
    wait_until(lambda: axis.drive.torque == 20, WAIT, 'the drive at torque 20')
    wait_until(lambda: axis.states[-1].halted, WAIT, 'halted by the command timeout')
    assert axis.drive.value(0x6071, 0) == struct.pack('<h', 5)  # held, not dropped


# The combined layout with RPDO 2 mapping the max torque (0x6072) beside the target velocity.
MAX_TORQUE_BESIDE_THE_TARGET = tuple(
    replace(pdo, mapping=((TARGET_VELOCITY, 0), (MAX_TORQUE, 0)))
    if (pdo.kind, pdo.number) == ('rpdo', 2) else pdo for pdo in layout_pdos('combined'))


def test_an_rpdo_mapping_an_object_the_gateway_does_not_command_repeats_the_drives_value(rig):
    # RPDO 2 maps the max torque (0x6072) beside the target velocity: a frame of the
    # gateway's making would set it to 0, and the drive could then give no torque at all.
    axis = rig(pdos=MAX_TORQUE_BESIDE_THE_TARGET)
    axis.enable(CSV)
    bus, frames = axis.gateway.raw_bus(), []
    try:
        # A stream, as a program sends: by SDO until the gateway has read the mapping and
        # the max torque, then in RPDO 2.
        def streamed(seen):
            axis.target.publish(Float64(data=1.0))
            return any(m.arbitration_id == 0x300 + NODE for m in seen)
        watch(bus, frames, streamed, 'RPDO 2 on the bus')
        wait_until(lambda: axis.drive.velocity == 1000, WAIT, 'the drive at 1000 counts/s')
    finally:
        bus.shutdown()
    sent = next(m for m in frames if m.arbitration_id == 0x300 + NODE)
    assert struct.unpack_from('<iH', sent.data) == (1000, 1000)
    assert axis.drive.value(MAX_TORQUE, 0) == struct.pack('<H', 1000)


def test_an_enable_waits_for_the_pdo_mapping_being_read_and_targets_then_go_by_pdo(rig):
    # Red team: drives enabled while the gateway still read their PDO mappings (one device
    # after the other, some 0.1 s each) took their first second of streamed targets by SDO:
    # applied at once instead of at a SYNC, and most of them dropped for newer ones.
    axis = rig()
    pdo = axis.gateway.node.gateway.pdo
    release, read = threading.Event(), pdo._parameters.read
    pdo._parameters.read = lambda *args: release.wait(WAIT) and read(*args)
    pdo.read_again(NODE)  # a read under way, as at start with other devices before it
    threading.Timer(1.0, release.set).start()
    # The wait is not the command's time: the steps still get the whole timeout after it.
    enabled = axis.command('enable', CSV, timeout=1.0)
    assert enabled.success, enabled.message
    bus, frames = axis.gateway.raw_bus(), []
    try:
        axis.target.publish(Float64(data=1.0))
        watch(bus, frames, lambda seen: any(m.arbitration_id - NODE in (
            *RPDO_COB_IDS.values(), SDO_REQUEST) for m in seen), 'the target sent')
        wait_until(lambda: axis.drive.velocity == 1000, WAIT, 'the drive at 1000 counts/s')
    finally:
        release.set()
        bus.shutdown()
    assert not target_writes(frames), 'the first target after the enable went by SDO'


def test_a_value_written_by_sdo_through_the_gateway_is_what_its_rpdo_repeats(rig):
    # The user lowers the max torque (0x6072) that RPDO 2 maps beside the target velocity,
    # with the gateway's own sdo_write: the frames after it must carry the new limit, not
    # the copy read when the drive was heard, or the next target would undo the limit.
    axis = rig(pdos=MAX_TORQUE_BESIDE_THE_TARGET)
    axis.enable(CSV)
    bus, frames = axis.gateway.raw_bus(), []
    try:
        def streamed(value):
            def sent(seen):
                axis.target.publish(Float64(data=value))
                return any(m.arbitration_id == 0x300 + NODE
                           and struct.unpack_from('<i', m.data)[0] == value * SCALE
                           for m in seen)
            return sent
        watch(bus, frames, streamed(1.0), 'RPDO 2 on the bus')
        written = axis.gateway.call('sdo_write', node_id=NODE, index=MAX_TORQUE, subindex=0,
                                    data=list(struct.pack('<H', 300)))
        assert written.success, written.message
        del frames[:]
        watch(bus, frames, streamed(2.0), 'RPDO 2 with the next target')
        after_it = [struct.unpack_from('<iH', m.data) for m in frames
                    if m.arbitration_id == 0x300 + NODE]
        # A write the drive refuses (one byte for a 16-bit object) changes nothing it holds:
        # the frames go on carrying 300.
        refused = axis.gateway.call('sdo_write', node_id=NODE, index=MAX_TORQUE, subindex=0,
                                    data=[7])
        assert not refused.success
        del frames[:]
        watch(bus, frames, streamed(3.0), 'RPDO 2 after the refused write')
    finally:
        bus.shutdown()
    assert after_it[-1] == (2000, 300), after_it
    sent = [struct.unpack_from('<iH', m.data) for m in frames
            if m.arbitration_id == 0x300 + NODE]
    assert sent[-1] == (3000, 300), sent
    assert axis.drive.value(MAX_TORQUE, 0) == struct.pack('<H', 300)


def test_a_cancelled_move_halts_the_drive_where_it_is(rig, layout):
    axis = rig(pdos=layout_pdos(layout))
    axis.enable(PP)
    assert axis.mover.wait_for_server(timeout_sec=10.0)
    goal = wait_for_future(axis.mover.send_goal_async(DriveMove.Goal(
        node_id=NODE, position=100.0, velocity=1.0)), WAIT)
    assert goal.accepted
    wait_until(lambda: axis.drive.position > 100, WAIT, 'the move under way')
    wait_for_future(goal.cancel_goal_async(), WAIT)
    result = wait_for_future(goal.get_result_async(), WAIT)
    assert result.status == GoalStatus.STATUS_CANCELED
    assert 'halted at position' in result.result.message, result.result.message
    assert axis.drive.velocity == 0 and axis.drive.statusword & 0x100
    assert axis.drive.position < 100_000


def test_a_stream_of_targets_that_are_not_sent_is_logged_once(rig, caplog):
    # A controller streams targets; the drive (run by SDO) stops answering SDO, so each
    # target times out. One line says so, not one a target (a 250 Hz stream would log 250
    # lines a second); the next target sent ends the incident.
    axis = rig(pdos=layout_pdos('sdo_only'))
    axis.enable(CSV)
    gateway = axis.gateway.node.gateway
    timeouts = gateway.sdo_statistics()[NODE].timeouts
    axis.drive._network.allowed = lambda cob_id: cob_id != 0x580 + NODE  # no SDO answers
    for value in range(1, 11):
        axis.target.publish(Float64(data=value / 10))
        # Apart, so none is replaced in the queue by the next (test below): each times out.
        wait_until(lambda value=value: gateway.sdo_statistics()[NODE].timeouts
                   >= timeouts + value, WAIT, f'target {value} timed out')

    def lines() -> list:
        return [r.message for r in caplog.records if 'a target was not sent' in r.message]
    # The targets queued together time out together: an answer is counted in the statistics
    # just before its caller hears it, so the line may follow the count by a moment.
    wait_until(lines, WAIT, 'the line saying a target was not sent')
    assert len(lines()) == 1, lines()


def test_targets_waiting_to_go_by_sdo_are_replaced_by_the_newest(rig):
    # Red team: a stream at 250 Hz to a drive run by SDO queued a transfer a target; the
    # queue outgrew the timeout, and every later request to the drive (its PDO mapping
    # read) timed out behind it. A target still queued when a newer one comes is dropped.
    axis = rig(pdos=layout_pdos('sdo_only'))
    axis.enable(CSV)
    gateway = axis.gateway.node.gateway
    bus, frames = axis.gateway.raw_bus(), []
    try:
        for value in range(1, 11):  # faster than SDO transfers go: they queue
            assert gateway.drives.target(NODE, value * 100).success
        wait_until(lambda: axis.drive.value(cia402.TARGET_VELOCITY) == struct.pack(
            '<i', 1000), WAIT, 'the last target taken')
        watch(bus, frames, lambda seen: 1000 in target_writes(seen), 'the last target sent')
    finally:
        bus.shutdown()
    sent = target_writes(frames)
    assert sent[-1] == 1000 and len(sent) < 10, f'every queued target went out: {sent}'


def test_targets_sent_and_lost_by_turns_are_one_incident_logged_once(caplog):
    service = DriveService.__new__(DriveService)  # the log's book-keeping alone
    service._lock, service._targets_failing = threading.RLock(), {}
    lost, sent = resolved(SdoResult.aborted(0x05040000, 'TIMEOUT')), resolved(SdoResult.ok())
    replaced = resolved(SdoResult.failed(f'node {NODE}: {REPLACED}; not sent'))
    for outcome in [lost, sent, lost, sent, replaced, lost] * 5:
        service._log_failed_target(NODE, outcome)
    lines = [r.message for r in caplog.records if 'a target was not sent' in r.message]
    assert len(lines) == 1 and 'TIMEOUT' in lines[0], lines
    for outcome in [replaced, sent]:  # a replaced target is not a lost one
        service._log_failed_target(NODE + 1, outcome)
    # Nor is one the shutdown kept back: the gateway says once that it is shutting down.
    service._log_failed_target(NODE + 2, resolved(SdoResult.failed(
        f'RPDO 1 of node {NODE + 2}: {SHUTTING_DOWN}; nothing was sent')))
    assert len([r for r in caplog.records if 'not sent' in r.message]) == 1


def target_writes(frames: list) -> list:
    """Return the target velocities written by SDO (0x60FF) in ``frames``, in order."""
    return [struct.unpack_from('<i', bytes(m.data), 4)[0] for m in frames
            if m.arbitration_id == 0x600 + NODE and bytes(m.data[1:4]) == b'\xff\x60\x00']


# ros2_canopen's RPDOs with the targets' RPDO synchronous, the controlword's not (as a bus.yml
# can set them): the controlword and the mode are applied as they come, the targets only at
# the SYNC after their frame. TPDO 2 (position, velocity) every 10 ms shows any motion.
MIXED = (PdoConfig('tpdo', 1, ((0x6041, 0), (0x6061, 0)), EVENT_DRIVEN, event_timer=20),
         PdoConfig('tpdo', 2, MOTION, TIMER_DRIVEN, event_timer=10),
         PdoConfig('rpdo', 1, ((cia402.CONTROLWORD, 0), (cia402.MODE, 0)), EVENT_DRIVEN),
         PdoConfig('rpdo', 2, ((TARGET_POSITION, 0), (TARGET_VELOCITY, 0)), SYNCHRONOUS),
         *(PdoConfig(kind, number, (), enabled=False)
           for kind in ('tpdo', 'rpdo') for number in (3, 4)))


@pytest.mark.parametrize('command', ['enable', 'set_mode'])
def test_a_holding_target_in_a_synchronous_rpdo_is_applied_before_the_mode_it_holds(rig,
                                                                                   command):
    # Another master left a target far away in 0x607A. Entering CSP, the drive follows
    # 0x607A at once: the target that holds the axis (its actual position) goes first, in
    # the synchronous RPDO 2, and the mode and the controlword in RPDO 1 must wait for the
    # SYNC that applies it, or the drive runs to the stale target meanwhile.
    axis = rig(pdos=MIXED, **{'sync.period': 0.05})
    gateway = axis.gateway.node.gateway
    wait_until(lambda: gateway.monitor.status(NODE).state == OPERATIONAL
               and gateway.pdo.mappings(NODE)[1], WAIT, 'the RPDOs read, the drive OPERATIONAL')
    if command == 'set_mode':
        axis.enable(PP)
    start = axis.drive.position
    axis.drive.set_value(TARGET_POSITION, 0, struct.pack('<i', start + 50000))
    bus, frames = axis.gateway.raw_bus(), []
    try:
        answer = axis.command(command, CSP)
        assert answer.success, answer.message
        assert answer.mode == CSP

        def after_the_mode(seen):  # two SYNCs of motion feedback after the mode was sent
            sent = [n for n, m in enumerate(seen)
                    if m.arbitration_id == 0x200 + NODE and m.data[2] == CSP]
            return sent and sum(m.arbitration_id == SYNC for m in seen[sent[0]:]) >= 2
        watch(bus, frames, after_the_mode, 'two SYNCs after the mode CSP in RPDO 1')
    finally:
        bus.shutdown()
    positions = {struct.unpack_from('<i', m.data)[0] for m in frames
                 if m.arbitration_id == 0x280 + NODE}
    assert positions == {start}, f'the drive moved from {start}: {sorted(positions)}'
    assert axis.drive.position == start
    hold = next(n for n, m in enumerate(frames) if m.arbitration_id == 0x300 + NODE
                and struct.unpack_from('<i', m.data)[0] == start)
    mode = next(n for n, m in enumerate(frames)
                if m.arbitration_id == 0x200 + NODE and m.data[2] == CSP)
    assert any(m.arbitration_id == SYNC for m in frames[hold:mode]), (
        'the mode went before the SYNC that applies the holding target: '
        + ' '.join(f'{m.arbitration_id:03X}#{bytes(m.data).hex()}' for m in frames[:mode + 1]))


def test_an_enable_that_waits_for_slow_syncs_gets_the_time_by_default(rig):
    # At a SYNC every second, the holding target in the synchronous RPDO 2 is applied a
    # SYNC or two after it went out, and the mode waits for that: more than the 2 s a
    # command gets by default without SYNC (a red team's enable timed out every time).
    axis = rig(pdos=MIXED, **{'sync.period': 1.0})
    gateway = axis.gateway.node.gateway
    wait_until(lambda: gateway.monitor.status(NODE).state == OPERATIONAL
               and gateway.pdo.mappings(NODE)[1], WAIT, 'the RPDOs read, the drive OPERATIONAL')
    answer = axis.command('enable', CSP)  # timeout 0: the default
    assert answer.success, answer.message
