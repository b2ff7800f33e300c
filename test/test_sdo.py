"""SDO read/write through the ROS services, against simulated devices on a virtual bus."""

import math
import re
import struct
import threading
import time

import can
import pytest

from conftest import frames_before_marker, wait_for_future, wait_until

BIG = bytes((i * 7) % 251 for i in range(65536))
# A request's timeout covers the whole transfer: 64 KiB segmented take seconds, many more
# on a loaded machine.
BIG_TIMEOUT = 60.0


def test_expedited_read_returns_the_bytes_on_the_bus(gateway):
    response = gateway.call('sdo_read', node_id=5, index=0x1000, subindex=0)
    assert response.success, response.message
    assert bytes(response.data) == struct.pack('<I', 0x00020192)
    assert response.abort_code == 0 and response.message == ''


def test_segmented_read_of_a_string(gateway):
    response = gateway.call('sdo_read', node_id=3, index=0x1008, subindex=0)
    assert response.success, response.message
    assert bytes(response.data) == b'cbcan simulated device'


@pytest.mark.parametrize('index, data', [
    (0x2000, b'\x7f'),
    (0x2001, struct.pack('<H', 0xBEEF)),
    (0x2002, struct.pack('<I', 0xDEADBEEF)),
    (0x2003, struct.pack('<i', -123456)),
    (0x2021, b'a longer string that needs segments'),
])
def test_written_value_reads_back(gateway, index, data):
    written = gateway.call('sdo_write', node_id=2, index=index, subindex=0, data=list(data))
    assert written.success, written.message
    assert gateway.device(2).node.data_store[index][0] == data
    read = gateway.call('sdo_read', node_id=2, index=index, subindex=0)
    assert bytes(read.data) == data


def test_64_kib_object_round_trip(gateway):
    written = gateway.call('sdo_write', node_id=5, index=0x2020, subindex=0, data=list(BIG),
                           timeout=BIG_TIMEOUT, wait=BIG_TIMEOUT + 10.0)
    assert written.success, written.message
    read = gateway.call('sdo_read', node_id=5, index=0x2020, subindex=0, timeout=BIG_TIMEOUT,
                        wait=BIG_TIMEOUT + 10.0)
    assert read.success, read.message
    assert bytes(read.data) == BIG


@pytest.mark.parametrize('service, fields, code, name', [
    ('sdo_read', dict(index=0x6000), 0x06020000, 'NOT_EXIST'),
    ('sdo_read', dict(index=0x1018, subindex=9), 0x06090011, 'SUBINDEX_NOT_EXIST'),
    ('sdo_read', dict(index=0x2011), 0x06010001, 'WRITE_ONLY'),
    ('sdo_write', dict(index=0x2010, data=[1, 2, 3, 4]), 0x06010002, 'READ_ONLY'),
    ('sdo_write', dict(index=0x2002, data=[1, 2]), 0x06070010, 'TYPE_MISMATCH'),
])
def test_device_abort_is_answered_with_code_and_meaning(gateway, service, fields, code, name):
    response = gateway.call(service, node_id=5, **fields)
    assert not response.success
    assert response.abort_code == code
    assert response.message.startswith(f'0x{code:08X} {name}: ')


def test_silent_device_times_out_with_one_request_and_an_abort(gateway):
    bus = gateway.raw_bus()
    try:
        started = time.monotonic()
        response = gateway.call('sdo_read', node_id=9, index=0x1000, subindex=0, timeout=0.3)
        elapsed = time.monotonic() - started
        frames = frames_before_marker(gateway, bus)
    finally:
        bus.shutdown()
    assert not response.success
    assert response.abort_code == 0x05040000
    assert 'TIMEOUT' in response.message
    assert elapsed >= 0.3
    requests = [f for f in frames if f.data[0] == 0x40]
    aborts = [f for f in frames if f.data[0] == 0x80]
    assert len(requests) == 1, 'a timed-out request must not be repeated'
    assert struct.unpack_from('<I', aborts[0].data, 4)[0] == 0x05040000


def test_a_timeout_says_when_the_node_was_never_heard_or_has_fallen_silent(make_gateway):
    # A new user's wrong node id met a bare TIMEOUT, the same as a device slow to answer.
    gateway = make_gateway(**{'heartbeat.timeout': 0.3})
    never = gateway.call('sdo_read', node_id=42, index=0x1000, subindex=0, timeout=0.2)
    assert never.abort_code == 0x05040000
    assert never.message.endswith('; node 42 has not been heard on the bus since the gateway '
                                  'started (no heartbeat, boot-up or node guarding reply): '
                                  'check its node id, bit rate, power and wiring'), never.message
    device = gateway.device(5)
    wait_until(lambda: gateway.call('nmt_state', node_id=5).state_name != 'NOT_DETECTED', 10.0,
               'node 5 heard')
    device.stop()
    wait_until(lambda: gateway.call('nmt_state', node_id=5).state_name == 'NOT_DETECTED', 10.0,
               'node 5 NOT_DETECTED')
    silent = gateway.call('sdo_read', node_id=5, index=0x1000, subindex=0, timeout=0.2)
    assert silent.abort_code == 0x05040000
    assert re.search(r'; node 5 has not been heard for \d+\.\d s \(NOT_DETECTED\)$',
                     silent.message), silent.message


