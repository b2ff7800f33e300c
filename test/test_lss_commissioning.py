"""Commissioning by LSS (CiA 305) against durand's LSS slave, a device stack that is not ours.

Every test runs the gateway node in-process on a private virtual bus, with its simulated
python-canopen devices 2, 3 and 5 (no LSS) and durand devices that are LSS slaves: new
ones without a node id (255) or configured ones to renumber.
"""

import math
import struct
import threading
import time

import can
import pytest

from cbcan_ros.msg import LssIdentity
from cbcan_ros.simulation.durand.device import DurandDevice

from conftest import wait_for_future, wait_until

VENDOR, PRODUCT, REVISION = 0x319, 0x51, 0x10000
SERIALS = (0x30, 0x7, 0x12)  # Fastscan finds the lowest identity first: 0x7, 0x12, 0x30
LSS_MASTER, LSS_SLAVE = 0x7E5, 0x7E4
ALL_WAITING = bytes([0x04, 0x00])
RESET_COMMUNICATION = 130
# A scan's own bound is its timeout; these only keep a broken test from hanging.
ANSWER = 60.0
# How long a probe waits for the durand devices' answers. The default on a bus without a wire
# (40 ms) was too short on a loaded machine for a device stack in Python: its answers came
# late, and the scan started again until it gave up as "disturbed".
PROBE_WAIT = 0.15


@pytest.fixture
def make_gateway(make_gateway):
    """Return the harness's gateway factory, with a probe wait loaded devices can keep."""
    return lambda **parameters: make_gateway(**{'lss__probe_timeout': PROBE_WAIT,
                                                **parameters})


def identity(serial: int) -> LssIdentity:
    """Return the LSS identity of the test device with ``serial``."""
    return LssIdentity(vendor_id=VENDOR, product_code=PRODUCT, revision=REVISION,
                       serial=serial)


def identities(response):
    """Return the serials of the devices a scan answered with, in its order."""
    assert all((d.vendor_id, d.product_code, d.revision) == (VENDOR, PRODUCT, REVISION)
               for d in response.devices), response.devices
    return [d.serial for d in response.devices]


@pytest.fixture
def lss_device(start_durand):
    """Return a factory ``lss_device(harness, serial, node_id=255, **options)``.

    It starts a durand LSS slave on the harness's bus, stopped after the test.
    """
    def factory(harness, serial: int, node_id: int = 255, **options) -> DurandDevice:
        return start_durand(node_id, channel=harness.channel, lss=True,
                            identity=(VENDOR, PRODUCT, REVISION, serial), **options)
    return factory


def frames(bus: can.BusABC, within: float, can_id=None):
    """Return the frames (on ``can_id``, or all) the raw bus receives within ``within`` s."""
    found = []
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        message = bus.recv(0.02)
        if message is not None and can_id in (None, message.arbitration_id):
            found.append(message)
    return found


