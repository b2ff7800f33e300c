"""A drive whose CAN adapter is pulled: it stops by itself, and nothing restarts it unasked.

The gateway runs behind ``test/faulty_bus.py`` (python-can's virtual bus with faults on
command) with one simulated CiA 402 drive (durand) that watches the gateway's heartbeat.
Pulling the adapter cuts the gateway off in both directions, as an unplugged USB adapter does.
A drive that boots, or falls silent, during a command is here too.
"""

from concurrent.futures import Future
from dataclasses import replace
import math
import queue
import struct
import threading
import time

import pytest
from std_msgs.msg import Float64
from test_drives import CSP, CSV, NODE, PDOS, PP, Rig, WAIT

from cbcan_ros.core.drives import cia402
from cbcan_ros.core.nmt import NOT_DETECTED

from conftest import wait_for_future, wait_until
import faulty_bus
from faulty_bus import FaultController

faulty_bus.register()

OWN_ID = 100
CONSUMER_MS = 300
CONSUMER_HEARTBEAT = 0x1016


def enabled_behind_a_faulty_adapter(start_durand, watching: bool = True, pdos=PDOS):
    """Return (rig, faults): a gateway behind the faulty adapter, its drive turning in CSV.

    ``watching``: the drive watches the gateway's heartbeat (and stops when cut off).
    """
    watch = ({'heartbeat.node_id': OWN_ID, 'heartbeat.period': 0.1,
              'drives.consumer_time': CONSUMER_MS / 1000} if watching
             else {'drives.keep_running_if_gateway_dies': True})
    axis = Rig(start_durand, pdos, **{'can.interface': 'faulty', 'heartbeat.timeout': 0.5,
                                      **watch})
    faults = FaultController.get(axis.gateway.channel)
    try:
        start_turning(axis, watching)
    except BaseException:
        axis.close()
        raise
    return axis, faults


def start_turning(axis, watching: bool) -> None:
    """Enable the drive in CSV and turn it; with ``watching``, once it watches the gateway."""
    if watching:
        entry = struct.pack('<I', OWN_ID << 16 | CONSUMER_MS)
        wait_until(lambda: axis.drive.value(CONSUMER_HEARTBEAT, 1) == entry, WAIT,
                   'the drive watching the gateway (0x1016:1)')
    axis.enable(CSV)
    axis.target.publish(Float64(data=1.0))
    wait_until(lambda: axis.drive.velocity > 0, WAIT, 'the drive turning')


@pytest.fixture
def pulled(ros_context, start_durand):
    """Return (rig, faults): a gateway behind the faulty adapter, its drive enabled in CSV."""
    axis, faults = enabled_behind_a_faulty_adapter(start_durand)
    yield axis, faults
    faults.clear()
    axis.close()


def hold_re_reads(axis, first=None, delay: float = 0.0) -> threading.Event:
    """Make the gateway's re-reads of the drive late; return the event that releases them.

    ``first``: what the first re-read answers instead (a failed read: ``{}``); ``delay``:
    each later one answers this long after the drive did, once released.
    """
    objects = axis.gateway.node.gateway.drives._drives[NODE].objects
    read_initial, release, reads = objects.read_initial, threading.Event(), []

    def held(timeout):
        reads.append(timeout)
        late = Future()
        if first is not None and len(reads) == 1:
            late.set_result(first)
            return late
        read = read_initial(timeout)

        def answer():
            if release.wait(WAIT):
                time.sleep(delay)
                late.set_result(read.result())
        threading.Thread(target=answer, daemon=True).start()
        return late
    objects.read_initial = held
    return release


def hold_next_answer(axis, method: str, wanted=lambda *args: True):
    """Make the answer of the gateway's next ``method`` read of the drive late.

    The read (``DriveObjects.read`` or ``read_initial``, the first call for which
    ``wanted(*args)``) goes to the drive at once; its answer is handed to the gateway only
    once ``release`` is set. Returns (answered, release, taken): the drive answered, let the
    gateway have it, the gateway took it.
    """
    objects = axis.gateway.node.gateway.drives._drives[NODE].objects
    answered, release, taken = threading.Event(), threading.Event(), threading.Event()
    real = getattr(objects, method)

    def held(*args):
        if answered.is_set() or not wanted(*args):
            return real(*args)
        result = real(*args).result(WAIT)  # the drive's values of now
        answered.set()
        late = Future()

        def answer():
            if release.wait(WAIT):
                late.set_result(result)  # taken in here, by the gateway's done callbacks
                taken.set()
        threading.Thread(target=answer, daemon=True).start()
        return late
    setattr(objects, method, held)
    return answered, release, taken


def pull(faults) -> None:
    """Unplug the adapter: nothing goes out, nothing comes in, it cannot be opened again."""
    faults.fail_open('adapter gone')
    faults.fail_send('adapter unplugged')
    faults.fail_receive('adapter unplugged')