def test_timed_out_write_is_sent_exactly_once(gateway):
    bus = gateway.raw_bus()
    try:
        response = gateway.call('sdo_write', node_id=9, index=0x2002, subindex=0,
                                data=[1, 2, 3, 4], timeout=0.2)
        frames = frames_before_marker(gateway, bus)
    finally:
        bus.shutdown()
    assert response.abort_code == 0x05040000
    downloads = [f for f in frames if f.data[0] & 0xE0 == 0x20]
    assert len(downloads) == 1


def test_default_timeout_is_the_parameter(make_gateway):
    gateway = make_gateway(sdo__timeout=0.05)
    response = gateway.call('sdo_read', node_id=9, index=0x1000, subindex=0)
    assert response.abort_code == 0x05040000


def test_object_larger_than_max_size_is_refused_and_aborted_on_the_bus(gateway):
    bus = gateway.raw_bus()
    try:
        response = gateway.call('sdo_read', node_id=5, index=0x1008, subindex=0, max_size=4)
        frames = frames_before_marker(gateway, bus)
    finally:
        bus.shutdown()
    assert not response.success
    assert response.abort_code == 0x05040005
    assert list(response.data) == []
    assert [struct.unpack_from('<I', f.data, 4)[0] for f in frames if f.data[0] == 0x80] == [
        0x05040005]
    assert [f.data[0] for f in frames if f.data[0] == 0x60] == [], 'no segment was fetched'


def test_max_size_applies_to_expedited_objects_and_allows_exact_size(gateway):
    refused = gateway.call('sdo_read', node_id=5, index=0x2002, subindex=0, max_size=3)
    assert (refused.success, refused.abort_code, list(refused.data)) == (False, 0x05040005, [])
    exact = gateway.call('sdo_read', node_id=5, index=0x2002, subindex=0, max_size=4)
    assert bytes(exact.data) == struct.pack('<I', 0x12345678)


def test_node_0_is_the_gateways_own_dictionary(gateway):
    product = gateway.call('sdo_read', node_id=0, index=0x1018, subindex=2)
    assert bytes(product.data) == struct.pack('<I', 0xCBCA)
    for index in (0x1000, 0x1001):
        assert gateway.call('sdo_read', node_id=0, index=index, subindex=0).success
    written = gateway.call('sdo_write', node_id=0, index=0x1017, subindex=0, data=[0xE8, 0x03])
    assert written.success, written.message
    assert list(gateway.call('sdo_read', node_id=0, index=0x1017, subindex=0).data) == [
        0xE8, 0x03]
    refused = gateway.call('sdo_write', node_id=0, index=0x1018, subindex=1, data=[0] * 4)
    assert refused.abort_code == 0x06010002
    missing = gateway.call('sdo_read', node_id=0, index=0x2000, subindex=0)
    assert missing.abort_code == 0x06020000
    too_big = gateway.call('sdo_read', node_id=0, index=0x1008, subindex=0, max_size=2)
    assert too_big.abort_code == 0x05040005


@pytest.mark.parametrize('service, fields, field', [
    ('sdo_read', dict(node_id=128), 'node_id 128 is out of range: allowed 0..127'),
    ('sdo_read', dict(node_id=5, timeout=-1.0), 'timeout -1.0 s is out of range'),
    ('sdo_read', dict(node_id=5, timeout=math.nan), 'timeout nan s is out of range'),
    ('sdo_read', dict(node_id=5, timeout=61.0), 'up to 60 s'),
    ('sdo_write', dict(node_id=5, data=[]), 'data is empty'),
    ('sdo_write', dict(node_id=255, data=[1]), 'node_id 255 is out of range'),
])
def test_invalid_request_is_refused_before_the_bus(gateway, service, fields, field):
    bus = gateway.raw_bus()
    try:
        response = gateway.call(service, index=0x2002, subindex=0, **fields)
        frames = frames_before_marker(gateway, bus)
    finally:
        bus.shutdown()
    assert (response.success, response.abort_code) == (False, 0)
    assert field in response.message
    assert frames == [], 'nothing was sent for the invalid request'


