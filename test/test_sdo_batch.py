"""The batch service ``~/sdo_batch``: order, per-device order, failures in the middle."""

import struct
import time

from cbcan_ros.msg import SdoAccess
from cbcan_ros.srv import SdoBatch

from conftest import wait_for_future

DEVICE_TYPE = struct.pack('<I', 0x00020192)


def batch(gateway, accesses, timeout=0.0, wait=20.0):
    client = gateway.client_node.create_client(SdoBatch, '/cbcan/sdo_batch')
    assert client.wait_for_service(timeout_sec=10.0)
    request = SdoBatch.Request(accesses=accesses, timeout=timeout)
    return wait_for_future(client.call_async(request), wait).results


def read(node, index, sub=0, max_size=0):
    return SdoAccess(node_id=node, index=index, subindex=sub, max_size=max_size)


def write(node, index, data, sub=0):
    return SdoAccess(node_id=node, index=index, subindex=sub, write=True, data=list(data))


def test_results_come_in_the_order_of_the_accesses(gateway):
    accesses = [read(5, 0x1000), write(2, 0x2002, struct.pack('<I', 7)), read(3, 0x1008),
                read(0, 0x1018, 2), read(2, 0x2002)]
    results = batch(gateway, accesses)
    assert [r.success for r in results] == [True] * 5, [r.message for r in results]
    assert bytes(results[0].data) == DEVICE_TYPE
    assert bytes(results[1].data) == b''
    assert bytes(results[2].data) == b'cbcan simulated device'
    assert bytes(results[3].data) == struct.pack('<I', 0xCBCA)
    assert bytes(results[4].data) == struct.pack('<I', 7), 'the write ran before the read'


def test_accesses_to_one_device_run_in_order_mixed_reads_and_writes(gateway):
    accesses = []
    for value in range(20):
        accesses.append(write(5, 0x2001, struct.pack('<H', value)))
        accesses.append(read(5, 0x2001))
    results = batch(gateway, accesses)
    for value in range(20):
        assert bytes(results[2 * value + 1].data) == struct.pack('<H', value)


def test_a_failure_in_the_middle_does_not_stop_the_rest(gateway):
    accesses = [read(5, 0x1000), read(5, 0x6000), write(5, 0x2010, b'\1\2\3\4'),
                read(9, 0x1000), read(5, 0x1018, 9), read(5, 0x1000)]
    results = batch(gateway, accesses, timeout=2.0)
    assert [r.abort_code for r in results] == [0, 0x06020000, 0x06010002, 0x05040000,
                                               0x06090011, 0]
    assert results[-1].success and bytes(results[-1].data) == DEVICE_TYPE
    assert all(r.message for r in results if not r.success)


def test_invalid_accesses_are_refused_each_with_a_message(gateway):
    accesses = [read(5, 0x1000), write(5, 0x2002, b''), read(200, 0x1000)]
    results = batch(gateway, accesses)
    assert results[0].success
    assert not results[1].success
    assert results[1].message == 'data is empty: write at least 1 byte'
    assert 'node_id 200 is out of range' in results[2].message


def test_write_protection_applies_to_every_access(make_gateway):
    gateway = make_gateway(sdo__write_allow=['5:0x2001'])
    results = batch(gateway, [write(5, 0x2001, b'\x11\x22'), write(5, 0x2002, b'\1\2\3\4')])
    assert results[0].success
    assert results[1].abort_code == 0x08000021
    assert gateway.device(5).node.sdo[0x2002].raw == 0x12345678


def test_an_oversized_batch_is_refused_whole_and_names_the_limit(gateway):
    results = batch(gateway, [read(5, 0x1000)] * 1025)
    assert len(results) == 1025
    assert not any(r.success for r in results)
    assert 'at most 1024' in results[0].message and '1025' in results[0].message


def test_devices_run_in_parallel_and_the_timeout_bounds_the_batch(gateway):
    # The first slow read ends a second before the batch's timeout, the second runs out of
    # time midway, the third never starts; the fast device's read is not held up by them.
    slow, timeout = 2.0, 3.0
    gateway.device(2).slow_read_delay = slow
    accesses = [read(2, 0x2200), read(2, 0x2200), read(2, 0x2200), read(3, 0x1000)]
    started = time.monotonic()
    results = batch(gateway, accesses, timeout=timeout)
    elapsed = time.monotonic() - started
    assert elapsed < timeout + slow, 'the batch outlived its timeout'
    assert results[0].success
    assert results[1].abort_code == 0x05040000  # ran out of time during the transfer
    assert results[2].abort_code == 0x05040000
    assert 'nothing was sent' in results[2].message
    assert bytes(results[3].data) == DEVICE_TYPE
