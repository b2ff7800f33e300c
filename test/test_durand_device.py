"""The durand-based simulated device against python-canopen's SDO client and NMT master.

Every test has a private ``virtual`` channel: the device, a canopen RemoteNode and a raw bus
that watches (and forges) frames.
"""

import random
import struct
import threading
import time
import uuid

import can
import canopen
from canopen.objectdictionary import ObjectDictionary
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError
import durand
import pytest

from cbcan_ros.simulation.durand.device import DurandDevice
from cbcan_ros.simulation.durand.scheduler import shared_scheduler

from conftest import wait_until

NODE_ID = 5
HEARTBEAT_COB = 0x700 + NODE_ID
SDO_RX, SDO_TX = 0x600 + NODE_ID, 0x580 + NODE_ID
EMCY_COB = 0x80 + NODE_ID
START, STOP, RESET_NODE, RESET_COMMUNICATION = 0x01, 0x02, 0x81, 0x82
SLOW_DELAY = 0.2
BLOCK_SIZES = [0, 1, 4, 7, 8, 889, 890, 4096, 65536]


def next_frame(bus: can.BusABC, can_id: int, timeout: float = 2.0, where=lambda data: True):
    """Return the data of the next frame on ``can_id`` that satisfies ``where``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        message = bus.recv(0.05)
        if message is not None and message.arbitration_id == can_id and where(message.data):
            return bytes(message.data)
    raise AssertionError(f'no frame on 0x{can_id:03X} within {timeout} s')


def no_frame(bus: can.BusABC, can_id: int, within: float) -> bool:
    """Return True when nothing arrives on ``can_id`` for ``within`` seconds."""
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        message = bus.recv(0.02)
        if message is not None and message.arbitration_id == can_id:
            return False
    return True


def drain(bus: can.BusABC) -> None:
    """Throw away what the raw bus has received so far."""
    while bus.recv(0) is not None:
        pass


def send(bus: can.BusABC, can_id: int, data: bytes = b'', remote: bool = False) -> None:
    """Send one standard frame."""
    bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False,
                         is_remote_frame=remote, dlc=len(data) if not remote else 1))


def block_download(sdo, index: int, subindex: int, data: bytes) -> None:
    """Block download the way canopen 2.4.1 needs it.

    Its raw block stream (``buffering=0``) takes at most 7 bytes a ``write()``; a shorter
    piece is refused (None) unless it completes ``size``, so ``size`` must be given, the
    data fed in 7-byte slices, and written at least once (an empty download included).
    """
    with sdo.open(index, subindex, 'wb', buffering=0, size=len(data), block_transfer=True,
                  request_crc_support=True) as stream:
        position = 0
        while True:
            position += stream.write(data[position:position + 7])
            if position >= len(data):
                break


def block_upload(sdo, index: int, subindex: int) -> bytes:
    """Block upload with CRC, as the gateway does it."""
    with sdo.open(index, subindex, 'rb', buffering=0, block_transfer=True,
                  request_crc_support=True) as stream:
        return stream.read()


def upload_raw(bus: can.BusABC, index: int, subindex: int = 0) -> bytes:
    """Expedited upload with forged frames; returns the answer to exactly this request."""
    send(bus, SDO_RX, struct.pack('<BHB4x', 0x40, index, subindex))
    return next_frame(bus, SDO_TX, where=lambda data: data[1:4] == struct.pack(
        '<HB', index, subindex) and data[0] & 0xE0 in (0x40, 0x80))


def pattern(size: int, seed: int = 0) -> bytes:
    """Return ``size`` bytes that differ from the device's default DOMAIN content."""
    return bytes((i * 7 + seed + 3) % 251 for i in range(size))


@pytest.fixture
def channel():
    """Return a python-can virtual channel of this test alone."""
    return f'durand-{uuid.uuid4().hex[:12]}'


@pytest.fixture
def bus(channel):
    """Return a raw bus on the channel, opened before any device so it sees boot-ups."""
    raw = can.Bus(interface='virtual', channel=channel)
    yield raw
    raw.shutdown()


