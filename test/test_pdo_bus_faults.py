"""PDO writes and SYNC while the adapter is pulled mid-path (test/faulty_bus.py).

Every pdo_write gets exactly one answer, whether the bus goes down before it is sent, while a
synchronous RPDO waits for its SYNC, or after; SYNC stops while the bus is down and comes back
with it, and the mapping is read again once the device is heard again. A send that fails
while RPDOs wait for their SYNC leaves the gateway able to send once the adapter works again.
"""

import threading

import pytest

from cbcan_ros.msg import PdoEntry
from cbcan_ros.simulation.durand.device import DurandDevice
from cbcan_ros.simulation.durand.pdos import PdoConfig

from conftest import new_channel, wait_for_future, wait_until
import faulty_bus
from faulty_bus import FaultController
from node_process import EDS

faulty_bus.register()

NODE = 10
PROMPT = 5.0
RECOVERY = 15.0
PDOS = (PdoConfig('rpdo', 1, ((0x2000, 0), (0x2001, 0)), transmission_type=255),
        PdoConfig('rpdo', 2, ((0x2002, 0),), transmission_type=1),
        PdoConfig('tpdo', 1, ((0x2001, 0),), transmission_type=1))


@pytest.fixture
def rig(make_gateway):
    """Return (gateway, faults, device): a durand device behind the faulty adapter."""
    channel = new_channel()
    faults = FaultController.get(channel)
    device = DurandDevice(NODE, channel=channel, pdos=PDOS)
    device.start()
    gateway = make_gateway(can__interface='faulty', can__channel=channel,
                           simulation__devices=None, nodes=[NODE], pdo__nodes=[NODE],
                           sync__period=0.05, heartbeat__timeout=0.5, node_10__eds=EDS)
    wait_until(lambda: gateway.node.gateway.pdo.mappings(NODE)[1], PROMPT, 'the mapping read')
    yield gateway, faults, device
    device.stop()


def syncs(faults) -> int:
    return sum(1 for message in faults.sent if message.arbitration_id == 0x80)


def test_every_pdo_write_gets_exactly_one_answer_when_the_adapter_is_pulled(rig):
    gateway, faults, device = rig
    answers = {}
    lock = threading.Lock()
    futures = []
    for number in range(200):
        pdo, entry = (1, 0x2000) if number % 2 else (2, 0x2002)
        future = gateway.call_async('pdo_write', node_id=NODE, pdo=pdo,
                                    entries=[PdoEntry(index=entry, value=float(number % 200))])

        def count(done, number=number):
            with lock:
                answers[number] = answers.get(number, 0) + 1
        future.add_done_callback(count)
        futures.append(future)
        if number == 100:
            faults.fail_open('adapter gone')
            faults.fail_receive('adapter unplugged')
    results = [wait_for_future(future, PROMPT) for future in futures]
    wait_until(lambda: len(answers) == len(futures), PROMPT, 'every done-callback')
    assert set(answers.values()) == {1}
    failed = [result for result in results if not result.success]
    assert failed, 'the pulled adapter failed no write'
    for result in failed:
        assert 'CAN bus is down' in result.message, result.message
    faults.clear()


def test_sync_stops_while_the_bus_is_down_and_resumes_with_it(rig):
    gateway, faults, device = rig
    wait_until(lambda: syncs(faults) >= 3, PROMPT, 'SYNC on the bus')
    faults.fail_open('adapter gone')
    faults.fail_receive('adapter unplugged')
    wait_until(lambda: not gateway.node.gateway.bus_status.up, PROMPT, 'the bus down')
    wait_until(lambda: not gateway.node.gateway.sync.status().running, PROMPT, 'SYNC stopped')
    before = syncs(faults)
    answer = gateway.call('pdo_write', node_id=NODE, pdo=2,
                          entries=[PdoEntry(index=0x2002, value=1.0)])
    assert not answer.success and 'CAN bus is down' in answer.message, answer.message
    assert syncs(faults) == before  # nothing is sent on a pulled adapter

    faults.clear()
    wait_until(lambda: syncs(faults) >= before + 3, RECOVERY, 'SYNC after the bus came back')
    status = gateway.node.gateway.sync.status()
    assert status.running and status.starts == 2
    # The device is heard again, its mapping read again, and synchronous RPDOs work.
    wait_until(lambda: gateway.call('nmt_command', node_id=NODE, command=1).success,
               RECOVERY, 'NMT working again')

    def applied():
        written = gateway.call('pdo_write', node_id=NODE, pdo=2,
                               entries=[PdoEntry(index=0x2002, value=77.0)])
        return written.success and device.value(0x2002) == (77).to_bytes(4, 'little')
    wait_until(applied, RECOVERY, 'a synchronous RPDO applied after the bus came back')


