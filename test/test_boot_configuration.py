"""Boot configuration (bus_config): each device checked, configured, verified, then started.

The devices are durand devices (an independent stack) that really forget: a reset node or a
power cycle (stop, then start again) brings back their defaults. What the tests read is what
the devices hold and the frames on the bus, in their order.
"""

import pathlib
import struct
import textwrap
import threading
import time
from typing import List

import can
import pytest

from cbcan_ros.simulation.durand.device import DurandDevice
from cbcan_ros.simulation.durand.dictionary import HEARTBEAT_DEFAULT

from conftest import new_channel, wait_until

ROOT = pathlib.Path(__file__).resolve().parent.parent
EDS = ROOT / 'config' / 'simulated_device.eds'
WAIT = 15.0
NODE = 10
SDO_REQUEST = 0x600
NMT = 0x000
START = 1


class Frames:
    """Every frame on the bus from now on, in order (a thread of its own reads them)."""

    def __init__(self, channel: str):
        self._bus = can.Bus(interface='virtual', channel=channel)
        self.frames: List[can.Message] = []
        self._stopped = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stopped.is_set():
            message = self._bus.recv(0.05)
            if message is not None:
                self.frames.append(message)

    def close(self) -> None:
        """Stop reading and close the bus."""
        self._stopped.set()
        self._thread.join()
        self._bus.shutdown()

    def send(self, arbitration_id: int, data: bytes) -> None:
        """Send a frame, as another device on the bus would."""
        self._bus.send(can.Message(arbitration_id=arbitration_id, data=data,
                                   is_extended_id=False))

    def snapshot(self) -> List[can.Message]:
        """Return the frames so far."""
        return list(self.frames)


def downloads(frames, node_id: int = NODE):
    """Return the positions and objects of the SDO downloads (writes) requested of a node."""
    return [(position, struct.unpack_from('<HB', frame.data, 1))
            for position, frame in enumerate(frames)
            if frame.arbitration_id == SDO_REQUEST + node_id and frame.data[0] >> 5 == 1]


def uploads(frames, node_id: int = NODE):
    """Return the positions and objects of the SDO uploads (reads) requested of a node."""
    return [(position, struct.unpack_from('<HB', frame.data, 1))
            for position, frame in enumerate(frames)
            if frame.arbitration_id == SDO_REQUEST + node_id and frame.data[0] >> 5 == 2]


def starts(frames, node_id: int = NODE):
    """Return the positions of the NMT start commands that reach a node."""
    return [position for position, frame in enumerate(frames)
            if frame.arbitration_id == NMT and frame.data[0] == START
            and frame.data[1] in (0, node_id)]


def boot_ups(frames, node_id: int = NODE):
    """Return the positions of a node's boot-up messages."""
    return [position for position, frame in enumerate(frames)
            if frame.arbitration_id == 0x700 + node_id and bytes(frame.data) == b'\x00']


def state_of(harness, node_id: int = NODE):
    """Return the boot state of a node as the gateway shows it."""
    return next(s for s in harness.node.gateway.boot.states() if s.node_id == node_id)


def wait_for_boot(harness, state: str, boots: int = 1, node_id: int = NODE):
    """Wait until the node's boot ended ``boots`` times, the last in ``state``."""
    try:
        return wait_until(lambda: (state_of(harness, node_id).boots >= boots
                                   and state_of(harness, node_id).state == state
                                   and state_of(harness, node_id)),
                          WAIT, f'node {node_id} {state} after {boots} boot(s)')
    except AssertionError as timed_out:
        raise AssertionError(f'{timed_out}; its boot: {state_of(harness, node_id)}') from None


def bus_file(tmp_path, text: str) -> str:
    """Write a bus description (its dcf paths relative to the file) and return its path."""
    (tmp_path / 'device.eds').write_text(EDS.read_text())
    path = tmp_path / 'bus.yml'
    path.write_text(textwrap.dedent(text))
    return str(path)