@pytest.fixture
def device(channel, bus):
    """Return a started DurandDevice with node id 5."""
    simulated = DurandDevice(NODE_ID, channel=channel, slow_read_delay=SLOW_DELAY)
    simulated.start()
    yield simulated
    simulated.stop()


@pytest.fixture
def network(channel):
    """Return a connected canopen Network on the channel."""
    master = canopen.Network()
    master.NOTIFIER_CYCLE = 0.05  # disconnect waits one cycle
    master.connect(interface='virtual', channel=channel)
    yield master
    master.disconnect()


@pytest.fixture
def master(network, device):
    """Return a canopen RemoteNode for the device, with an empty dictionary."""
    node = canopen.RemoteNode(NODE_ID, ObjectDictionary())
    network.add_node(node)
    return node


@pytest.mark.parametrize('index, subindex, expected', [
    (0x1000, 0, struct.pack('<I', 0x00020192)),
    (0x1001, 0, b'\x00'),
    (0x1008, 0, b'cbcan simulated device'),
    (0x100A, 0, b'1.0'),
    (0x1017, 0, struct.pack('<H', 200)),
    (0x1018, 0, b'\x04'),
    (0x1018, 1, struct.pack('<I', 0)),
    (0x1018, 2, struct.pack('<I', 0x51)),
    (0x1018, 3, struct.pack('<I', 0x10000)),
    (0x1018, 4, struct.pack('<I', 0)),
    (0x2000, 0, b'\x12'),
    (0x2001, 0, struct.pack('<H', 0x1234)),
    (0x2002, 0, struct.pack('<I', 0x12345678)),
    (0x2003, 0, struct.pack('<i', -2)),
    (0x2010, 0, struct.pack('<I', 0xCAFEBABE)),
    (0x2021, 0, b'hello from the bus'),
    (0x2020, 0, bytes(range(200))),
])
def test_upload_gives_the_eds_defaults(master, device, index, subindex, expected):
    assert master.sdo.upload(index, subindex) == expected
    assert device.value(index, subindex) == expected


@pytest.mark.parametrize('force_segment', [False, True])
@pytest.mark.parametrize('index, data', [
    (0x2000, b'\x34'),
    (0x2001, struct.pack('<H', 0xBEEF)),
    (0x2002, struct.pack('<I', 0xDEADBEEF)),
    (0x2003, struct.pack('<i', -123456)),
    (0x2021, b'a visible string long enough to be segmented'),
    (0x2020, b'\x01\x02'),
    (0x2020, pattern(1000)),
])
def test_download_reaches_the_device_and_uploads_back(master, device, index, data,
                                                      force_segment):
    master.sdo.download(index, 0, data, force_segment=force_segment)
    assert device.value(index) == data
    assert master.sdo.upload(index, 0) == data


def test_write_only_object_is_stored_but_cannot_be_read(master, device):
    master.sdo.download(0x2011, 0, struct.pack('<I', 77))
    assert device.value(0x2011) == struct.pack('<I', 77)
    with pytest.raises(SdoAbortedError) as refused:
        master.sdo.upload(0x2011, 0)
    assert refused.value.code == 0x06010001


@pytest.mark.parametrize('action, code', [
    (lambda sdo: sdo.download(0x2010, 0, b'\x00\x00\x00\x00'), 0x06010002),
    (lambda sdo: sdo.upload(0x3000, 0), 0x06020000),
    (lambda sdo: sdo.upload(0x1018, 7), 0x06090011),
    (lambda sdo: sdo.download(0x2020, 0, bytes(65537)), 0x06070012),
    (lambda sdo: block_download(sdo, 0x2020, 0, bytes(65537)), 0x06070012),
])
def test_refusals_carry_the_cia301_abort_code(master, device, action, code):
    with pytest.raises(SdoAbortedError) as refused:
        action(master.sdo)
    assert refused.value.code == code
    assert device.value(0x2020) == bytes(range(200))


