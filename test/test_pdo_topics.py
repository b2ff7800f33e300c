"""PDOs both ways and SYNC, against durand devices (a CANopen stack that is not ours).

The gateway node runs in this process on a private virtual bus with durand devices whose PDOs
are configured as a drive's would be; this process subscribes to ``~/node_<id>/rpdo``,
publishes on ``~/node_<id>/tpdo`` and calls ``~/pdo_write`` as a robot would, and reads the
device's objects back by SDO (and straight from durand) to see what the frames did.
"""

import struct
import threading
import time

import can
import pytest

from cbcan_ros.msg import Pdo, PdoEntry
from cbcan_ros.ros.pdo import PDO_QOS
from cbcan_ros.simulation.durand.device import DurandDevice
from cbcan_ros.simulation.durand.pdos import PdoConfig

from conftest import new_channel, wait_until
from node_process import EDS

DEVICES = (10, 11)
SYNC_PERIOD = 0.02
EVENT_TIMER = 50  # ms
LOCAL_CONTROL = 0x08000021
PROMPT = 5.0  # seconds within which something that should happen at once has happened

# A drive-like set: TPDO 1 synchronous (every SYNC) with a 16-bit and a signed 32-bit value,
# TPDO 2 event-driven with an event timer, RPDO 1 asynchronous, RPDO 2 synchronous.
PDOS = (
    PdoConfig('tpdo', 1, ((0x2001, 0), (0x2003, 0)), transmission_type=1),
    PdoConfig('tpdo', 2, ((0x2002, 0),), transmission_type=254, event_timer=EVENT_TIMER),
    PdoConfig('rpdo', 1, ((0x2000, 0), (0x2001, 0)), transmission_type=255),
    PdoConfig('rpdo', 2, ((0x2002, 0),), transmission_type=1),
)


class Recorder:
    """Every Pdo message of one topic, by PDO number."""

    def __init__(self, node, node_id: int):
        self.messages = []
        self._lock = threading.Lock()
        node.create_subscription(Pdo, f'/cbcan/node_{node_id}/rpdo', self._on_message, PDO_QOS)

    def _on_message(self, message) -> None:
        with self._lock:
            self.messages.append(message)

    def of(self, pdo: int) -> list:
        """Return the messages of TPDO ``pdo`` so far."""
        with self._lock:
            return [message for message in self.messages if message.pdo == pdo]

    def next_of(self, pdo: int, timeout: float = PROMPT):
        """Wait for a message of ``pdo`` after those seen so far and return it."""
        seen = len(self.of(pdo))
        wait_until(lambda: len(self.of(pdo)) > seen, timeout, f'a new message of TPDO {pdo}')
        return self.of(pdo)[seen]


@pytest.fixture
def rig(make_gateway):
    """Return (gateway, devices by node id, recorders by node id) on a private bus."""
    channel = new_channel()
    devices = {node_id: DurandDevice(node_id, channel=channel, pdos=PDOS)
               for node_id in DEVICES}
    for device in devices.values():
        device.start()

    def start(**parameters):
        settings = dict(can__channel=channel, simulation__devices=None, nodes=list(DEVICES),
                        pdo__nodes=list(DEVICES), sync__period=SYNC_PERIOD,
                        **{f'node_{node_id}__eds': EDS for node_id in DEVICES})
        settings.update(parameters)
        gateway = make_gateway(**settings)
        recorders = {node_id: Recorder(gateway.client_node, node_id) for node_id in DEVICES}
        for node_id in DEVICES:
            wait_until(lambda n=node_id: gateway.node.gateway.pdo.mappings(n)[0], PROMPT,
                       f'the PDO mapping of node {node_id} read')
        return gateway, devices, recorders

    yield start
    for device in devices.values():
        device.stop()


def start_devices(gateway, *node_ids):
    for node_id in node_ids or DEVICES:
        assert gateway.call('nmt_command', node_id=node_id, command=1).success
    gateway.wait_for_states({node_id: 'OPERATIONAL' for node_id in node_ids or DEVICES})


def values(message) -> dict:
    return {(entry.index, entry.subindex): entry.value for entry in message.entries}