def first_frame(bus: can.BusABC, can_id: int, timeout: float = 10.0) -> bytes:
    """Return the data of the next frame on ``can_id``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        message = bus.recv(0.05)
        if message is not None and message.arbitration_id == can_id:
            return bytes(message.data)
    raise AssertionError(f'no frame on 0x{can_id:03X} within {timeout} s')


def assert_all_waiting(devices):
    """Every LSS slave is back in the waiting state (checked on the device itself)."""
    wait_until(lambda: all(d.lss_waiting for d in devices), 5.0,
               'every device in the LSS waiting state')


def read_serial(gateway, node_id: int) -> int:
    """Return 0x1018:4 of ``node_id`` read by SDO through the gateway."""
    response = gateway.call('sdo_read', node_id=node_id, index=0x1018, subindex=4, timeout=2.0)
    assert response.success, response.message
    return struct.unpack('<I', bytes(response.data))[0]


def test_one_scan_numbers_three_new_devices_which_then_boot_with_their_ids(make_gateway,
                                                                           lss_device):
    # Heard on the bus: 2, 3, 5 (simulated devices); expected: 4. Ids start at 2 and skip them.
    gateway = make_gateway(nodes=[4])
    devices = [lss_device(gateway, serial) for serial in SERIALS]
    gateway.wait_for_states({2: 'PRE_OPERATIONAL', 3: 'PRE_OPERATIONAL', 5: 'PRE_OPERATIONAL'})
    bus = gateway.raw_bus()
    try:
        response = gateway.call('lss_scan', wait=ANSWER, first_node_id=2, store=True)
        assert response.success, response.message
        assert identities(response) == sorted(SERIALS)
        assert list(response.node_ids) == [6, 7, 8]
        for node_id in (6, 7, 8):
            assert first_frame(bus, 0x700 + node_id) == b'\x00', f'boot-up of node {node_id}'
    finally:
        bus.shutdown()
    by_serial = dict(zip(sorted(SERIALS), (6, 7, 8), strict=True))
    for device in devices:
        serial = device.identity[3]
        assert device.node_id == by_serial[serial]
        assert device.stored == {'bitrate': None, 'node_id': by_serial[serial]}
    assert_all_waiting(devices)
    # Heartbeats keep them on ~/node_states; SDO reaches each on its new id.
    gateway.wait_for_states({6: 'PRE_OPERATIONAL', 7: 'PRE_OPERATIONAL', 8: 'PRE_OPERATIONAL',
                             4: 'NOT_DETECTED'})
    time.sleep(0.5)
    gateway.wait_for_states({6: 'PRE_OPERATIONAL', 7: 'PRE_OPERATIONAL', 8: 'PRE_OPERATIONAL'})
    for serial, node_id in by_serial.items():
        assert read_serial(gateway, node_id) == serial
    again = gateway.call('lss_scan', wait=ANSWER, first_node_id=2)
    assert (again.success, list(again.devices)) == (True, []), again.message


def test_scan_with_first_node_id_0_reports_one_device_and_leaves_it_unconfigured(
        make_gateway, lss_device):
    gateway = make_gateway()
    devices = [lss_device(gateway, serial) for serial in SERIALS]
    response = gateway.call('lss_scan', wait=ANSWER, first_node_id=0)
    assert response.success, response.message
    assert identities(response) == [min(SERIALS)]
    assert list(response.node_ids) == [0]
    assert 'left it unconfigured' in response.message
    assert [d.node_id for d in devices] == [255, 255, 255]
    assert_all_waiting(devices)


def test_scan_finding_nothing_answers_quickly_with_an_empty_list(gateway):
    bus = gateway.raw_bus()
    try:
        started = time.monotonic()
        response = gateway.call('lss_scan', wait=ANSWER, first_node_id=10)
        elapsed = time.monotonic() - started
        sent = frames(bus, 0.3, LSS_MASTER)
    finally:
        bus.shutdown()
    assert response.success, response.message
    assert (list(response.devices), list(response.node_ids)) == ([], [])
    assert 'no unconfigured device found' in response.message
    assert elapsed < 3.0, f'{elapsed:.2f} s (make bench measures the real figure)'
    # Waiting, the reset probe, waiting again: nothing was left in another state.
    assert [bytes(m.data) for m in sent] == [
        ALL_WAITING.ljust(8, b'\0'), bytes([0x51, 0, 0, 0, 0, 0x80, 0, 0]),
        ALL_WAITING.ljust(8, b'\0')]


def test_unconfigured_device_given_an_id_by_identity_boots_with_it(make_gateway, lss_device):
    gateway = make_gateway()
    device = lss_device(gateway, 0x7)
    bus = gateway.raw_bus()
    try:
        response = gateway.call('lss_configure', wait=ANSWER, identity=identity(0x7),
                                node_id=30)
        assert response.success, response.message
        assert first_frame(bus, 0x700 + 30) == b'\x00'
    finally:
        bus.shutdown()
    assert 'boots now as node 30' in response.message
    assert (device.node_id, device.stored) == (30, {})
    assert read_serial(gateway, 30) == 0x7
    assert_all_waiting([device])


def test_configured_device_is_renumbered_and_takes_the_id_at_reset_communication(
        make_gateway, lss_device):
    gateway = make_gateway()
    device = lss_device(gateway, 0x12, node_id=20)
    gateway.wait_for_states({20: 'PRE_OPERATIONAL'})
    inquired = gateway.call('lss_inquire', wait=ANSWER, identity=identity(0x12))
    assert (inquired.success, inquired.node_id) == (True, 20), inquired.message
    response = gateway.call('lss_configure', wait=ANSWER, identity=identity(0x12), node_id=21,
                            store=True)
    assert response.success, response.message
    assert 'keeps node id 20 until its next NMT reset communication' in response.message
    assert (device.node_id, device.stored) == (20, {'bitrate': None, 'node_id': 21})
    assert gateway.call('nmt_command', node_id=20, command=RESET_COMMUNICATION).success
    wait_until(lambda: device.node_id == 21, 5.0, 'the device on node id 21')
    gateway.wait_for_states({21: 'PRE_OPERATIONAL'})
    assert read_serial(gateway, 21) == 0x12
    inquired = gateway.call('lss_inquire', wait=ANSWER, identity=identity(0x12))
    assert (inquired.success, inquired.node_id) == (True, 21), inquired.message
    assert_all_waiting([device])


def test_bit_rate_is_set_and_stored(make_gateway, lss_device):
    gateway = make_gateway()
    device = lss_device(gateway, 0x12, node_id=20)
    response = gateway.call('lss_configure', wait=ANSWER, identity=identity(0x12),
                            bitrate=250000, store=True)
    assert (response.success, response.error_code) == (True, 0), response.message
    assert device.stored == {'bitrate': 250000, 'node_id': 20}
    assert 'takes effect when the device is next powered on' in response.message
    assert device.node_id == 20, 'the bus keeps running at its rate meanwhile'
    assert_all_waiting([device])


@pytest.mark.parametrize('options, fields, what', [
    (dict(lss_bit_rates=False), dict(bitrate=125000, store=True), 'configure bit timing'),
    (dict(lss_store=False), dict(node_id=40, store=True), 'store configuration'),
])
def test_device_that_refuses_is_answered_with_its_lss_error_code(make_gateway, lss_device,
                                                                 options, fields, what):
    gateway = make_gateway()
    device = lss_device(gateway, 0x7, node_id=20, **options)
    response = gateway.call('lss_configure', wait=ANSWER, identity=identity(0x7), **fields)
    assert (response.success, response.error_code) == (False, 1), response.message
    assert f'refused {what}' in response.message
    assert 'LSS error 1' in response.message
    assert device.stored == {}
    assert_all_waiting([device])


def test_absent_device_is_answered_that_nobody_answered(make_gateway, lss_device):
    gateway = make_gateway()
    lss_device(gateway, 0x7, node_id=20)
    for service, fields in (('lss_configure', dict(node_id=40)), ('lss_inquire', {})):
        response = gateway.call(service, wait=ANSWER, identity=identity(0x99), **fields)
        assert not response.success
        assert 'serial 0x00000099 answered' in response.message, response.message


def test_inquire_tells_255_for_an_unconfigured_device(make_gateway, lss_device):
    gateway = make_gateway()
    lss_device(gateway, 0x30)
    response = gateway.call('lss_inquire', wait=ANSWER, identity=identity(0x30))
    assert (response.success, response.node_id) == (True, 255), response.message
    assert 'unconfigured' in response.message


@pytest.mark.parametrize('service, fields, words', [
    ('lss_scan', dict(first_node_id=128), 'first_node_id 128 is out of range'),
    ('lss_scan', dict(first_node_id=5, timeout=-1.0), 'timeout -1.0 s is out of range'),
    ('lss_scan', dict(first_node_id=5, timeout=math.nan), 'timeout nan s is out of range'),
    ('lss_scan', dict(first_node_id=5, timeout=1e9), 'timeout 1000000000.0 s is out of range'),
    ('lss_configure', dict(node_id=128), 'node_id 128 is out of range'),
    ('lss_configure', dict(node_id=255), 'node_id 255 is out of range'),
    ('lss_configure', dict(bitrate=100000, store=True), 'bitrate 100000 is not in the CiA 305'),
    ('lss_configure', dict(bitrate=4294967295, store=True), 'bitrate 4294967295 is not in'),
    ('lss_configure', dict(bitrate=250000), 'bitrate 250000 needs store: true'),
    ('lss_configure', {}, 'nothing to configure: give node_id, bitrate or store'),
    ('lss_configure', dict(node_id=5, timeout=math.inf), 'timeout inf s is out of range'),
    ('lss_inquire', dict(timeout=-0.5), 'timeout -0.5 s is out of range'),
])
def test_field_out_of_range_is_refused_by_name_and_nothing_is_sent(gateway, service, fields,
                                                                     words):
    if service != 'lss_scan':
        fields = dict(fields, identity=identity(0x7))
    bus = gateway.raw_bus()
    try:
        response = gateway.call(service, **fields)
        sent = frames(bus, 0.3, LSS_MASTER)
    finally:
        bus.shutdown()
    assert not response.success
    assert words in response.message, response.message
    assert sent == []


def test_read_only_refuses_every_lss_service_and_sends_nothing(make_gateway, lss_device):
    gateway = make_gateway(read_only=True)
    device = lss_device(gateway, 0x7)
    bus = gateway.raw_bus()
    try:
        answers = [gateway.call('lss_scan', first_node_id=10),
                   gateway.call('lss_configure', identity=identity(0x7), node_id=10),
                   gateway.call('lss_inquire', identity=identity(0x7))]
        sent = frames(bus, 0.3, LSS_MASTER)
    finally:
        bus.shutdown()
    for response in answers:
        assert not response.success
        assert 'read-only (parameter read_only)' in response.message, response.message
        assert 'nothing was sent' in response.message
    assert sent == []
    assert device.node_id == 255


def test_sdo_and_nmt_to_other_devices_keep_working_during_a_scan(make_gateway, lss_device):
    gateway = make_gateway()
    devices = [lss_device(gateway, serial) for serial in SERIALS]
    scan = gateway.call_async('lss_scan', first_node_id=10)
    reads = commands = 0
    while not scan.done():
        read = gateway.call('sdo_read', node_id=5, index=0x1000, subindex=0, timeout=2.0)
        assert read.success, read.message
        assert gateway.call('nmt_command', node_id=2,
                            command=1 if commands % 2 == 0 else 128).success
        reads, commands = reads + 1, commands + 1
    response = wait_for_future(scan, ANSWER)
    assert response.success, response.message
    assert list(response.node_ids) == [10, 11, 12]
    assert reads >= 3, 'the scan was over before the other traffic could overlap it'
    assert sorted(d.node_id for d in devices) == [10, 11, 12]
    assert_all_waiting(devices)


def test_second_lss_call_waits_its_timeout_or_is_told_busy(make_gateway, lss_device):
    gateway = make_gateway()
    lss_device(gateway, 0x99, node_id=20)
    devices = [lss_device(gateway, serial) for serial in SERIALS]
    scan = gateway.call_async('lss_scan', first_node_id=30)
    wait_until(lambda: any(d.node_id != 255 for d in devices) or scan.done(), 30.0,
               'the scan under way')
    impatient = gateway.call('lss_inquire', identity=identity(0x99), timeout=0.01)
    patient = gateway.call_async('lss_inquire', identity=identity(0x99), timeout=60.0)
    assert not impatient.success
    assert 'busy: another LSS operation' in impatient.message, impatient.message
    assert 'nothing was sent' in impatient.message
    scanned = wait_for_future(scan, ANSWER)
    assert scanned.success, scanned.message
    waited = wait_for_future(patient, ANSWER)
    assert (waited.success, waited.node_id) == (True, 20), waited.message


def test_shutdown_during_a_scan_answers_every_call_and_only_returns_devices_to_waiting(
        make_gateway, lss_device):
    gateway = make_gateway()
    devices = [lss_device(gateway, serial) for serial in SERIALS]
    bus = gateway.raw_bus()
    try:
        scan = gateway.call_async('lss_scan', first_node_id=30, timeout=60.0)
        queued = gateway.call_async('lss_inquire', identity=identity(0x7), timeout=60.0)
        first_frame(bus, LSS_MASTER)  # the scan is under way
        # The moment shutdown closes the bus to everything but the frames that end a running
        # operation; until then the scan goes on (the thread below may start late).
        supervisor = gateway.node.gateway.bus
        gated, restrict = [], supervisor.restrict_sending
        supervisor.restrict_sending = lambda *rule: (restrict(*rule), gated.append(time.time()))
        stopping = threading.Thread(target=gateway.node.interface.shut_down)
        stopping.start()
        answers = [wait_for_future(scan, 10.0), wait_for_future(queued, 10.0)]
        stopping.join(10.0)
        late = [m for m in frames(bus, 0.3, LSS_MASTER) if m.timestamp > gated[0]]
    finally:
        bus.shutdown()
    for response in answers:
        assert not response.success
        assert 'shutting down' in response.message, response.message
    assert 'nothing was sent' in answers[1].message
    assert all(bytes(m.data[:2]) == ALL_WAITING for m in late), late
    assert_all_waiting(devices)


def test_scan_storing_in_a_device_that_cannot_store_says_so_and_lists_its_new_id(
        make_gateway, lss_device):
    gateway = make_gateway()
    device = lss_device(gateway, 0x7, lss_store=False)
    response = gateway.call('lss_scan', wait=ANSWER, first_node_id=40, store=True)
    assert not response.success
    assert (identities(response), list(response.node_ids)) == ([0x7], [40])
    assert 'has node id 40 but it is not stored: the device refused store configuration: ' \
           'LSS error 1 (storing the configuration is not supported)' in response.message
    wait_until(lambda: device.node_id == 40, 5.0, 'the device on its new id')
    assert_all_waiting([device])