def test_wrong_length_for_a_number_is_refused(master, device):
    with pytest.raises(SdoAbortedError) as refused:
        master.sdo.download(0x2001, 0, b'\x01\x02\x03\x04')
    # durand answers 0x06070010 (length does not match); 0x06070012 would be as right
    assert refused.value.code in (0x06070010, 0x06070012)
    assert device.value(0x2001) == struct.pack('<H', 0x1234)


def test_slow_object_answers_after_the_delay_while_heartbeats_go_on(master, device, bus):
    device.set_value(0x1017, 0, 50)
    drain(bus)
    started = time.monotonic()
    assert master.sdo.upload(0x2200, 0) == struct.pack('<I', 0x51057)
    assert time.monotonic() - started >= SLOW_DELAY
    beats = 0
    while (message := bus.recv(0)) is not None:
        beats += message.arbitration_id == HEARTBEAT_COB
    assert beats >= 2  # the slow read holds up neither the scheduler nor other devices


@pytest.mark.parametrize('size', BLOCK_SIZES)
def test_block_upload_with_crc(master, device, size):
    data = pattern(size)
    device.set_value(0x2020, 0, data)
    assert block_upload(master.sdo, 0x2020, 0) == data


@pytest.mark.parametrize('size', BLOCK_SIZES)
def test_block_download_with_crc(master, device, size):
    data = pattern(size, seed=size)
    block_download(master.sdo, 0x2020, 0, data)
    assert device.value(0x2020) == data


def test_block_download_with_one_write_sends_one_segment_and_is_aborted(master, device):
    data = pattern(890)
    with pytest.raises(SdoAbortedError) as refused:
        with master.sdo.open(0x2020, 0, 'wb', buffering=0, size=len(data),
                             block_transfer=True) as stream:
            assert stream.write(data) == 7  # canopen's raw block stream takes 7 bytes a call
    assert refused.value.code == 0x05040003  # the end request arrives as a sub-block
    assert device.value(0x2020) == bytes(range(200))


def test_boot_up_then_heartbeats_in_pre_operational(device, bus):
    assert next_frame(bus, HEARTBEAT_COB) == b'\x00'
    assert next_frame(bus, HEARTBEAT_COB) == b'\x7f'
    assert next_frame(bus, HEARTBEAT_COB) == b'\x7f'
    assert device.state == 127


def test_nmt_commands_change_state_and_heartbeat(master, device, bus):
    next_frame(bus, HEARTBEAT_COB, where=lambda d: d == b'\x7f')  # past the boot-up
    master.nmt.send_command(START)
    assert next_frame(bus, HEARTBEAT_COB, where=lambda d: d != b'\x7f') == b'\x05'
    assert device.state == 5
    master.nmt.send_command(STOP)
    assert next_frame(bus, HEARTBEAT_COB, where=lambda d: d != b'\x05') == b'\x04'
    with pytest.raises(SdoCommunicationError):
        master.sdo.upload(0x2000, 0)  # CiA 301: no SDO in stopped
    master.nmt.send_command(0x80)
    assert next_frame(bus, HEARTBEAT_COB, where=lambda d: d != b'\x04') == b'\x7f'
    assert master.sdo.upload(0x2000, 0) == b'\x12'


def test_reset_node_boots_again_with_every_default(master, device, bus):
    master.sdo.download(0x2000, 0, b'\x99')
    master.sdo.download(0x1017, 0, struct.pack('<H', 1000))
    master.nmt.send_command(START)
    wait_until(lambda: device.state == 5, 10.0, 'operational')
    drain(bus)
    master.nmt.send_command(RESET_NODE)
    assert next_frame(bus, HEARTBEAT_COB) == b'\x00'
    assert next_frame(bus, HEARTBEAT_COB) == b'\x7f'
    assert device.state == 127
    assert device.value(0x2000) == b'\x12'
    assert device.value(0x1017) == struct.pack('<H', 200)