CONFIGURED = textwrap.dedent("""\
    master:
      node_id: 1
      boot_timeout: 1000
    nodes:
      arm_io:
        node_id: 10
        dcf: device.eds
        driver: ros2_canopen::ProxyDriver
        heartbeat_producer: 100
        sdo:
          - {index: 0x2000, sub_index: 0, value: 0x34}
          - {index: 0x2002, sub_index: 0, value: "0x0BADCAFE"}
          - {index: 0x2003, sub_index: 0, value: -7}
          - {index: 0x2021, sub_index: 0, value: "robot arm io"}
        tpdo:
          1:
            transmission: 254
            mapping:
              - {index: 0x2001, sub_index: 0}
              - {index: 0x2003, sub_index: 0}
    """)

# What the configuration leaves in the device: (index, subindex, bytes).
CONFIGURATION = [(0x2000, 0, b'\x34'), (0x2002, 0, struct.pack('<I', 0x0BADCAFE)),
                 (0x2003, 0, struct.pack('<i', -7)), (0x2021, 0, b'robot arm io'),
                 (0x1017, 0, struct.pack('<H', 100)), (0x1800, 2, bytes([254])),
                 (0x1A00, 0, b'\x02'), (0x1A00, 1, struct.pack('<I', 0x20010010)),
                 (0x1A00, 2, struct.pack('<I', 0x20030020)),
                 (0x1800, 1, struct.pack('<I', 0x180 + NODE))]


def held(device, index: int, subindex: int) -> bytes:
    """Return what the device holds; a TPDO's COB-ID without bit 30 (no RTR), its own."""
    value = device.value(index, subindex)
    if (index, subindex) == (0x1800, 1):
        return struct.pack('<I', struct.unpack('<I', value)[0] & ~(1 << 30))
    return value


def differences(device) -> list:
    """Return the objects of the configuration the device does not hold, with its value."""
    return [(hex(index), sub, held(device, index, sub)) for index, sub, data
            in CONFIGURATION if held(device, index, sub) != data]



@pytest.fixture
def rig(make_gateway, tmp_path):
    """Start devices and a gateway with a bus description; yields a ``start`` factory."""
    made = []

    def start(text: str = CONFIGURED, node_ids=(NODE,), **parameters):
        channel = new_channel()
        frames = Frames(channel)
        devices = {node_id: DurandDevice(node_id, channel=channel) for node_id in node_ids}
        for device in devices.values():
            device.start()
        made.append((frames, devices))
        gateway = make_gateway(can__channel=channel, simulation__devices=None,
                               bus_config=bus_file(tmp_path, text), **parameters)
        return gateway, devices, frames

    yield start
    for frames, devices in made:
        frames.close()
        for device in devices.values():
            device.stop()


def test_a_device_is_configured_verified_and_started_at_start(rig):
    gateway, devices, frames = rig()
    state = wait_for_boot(gateway, 'BOOTED')
    assert not differences(devices[NODE])
    wait_until(lambda: devices[NODE].state == 5, WAIT, 'the device OPERATIONAL')
    assert state.error_status == '' and state.writes == 12, state
    assert 'written and verified' in state.message and 'started' in state.message, state
    seen = wait_until(lambda: starts(frames.snapshot()) and frames.snapshot(), WAIT,
                      'the NMT start on the bus')
    written = [obj for _, obj in downloads(seen)]
    assert written[:4] == [(0x2000, 0), (0x2002, 0), (0x2003, 0), (0x2021, 0)], written
    # The TPDO is disabled while its mapping changes, then enabled (CiA 301).
    assert written[4] == (0x1800, 1) and written[-1] == (0x1017, 0), written
    started = starts(seen)
    assert len(started) == 1, started
    read_back = [position for position, obj in uploads(seen) if obj == (0x1A00, 2)]
    assert read_back and max(position for position, _ in downloads(seen)) < read_back[0] \
        < started[0], 'started before its configuration was written and read back'


def test_a_reset_device_comes_back_configured_and_is_started_after_its_last_write(rig):
    gateway, devices, frames = rig()
    wait_for_boot(gateway, 'BOOTED')
    assert gateway.call('nmt_command', node_id=NODE, command=129).success  # reset node
    state = wait_for_boot(gateway, 'BOOTED', boots=2)
    assert not differences(devices[NODE])
    assert 'booted again' not in state.message

    def started_again():
        seen = frames.snapshot()
        after = seen[boot_ups(seen)[-1]:]
        return starts(after) and after
    after = wait_until(started_again, WAIT, 'an NMT start after the last boot-up')
    assert downloads(after) and starts(after), 'not configured and started again'
    assert max(p for p, _ in downloads(after)) < starts(after)[0]


