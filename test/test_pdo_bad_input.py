"""Property-based tests: any PDO frame, mapping, Pdo message or PdoWrite request is handled.

Generated with hypothesis:

* mappings a device may report (any UNSIGNED32 entries, dummies, lengths summing past 64
  bits) and frames of every length 0..8: the mapping is refused with a message when longer
  than a frame; a frame shorter than the mapping is counted, never published; any other is
  decoded to exactly the bits a reference reading of the frame gives, and its message builds;
* ``PdoWrite`` requests and ``Pdo`` messages on the tpdo topic, every field across its range:
  one answer each, a refusal says why, and whatever is accepted reaches the device's objects
  exactly as a small model of the mapping says (read back from durand).
"""

import math
import struct

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import pytest

from cbcan_ros.core.pdo.mapping import decode, EntryValue, MAX_BITS, parse_mapping, ReceivedPdo
from cbcan_ros.core.pdo.service import PdoService
from cbcan_ros.core.sdo.write_protection import WriteProtection
from cbcan_ros.msg import Pdo, PdoEntry
from cbcan_ros.ros.pdo import pdo_message, PDO_QOS
from cbcan_ros.simulation.durand.device import DurandDevice
from cbcan_ros.simulation.durand.pdos import PdoConfig

from conftest import new_channel, wait_for_future, wait_until
from node_process import EDS

FUZZ = settings(max_examples=150, deadline=None, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])
NODE = 10
PROMPT = 5.0
MESSAGE_LIMIT = 600
TYPES = [0, 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x10, 0x11, 0x15, 0x1B, 0x09]
SIGNED = {0x02: 8, 0x03: 16, 0x04: 32, 0x10: 24, 0x15: 64}


class _Variable:
    def __init__(self, name, data_type):
        self.qualname, self.data_type = name, data_type


class _Dictionary:
    """Gives every object the data type hypothesis drew for its index."""

    def __init__(self, types):
        self._types = types

    def get_variable(self, index, subindex):
        data_type = self._types.get(index)
        return None if data_type is None else _Variable(f'object {index:04X}', data_type)


mapping_entries = st.lists(st.one_of(
    st.integers(0, 0xFFFFFFFF),
    st.builds(lambda index, sub, bits: index << 16 | sub << 8 | bits,
              st.sampled_from([0x0001, 0x0005, 0x0007, 0x2000, 0x2001, 0x6040, 0x6064]),
              st.integers(0, 3), st.sampled_from([1, 3, 7, 8, 12, 16, 24, 32, 40, 64]))),
    max_size=12)