def test_reset_communication_keeps_application_values(master, device, bus):
    master.sdo.download(0x2000, 0, b'\x99')
    master.sdo.download(0x1017, 0, struct.pack('<H', 1000))
    drain(bus)
    master.nmt.send_command(RESET_COMMUNICATION)
    assert next_frame(bus, HEARTBEAT_COB) == b'\x00'
    assert device.value(0x2000) == b'\x99'
    assert device.value(0x1017) == struct.pack('<H', 200)


def test_node_guarding_reply_toggles_while_the_heartbeat_is_off(master, device, bus):
    master.sdo.download(0x1017, 0, b'\x00\x00')
    drain(bus)  # the heartbeat timer is cancelled before the download is acknowledged
    replies = []
    for _ in range(3):
        send(bus, HEARTBEAT_COB, remote=True)
        replies.append(next_frame(bus, HEARTBEAT_COB))
    assert replies == [b'\x7f', b'\xff', b'\x7f']
    master.nmt.send_command(START)
    wait_until(lambda: device.state == 5, 10.0, 'operational')
    send(bus, HEARTBEAT_COB, remote=True)
    assert next_frame(bus, HEARTBEAT_COB) == b'\x85'


def test_no_guarding_reply_while_heartbeats_are_produced(master, device, bus):
    master.sdo.download(0x1017, 0, struct.pack('<H', 5000))
    drain(bus)
    send(bus, HEARTBEAT_COB, remote=True)
    assert no_frame(bus, HEARTBEAT_COB, within=0.2)


def test_emcy_frame_and_error_reset(device, bus):
    device.emergency(0x1234, error_register=0x05, manufacturer=b'\xaa\xbb\xcc')
    assert next_frame(bus, EMCY_COB) == bytes.fromhex('341205aabbcc0000')
    assert device.value(0x1001) == b'\x05'
    device.emergency(0x5000)
    assert next_frame(bus, EMCY_COB) == bytes.fromhex('0050010000000000')
    device.emergency(0)
    assert next_frame(bus, EMCY_COB) == bytes(8)
    assert device.value(0x1001) == b'\x00'
    with pytest.raises(ValueError):
        device.emergency(0x1000, manufacturer=bytes(6))


def test_stop_is_quick_and_silent_and_start_boots_again(device, bus):
    started = time.monotonic()
    device.stop()
    assert time.monotonic() - started < 2.0  # no wait for a heartbeat period or a timeout
    assert not device.running
    drain(bus)
    assert no_frame(bus, HEARTBEAT_COB, within=0.3)  # heartbeat period is 0.2 s
    device.start()
    assert next_frame(bus, HEARTBEAT_COB) == b'\x00'
    assert next_frame(bus, HEARTBEAT_COB) == b'\x7f'


def test_devices_share_the_scheduler_and_one_stops_alone(channel, bus, network):
    devices = {node_id: DurandDevice(node_id, channel=channel) for node_id in (2, 3)}
    try:
        for simulated in devices.values():
            simulated.start()
        assert durand.get_scheduler() is shared_scheduler()
        for node_id in devices:
            assert next_frame(bus, 0x700 + node_id, where=lambda d: d == b'\x7f')
        stopped = devices[2].node
        devices[2].stop()
        owners = {getattr(callback, '__self__', None) for callback in shared_scheduler().pending()}
        assert stopped.heartbeat_producer not in owners and stopped.emcy not in owners
        drain(bus)
        for _ in range(2):  # two more heartbeats of node 3, none of node 2 meanwhile
            message = bus.recv(1.0)
            while message is not None and message.arbitration_id != 0x703:
                assert message.arbitration_id != 0x702
                message = bus.recv(1.0)
            assert message is not None and bytes(message.data) == b'\x7f'
        remote = canopen.RemoteNode(3, ObjectDictionary())
        network.add_node(remote)
        assert remote.sdo.upload(0x1000, 0) == struct.pack('<I', 0x00020192)
    finally:
        for simulated in devices.values():
            simulated.stop()