def test_synchronous_tpdo_arrives_once_after_every_sync_decoded_by_the_eds(rig):
    gateway, devices, recorders = rig()
    bus = gateway.raw_bus()
    try:
        start_devices(gateway, 10)
        recorders[10].next_of(1)
        while bus.recv(0) is not None:
            pass  # frames from before it was operational
        frames = []
        deadline = time.monotonic() + 0.5
        while time.monotonic() < deadline:
            message = bus.recv(0.1)
            if message is not None and message.arbitration_id in (0x80, 0x18A):
                frames.append(message.arbitration_id)
    finally:
        bus.shutdown()
    # Every SYNC is answered by exactly one TPDO 1 (counted, not timed: on a busy machine
    # the device may answer a SYNC after the next one has gone out).
    after_first_sync = frames[frames.index(0x80):]
    syncs, tpdos = after_first_sync.count(0x80), after_first_sync.count(0x18A)
    assert syncs >= 10, frames
    assert syncs - 2 <= tpdos <= syncs, frames

    message = recorders[10].next_of(1)
    assert (message.node_id, message.pdo, message.cob_id) == (10, 1, 0x18A)
    assert bytes(message.data) == struct.pack('<Hi', 0x1234, -2)
    first_entry, second_entry = message.entries
    assert (first_entry.index, first_entry.subindex, first_entry.name) == (
        0x2001, 0, 'Demo UNSIGNED16')
    assert (first_entry.data_type, first_entry.bits, first_entry.value) == (0x06, 16, 0x1234)
    assert (second_entry.name, second_entry.data_type, second_entry.value) == (
        'Demo INTEGER32', 0x04, -2.0)
    assert bytes(second_entry.data) == struct.pack('<i', -2)
    assert abs(message.stamp.sec + message.stamp.nanosec * 1e-9 - time.time()) < 2.0


def test_event_driven_tpdo_comes_with_its_event_timer_and_carries_sdo_written_values(rig):
    gateway, devices, recorders = rig()
    start_devices(gateway, 10)
    wait_until(lambda: len(recorders[10].of(2)) >= 5, PROMPT,
               'five TPDO 2 frames from the event timer alone')
    assert values(recorders[10].of(2)[-1]) == {(0x2002, 0): 0x12345678}

    written = gateway.call('sdo_write', node_id=10, index=0x2001, subindex=0,
                           data=list(struct.pack('<H', 0x4321)))
    assert written.success, written.message
    wait_until(lambda: values(recorders[10].of(1)[-1])[(0x2001, 0)] == 0x4321, PROMPT,
               'the SDO-written value in TPDO 1')


def test_rpdos_asynchronous_and_synchronous_change_the_device_objects(rig):
    gateway, devices, recorders = rig()
    start_devices(gateway, 10)

    answer = gateway.call('pdo_write', node_id=10, pdo=1, entries=[
        PdoEntry(index=0x2000, subindex=0, value=7.0),
        PdoEntry(index=0x2001, subindex=0, data=list(struct.pack('<H', 300)))])
    assert answer.success, answer.message
    wait_until(lambda: devices[10].value(0x2000) == b'\x07', PROMPT, 'RPDO 1 applied')
    assert devices[10].value(0x2001) == struct.pack('<H', 300)
    # Entries not given keep the value last sent.
    answer = gateway.call('pdo_write', node_id=10, pdo=1,
                          entries=[PdoEntry(index=0x2000, subindex=0, value=8.0)])
    assert answer.success, answer.message
    wait_until(lambda: devices[10].value(0x2000) == b'\x08', PROMPT, 'RPDO 1 applied again')
    read = gateway.call('sdo_read', node_id=10, index=0x2001, subindex=0)
    assert bytes(read.data) == struct.pack('<H', 300)

    # Synchronous: answered once sent after a SYNC, applied by the device at the next one.
    answer = gateway.call('pdo_write', node_id=10, pdo=2,
                          entries=[PdoEntry(index=0x2002, subindex=0, value=99.0)])
    assert answer.success, answer.message
    wait_until(lambda: bytes(gateway.call('sdo_read', node_id=10, index=0x2002,
                                          subindex=0).data) == struct.pack('<I', 99),
               PROMPT, 'RPDO 2 applied at a SYNC')

    # The topic sends as the service does.
    publisher = gateway.client_node.create_publisher(Pdo, '/cbcan/node_10/tpdo', PDO_QOS)
    wait_until(lambda: publisher.get_subscription_count() > 0, PROMPT, 'the tpdo subscription')
    publisher.publish(Pdo(pdo=1, data=[0x2A, 0x10, 0x27]))
    wait_until(lambda: devices[10].value(0x2000) == b'\x2a', PROMPT, 'RPDO 1 from the topic')
    assert devices[10].value(0x2001) == struct.pack('<H', 10000)


def test_synchronous_rpdo_leaves_after_a_sync_and_before_the_next(rig):
    # A quarter of a 200 ms period: the RPDO leaves 50 ms after the SYNC is due, which
    # python-can's sending thread keeps under busy cores (at 20 ms, 5 ms it did not always:
    # the known limit in docs/pdo_and_sync.md).
    gateway, devices, recorders = rig(sync__period=0.2)
    start_devices(gateway, 10)
    bus = gateway.raw_bus()
    try:
        answer = gateway.call('pdo_write', node_id=10, pdo=2,
                              entries=[PdoEntry(index=0x2002, subindex=0, value=5.0)])
        assert answer.success, answer.message
        frames = []
        deadline = time.monotonic() + PROMPT
        while time.monotonic() < deadline and 0x30A not in frames:
            message = bus.recv(0.1)
            if message is not None and message.arbitration_id in (0x80, 0x30A):
                frames.append(message.arbitration_id)
    finally:
        bus.shutdown()
    assert frames[-1] == 0x30A and 0x80 in frames[:-1], frames


