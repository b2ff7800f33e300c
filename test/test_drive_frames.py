"""Which RPDOs carry a write to a drive, and in what order, on the layouts drives ship.

``drive_frames.plan`` alone, on the mappings of vendor EDS files and of ros2_canopen's
examples: the controlword in exactly one frame, the last; what no RPDO carries by SDO first;
no synchronous frame before an event-driven controlword frame.
"""

from struct import pack

import pytest

from cbcan_ros.core.drives import cia402
from cbcan_ros.core.drives.frames import Frame, frame_data, frame_values, plan, usable_frames
from cbcan_ros.core.pdo.mapping import encode, EntryValue, MappedEntry, PdoMapping

CW, MODE, TARGET = cia402.CONTROLWORD, cia402.MODE, cia402.TARGET_POSITION
VELOCITY, TORQUE = cia402.TARGET_VELOCITY, cia402.TARGET_TORQUE
EVERYTHING = {CW: 0x0F, MODE: 1, TARGET: 0, VELOCITY: 0, TORQUE: 0,
              cia402.PROFILE_VELOCITY_OBJECT: 0}

# Maxon EPOS2, Faulhaber MC, Wittenstein simco: the controlword in every RPDO.
VENDOR = {1: (CW,), 2: (CW, MODE), 3: (CW, TARGET), 4: (CW, VELOCITY)}
# ros2_canopen's canopen_tests/config/cia402/bus.yml.
ROS2_CANOPEN = {1: (CW, MODE), 2: (TARGET, VELOCITY)}
# make run's simulated drive.
COMBINED = {1: (CW, TARGET, MODE), 2: (VELOCITY, TORQUE)}


def frames(layout, synchronous=()):
    """Return the frames of ``layout`` (number: objects), ``synchronous`` ones so."""
    return [Frame(number, indexes, number in synchronous)
            for number, indexes in sorted(layout.items())]


def sent(layout, values, synchronous=(), controlword_known=True):
    """Return (objects by SDO, [(RPDO number, carries the write's controlword)])."""
    chosen = plan(values, frames(layout, synchronous), controlword_known)
    last = len(chosen.frames) - 1
    return chosen.by_sdo, [(frame.number, CW in values and n == last and frame.controlword)
                           for n, frame in enumerate(chosen.frames)]


@pytest.mark.parametrize('layout, expected', [
    (VENDOR, [(3, True)]),
    (ROS2_CANOPEN, [(2, False), (1, True)]),
    (COMBINED, [(1, True)]),
], ids=['vendor', 'ros2_canopen', 'combined'])
def test_a_set_point_goes_with_its_target_before_or_with_its_controlword(layout, expected):
    assert sent(layout, [TARGET, CW]) == ((), expected)


def test_a_mode_change_with_its_target_on_the_vendor_layout_sends_the_new_word_once():
    # RPDO 2 (mode) and RPDO 3 (target) both map the controlword: the first repeats the
    # word commanded before, the last carries the new one.
    assert sent(VENDOR, [MODE, TARGET, CW]) == ((), [(2, False), (3, True)])
    chosen = plan([MODE, TARGET, CW], frames(VENDOR), True)
    first = frame_values(chosen.frames[0], {**EVERYTHING, CW: 0x1F}, 0x0F, False)
    assert first == {CW: 0x0F, MODE: 1}


def test_a_controlword_alone_goes_in_the_smallest_frame_that_maps_it():
    assert sent(VENDOR, [CW]) == ((), [(1, True)])


def test_objects_no_rpdo_carries_go_by_sdo_before_the_frames():
    assert sent(ROS2_CANOPEN, [TORQUE, CW]) == ((TORQUE,), [(1, True)])


def test_without_an_rpdo_for_the_controlword_the_whole_write_goes_by_sdo_controlword_last():
    assert sent({1: (TARGET,)}, [CW, TARGET]) == ((TARGET, CW), [])
    assert sent({}, [CW, MODE]) == ((MODE, CW), [])


def test_a_synchronous_frame_never_goes_before_an_event_driven_controlword_frame():
    # RPDO 2 (target) applied at the next SYNC, RPDO 1 (controlword) at once: the edge
    # would come first. Nothing fits, so all goes by SDO, in order.
    assert sent(ROS2_CANOPEN, [TARGET, CW], synchronous={2}) == ((TARGET, CW), [])
    # Both synchronous: the controlword's frame still last.
    assert sent(ROS2_CANOPEN, [TARGET, CW], synchronous={1, 2}) == ((), [(2, False),
                                                                         (1, True)])