def heard_again(axis) -> None:
    """Wait until the gateway hears the drive again and has taken a TPDO of it since."""
    wait_until(lambda: axis.gateway.node.gateway.monitor.status(NODE).state != NOT_DETECTED,
               WAIT, 'the drive heard again')
    watch = axis.gateway.raw_bus()
    try:  # frames arrive in order: the gateway has the TPDO once this raw bus has it
        wait_until(lambda: (lambda m: m is not None and m.arbitration_id == 0x180 + NODE)(
            watch.recv(0.1)), WAIT, 'a TPDO of the drive (its statusword) on the bus again')
    finally:
        watch.shutdown()


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
    release = hold_re_reads(axis)
    pull(faults)
    wait_until(lambda: axis.latest_state() == 'UNKNOWN', WAIT, 'drive_state UNKNOWN')
    faults.clear()
    heard_again(axis)
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


def hold_tpdos_until_re_read(axis) -> None:
    """Make the gateway's drive service take TPDOs only once its re-read of the drive is done.

    As a busy machine can: TPDOs are taken on the bus's dispatch thread, SDO answers on
    another, and a TPDO the drive sent before an SDO answer can be taken after it.
    """
    gateway = axis.gateway.node.gateway
    drives, listeners, waiting = gateway.drives, gateway.pdo._listeners, queue.Queue()
    drive = drives._drives[NODE]

    def take_in_order():
        while True:
            received = waiting.get()
            try:
                wait_until(lambda: drive.ready == drive.read_wanted, WAIT, 'the re-read done')
            except AssertionError:
                return  # the test fails on what it sees
            drives._on_pdo(received)
    threading.Thread(target=take_in_order, daemon=True).start()
    listeners[listeners.index(drives._on_pdo)] = waiting.put


@pytest.mark.parametrize('late, acts_after', [(False, 0.0), (True, 0.0), (True, 0.2)],
                         ids=['tpdo_on_time', 'tpdo_after_re_read', 'acts_after_confirming'])
def test_a_drive_found_running_is_shown_stopped_once_the_gateway_stops_it(
        ros_context, start_durand, late, acts_after):
    """The stop's statusword counts, sent on change only, and whenever its TPDO is taken.

    An enable that went by a state shown OPERATION_ENABLED would send nothing and leave the
    drive in quick stop, deaf to every target. A drive may confirm the stop before it acts
    on it: the read-back waits for the statusword that shows it.
    """
    on_change = tuple(replace(pdo, event_timer=0) if (pdo.kind, pdo.number) == ('tpdo', 1)
                      else pdo for pdo in PDOS)
    axis, faults = enabled_behind_a_faulty_adapter(start_durand, watching=False, pdos=on_change)
    axis.drive.acts_after_confirming = acts_after
    try:
        pull(faults)
        wait_until(lambda: axis.latest_state() == 'UNKNOWN', WAIT, 'drive_state UNKNOWN')
        if late:
            hold_tpdos_until_re_read(axis)
        seen = len(axis.states)
        faults.clear()  # it ran on meanwhile: nothing told it to stop
        wait_until(lambda: axis.drive.drive_state != 'OPERATION_ENABLED', WAIT,
                   'the gateway stopping the drive it found running')
        wait_until(lambda: axis.latest_state() == axis.drive.drive_state, WAIT,
                   'drive_state showing the state the drive is in')
        shown = [message.state for message in axis.states[seen:]]
        assert 'OPERATION_ENABLED' not in shown, f'shown running after it was stopped: {shown}'
        axis.enable(CSV)
        axis.target.publish(Float64(data=1.0))
        wait_until(lambda: axis.drive.velocity > 0, WAIT, 'the drive turning after the enable')
    finally:
        faults.clear()
        axis.close()


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


def test_a_re_read_that_fails_is_tried_again_until_one_succeeds_even_when_slow(pulled):
    """One re-read at a time: each slower than the drive's heartbeat still gets to finish."""
    axis, faults = pulled
    hold_re_reads(axis, first={}, delay=0.6).set()
    pull(faults)
    wait_until(lambda: axis.latest_state() == 'UNKNOWN', WAIT, 'drive_state UNKNOWN')
    faults.clear()
    wait_until(lambda: axis.latest_state() not in (None, 'UNKNOWN'), WAIT,
               'the drive re-read after a failed read')