def reference_bits(data: bytes, offset: int, bits: int) -> int:
    """Read ``bits`` bits from ``offset`` of a frame bit by bit (CiA 301: LSB first)."""
    return sum(((data[(offset + i) // 8] >> ((offset + i) % 8)) & 1) << i for i in range(bits))


@FUZZ
@given(mapped=mapping_entries, frame=st.binary(max_size=8),
       types=st.dictionaries(st.sampled_from([0x2000, 0x2001, 0x6040, 0x6064]),
                             st.sampled_from(TYPES)))
def test_any_mapping_and_frame_decode_to_exactly_the_frames_bits(mapped, frame, types):
    mapping = parse_mapping(NODE, 'tpdo', 1, 0x18A, 1, 0, mapped, _Dictionary(types))
    total = sum(value & 0xFF for value in mapped)
    if total > MAX_BITS:
        assert mapping.problem and f'{total} bits' in mapping.problem and 'refused' in \
            mapping.problem, mapping.problem
        return
    assert not mapping.problem
    assert mapping.bits == total
    if len(frame) < mapping.size:
        return  # counted and dropped by the service (test below)
    for decoded in decode(mapping, frame):
        entry = decoded.entry
        raw = reference_bits(frame, entry.offset, entry.bits)
        assert decoded.data == raw.to_bytes((entry.bits + 7) // 8, 'little')
        if entry.dummy:
            assert decoded.value == 0.0
        elif (entry.data_type, entry.bits) in ((0x08, 32), (0x11, 64)):
            code = '<f' if entry.bits == 32 else '<d'
            expected = struct.unpack(code, decoded.data)[0]
            assert decoded.value == expected or (math.isnan(expected) and
                                                 math.isnan(decoded.value))
        elif entry.data_type in SIGNED and raw >> (entry.bits - 1):
            assert decoded.value == float(raw - (1 << entry.bits))
        else:
            assert decoded.value == float(raw)
        message = pdo_message(ReceivedPdo(mapping, frame, 0.0))
        assert bytes(message.data) == frame


class _Network:
    def subscribe(self, *_):
        pass

    def send_message(self, *_):
        pass


@FUZZ
@given(mapped=mapping_entries, frames=st.lists(st.binary(max_size=8), max_size=10))
def test_a_frame_shorter_than_its_mapping_is_counted_never_published(mapped, frames):
    service = PdoService(_Network(), [NODE], None, WriteProtection(), None, {})
    published = []
    service.add_listener(published.append)
    mapping = parse_mapping(NODE, 'tpdo', 1, 0x18A, 1, 0, mapped)
    service._by_cob[0x18A] = mapping  # as a mapping read installs it
    for frame in frames:
        service._on_frame(0x18A, bytearray(frame), 1.0)
    statistics = service.statistics()[NODE]
    if mapping.problem:
        assert (published, statistics.unusable) == ([], len(frames))
        return
    short = [frame for frame in frames if len(frame) < mapping.size]
    assert statistics.short_frames == len(short)
    assert [received.data for received in published] == [
        frame for frame in frames if len(frame) >= mapping.size]


RPDO = ((0x2000, 0, 8), (0x2001, 0, 16))  # RPDO 1 of the device: UNSIGNED8, UNSIGNED16


@pytest.fixture
def fuzzed(make_gateway):
    """Return (gateway, device): durand device 10, operational, its RPDO 1 asynchronous."""
    channel = new_channel()
    device = DurandDevice(NODE, channel=channel, pdos=[
        PdoConfig('rpdo', 1, tuple((index, sub) for index, sub, _ in RPDO), 255)])
    device.start()
    gateway = make_gateway(can__channel=channel, simulation__devices=None, nodes=[NODE],
                           pdo__nodes=[NODE], node_10__eds=EDS)
    wait_until(lambda: gateway.node.gateway.pdo.mappings(NODE)[1], PROMPT, 'the mapping read')
    assert gateway.call('nmt_command', node_id=NODE, command=1).success
    gateway.wait_for_states({NODE: 'OPERATIONAL'})
    # Entries not given keep the value last sent (0 at first): start where the device is.
    assert gateway.call('pdo_write', node_id=NODE, pdo=1, data=[0x12, 0x34, 0x12]).success
    wait_until(lambda: device.value(0x2001) == b'\x34\x12', PROMPT, 'the first write applied')
    yield gateway, device
    device.stop()


def model(node_id, pdo, entries, data, state):
    """Return the device's new (0x2000, 0x2001) values for a write, or None if refused."""
    if node_id != NODE or pdo != 1:
        return None
    if data:
        if entries or len(data) != 3:
            return None
        return data[0], int.from_bytes(data[1:3], 'little')
    values = list(state)
    for entry in entries:
        positions = [i for i, (index, sub, _) in enumerate(RPDO)
                     if (index, sub) == (entry.index, entry.subindex)]
        if not positions:
            return None
        bits = RPDO[positions[0]][2]
        if entry.data:
            if len(entry.data) != bits // 8:
                return None
            number = int.from_bytes(bytes(entry.data), 'little')
        else:
            if not math.isfinite(entry.value) or not entry.value.is_integer():
                return None
            number = int(entry.value)
            if not 0 <= number < 1 << bits:
                return None
        values[positions[0]] = number
    return tuple(values)


def handled_writes(gateway) -> int:
    statistics = gateway.node.gateway.pdo.statistics()[NODE]
    return statistics.sent + statistics.refused


entries_strategy = st.lists(st.builds(
    PdoEntry,
    index=st.one_of(st.sampled_from([0x2000, 0x2001, 0x2002, 0x0005]), st.integers(0, 0xFFFF)),
    subindex=st.one_of(st.just(0), st.integers(0, 255)),
    value=st.one_of(st.integers(-2, 70000).map(float), st.floats(allow_nan=True)),
    data=st.one_of(st.just([]), st.lists(st.integers(0, 255), max_size=4))), max_size=4)


@FUZZ
@given(node_id=st.one_of(st.just(NODE), st.integers(0, 255)),
       pdo=st.one_of(st.just(1), st.integers(0, 0xFFFF)), entries=entries_strategy,
       data=st.one_of(st.just([]), st.lists(st.integers(0, 255), max_size=10)),
       by_topic=st.booleans())
def test_any_pdo_write_or_message_is_answered_and_applied_exactly_as_mapped(
        fuzzed, node_id, pdo, entries, data, by_topic):
    gateway, device = fuzzed
    state = (device.value(0x2000)[0], int.from_bytes(device.value(0x2001), 'little'))
    expected = model(node_id, pdo, entries, data, state)
    if by_topic:
        publisher = getattr(gateway, 'tpdo_publisher', None) or gateway.client_node.\
            create_publisher(Pdo, f'/cbcan/node_{NODE}/tpdo', PDO_QOS)
        gateway.tpdo_publisher = publisher
        wait_until(lambda: publisher.get_subscription_count() > 0, PROMPT, 'the subscription')
        expected = model(NODE, pdo, entries, data, state) if node_id in (0, NODE) else None
        handled = handled_writes(gateway)
        publisher.publish(Pdo(node_id=node_id, pdo=pdo, entries=entries, data=data))
        wait_until(lambda: handled_writes(gateway) == handled + 1, PROMPT,
                   'the message sent or refused')
    else:
        answer = wait_for_future(gateway.call_async(
            'pdo_write', node_id=node_id, pdo=pdo, entries=entries, data=data), PROMPT)
        assert answer.success == (expected is not None), (answer.message, expected)
        assert len(answer.message) <= MESSAGE_LIMIT
        if not answer.success:
            assert answer.message
    # A marker write through the same path: once applied, the fuzzed one was handled before.
    marker = (state[0] + 1) % 256 if expected is None else (expected[0] + 1) % 256
    after = (marker, state[1] if expected is None else expected[1])
    assert gateway.call('pdo_write', node_id=NODE, pdo=1,
                        entries=[PdoEntry(index=0x2000, value=float(marker))]).success
    wait_until(lambda: (device.value(0x2000)[0],
                        int.from_bytes(device.value(0x2001), 'little')) == after, PROMPT,
               f'the device at {after} (model said {expected})')


def test_written_value_uses_the_entry_value_when_no_data_is_given():
    mapping = parse_mapping(NODE, 'rpdo', 1, 0x20A, 255, 0, [0x20000008, 0x20010010])
    service = PdoService(_Network(), [NODE], None, WriteProtection(), None, {})
    service._devices[NODE].rpdos = {1: mapping}
    frames = []
    service._network.send_message = lambda cob, data: frames.append((cob, bytes(data)))
    result = service.write(NODE, 1, [EntryValue(0x2001, 0, 513.0)]).result()
    assert result.success, result.message
    assert frames == [(0x20A, b'\x00\x01\x02')]