def test_a_short_heartbeat_is_not_held_back_by_a_long_one(channel, bus):
    devices = [DurandDevice(node_id, channel=channel) for node_id in (2, 3)]
    try:
        for simulated in devices:
            simulated.start()
            simulated.set_value(0x1017, 0, 2000)  # the scheduler now sleeps for ~2 s
        drain(bus)
        devices[1].set_value(0x1017, 0, 50)
        deadline = time.monotonic() + 0.5
        beats = 0
        while time.monotonic() < deadline:
            message = bus.recv(0.05)
            beats += message is not None and message.arbitration_id == 0x703
        assert beats >= 6  # durand's plain SyncScheduler gives 1 here
    finally:
        for simulated in devices:
            simulated.stop()


def test_malformed_frames_do_not_kill_the_device(device, bus):
    rng = random.Random(20261123)
    frames = [b'', b'\x80', b'\xa4\x20\x20', b'\xc6\x20\x20\x00', b'\xa3', b'\xa2\x7f',
              b'\x21\x20\x20\x00\xff\xff\xff\xff', b'\x40', b'\x60', b'\x00', b'\xc1']
    frames += [bytes(rng.randrange(256) for _ in range(rng.randrange(9))) for _ in range(500)]
    for data in frames:
        send(bus, SDO_RX, data)
    for data in (b'', b'\x81', b'\x01\x05\x00', bytes(8)):
        send(bus, 0x000, data)  # NMT with wrong lengths: ignored
    send(bus, SDO_RX, remote=True)
    send(bus, 0x7E5, b'\x04')
    send(bus, SDO_RX, b'\x80' + bytes(7))  # ends whatever the garbage left open
    assert upload_raw(bus, 0x2000) == bytes.fromhex('4f00200012000000')
    assert device.running and device.state == 127
    assert next_frame(bus, HEARTBEAT_COB) == b'\x7f'


def test_abort_without_index_ends_an_open_block_upload(device, bus):
    send(bus, SDO_RX, bytes.fromhex('a42020007f000000'))
    assert next_frame(bus, SDO_TX)[0] == 0xC6
    send(bus, SDO_RX, bytes.fromhex('8000000000000405'))  # as canopen's client aborts
    assert upload_raw(bus, 0x2000) == bytes.fromhex('4f00200012000000')


def test_a_transfer_the_master_abandons_is_dropped_after_the_server_timeout(device, bus):
    device.SDO_SERVER_TIMEOUT = 0.1
    send(bus, SDO_RX, bytes.fromhex('a42020007f000000'))
    assert next_frame(bus, SDO_TX)[0] == 0xC6
    time.sleep(0.15)  # the master goes quiet for longer than the server timeout
    assert upload_raw(bus, 0x2000) == bytes.fromhex('4f00200012000000')


def test_values_can_be_set_and_read_directly(device):
    device.set_value(0x2003, 0, -7)
    assert device.value(0x2003) == struct.pack('<i', -7)
    device.set_value(0x2021, 0, 'direct')
    assert device.value(0x2021) == b'direct'
    device.set_value(0x2200, 0, struct.pack('<I', 42))
    assert device.value(0x2200) == struct.pack('<I', 42)
    with pytest.raises(ValueError):
        device.set_value(0x2001, 0, b'\x01')
    with pytest.raises(ValueError):
        device.set_value(0x2020, 0, bytes(65537))


def test_several_threads_can_use_one_device(master, device):
    errors = []

    def read_many():
        try:
            for _ in range(50):
                assert device.value(0x2002) == struct.pack('<I', 0x12345678)
        except Exception as exc:
            errors.append(exc)

    threads = [threading.Thread(target=read_many) for _ in range(4)]
    for thread in threads:
        thread.start()
    for _ in range(50):
        assert master.sdo.upload(0x2002, 0) == struct.pack('<I', 0x12345678)
    for thread in threads:
        thread.join()
    assert not errors
