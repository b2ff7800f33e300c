"""A ros2_canopen user's bus.yml starts the gateway: their example files, our devices' EDS.

The files of ``test/bus_descriptions`` are ros2_canopen's own examples (and one written in the
shape of its SDO example); the EDS files they name are ours, the devices durand's. Each device
must boot: checked, configured as the file says, and started.
"""

import pathlib
import shutil
import struct

from action_msgs.msg import GoalStatus
import pytest
from rclpy.action import ActionClient

from cbcan_ros.action import DriveMove
from cbcan_ros.simulation.durand.device import DurandDevice
from cbcan_ros.simulation.durand.drive import DurandDrive

from conftest import frames_within, new_channel, wait_for_future, wait_until

ROOT = pathlib.Path(__file__).resolve().parent.parent
FILES = ROOT / 'test' / 'bus_descriptions'
DEVICE_EDS = ROOT / 'config' / 'simulated_device.eds'
DRIVE_EDS = ROOT / 'config' / 'cia402_drive.eds'
WAIT = 20.0
PP = 1


def copied(tmp_path, name: str, eds_names) -> str:
    """Copy a bus file and put our EDS under the names it gives; return its path."""
    shutil.copy(FILES / name, tmp_path / 'bus.yml')
    for eds_name, source in eds_names.items():
        shutil.copy(source, tmp_path / eds_name)
    return str(tmp_path / 'bus.yml')


def booted(harness, node_ids):
    """Wait until every node booted; return their states by node id."""
    def states():
        shown = {s.node_id: s for s in harness.node.gateway.boot.states()}
        return all(shown[n].state == 'BOOTED' for n in node_ids) and shown
    try:
        return wait_until(states, WAIT, f'nodes {node_ids} BOOTED')
    except AssertionError as timed_out:
        raise AssertionError(f'{timed_out}; their boots: '
                             f'{harness.node.gateway.boot.states()}') from None


@pytest.mark.parametrize('name', ['simple.yml', 'simple_diagnostics.yml', 'proxy_sdo.yml'])
def test_a_proxy_bus_file_boots_and_starts_every_device(make_gateway, tmp_path, name):
    channel = new_channel()
    devices = [DurandDevice(node_id, channel=channel) for node_id in (2, 3)]
    for device in devices:
        device.start()
    try:
        gateway = make_gateway(can__channel=channel, simulation__devices=None,
                               bus_config=copied(tmp_path, name, {'simple.eds': DEVICE_EDS}))
        states = booted(gateway, (2, 3))
        assert [states[n].name for n in (2, 3)] == ['proxy_device_1', 'proxy_device_2']
        wait_until(lambda: all(device.state == 5 for device in devices), WAIT,
                   'every device OPERATIONAL')
        assert gateway.node.gateway.pdo.node_ids == [2, 3]  # ProxyDriver: PDOs served
        if name == 'proxy_sdo.yml':  # the sdo list of defaults, one node's own list
            assert devices[0].value(0x2003) == struct.pack('<i', 0x12345678)
            assert devices[0].value(0x2002) == struct.pack('<I', 0xFFFF)
            assert devices[1].value(0x2003) == struct.pack('<i', 7)
            assert devices[1].value(0x1017) == struct.pack('<H', 500)
            assert devices[1].value(0x1A00, 1) == struct.pack('<I', 0x20020020)
    finally:
        for device in devices:
            device.stop()


@pytest.fixture
def cia402_example(make_gateway, tmp_path):
    """Return ``start(**drive_options)``: a drive at node 2, the gateway on cia402.yml.

    ros2_canopen's CiA 402 example file, with our drive EDS under the name it gives.
    """
    drives = []

    def start(**drive_options):
        channel = new_channel()
        drive = DurandDrive(2, channel=channel, **drive_options)
        drive.start()
        drives.append(drive)
        gateway = make_gateway(can__channel=channel, simulation__devices=None,
                               drives__consumer_time=3.0, drives__command_timeout=0.0,
                               bus_config=copied(tmp_path, 'cia402.yml',
                                                 {'cia402_slave.eds': DRIVE_EDS}))
        return gateway, drive

    yield start
    for drive in drives:
        drive.stop()


def test_ros2_canopens_cia402_example_configures_a_drive_that_then_moves(cia402_example):
    gateway, drive = cia402_example()
    booted(gateway, (2,))
    assert drive.value(0x60C2, 1) == bytes([50])
    assert drive.value(0x6081) == struct.pack('<I', 1000)
    assert drive.value(0x1601, 0) == b'\x02'  # RPDO 2: target position, velocity
    assert drive.value(0x1601, 1) == struct.pack('<I', 0x607A0020)
    wait_until(lambda: drive.state == 5, WAIT, 'the drive OPERATIONAL')
    assert gateway.node.gateway.sync.status().period == pytest.approx(0.01)
    # The file's drive: joint name its node's, ros2_canopen's scale of 1000 per rad.
    assert gateway.call('drive_command', node_id=2, command='enable', mode=PP).success
    start = drive.position
    mover = ActionClient(gateway.client_node, DriveMove, '/cbcan/move')
    assert mover.wait_for_server(timeout_sec=10.0)
    goal = wait_for_future(mover.send_goal_async(DriveMove.Goal(
        node_id=2, position=start / 1000 + 0.5, velocity=1.0)), WAIT)
    result = wait_for_future(goal.get_result_async(), WAIT)
    assert result.status == GoalStatus.STATUS_SUCCEEDED, result.result.message
    assert drive.position == start + 500
    mover.destroy()


def test_a_drive_whose_boot_failed_cannot_be_enabled(cia402_example):
    gateway, drive = cia402_example(identity=(0, 0x51, 0x10000, 0))  # not a 0x402
    wait_until(lambda: gateway.node.gateway.boot.states()[0].state == 'FAILED', WAIT,
               'the boot failed')
    wait_until(lambda: gateway.node.gateway.drives.status(2).state != 'UNKNOWN', WAIT,
               'the drive read, though not started')
    bus = gateway.raw_bus()
    try:
        answer = gateway.call('drive_command', node_id=2, command='enable', mode=PP)
        assert not answer.success, answer.message
        assert 'boot failed (CiA 302-2 error M' in answer.message, answer.message
        sent = frames_within(bus, 0.5)  # what the refusal may have sent
    finally:
        bus.shutdown()
    assert not [m for m in sent if m.arbitration_id == 0x602 and m.data[1:3] == b'\x40\x60'
                and m.data[0] >> 5 == 1], 'a controlword was written'
    assert drive.drive_state != 'OPERATION_ENABLED' and drive.state == 127


def test_make_runs_bus_description_boots_its_simulated_devices(make_gateway):
    gateway = make_gateway(simulation__drives=[6], drives__consumer_time=3.0,
                           bus_config=str(ROOT / 'config' / 'simulation_bus.yml'))
    states = booted(gateway, (2, 3, 5, 6))
    assert [states[n].name for n in (2, 3, 5, 6)] == ['conveyor_io', 'gripper_io', 'lamp_io',
                                                      'wheel']
    assert 'not started (start: false)' in states[5].message
    assert gateway.device(2).node.get_data(0x2021, 0) == b'conveyor'
    wait_until(lambda: gateway.device(2).state == 5 and gateway.device(5).state == 127, WAIT,
               'node 2 started, node 5 left pre-operational')