def test_an_earlier_frame_that_maps_the_controlword_needs_the_word_commanded_before():
    assert sent(VENDOR, [MODE, TARGET, CW], controlword_known=False) == ((MODE, TARGET, CW), [])


def test_an_rpdo_that_maps_an_object_the_gateway_holds_no_value_for_is_not_used():
    max_torque = 0x6072
    mapping = PdoMapping(node_id=7, kind='rpdo', number=4, cob_id=0x507, transmission_type=255,
                         enabled=True, entries=(MappedEntry(CW, 0, 16, 0),
                                                MappedEntry(max_torque, 0, 16, 16)))
    assert usable_frames({4: mapping}, EVERYTHING, sync_producing=False) == []
    plain = PdoMapping(node_id=7, kind='rpdo', number=1, cob_id=0x207, transmission_type=1,
                       enabled=True, entries=(MappedEntry(CW, 0, 16, 0),))
    assert usable_frames({1: plain}, EVERYTHING, sync_producing=False) == []
    assert usable_frames({1: plain}, EVERYTHING, sync_producing=True) == [
        Frame(1, (CW,), True)]


def test_an_rpdo_that_maps_another_object_is_used_with_the_bytes_read_from_the_drive():
    max_torque = 0x6072
    mapping = PdoMapping(node_id=7, kind='rpdo', number=4, cob_id=0x507, transmission_type=255,
                         enabled=True, entries=(MappedEntry(CW, 0, 16, 0),
                                                MappedEntry(max_torque, 0, 16, 16)))
    held = {(max_torque, 0): b'\xe8\x03'}
    assert usable_frames({4: mapping}, EVERYTHING, False, held) == [
        Frame(4, (CW,), False, ((max_torque, 0),))]
    assert usable_frames({4: mapping}, EVERYTHING, False, {(max_torque, 0): b'\xe8'}) == []


def rpdo(*entries):
    """Return RPDO 1 of node 7 mapping ``entries`` ((index, subindex, bits)), in order."""
    mapped, offset = [], 0
    for index, subindex, bits in entries:
        mapped.append(MappedEntry(index, subindex, bits, offset))
        offset += bits
    return PdoMapping(node_id=7, kind='rpdo', number=1, cob_id=0x207, transmission_type=255,
                      enabled=True, entries=tuple(mapped))


HELD = {(0x6072, 0): b'\xe8\x03', (0x2010, 3): b'\x01\x02\x03'}
VALUES = {CW: 0x1F, MODE: -3, TARGET: -123456, VELOCITY: 70000, TORQUE: -250,
          cia402.PROFILE_VELOCITY_OBJECT: 4000000000}


@pytest.mark.parametrize('entries', [
    ((CW, 0, 16), (TARGET, 0, 32), (MODE, 0, 8)),          # make run's RPDO 1
    ((CW, 0, 16), (VELOCITY, 0, 32)),                       # a vendor's RPDO 4
    ((TARGET, 0, 32), (VELOCITY, 0, 32)),                   # ros2_canopen's RPDO 2
    ((CW, 0, 16), (0x6072, 0, 16), (TORQUE, 0, 16)),        # with a held object
    ((0x2010, 3, 24), (CW, 0, 16), (cia402.PROFILE_VELOCITY_OBJECT, 0, 32)),
], ids=['combined', 'vendor', 'ros2_canopen', 'held', 'vendor_object'])
def test_a_frame_packed_at_once_is_the_frame_built_entry_by_entry(entries):
    # Bytes on the bus must not depend on which way a frame was built.
    mapping = rpdo(*entries)
    frame, = usable_frames({1: mapping}, VALUES, False, HELD)
    assert frame.layout is not None
    by_entries = encode(mapping, bytes(mapping.size), [
        EntryValue(index, 0, data=pack(cia402.FORMATS[index], VALUES[index]))
        for index in frame.indexes] + [
        EntryValue(index, subindex, data=HELD[(index, subindex)])
        for index, subindex in frame.held])
    assert frame_data(frame, frame_values(frame, VALUES, None, True), HELD) == by_entries


@pytest.mark.parametrize('entries', [
    ((CW, 0, 16), (0x0005, 0, 8), (TARGET, 0, 32)),         # a dummy entry: kept as it was
    ((CW, 0, 16), (TARGET, 0, 16)),                         # narrower than its type: refused
    ((CW, 0, 12), (MODE, 0, 4)),                            # not on whole bytes
], ids=['dummy', 'narrow', 'bits'])
def test_a_frame_not_of_whole_typed_bytes_goes_entry_by_entry(entries):
    frame, = usable_frames({1: rpdo(*entries)}, VALUES, False, HELD)
    assert frame.layout is None