def test_a_send_failing_while_a_write_waits_for_its_sync_answers_both_and_sending_goes_on(
        make_gateway):
    # Once a defect: the failing send's own thread told SYNC the bus was down, which sent the
    # waiting RPDO from that thread while it still held canopen's send lock: the gateway
    # never sent a frame again. A long SYNC period keeps the write waiting meanwhile.
    channel = new_channel()
    faults = FaultController.get(channel)
    device = DurandDevice(NODE, channel=channel, pdos=PDOS)
    device.start()
    try:
        gateway = make_gateway(can__interface='faulty', can__channel=channel,
                               simulation__devices=None, nodes=[NODE], pdo__nodes=[NODE],
                               sync__period=2.0, node_10__eds=EDS)
        wait_until(lambda: gateway.node.gateway.pdo.mappings(NODE)[1], PROMPT,
                   'the mapping read')
        pdo = gateway.node.gateway.pdo
        while True:  # until one write is seen waiting (one may come just as its SYNC did)
            waiting = gateway.call_async('pdo_write', node_id=NODE, pdo=2,
                                         entries=[PdoEntry(index=0x2002, value=5.0)])
            wait_until(lambda w=waiting: pdo._pending_sync or w.done(), PROMPT,
                       'the write waiting for its SYNC')
            if not waiting.done():
                break
        faults.fail_send('transmit buffer full')
        nmt = gateway.call('nmt_command', node_id=NODE, command=1)
        assert not nmt.success and 'transmit buffer full' in nmt.message, nmt.message
        written = wait_for_future(waiting, PROMPT)
        assert not written.success and 'CAN bus is down' in written.message, written.message
        faults.clear()
        wait_until(lambda: gateway.call('nmt_command', node_id=NODE, command=1).success,
                   RECOVERY, 'NMT sent again')
        wait_until(lambda: device.state == 5, RECOVERY, 'the device OPERATIONAL')
    finally:
        device.stop()


def test_the_sync_counter_runs_unbroken_and_starts_again_at_1_after_the_bus_came_back(
        make_gateway):
    # SYNC with a counter, sent by the gateway's own SYNC thread (a bus without a timer of
    # its own): 1, 2, ... overflow, 1, ... with none left out or sent twice, none while the
    # adapter is pulled, and from 1 again on the reopened bus, as after a device's reset.
    channel = new_channel()
    faults = FaultController.get(channel)
    overflow = 5
    gateway = make_gateway(can__interface='faulty', can__channel=channel,
                           simulation__devices=None, sync__period=0.02,
                           sync__counter_overflow=overflow)
    wait_until(lambda: syncs(faults) >= 2 * overflow + 2, PROMPT, 'SYNCs')
    faults.fail_open('adapter gone')
    faults.fail_receive('adapter unplugged')
    wait_until(lambda: not gateway.node.gateway.sync.status().running, PROMPT, 'SYNC stopped')
    before = [message.data[0] for message in faults.sent if message.arbitration_id == 0x80]
    faults.clear()
    wait_until(lambda: syncs(faults) >= len(before) + 2 * overflow + 2, RECOVERY,
               'SYNC after the bus came back')
    after = [message.data[0] for message in faults.sent
             if message.arbitration_id == 0x80][len(before):]
    for run in (before, after):
        assert run[0] == 1 and all(later == earlier % overflow + 1 for earlier, later
                                   in zip(run, run[1:], strict=False)), (before, after)