def test_a_stopped_device_sends_no_pdos_and_flows_again_when_started(rig):
    gateway, devices, recorders = rig()
    start_devices(gateway, 10)
    recorders[10].next_of(1)
    bus = gateway.raw_bus()
    try:
        assert gateway.call('nmt_command', node_id=10, command=2).success
        gateway.wait_for_states({10: 'STOPPED'})
        stopped_at = time.time()
        while bus.recv(0) is not None:
            pass  # frames from before the state was reported
        frames = []
        while frames.count(0x80) < 10:  # ten SYNCs: a running device sends ten TPDO 1
            message = bus.recv(PROMPT)
            assert message is not None, 'no SYNC'
            frames.append(message.arbitration_id)
    finally:
        bus.shutdown()
    assert not [cob for cob in frames if cob in (0x18A, 0x28A)], frames
    late = [message for message in recorders[10].messages
            if message.stamp.sec + message.stamp.nanosec * 1e-9 > stopped_at]
    assert not late, 'a PDO published that arrived after the device was STOPPED'
    start_devices(gateway, 10)
    recorders[10].next_of(1)


def test_a_device_reset_mid_run_is_read_again_and_flows_with_its_new_mapping(rig):
    gateway, devices, recorders = rig()
    start_devices(gateway, 10)
    recorders[10].next_of(1)
    # Its stored parameters change (as a tool would), then it resets: new mapping at boot.
    # TPDO 2 disabled too: a PDO that is off is read, and re-read, without subscribing to it.
    for first in (0x2002, 0x2003):
        devices[10].configure_pdos([PdoConfig('tpdo', 1, ((first, 0), (0x2000, 0)), 1),
                                    PdoConfig('tpdo', 2, ((0x2002, 0),), 254, enabled=False)])
        assert gateway.call('nmt_command', node_id=10, command=129).success
        wait_until(lambda first=first: [
            e.index for e in gateway.node.gateway.pdo.mappings(10)[0][1].entries] ==
            [first, 0x2000], PROMPT, 'the new mapping read after the boot-up')
    assert not gateway.node.gateway.pdo.mappings(10)[0][2].enabled
    start_devices(gateway, 10)
    message = recorders[10].next_of(1)
    assert [(entry.index, entry.value) for entry in message.entries] == [
        (0x2003, -2.0), (0x2000, 0x12)]
    assert bytes(message.data) == struct.pack('<iB', -2, 0x12)


def test_several_devices_publish_on_their_own_topics(rig):
    gateway, devices, recorders = rig()
    devices[11].set_value(0x2001, 0, 0x1111)
    start_devices(gateway)
    for node_id, expected in ((10, 0x1234), (11, 0x1111)):
        message = recorders[node_id].next_of(1)
        assert (message.node_id, message.cob_id) == (node_id, 0x180 + node_id)
        assert values(message)[(0x2001, 0)] == expected


@pytest.mark.parametrize('request_fields, words', [
    (dict(node_id=12, pdo=1), ['node_id 12', 'pdo.nodes']),
    (dict(node_id=10, pdo=0), ['pdo 0', '1..512']),
    (dict(node_id=10, pdo=5), ['no RPDO 5', 'its RPDOs: 1, 2, 3, 4']),
    (dict(node_id=10, pdo=3), ['RPDO 3 of node 10 maps no object']),
    (dict(node_id=10, pdo=1, entries=[PdoEntry(index=0x2000, value=256.0)]),
     ['0x2000:0', '256', '0..255']),
    (dict(node_id=10, pdo=1, entries=[PdoEntry(index=0x2000, value=1.5)]),
     ['0x2000:0', 'whole number']),
    (dict(node_id=10, pdo=1, entries=[PdoEntry(index=0x2002, value=1.0)]),
     ['0x2002:0 is not mapped to RPDO 1 of node 10', '0x2001:0']),
    (dict(node_id=10, pdo=1, data=[1, 2]), ['data has 2 bytes', 'takes 3']),
    (dict(node_id=10, pdo=1, data=[1, 2, 3], entries=[PdoEntry(index=0x2000)]),
     ['not both']),
])
def test_a_write_that_cannot_be_sent_says_why_and_sends_nothing(rig, request_fields, words):
    gateway, devices, recorders = rig()
    bus = gateway.raw_bus()
    try:
        answer = gateway.call('pdo_write', **request_fields)
        assert not answer.success
        for word in words:
            assert word in answer.message, answer.message
        assert gateway.call('pdo_write', node_id=11, pdo=1, data=[0, 0, 0]).success  # marker
        sent = []
        while (message := bus.recv(0.5)) is not None and message.arbitration_id != 0x20B:
            sent.append(message.arbitration_id)
    finally:
        bus.shutdown()
    assert not [cob for cob in sent if 0x200 <= cob <= 0x57F], sent