def test_short_frame_from_a_misbehaving_device_is_ignored_and_named(gateway):
    """A 2-byte SDO response made canopen raise struct.error: it is ignored and counted."""
    bus = gateway.raw_bus()
    stop = threading.Event()

    def misbehave():
        while not stop.is_set():
            message = bus.recv(0.05)
            if message is not None and message.arbitration_id == 0x609:
                bus.send(can.Message(arbitration_id=0x589, data=[0x43, 0x00],
                                     is_extended_id=False))

    responder = threading.Thread(target=misbehave)
    responder.start()
    try:
        response = gateway.call('sdo_read', node_id=9, index=0x1000, subindex=0, timeout=0.5)
    finally:
        stop.set()
        responder.join()
        bus.shutdown()
    assert not response.success
    assert response.abort_code == 0x05040000
    assert '1 frame(s) that did not answer this request were ignored' in response.message
    assert gateway.call('sdo_read', node_id=5, index=0x1000, subindex=0).success


def test_slow_device_blocks_neither_other_devices_nor_the_executor(gateway):
    gateway.device(2).slow_read_delay = 4.0  # far longer than the other calls take, even loaded
    slow = gateway.call_async('sdo_read', node_id=2, index=0x2200, subindex=0, timeout=10.0)
    fast = gateway.call('sdo_read', node_id=3, index=0x1000, subindex=0, timeout=2.0)
    state = gateway.call('nmt_state', node_id=3)
    assert fast.success and state.success
    assert not slow.done(), 'the other calls were answered while the slow device was busy'
    assert wait_for_future(slow, 15.0).success


def test_requests_to_one_device_are_served_one_after_another(gateway):
    # The queued request's timeout covers its wait behind the slow one (0.4 s).
    slow = gateway.call_async('sdo_read', node_id=2, index=0x2200, subindex=0, timeout=5.0)
    queued = gateway.call_async('sdo_read', node_id=2, index=0x1000, subindex=0, timeout=5.0)
    other = gateway.call('sdo_read', node_id=5, index=0x1000, subindex=0, timeout=2.0)
    assert other.success
    wait_until(queued.done, 10.0, 'the queued request')
    assert slow.done(), 'the queued request was answered only after the slow one'
    assert slow.result().success and queued.result().success


def test_concurrent_calls_to_several_devices_all_get_their_own_answer(gateway):
    futures = {(node, index): gateway.call_async('sdo_read', node_id=node, index=index,
                                                 subindex=0)
               for node in (2, 3, 5) for index in (0x1000, 0x2001, 0x2002, 0x1008)}
    expected = {0x1000: struct.pack('<I', 0x00020192), 0x2001: struct.pack('<H', 0x1234),
                0x2002: struct.pack('<I', 0x12345678), 0x1008: b'cbcan simulated device'}
    for (node, index), future in futures.items():
        assert bytes(wait_for_future(future, 10.0).data) == expected[index], (node, index)


def test_block_transfer_falls_back_for_devices_without_it(make_gateway):
    gateway = make_gateway(sdo__block_transfer=True)
    written = gateway.call('sdo_write', node_id=5, index=0x2020, subindex=0, data=list(BIG),
                           timeout=BIG_TIMEOUT, wait=BIG_TIMEOUT + 10.0)
    assert written.success, written.message
    read = gateway.call('sdo_read', node_id=5, index=0x2020, subindex=0, timeout=BIG_TIMEOUT,
                        wait=BIG_TIMEOUT + 10.0)
    assert bytes(read.data) == BIG
    assert bytes(gateway.call('sdo_read', node_id=2, index=0x1008, subindex=0).data) == (
        b'cbcan simulated device')


def test_destroy_node_answers_waiting_calls_and_sends_no_request(gateway):
    bus = gateway.raw_bus()
    try:
        calls = [gateway.call_async('sdo_read', node_id=9, index=0x1000, subindex=0,
                                    timeout=20.0) for _ in range(4)]
        calls += [gateway.call_async('sdo_write', node_id=9, index=0x2002, subindex=0,
                                     data=[1, 2, 3, 4], timeout=20.0) for _ in range(4)]
        def first_request():  # the simulated devices' heartbeats share the bus
            message = bus.recv(0.05)
            return message if message is not None and message.arbitration_id == 0x609 else None
        first = wait_until(first_request, 10.0, 'the first request on the bus')
        assert first.data[0] == 0x40
        gateway.node.destroy_node()
        # At once: long before their 20 s timeout (and their answers say why).
        answers = [wait_for_future(call, 10.0) for call in calls]
        later = []
        while (message := bus.recv(0.2)) is not None:
            later.append(message)
    finally:
        bus.shutdown()
    for answer in answers:
        assert not answer.success and 'shutting down' in answer.message, answer.message
    sdo = [m for m in later if m.arbitration_id == 0x609]
    assert [m.data[0] for m in sdo] == [0x80], 'only the abort of the running read'
    assert struct.unpack_from('<I', sdo[0].data, 4)[0] == 0x08000022
