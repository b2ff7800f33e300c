"""A drive whose CAN adapter is pulled: it stops by itself, and nothing restarts it unasked.

The gateway runs behind ``test/faulty_bus.py`` (python-can's virtual bus with faults on
command) with one simulated CiA 402 drive (durand) that watches the gateway's heartbeat.
Pulling the adapter cuts the gateway off in both directions, as an unplugged USB adapter does.
"""

from concurrent.futures import Future
import math
import struct
import threading

import pytest
from std_msgs.msg import Float64
from test_drives import CSV, NODE, Rig, WAIT

from cbcan_ros.core.nmt import NOT_DETECTED

from conftest import wait_for_future, wait_until
import faulty_bus
from faulty_bus import FaultController

faulty_bus.register()

OWN_ID = 100
CONSUMER_MS = 300
CONSUMER_HEARTBEAT = 0x1016


@pytest.fixture
def pulled(ros_context, start_durand):
    """Return (rig, faults): a gateway behind the faulty adapter, its drive enabled in CSV."""
    axis = Rig(start_durand, **{'can.interface': 'faulty', 'heartbeat.node_id': OWN_ID,
                                'heartbeat.period': 0.1, 'heartbeat.timeout': 0.5,
                                'drives.consumer_time': CONSUMER_MS / 1000})
    faults = FaultController.get(axis.gateway.channel)
    entry = struct.pack('<I', OWN_ID << 16 | CONSUMER_MS)
    wait_until(lambda: axis.drive.value(CONSUMER_HEARTBEAT, 1) == entry, WAIT,
               'the drive watching the gateway (0x1016:1)')
    axis.enable(CSV)
    axis.target.publish(Float64(data=1.0))
    wait_until(lambda: axis.drive.velocity > 0, WAIT, 'the drive turning')
    yield axis, faults
    faults.clear()
    axis.close()


def pull(faults) -> None:
    """Unplug the adapter: nothing goes out, nothing comes in, it cannot be opened again."""
    faults.fail_open('adapter gone')
    faults.fail_send('adapter unplugged')
    faults.fail_receive('adapter unplugged')


def test_a_drive_cut_off_by_a_pulled_adapter_stops_and_is_not_restarted_when_it_returns(pulled):
    axis, faults = pulled
    pull(faults)
    # The drive's own consumer misses the gateway's beats: the reaction of 0x6007.
    wait_until(lambda: axis.drive.drive_state != 'OPERATION_ENABLED', WAIT,
               'the drive stopping by itself')
    wait_until(lambda: axis.latest_state() == 'UNKNOWN', WAIT, 'drive_state UNKNOWN')
    answer = axis.command('enable', CSV)
    assert not answer.success
    assert 'CAN bus is down' in answer.message and 'nothing was sent' in answer.message, \
        answer.message

    faults.clear()
    wait_until(lambda: axis.latest_state() not in (None, 'UNKNOWN'), WAIT,
               'the drive heard again once the adapter is back')
    axis.target.publish(Float64(data=1.0))
    wait_until(lambda: axis.latest_state() in ('FAULT', 'QUICK_STOP_ACTIVE', 'SWITCH_ON_DISABLED',
                                                'READY_TO_SWITCH_ON', 'SWITCHED_ON'), WAIT,
               f'the drive shown stopped, not running (state {axis.latest_state()})')
    assert axis.drive.drive_state != 'OPERATION_ENABLED', 'restarted without an enable'
    assert math.isclose(axis.drive.velocity, 0.0, abs_tol=1.0) or \
        axis.drive.drive_state == 'QUICK_STOP_ACTIVE'
    # Asked again, it runs again.
    if axis.latest_state() == 'FAULT':
        reset = axis.command('fault_reset')
        assert reset.success, reset.message
    axis.enable(CSV)
    axis.target.publish(Float64(data=1.0))
    wait_until(lambda: axis.drive.velocity > 0, WAIT, 'the drive turning after a fresh enable')


def test_a_drive_heard_again_takes_no_command_until_it_is_re_read(pulled):
    """The re-read (statusword, modes, the consumer written again) comes before any enable.

    Its values would otherwise land after an enable made meanwhile from the drive's TPDOs,
    showing the drive stopped again and refusing every target of the enabled drive; and the
    drive would run before it watches the gateway again.
    """
    axis, faults = pulled
    objects = axis.gateway.node.gateway.drives._drives[NODE].objects
    read_initial, release = objects.read_initial, threading.Event()

    def held(timeout):  # the drive's answers are late, as from a busy drive
        late = Future()
        read = read_initial(timeout)
        threading.Thread(target=lambda: release.wait(WAIT) and late.set_result(read.result()),
                         daemon=True).start()
        return late
    objects.read_initial = held
    pull(faults)
    wait_until(lambda: axis.latest_state() == 'UNKNOWN', WAIT, 'drive_state UNKNOWN')
    faults.clear()
    wait_until(lambda: axis.gateway.node.gateway.monitor.status(NODE).state != NOT_DETECTED,
               WAIT, 'the drive heard again')
    watch = axis.gateway.raw_bus()
    try:
        wait_until(lambda: (lambda m: m is not None and m.arbitration_id == 0x180 + NODE)(
            watch.recv(0.1)), WAIT, 'a TPDO of the drive (its statusword) on the bus again')
    finally:
        watch.shutdown()
    refused = axis.command('enable', CSV)
    assert not refused.success and 'UNKNOWN' in refused.message, refused.message
    assert axis.latest_state() == 'UNKNOWN'
    release.set()
    wait_until(lambda: axis.latest_state() not in (None, 'UNKNOWN'), WAIT, 'the drive re-read')
    if axis.latest_state() == 'FAULT':
        assert axis.command('fault_reset').success
    axis.enable(CSV)
    axis.target.publish(Float64(data=1.0))
    wait_until(lambda: axis.drive.velocity > 0, WAIT, 'the drive turning after the enable')


def test_a_command_under_way_when_the_adapter_is_pulled_gets_one_answer_naming_the_fault(
        pulled):
    axis, faults = pulled
    stopped = axis.command('disable')
    assert stopped.success, stopped.message
    faults.fail_send('adapter unplugged', after=1)  # the first step leaves, then the cut
    faults.fail_receive('adapter unplugged')
    faults.fail_open('adapter gone')
    pending = axis.gateway.call_async('drive_command', node_id=NODE, command='enable',
                                      mode=CSV, timeout=2.0)
    answer = wait_for_future(pending, WAIT)
    assert not answer.success, answer.message
    assert 'CAN bus is down' in answer.message, answer.message
    assert axis.drive.drive_state != 'OPERATION_ENABLED'