def boot_threads(node_id: int = NODE):
    """Return the gateway's boot threads of a node now."""
    return [thread for thread in threading.enumerate() if thread.name == f'boot-{node_id}']


def test_every_boot_of_a_device_runs_on_its_one_boot_thread(rig):
    """A boot-up wakes the device's boot thread: the receive thread starts no thread.

    Starting one there waited for the new thread to run while every frame behind the
    boot-up (other devices' SDO answers among them) waited too.
    """
    gateway, devices, frames = rig()
    wait_for_boot(gateway, 'BOOTED')
    first = boot_threads()
    assert len(first) == 1, first
    for boots in (2, 3):
        assert gateway.call('nmt_command', node_id=NODE, command=129).success  # reset node
        wait_for_boot(gateway, 'BOOTED', boots=boots)
        assert boot_threads() == first
    assert not differences(devices[NODE])


def test_a_power_cycled_device_comes_back_configured(rig):
    gateway, devices, frames = rig()
    wait_for_boot(gateway, 'BOOTED')
    devices[NODE].stop()
    devices[NODE] = DurandDevice(NODE, channel=gateway.channel)  # a new one: the defaults
    devices[NODE].start()
    wait_for_boot(gateway, 'BOOTED', boots=2)
    assert not differences(devices[NODE])
    assert devices[NODE].value(0x1017) == struct.pack('<H', 100)
    wait_until(lambda: devices[NODE].state == 5, WAIT, 'the device OPERATIONAL')


def _eds_with(tmp_path, old: str, new: str) -> None:
    """Let the bus description's device.eds say ``new`` where the shipped one says ``old``."""
    path = tmp_path / 'device.eds'
    path.write_text(EDS.read_text().replace(old, new, 1))


@pytest.mark.parametrize('letter, key, value', [
    ('D', 'vendor_id', 0x1234),
    ('M', 'product_code', 0x52),
    ('N', 'revision_number', 0x20000),
    ('O', 'serial_number', 7),
])
def test_a_device_of_another_identity_is_not_started(rig, letter, key, value):
    gateway, devices, frames = rig(CONFIGURED + f'    {key}: {value}\n')
    state = wait_for_boot(gateway, 'FAILED')
    assert state.error_status == letter, state
    assert key in state.message and f'0x{value:08X}' in state.message, state
    assert not starts(frames.snapshot()) and devices[NODE].state == 127
    assert not downloads(frames.snapshot()), 'a device of another identity was written'


def test_a_device_that_never_answers_fails_with_b(rig):
    text = CONFIGURED.replace('node_id: 10', 'node_id: 11').replace('boot_timeout: 1000',
                                                                   'boot_timeout: 300')
    gateway, devices, frames = rig(text)
    state = wait_for_boot(gateway, 'FAILED', node_id=11)
    assert state.error_status == 'B' and '0x1000' in state.message, state
    assert not starts(frames.snapshot(), 11)


def test_a_device_of_another_type_fails_with_c(rig, tmp_path):
    gateway_text = CONFIGURED.replace('dcf: device.eds', 'dcf: other.eds')
    (tmp_path / 'other.eds').write_text(EDS.read_text().replace(
        'DefaultValue=0x00020192', 'DefaultValue=0x00040192', 1))
    gateway, devices, frames = rig(gateway_text)
    state = wait_for_boot(gateway, 'FAILED')
    assert state.error_status == 'C' and '0x00020192' in state.message, state
    assert not starts(frames.snapshot())


def test_a_write_the_device_refuses_fails_with_j_naming_object_value_and_abort_code(rig):
    text = CONFIGURED.replace('      - {index: 0x2000, sub_index: 0, value: 0x34}\n',
                              '      - {index: 0x2000, sub_index: 0, value: 0x34}\n'
                              '      - {index: 0x2010, sub_index: 0, value: 5}\n')
    gateway, devices, frames = rig(text)
    state = wait_for_boot(gateway, 'FAILED')
    assert state.error_status == 'J', state
    assert '0x2010:0' in state.message and '0x06010002' in state.message, state
    assert not starts(frames.snapshot()) and devices[NODE].state == 127
    written = [obj for _, obj in downloads(frames.snapshot())]
    assert written == [(0x2000, 0), (0x2010, 0)], 'the boot went on writing after a failure'