def test_a_drive_that_boots_during_a_move_ends_the_move_and_stays_off(ros_context, start_durand):
    axis = Rig(start_durand)
    try:
        axis.enable(PP)
        future, _cancel = axis.gateway.node.gateway.drives.move(NODE, 10 ** 6, velocity=1000)
        wait_until(lambda: axis.drive.velocity > 0, WAIT, 'the drive moving')
        seen = len(axis.states)
        assert axis.gateway.call('nmt_command', node_id=NODE, command=129).success
        result = future.result(WAIT)
        assert not result.success and 'booted during the command' in result.message, \
            result.message
        wait_until(lambda: 'UNKNOWN' in [m.state for m in axis.states[seen:]], WAIT,
                   'drive_state UNKNOWN after the boot')
        wait_until(lambda: axis.latest_state() not in (None, 'UNKNOWN'), WAIT,
                   'the drive re-read after its boot')
        assert axis.drive.drive_state != 'OPERATION_ENABLED'
        refused = axis.command('halt')
        assert not refused.success and 'enable' in refused.message, refused.message
    finally:
        axis.close()


def test_an_enable_under_way_when_the_drive_boots_fails_though_it_is_read_again_first(
        ros_context, start_durand):
    # Without a heartbeat consumer nothing of the re-read queues behind the enable's next
    # SDO: the drive is read again and shown SWITCH_ON_DISABLED before the enable goes on.
    # Once a defect: the enable then took it for its own and enabled the booted drive.
    # Nothing more goes to it: not the target that holds the axis, not the mode.
    axis = Rig(start_durand)
    try:
        answered, release, taken = hold_next_answer(
            axis, 'read', lambda indexes, _timeout: list(indexes) == [0x6064])
        enabling = axis.gateway.node.gateway.drives.command(NODE, 'enable', CSP, WAIT)
        wait_until(answered.is_set, WAIT, "the enable's read of the position to hold")
        seen = len(axis.states)
        assert axis.gateway.call('nmt_command', node_id=NODE, command=129).success
        wait_until(lambda: 'UNKNOWN' in [m.state for m in axis.states[seen:]]
                   and axis.latest_state() not in (None, 'UNKNOWN'), WAIT,
                   'the drive booted and read again')
        release.set()
        result = enabling.result(WAIT)
        assert not result.success and 'booted during the command' in result.message, \
            result.message
        assert axis.drive.drive_state == 'SWITCH_ON_DISABLED'
        assert axis.drive.value(0x6060) != bytes([CSP]), 'the mode was sent to the booted drive'
    finally:
        axis.close()


@pytest.mark.parametrize('command, word, stopped', [
    ('quick_stop', cia402.QUICK_STOP, ('QUICK_STOP_ACTIVE', 'SWITCH_ON_DISABLED')),
    ('disable', cia402.DISABLE_VOLTAGE, ('SWITCH_ON_DISABLED',))])
def test_a_stop_whose_drive_falls_silent_meanwhile_is_answered_by_its_sdo_confirmation(
        ros_context, start_durand, command, word, stopped):
    # Once a defect: the stop then waited for a statusword the gateway no longer takes from
    # a drive it does not hear, and answered "timed out" though the drive had stopped.
    axis = Rig(start_durand, **{'heartbeat.timeout': 0.5})
    try:
        axis.enable(CSV)
        axis.target.publish(Float64(data=1.0))
        wait_until(lambda: axis.drive.velocity > 0, WAIT, 'the drive turning')
        service = axis.gateway.node.gateway.drives
        send, silent = service.send, threading.Event()

        def held(drive, values, *args, **options):  # the stop waits, as behind a slow send
            if values.get(cia402.CONTROLWORD) == word:
                assert silent.wait(WAIT)
            return send(drive, values, *args, **options)
        service.send = held
        stopping = service.command(NODE, command, 0, 10.0)
        axis.drive.set_value(0x1017, 0, 0)  # its heartbeat stops; it goes on answering SDOs
        wait_until(lambda: service.status(NODE).state == 'UNKNOWN', WAIT,
                   'the drive no longer heard, shown UNKNOWN')
        silent.set()
        result = stopping.result(WAIT)
        assert result.success, result.message
        assert 'not heard' in result.message and 'written by SDO' in result.message, \
            result.message
        assert axis.drive.drive_state in stopped
    finally:
        axis.close()


def test_a_running_drive_heard_again_but_not_re_read_is_stopped_at_shutdown(
        ros_context, start_durand):
    axis, faults = enabled_behind_a_faulty_adapter(start_durand, watching=False)
    try:
        hold_re_reads(axis)  # never released: the re-read is still pending at shutdown
        pull(faults)
        wait_until(lambda: axis.latest_state() == 'UNKNOWN', WAIT, 'drive_state UNKNOWN')
        faults.clear()
        heard_again(axis)
        assert axis.drive.drive_state == 'OPERATION_ENABLED', 'nobody stopped it yet'
        assert axis.latest_state() == 'UNKNOWN'
    finally:
        faults.clear()
        axis.close()
    wait_until(lambda: axis.drive.drive_state != 'OPERATION_ENABLED', WAIT,
               'the drive stopped by the shutdown')