@pytest.mark.parametrize('protection', [dict(read_only=True),
                                        dict(sdo__write_allow=['10:0x2000'])])
def test_write_protection_covers_every_mapped_object_of_an_rpdo(rig, protection):
    gateway, devices, recorders = rig(**protection)
    answer = gateway.call('pdo_write', node_id=10, pdo=1,
                          entries=[PdoEntry(index=0x2000, value=1.0)])
    assert (answer.success, answer.abort_code) == (False, LOCAL_CONTROL)
    assert '0x2001:0' in answer.message or 'read-only' in answer.message, answer.message
    assert devices[10].value(0x2000) == b'\x12'


def test_sync_counter_wraps_at_its_overflow(rig):
    gateway, devices, recorders = rig(sync__counter_overflow=3)
    bus = gateway.raw_bus()
    try:
        counters = []
        while len(counters) < 8:
            message = bus.recv(PROMPT)
            assert message is not None, 'no SYNC'
            if message.arbitration_id == 0x80:
                counters.append(message.data[0])
    finally:
        bus.shutdown()
    start = counters.index(1)
    assert counters[start:start + 6] == [1, 2, 3, 1, 2, 3], counters


def test_pdo_configure_writes_the_files_parameters_at_boot(make_gateway):
    channel = new_channel()
    device = DurandDevice(10, channel=channel)  # no PDO set up of its own
    device.start()
    try:
        gateway = make_gateway(can__channel=channel, simulation__devices=None, pdo__nodes=[10],
                               pdo__configure=True, node_10__eds=EDS, nodes=[10])
        recorder = Recorder(gateway.client_node, 10)
        assert gateway.call('nmt_command', node_id=10, command=129).success
        wait_until(lambda: gateway.node.gateway.pdo.mappings(10)[0].get(1) is not None and
                   gateway.node.gateway.pdo.mappings(10)[0][1].entries, PROMPT,
                   "the file's TPDO 1 written and read back")
        start_devices(gateway, 10)
        message = recorder.next_of(1)
        assert [entry.name for entry in message.entries] == ['Demo UNSIGNED16', 'Demo INTEGER32']
    finally:
        device.stop()


def test_a_frame_shorter_than_its_mapping_is_counted_and_not_published(rig):
    gateway, devices, recorders = rig()
    bus = can.Bus(interface='virtual', channel=gateway.channel)
    try:
        start_devices(gateway, 10)
        recorders[10].next_of(1)
        statistics = gateway.node.gateway.pdo.statistics()[10]
        bus.send(can.Message(arbitration_id=0x18A, data=b'\x01\x02', is_extended_id=False))
        wait_until(lambda: gateway.node.gateway.pdo.statistics()[10].short_frames ==
                   statistics.short_frames + 1, PROMPT, 'the short frame counted')
    finally:
        bus.shutdown()
    assert all(len(message.data) >= 6 for message in recorders[10].of(1))


def test_pdo_configure_refused_by_read_only_still_reads_the_devices_mapping(make_gateway,
                                                                           caplog):
    channel = new_channel()
    device = DurandDevice(10, channel=channel, pdos=PDOS)
    device.start()
    try:
        gateway = make_gateway(can__channel=channel, simulation__devices=None, pdo__nodes=[10],
                               pdo__configure=True, node_10__eds=EDS, nodes=[10],
                               read_only=True)
        device.stop()
        device.start()  # power cycled: it boots (read_only refuses an NMT reset)
        wait_until(lambda: any('boot failed (CiA 302-2 error J)' in record.message and
                               '0x1400:1 (RPDO 1)' in record.message and
                               '0x08000021' in record.message for record in caplog.records),
                   PROMPT, 'the refused configuration logged')
        boot = gateway.node.gateway.boot.states()[0]
        assert (boot.node_id, boot.state, boot.error_status) == (10, 'FAILED', 'J'), boot
        wait_until(lambda: gateway.node.gateway.pdo.mappings(10)[0].get(1) is not None,
                   PROMPT, "the device's own mapping read")
        assert [entry.index for entry in gateway.node.gateway.pdo.mappings(10)[0][1].entries] \
            == [0x2001, 0x2003]
    finally:
        device.stop()