def test_a_value_the_device_does_not_keep_fails_with_j(rig, make_gateway, tmp_path):
    channel = new_channel()
    device = DurandDevice(NODE, channel=channel)
    device.start()
    try:
        # A device that takes the write but keeps its own value (as a drive clamps a limit).
        device.node.object_dictionary.set_read_callback(0x2002, 0, lambda: 0x1000)
        gateway = make_gateway(can__channel=channel, simulation__devices=None,
                               bus_config=bus_file(tmp_path, CONFIGURED))
        state = wait_for_boot(gateway, 'FAILED')
        assert state.error_status == 'J', state
        assert '0x2002:0 reads back 0x1000 after writing 0xBADCAFE' in state.message, state
        assert device.state == 127
    finally:
        device.stop()


def test_a_device_whose_heartbeat_never_comes_fails_with_k(make_gateway, tmp_path):
    text = CONFIGURED + '    reset_communication: false\n'  # its boot-up would not come
    channel = new_channel()
    device = DurandDevice(NODE, channel=channel)
    device.start()
    try:
        device._network.allowed = lambda cob_id: cob_id != 0x700 + NODE  # no heartbeat
        gateway = make_gateway(can__channel=channel, simulation__devices=None,
                               bus_config=bus_file(tmp_path, text))
        state = wait_for_boot(gateway, 'FAILED')
        assert state.error_status == 'K' and '100 ms' in state.message, state
        assert device.state == 127
    finally:
        device.stop()


@pytest.mark.parametrize('producer', [1500, 0])
def test_a_device_is_watched_at_the_heartbeat_its_bus_description_gives_it(rig, producer,
                                                                           caplog):
    # Red team: heartbeat_producer 5000 (or 0: none) against heartbeat.timeout 3 s lost the
    # device between two heartbeats, and its boot reset it again, every few seconds for ever.
    text = CONFIGURED.replace('heartbeat_producer: 100', f'heartbeat_producer: {producer}')
    gateway, devices, frames = rig(text, heartbeat__timeout=0.5)
    wait_for_boot(gateway, 'BOOTED')
    ups = len(boot_ups(frames.snapshot()))
    shown = []
    watched_until = time.monotonic() + 2.0  # four heartbeat.timeout: a bounded test of absence
    while time.monotonic() < watched_until:
        shown.append(gateway.call('nmt_state', node_id=NODE).state_name)
        time.sleep(0.1)
    assert 'NOT_DETECTED' not in shown, shown
    assert state_of(gateway).boots == 1 and len(boot_ups(frames.snapshot())) == ups, \
        'booted again'
    if producer:  # lost within 3 of its periods once it is gone
        devices[NODE].stop()
        gateway.wait_for_states({NODE: 'NOT_DETECTED'}, timeout=3 * producer / 1000 + WAIT)
    else:
        assert 'cannot tell when it is gone' in caplog.text, 'no warning at start'


def test_a_failed_mandatory_device_holds_every_device_unstarted(rig):
    text = CONFIGURED + ('    mandatory: true\n    product_code: 0x52\n'
                         '  gripper:\n    node_id: 11\n    dcf: device.eds\n')
    gateway, devices, frames = rig(text, node_ids=(NODE, 11))
    wait_for_boot(gateway, 'FAILED')
    held = wait_until(lambda: state_of(gateway, 11).state == 'WAITING'
                      and 'mandatory' in state_of(gateway, 11).message
                      and state_of(gateway, 11), WAIT, 'node 11 held back')
    assert 'arm_io' in held.message and 'M:' in held.message, held
    assert not starts(frames.snapshot(), 11) and devices[11].state == 127
    answer = gateway.call('boot', node_id=11)
    assert not answer.success and 'mandatory' in answer.message, answer.message


