"""EMCY and SDO statistics in the gateway core, with real frames on a private virtual bus.

The gateway node runs in this process (conftest's Harness); EMCY frames are forged on a raw
bus of the same channel, as a device would send them, and ``~/emcy`` is read by a subscriber.
"""

import logging
import threading

import can
import pytest

from cbcan_ros.core.sdo.requests import Access
from cbcan_ros.msg import Emcy
from cbcan_ros.ros.emcy import EMCY_QOS

from conftest import wait_until

EMCY_LOGGER = 'cbcan_ros.core.emcy'
TIMEOUT = 0x05040000
NOT_EXIST = 0x06020000


def send_emcy(bus: can.BusABC, node_id: int, data: bytes) -> None:
    """Send raw ``data`` on the EMCY COB-ID of ``node_id``."""
    bus.send(can.Message(arbitration_id=0x80 + node_id, data=data, is_extended_id=False))


@pytest.fixture
def setup(make_gateway):
    """Return (harness, raw bus, received Emcy messages) for a gateway with devices 2, 3, 5."""
    harness = make_gateway()
    received = []
    lock = threading.Lock()

    def on_emcy(message):
        with lock:
            received.append(message)
    harness.client_node.create_subscription(Emcy, '/cbcan/emcy', on_emcy, EMCY_QOS)
    wait_until(lambda: harness.node.count_subscribers('/cbcan/emcy'), 10.0,
               'the test subscribed to ~/emcy')
    bus = harness.raw_bus()
    yield harness, bus, received
    bus.shutdown()


def test_emcy_is_published_and_stays_active_until_an_error_reset(setup):
    harness, bus, received = setup
    emcy = harness.node.gateway.emcy

    send_emcy(bus, 5, bytes.fromhex('2031 05 aabbccddee'))  # 0x3120 (under-voltage), reg 0x05
    wait_until(lambda: len(received) == 1, 10.0, 'the EMCY on ~/emcy')
    message = received[0]
    assert (message.node_id, message.error_code, message.error_register) == (5, 0x3120, 0x05)
    assert bytes(message.manufacturer_data) == bytes.fromhex('aabbccddee')
    assert message.description == 'Voltage'
    assert message.stamp.sec > 0
    status = emcy.status(5)
    assert status.active.error_code == 0x3120 and status.last == status.active
    assert status.active.summary == '0x3120 Voltage'

    send_emcy(bus, 5, bytes.fromhex('1042 09 0000000000'))  # a second error: temperature
    wait_until(lambda: len(received) == 2, 10.0, 'the second EMCY')
    assert received[1].description == 'Temperature'
    assert emcy.status(5).active.error_code == 0x4210

    send_emcy(bus, 5, bytes(8))  # error reset
    wait_until(lambda: len(received) == 3, 10.0, 'the error reset on ~/emcy')
    assert (received[2].error_code, received[2].description) == (0, 'Error Reset / No Error')
    status = emcy.status(5)
    assert status.active is None
    assert status.last.error_code == 0
    assert emcy.status(3).last is None  # other devices are untouched


def test_a_malformed_emcy_is_logged_once_and_receiving_goes_on(setup, caplog):
    caplog.set_level(logging.INFO, logger=EMCY_LOGGER)
    harness, bus, received = setup
    emcy = harness.node.gateway.emcy
    for _ in range(3):
        send_emcy(bus, 5, b'\x00\x50\x01')
    wait_until(lambda: emcy.status(5).malformed == 3, 10.0, 'three malformed frames counted')
    send_emcy(bus, 5, bytes.fromhex('0050 01 0000000000'))
    wait_until(lambda: len(received) == 1, 10.0, 'a good EMCY after the malformed ones')
    assert received[0].error_code == 0x5000
    assert emcy.status(5).active.description == 'Device Hardware'
    warnings = [r.message for r in caplog.records if r.name == EMCY_LOGGER]
    assert len(warnings) == 1, warnings
    assert 'node 5' in warnings[0] and '3 bytes' in warnings[0], warnings
    # The bus thread survived: the SDO answers and heartbeats still come in.
    assert harness.call('sdo_read', node_id=5, index=0x1000, subindex=0).success


def test_sdo_statistics_count_requests_aborts_timeouts_and_latency(setup):
    harness, _bus, _received = setup
    gateway = harness.node.gateway
    assert gateway.sdo_statistics() == {}
    assert harness.call('sdo_read', node_id=5, index=0x1000, subindex=0).success
    assert harness.call('sdo_read', node_id=5, index=0x1001, subindex=0).success
    answer = harness.call('sdo_read', node_id=5, index=0x6000, subindex=0)
    assert answer.abort_code == NOT_EXIST
    answer = harness.call('sdo_read', node_id=9, index=0x1000, subindex=0, timeout=0.1)
    assert answer.abort_code == TIMEOUT  # no device 9 on the bus
    batch = gateway.sdo_batch([Access(2, 0x1000, 0), Access(2, 0x6000, 0),
                               Access(2, 0x1001, 0)]).result(5)
    assert [r.success for r in batch] == [True, False, True]

    statistics = gateway.sdo_statistics()
    assert sorted(statistics) == [2, 5, 9]
    five, nine, two = statistics[5], statistics[9], statistics[2]
    assert (five.requests, five.aborts, five.timeouts) == (3, 1, 0)
    assert 0 < five.latency_p50 < 0.5
    assert (nine.requests, nine.aborts, nine.timeouts, nine.latency_p50) == (1, 0, 1, None)
    assert (two.requests, two.aborts, two.timeouts) == (3, 1, 0)
    assert 0 < two.latency_p50 < 0.5

