"""Bus supervision: receive, send and open failures and bus-off, as a caller meets them.

The gateway runs on the fault-injecting ``faulty`` python-can interface (test/faulty_bus.py);
the simulated devices sit on the plain ``virtual`` bus of the same channel, so a fault hits the
gateway's adapter only, as a pulled cable or a dead USB adapter does on a robot.
"""

import logging
import pathlib
import struct
import threading
import time

import pytest

from cbcan_ros.msg import LssIdentity
from cbcan_ros.simulation.canopen_device import SimulatedDevice
from cbcan_ros.simulation.durand.device import DurandDevice

from conftest import HEAVY, new_channel, wait_for_future, wait_until
import faulty_bus
from faulty_bus import FaultController

EDS = str(pathlib.Path(__file__).resolve().parent.parent / 'config' / 'simulated_device.eds')
DEVICE_TYPE = struct.pack('<I', 0x00020192)
BUS_LOGGER = 'cbcan_ros.core.bus'
RECOVERY = 20.0  # backoff doubles up to 5 s; generous for a loaded CI machine
# "At once" is proven against the behaviour, not a stopwatch: the calls' timeout (LONG) and
# the slow device's delay (SLOW) are far longer than PROMPT, the ceiling for an answer that
# a quiet machine gives in milliseconds, so an answer within PROMPT is neither.
PROMPT = 5.0
SLOW = 6.0
LONG = 30.0
# Fatek CBCAN words (docs/plc_mailbox_formats.md): the flag, SDO read, result 4 = failed, and
# the abort words (low, high) of 0x08000000, the code of a bus that went down
MAILBOX_FLAG, MAILBOX_READ, MAILBOX_RESULT_FAILED = 0xCA0E, 5055, 4
MAILBOX_BUS_DOWN = [0x0000, 0x0800]

faulty_bus.register()


@pytest.fixture
def start_faulty(make_gateway):
    """Return a factory ``start_faulty(arm=None, **parameters) -> (gateway, faults)``.

    ``arm(faults)`` runs before the gateway opens its bus (to start with the bus down).
    """
    devices = []

    def factory(arm=None, **parameters):
        channel = new_channel()
        faults = FaultController.get(channel)
        if arm is not None:
            arm(faults)
        for node_id in (2, 3):
            device = SimulatedDevice(node_id, EDS, 'virtual', channel)
            device.start()
            devices.append(device)
        settings = dict(can__interface='faulty', can__channel=channel,
                        simulation__devices=None, nodes=[2, 3], heartbeat__timeout=0.5,
                        state_publish_period=0.1)
        settings.update(parameters)
        gateway = make_gateway(**settings)
        gateway.devices = {device.node_id: device for device in devices[-2:]}
        return gateway, faults

    yield factory
    for device in devices:
        device.stop()


def read_device_type(gateway, node_id=2, **fields):
    return gateway.call('sdo_read', node_id=node_id, index=0x1000, subindex=0, **fields)


def wait_for_recovery(gateway):
    wait_until(lambda: read_device_type(gateway).success, RECOVERY, 'SDO working again')
    gateway.wait_for_states({2: 'PRE_OPERATIONAL', 3: 'PRE_OPERATIONAL'}, RECOVERY)


def down_logs(caplog):
    return [r for r in caplog.records if r.name == BUS_LOGGER and 'is down' in r.message]