def test_a_configuration_date_that_matches_skips_the_writes(rig, tmp_path):
    text = CONFIGURED.replace('dcf: device.eds', 'dcf: dated.dcf') + (
        '    store_configuration: true\n    reset_communication: false\n')
    (tmp_path / 'dated.dcf').write_text(EDS.read_text().replace(
        'ParameterName=Configuration date\nObjectType=0x7\nDataType=0x0007\nAccessType=rw\n'
        'DefaultValue=0\n', 'ParameterName=Configuration date\nObjectType=0x7\n'
        'DataType=0x0007\nAccessType=rw\nDefaultValue=0\nParameterValue=9000\n').replace(
        'ParameterName=Configuration time\nObjectType=0x7\nDataType=0x0007\nAccessType=rw\n'
        'DefaultValue=0\n', 'ParameterName=Configuration time\nObjectType=0x7\n'
        'DataType=0x0007\nAccessType=rw\nDefaultValue=0\nParameterValue=3600000\n'))
    gateway, devices, frames = rig(text)
    first = wait_for_boot(gateway, 'BOOTED')
    assert first.writes > 0 and 'stored' in first.message, first
    assert devices[NODE].value(0x1020, 1) == struct.pack('<I', 9000)
    written = [obj for _, obj in downloads(frames.snapshot())]
    assert written[-3:] == [(0x1020, 1), (0x1020, 2), (0x1010, 1)], written
    before = len(frames.snapshot())
    devices[NODE].stop()  # power cycle: the stored configuration comes back with it
    devices[NODE].start()
    second = wait_for_boot(gateway, 'BOOTED', boots=2)
    assert second.writes == 0 and '0x1020 matches' in second.message, second
    assert not downloads(frames.snapshot()[before:]), 'written though 0x1020 matched'
    assert not differences(devices[NODE])


def test_a_boot_up_during_the_writes_ends_that_boot_and_boots_again(rig):
    writes = ''.join(f'      - {{index: 0x2001, sub_index: 0, value: {n}}}\n'
                     for n in range(60))
    text = CONFIGURED.replace('    sdo:\n', '    sdo:\n' + writes)
    gateway, devices, frames = rig(text)
    wait_for_boot(gateway, 'BOOTED')
    assert gateway.call('boot', node_id=NODE, timeout=0.001).success is False
    # The boot runs again (reset communication, then every write): reset the device while
    # it is being written.
    wait_until(lambda: len(downloads(frames.snapshot())) >= 90, WAIT, 'the writes under way')
    frames.send(NMT, bytes([129, NODE]))
    wait_for_boot(gateway, 'BOOTED', boots=2)

    def started():
        # The start goes out before the boot shows BOOTED: recorded a moment after.
        seen = frames.snapshot()
        ups = [p for p in boot_ups(seen) if p > downloads(seen)[89][0]]
        return seen if ups and starts(seen[ups[0]:]) else None
    seen = wait_until(started, WAIT, 'the NMT start after the boot-up recorded')
    boot_up = [p for p in boot_ups(seen) if p > downloads(seen)[89][0]][0]
    restarted = next(p for p, obj in uploads(seen) if p > boot_up and obj == (0x1000, 0))
    late = [obj for p, obj in downloads(seen) if boot_up < p < restarted]
    # At most the one write already on its way when the boot-up came.
    assert len(late) <= 1, late
    assert not differences(devices[NODE])
    assert len(starts(seen[boot_up:])) == 1


def test_the_boot_service_answers_with_every_devices_state(rig):
    gateway, devices, frames = rig()
    wait_for_boot(gateway, 'BOOTED')
    answer = gateway.call('boot', node_id=0, timeout=10.0)
    assert answer.success, answer.message
    assert [(s.node_id, s.name, s.state, s.boots) for s in answer.states] == [
        (NODE, 'arm_io', 'BOOTED', 2)]
    unknown = gateway.call('boot', node_id=12)
    assert not unknown.success and 'node_id 12' in unknown.message, unknown.message


def test_pdo_configure_without_a_bus_description_is_a_boot_too(make_gateway):
    channel = new_channel()
    device = DurandDevice(NODE, channel=channel)
    device.start()
    try:
        gateway = make_gateway(can__channel=channel, simulation__devices=None,
                               pdo__nodes=[NODE], pdo__configure=True, nodes=[NODE],
                               **{f'node_{NODE}__eds': str(EDS)})
        state = wait_for_boot(gateway, 'BOOTED')
        assert state.name == f'node_{NODE}' and 'not started' in state.message, state
        assert device.state == 127  # pdo.configure never started a device
        assert device.value(0x1017) == struct.pack('<H', HEARTBEAT_DEFAULT)
    finally:
        device.stop()
