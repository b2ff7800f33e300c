"""A drive configured with nothing but drives.nodes stops by itself when the gateway dies.

The gateway beats as node 127 (no heartbeat.node_id given), writes each drive's heartbeat
consumer (0x1016:1) and, where the drive's abort connection option (0x6007) is 0 (no
reaction, as some drives ship), sets it, or refuses enable when told to leave it. Giving all
of that up takes a parameter that says so.
"""

import struct

import test_drives
from test_drives import CSV, WAIT

from cbcan_ros.simulation.durand.drive_objects import ABORT_CONNECTION_OPTION, CONSUMER_HEARTBEAT

from conftest import wait_until

rig = test_drives.rig  # a gateway with one simulated drive (a fixture)
OWN_ID = 127


def watched(axis, milliseconds: int = 3000) -> bool:
    """Return whether the drive holds the gateway's heartbeat in 0x1016:1."""
    return axis.drive.value(CONSUMER_HEARTBEAT, 1) == struct.pack('<I', OWN_ID << 16
                                                                   | milliseconds)


def test_drives_watch_the_gateway_heartbeat_without_any_parameter_for_it(rig):
    axis = rig(**{'drives.consumer_time': None})  # the defaults, as a new user has them
    wait_until(lambda: watched(axis, 500), WAIT, "the drive watching node 127's heartbeat")
    bus = axis.gateway.raw_bus()
    try:
        wait_until(lambda: (lambda m: m is not None and m.arbitration_id == 0x700 + OWN_ID)(
            bus.recv(0.1)), WAIT, 'the gateway heartbeat on the bus')
    finally:
        bus.shutdown()
    assert axis.drive.value(ABORT_CONNECTION_OPTION, 0) == struct.pack('<h', 3)


def test_a_drive_without_a_reaction_to_a_lost_heartbeat_is_set_to_quick_stop(rig):
    axis = rig(before_gateway=lambda drive: drive.set_value(ABORT_CONNECTION_OPTION, 0,
                                                          struct.pack('<h', 0)))
    wait_until(lambda: axis.drive.value(ABORT_CONNECTION_OPTION, 0) == struct.pack('<h', 3),
               WAIT, '0x6007 set from 0 to 3 (quick stop)')
    axis.enable(CSV)


def test_a_drive_left_without_a_reaction_is_refused_enable_saying_why(rig):
    axis = rig(before_gateway=lambda drive: drive.set_value(ABORT_CONNECTION_OPTION, 0,
                                                          struct.pack('<h', 0)),
               **{'drives.abort_connection': 'none'})
    wait_until(lambda: watched(axis), WAIT, 'the drive watching the heartbeat')

    def refused():
        answer = axis.command('enable', CSV)
        return not answer.success and '0x6007' in answer.message and answer
    answer = wait_until(refused, WAIT, 'enable refused naming 0x6007')
    assert 'nothing was sent' in answer.message
    assert axis.drive.drive_state == 'SWITCH_ON_DISABLED'
    assert axis.drive.value(ABORT_CONNECTION_OPTION, 0) == struct.pack('<h', 0)


def test_keeping_drives_running_without_the_gateway_writes_nothing_for_it(rig):
    axis = rig(**{'drives.keep_running_if_gateway_dies': True})
    axis.enable(CSV)
    assert axis.drive.value(CONSUMER_HEARTBEAT, 1) == bytes(4)
    bus = axis.gateway.raw_bus()
    try:
        seen = [bus.recv(0.05) for _ in range(10)]
    finally:
        bus.shutdown()
    assert not [m for m in seen if m is not None and m.arbitration_id == 0x700 + OWN_ID]