def test_receive_error_is_reported_once_and_the_bus_comes_back(start_faulty, caplog):
    caplog.set_level(logging.INFO, logger=BUS_LOGGER)
    gateway, faults = start_faulty()
    gateway.wait_for_states({2: 'PRE_OPERATIONAL', 3: 'PRE_OPERATIONAL'})
    assert bytes(read_device_type(gateway).data) == DEVICE_TYPE
    faults.fail_open('adapter gone')  # keep it down while we look
    assert faults.fail_receive('adapter unplugged') == 1

    gateway.wait_for_states({2: 'NOT_DETECTED', 3: 'NOT_DETECTED'}, PROMPT)
    answer = read_device_type(gateway, wait=PROMPT, timeout=LONG)
    assert not answer.success
    assert 'CAN bus is down' in answer.message, answer.message
    status = gateway.node.gateway.bus_status
    assert not status.up and status.reason
    # Several reopen attempts fail meanwhile (0.1, 0.2, 0.4 s ...), but the fault is one line.
    wait_until(lambda: faults.open_failures >= 3, RECOVERY, 'three failed reopen attempts')
    assert len(down_logs(caplog)) == 1, [r.message for r in down_logs(caplog)]
    assert 'adapter unplugged' in down_logs(caplog)[0].message

    faults.clear()
    wait_for_recovery(gateway)
    assert bytes(read_device_type(gateway).data) == DEVICE_TYPE
    assert gateway.node.gateway.bus_status.reopen_count == 1
    assert any('up again' in r.message for r in caplog.records if r.name == BUS_LOGGER)


def test_pending_and_queued_calls_are_answered_at_once_when_the_bus_goes_down(start_faulty):
    gateway, faults = start_faulty()
    gateway.devices[2].slow_read_delay = SLOW
    slow = gateway.call_async('sdo_read', node_id=2, index=0x2200, subindex=0, timeout=LONG)
    queued = [gateway.call_async('sdo_read', node_id=2, index=0x1000, subindex=0, timeout=LONG)
              for _ in range(5)]
    wait_until(lambda: any(m.arbitration_id == 0x602 for m in faults.sent), PROMPT,
               'the slow request on the bus')
    faults.fail_open('adapter gone')
    faults.fail_receive('adapter unplugged')
    answers = [wait_for_future(future, PROMPT) for future in [slow, *queued]]
    for response in answers:
        assert not response.success
        assert 'CAN bus is down' in response.message, response.message
    faults.clear()
    wait_for_recovery(gateway)


def test_calls_are_answered_while_the_driver_is_still_closing_the_dead_adapter(start_faulty):
    # Once the callers heard only after the driver's shutdown() returned, however long a
    # dead adapter made it take.
    gateway, faults = start_faulty()
    gateway.devices[2].slow_read_delay = SLOW
    slow = gateway.call_async('sdo_read', node_id=2, index=0x2200, subindex=0, timeout=LONG)
    wait_until(lambda: any(m.arbitration_id == 0x602 for m in faults.sent), PROMPT,
               'the slow request on the bus')
    faults.closing = threading.Event()
    try:
        faults.fail_open('adapter gone')
        faults.fail_receive('adapter unplugged')
        answer = wait_for_future(slow, PROMPT)
        assert not answer.success and 'CAN bus is down' in answer.message, answer.message
        assert faults.buses, 'the driver has finished closing the adapter'
    finally:
        faults.closing.set()
    faults.clear()
    wait_for_recovery(gateway)


def test_mailbox_calls_waiting_when_the_bus_goes_down_are_answered_at_once(start_faulty):
    # The PLC mailbox runs on its own event loop: a block waiting on the bus, and blocks
    # queued behind it, get their failed answer when the bus goes, as SDO calls do.
    gateway, faults = start_faulty(sdo__timeout=LONG)
    gateway.devices[2].slow_read_delay = SLOW
    block = [MAILBOX_FLAG, MAILBOX_READ, 2, 0x2200, 0, 4] + [0] * 64
    calls = [gateway.call_async('plc_mailbox', format='cbcan', registers=block)
             for _ in range(4)]
    wait_until(lambda: any(m.arbitration_id == 0x602 for m in faults.sent), PROMPT,
               'the slow request on the bus')
    faults.fail_open('adapter gone')
    faults.fail_receive('adapter unplugged')
    answers = [wait_for_future(future, PROMPT) for future in calls]
    for answer in answers:
        assert [answer.registers[0], *answer.registers[6:8]] == \
            [MAILBOX_RESULT_FAILED, *MAILBOX_BUS_DOWN], list(answer.registers[:8])
    faults.clear()
    wait_for_recovery(gateway)


def test_send_failure_takes_the_bus_down_and_it_recovers(start_faulty):
    gateway, faults = start_faulty()
    wait_until(lambda: read_device_type(gateway).success, PROMPT, 'a first read')
    faults.fail_open('adapter gone')
    faults.fail_send('transmit buffer overflow')
    answer = read_device_type(gateway)
    assert not answer.success
    assert 'transmit buffer overflow' in answer.message, answer.message
    nmt = gateway.call('nmt_command', node_id=2, command=1)
    assert not nmt.success and 'CAN bus is down' in nmt.message, nmt.message
    gateway.wait_for_states({2: 'NOT_DETECTED'}, PROMPT)
    faults.clear()
    wait_for_recovery(gateway)
    assert gateway.call('nmt_command', node_id=2, command=1).success
    gateway.wait_for_states({2: 'OPERATIONAL'})


def test_a_failing_bus_status_listener_neither_ends_supervision_nor_deafens_the_rest(
        start_faulty, caplog):
    # Listeners are told on the bus thread, which also reopens the bus: one that raised
    # used to end that thread, and the bus stayed down for good.
    caplog.set_level(logging.INFO, logger=BUS_LOGGER)
    gateway, faults = start_faulty()
    gateway.wait_for_states({2: 'PRE_OPERATIONAL', 3: 'PRE_OPERATIONAL'})
    bus = gateway.node.gateway.bus
    told = []

    def failing(status):
        raise RuntimeError('a listener bug')

    bus.add_listener(failing)
    bus.add_listener(told.append)
    faults.fail_receive('adapter unplugged')
    wait_until(lambda: any(not status.up for status in told), PROMPT, 'the bus down told')
    wait_for_recovery(gateway)
    assert told[-1].up
    failures = [r for r in caplog.records
                if r.name == BUS_LOGGER and 'a bus status listener failed' in r.message]
    assert len(failures) == 1, [r.message for r in failures]


def test_bus_off_reopens_the_bus(start_faulty):
    gateway, faults = start_faulty()
    wait_until(lambda: read_device_type(gateway).success, PROMPT, 'a first read')
    opened = faults.open_count
    assert faults.bus_off() == 1
    wait_until(lambda: faults.open_count > opened, RECOVERY, 'the bus reopened after bus-off')
    wait_for_recovery(gateway)
    assert gateway.node.gateway.bus_status.reopen_count == 1


def test_node_starts_without_an_adapter_and_connects_when_it_appears(start_faulty):
    gateway, faults = start_faulty(arm=lambda faults: faults.fail_open('no such adapter'))
    answer = read_device_type(gateway)
    assert not answer.success
    assert 'cannot open the bus' in answer.message and 'no such adapter' in answer.message
    state = gateway.call('nmt_state', node_id=2)
    assert state.state_name == 'NOT_DETECTED'
    faults.clear()
    wait_for_recovery(gateway)
    assert gateway.node.gateway.bus_status.up


def test_node_guarding_survives_send_errors_and_resumes(start_faulty):
    gateway, faults = start_faulty(node_guarding=[3], node_guarding_period=0.1)
    assert gateway.call('sdo_write', node_id=3, index=0x1017, subindex=0, data=[0, 0]).success
    assert gateway.call('nmt_command', node_id=3, command=1).success
    gateway.wait_for_states({3: 'OPERATIONAL'})
    faults.fail_open('adapter gone')
    faults.fail_send('transmit failed')
    gateway.wait_for_states({3: 'NOT_DETECTED'}, PROMPT)
    faults.clear()
    # No heartbeat from node 3: only the guarding replies can bring it back.
    gateway.wait_for_states({3: 'OPERATIONAL'}, RECOVERY)
    guarding = [m for m in faults.sent if m.arbitration_id == 0x703 and m.is_remote_frame]
    count = len(guarding)
    wait_until(lambda: len([m for m in faults.sent if m.arbitration_id == 0x703]) > count + 2,
               RECOVERY, 'guarding requests going on after the fault')


@HEAVY
def test_a_thousand_concurrent_calls_each_get_one_honest_answer(start_faulty):
    gateway, _faults = start_faulty(sdo__queue_limit=16)
    futures = [gateway.call_async('sdo_read', node_id=2 + i % 2, index=0x1000, subindex=0,
                                  timeout=10.0)
               for i in range(1000)]
    answers = [wait_for_future(future, 60.0) for future in futures]
    served = [a for a in answers if a.success]
    refused = [a for a in answers if not a.success]
    assert len(answers) == 1000
    assert all(bytes(a.data) == DEVICE_TYPE for a in served)
    assert served, 'some calls were served'
    for answer in refused:
        assert answer.abort_code == 0x060A0023, answer.message
        assert 'busy' in answer.message and '16' in answer.message, answer.message
        assert 'sdo.queue_limit' in answer.message
    assert bytes(read_device_type(gateway).data) == DEVICE_TYPE


def test_lss_calls_are_answered_at_once_when_the_bus_goes_down_and_work_after(start_faulty):
    gateway, faults = start_faulty()
    devices = [DurandDevice(255, 'virtual', gateway.channel, lss=True,
                            identity=(0x319, 0x51, 0x10000, serial)) for serial in (7, 0x12)]
    try:
        for device in devices:
            device.start()
        scan = gateway.call_async('lss_scan', first_node_id=10, timeout=60.0)
        wait_until(lambda: any(m.arbitration_id == 0x7E5 for m in faults.sent), PROMPT * 5,
                   'the scan under way')
        faults.fail_open('adapter gone')
        faults.fail_receive('adapter unplugged')
        response = wait_for_future(scan, PROMPT * 3)  # its own timeout is 60 s
        assert not response.success
        assert 'the CAN bus is down' in response.message, response.message
        refused = gateway.call('lss_inquire', identity=LssIdentity(
            vendor_id=0x319, product_code=0x51, revision=0x10000, serial=7))
        assert 'the CAN bus is down' in refused.message and 'nothing was sent' in \
            refused.message, refused.message
        faults.clear()
        wait_for_recovery(gateway)
        again = gateway.call('lss_scan', wait=60.0, first_node_id=10)
        assert again.success, again.message
        assert sorted(d.node_id for d in devices) == sorted(
            list(again.node_ids) + list(response.node_ids))
    finally:
        for device in devices:
            device.stop()


def test_a_bus_outage_is_neither_syncs_skipped_nor_a_period_error(start_faulty):
    # Once a defect: every SYNC the refusing adapter did not take, until the bus thread saw
    # the bus down, counted in /diagnostics as "SYNCs skipped", which says the host woke the
    # SYNC thread late (12-29 for a 1 s outage at 10 ms on an idle machine, every time).
    # A busy machine's stalls skip SYNCs too, in bursts (one stall of 70 ms: 7 of them) that
    # a window may or may not catch: so up to three outages, the defect failing each one.
    period, outage = 0.01, 1.0
    gateway, faults = start_faulty(sync__period=period)
    sync = gateway.node.gateway.sync
    wait_until(lambda: sync.status().measured_period is not None, RECOVERY, 'SYNCs measured')
    tries = []
    for _ in range(3):
        # As long without an outage first: what this machine's load alone makes late.
        before = sync.status().skipped
        time.sleep(outage + 50 * period)
        late = sync.status().skipped - before
        before = sync.status().skipped
        faults.fail_send('transmit failed')
        time.sleep(outage)  # the adapter refuses every frame for that long
        faults.clear()
        wait_for_recovery(gateway)
        wait_until(lambda: sync.status().running, RECOVERY, 'SYNC produced again')
        time.sleep(50 * period)
        after = sync.status()
        tries.append((after.skipped - before, late))
        # A busy machine may really wake the thread late a few times more in these 1.5 s.
        if after.skipped - before <= late + 5:
            break
    assert after.skipped - before <= late + 5, (
        f'SYNCs counted as skipped with the outage (and without it), each try: {tries}')
    assert after.measured_jitter < outage / 2, f'the outage shown as a period error: {after}'
