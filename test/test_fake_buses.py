"""The test doubles for bus supervision: the fake slcan adapter and the fault-injecting bus."""

import threading
import time
import uuid

import can
import pytest
import serial

from conftest import wait_until
from fake_slcan import FakeSlcanAdapter
from faulty_bus import CAN_ERR_BUSOFF, FaultController, register

register()


def unique_channel(prefix: str) -> str:
    """Return a virtual-bus channel name no other test uses."""
    return f'{prefix}-{uuid.uuid4().hex[:8]}'


def recv_in_thread(bus: can.BusABC, timeout):
    """Start ``bus.recv(timeout)`` in a thread; the returned dict gets 'message' or 'error'."""
    outcome = {}

    def run():
        try:
            outcome['message'] = bus.recv(timeout)
        except Exception as error:
            outcome['error'] = error

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    outcome['thread'] = thread
    return outcome


def recv_frame(bus: can.BusABC, timeout: float = 10.0) -> can.Message:
    """Return the next frame on ``bus`` (slcan acks make recv return None on the way)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        message = bus.recv(0.05)
        if message is not None:
            return message
    raise AssertionError(f'no frame within {timeout} s')


def open_slcan(path) -> can.BusABC:
    """Open python-can's real slcan driver on ``path`` at 500 kbit/s, without its 2 s nap."""
    return can.Bus(interface='slcan', channel=str(path), bitrate=500000, sleep_after_open=0)


@pytest.fixture
def adapter(tmp_path):
    """Plug a fake slcan adapter in at ``tmp_path / 'usb-can'``."""
    fake = FakeSlcanAdapter(tmp_path / 'usb-can', unique_channel('slcan'))
    yield fake
    fake.close()


def test_slcan_driver_exchanges_frames_with_a_virtual_peer(adapter):
    driver = open_slcan(adapter.link_path)
    peer = can.Bus(interface='virtual', channel=adapter.channel)
    try:
        wait_until(lambda: adapter.is_open, 10.0, 'the driver to open the CAN channel')
        assert 'S6' in adapter.commands and adapter.open_count == 1

        driver.send(can.Message(arbitration_id=0x602, data=b'\x40\x00\x10\x00',
                                is_extended_id=False))
        sent = peer.recv(10.0)
        assert (sent.arbitration_id, bytes(sent.data)) == (0x602, b'\x40\x00\x10\x00')

        peer.send(can.Message(arbitration_id=0x1ABCDEF0, data=b'\x01\x02', is_extended_id=True))
        peer.send(can.Message(arbitration_id=0x705, is_remote_frame=True, dlc=1,
                              is_extended_id=False))
        first, second = recv_frame(driver), recv_frame(driver)
        assert (first.arbitration_id, first.is_extended_id, bytes(first.data)) == (
            0x1ABCDEF0, True, b'\x01\x02')
        assert (second.arbitration_id, second.is_remote_frame, second.dlc) == (0x705, True, 1)
        # The adapter counts a line once written, which the driver may read first.
        wait_until(lambda: (adapter.frames_to_bus, adapter.frames_to_driver) == (1, 2), 10.0,
                   f'the counts (1, 2) (now {adapter.frames_to_bus, adapter.frames_to_driver})')
    finally:
        peer.shutdown()
        driver.shutdown()


def test_unplug_makes_the_slcan_driver_raise(adapter):
    driver = open_slcan(adapter.link_path)
    try:
        wait_until(lambda: adapter.is_open, 10.0, 'the driver to open the CAN channel')
        # The unplug wakes a recv blocked for far longer than this test waits for it.
        waiting = recv_in_thread(driver, 60.0)
        time.sleep(0.05)  # let recv block (correctness does not depend on it)
        adapter.unplug()
        waiting['thread'].join(10.0)
        error = waiting.get('error')
        assert isinstance(error, can.CanOperationError), waiting
        assert isinstance(error.__cause__, (serial.SerialException, OSError))
        with pytest.raises(can.CanOperationError):
            driver.recv(0.1)  # and it keeps failing
        with pytest.raises(can.CanOperationError) as sending:
            driver.send(can.Message(arbitration_id=0x80, data=b'', is_extended_id=False))
        assert isinstance(sending.value.__cause__, serial.SerialException)
        # python-can 4.6.1: shutdown() writes 'C' first, raises, and leaves the port open.
        with pytest.raises(can.CanOperationError):
            driver.shutdown()
        assert driver.serialPortOrig.is_open
    finally:
        driver.serialPortOrig.close()


def test_reopening_fails_while_unplugged_and_works_after_plug(adapter):
    adapter.unplug()
    with pytest.raises(can.CanInitializationError):
        open_slcan(adapter.link_path)
    adapter.plug()
    driver = open_slcan(adapter.link_path)
    peer = can.Bus(interface='virtual', channel=adapter.channel)
    try:
        wait_until(lambda: adapter.is_open, 10.0, 'the driver to open the CAN channel')
        peer.send(can.Message(arbitration_id=0x701, data=b'\x05', is_extended_id=False))
        assert recv_frame(driver).arbitration_id == 0x701
        assert (adapter.plug_count, adapter.open_count) == (2, 1)
    finally:
        peer.shutdown()
        driver.shutdown()


def test_bus_frames_are_dropped_until_the_driver_opens_the_channel(adapter):
    peer = can.Bus(interface='virtual', channel=adapter.channel)
    try:
        peer.send(can.Message(arbitration_id=0x700, data=b'\x7f', is_extended_id=False))
        wait_until(lambda: adapter.frames_dropped == 1, 10.0, 'the frame to be dropped')
        assert adapter.frames_to_driver == 0
    finally:
        peer.shutdown()


@pytest.fixture
def faulty():
    """Return (controller, FaultyBus opened through can.Bus, virtual peer) on a fresh channel."""
    channel = unique_channel('faulty')
    bus = can.Bus(interface='faulty', channel=channel, bitrate=500000)
    peer = can.Bus(interface='virtual', channel=channel)
    yield FaultController.get(channel), bus, peer
    bus.shutdown()
    peer.shutdown()
    FaultController.forget(channel)


def test_faulty_bus_passes_frames_and_records_what_it_sent(faulty):
    controller, bus, peer = faulty
    bus.send(can.Message(arbitration_id=0x605, data=b'\x40', is_extended_id=False))
    assert peer.recv(10.0).arbitration_id == 0x605
    peer.send(can.Message(arbitration_id=0x585, data=b'\x43', is_extended_id=False))
    assert bus.recv(10.0).arbitration_id == 0x585
    assert [m.arbitration_id for m in controller.sent] == [0x605]
    assert (controller.open_count, controller.buses) == (1, [bus])


def test_fail_receive_wakes_a_blocked_recv_and_sticks_to_that_bus(faulty):
    controller, bus, peer = faulty
    waiting = recv_in_thread(bus, None)
    time.sleep(0.05)  # let recv block (correctness does not depend on it)
    assert controller.fail_receive('adapter gone') == 1
    waiting['thread'].join(10.0)  # a recv without timeout: only the fault can end it
    assert isinstance(waiting.get('error'), can.CanOperationError), waiting
    assert str(waiting['error']) == 'adapter gone'
    peer.send(can.Message(arbitration_id=0x181, data=b'', is_extended_id=False))
    with pytest.raises(can.CanOperationError):
        bus.recv(0.1)
    assert controller.receive_failures == 2

    reopened = can.Bus(interface='faulty', channel=controller.channel)
    try:
        peer.send(can.Message(arbitration_id=0x182, data=b'', is_extended_id=False))
        assert reopened.recv(10.0).arbitration_id == 0x182
    finally:
        reopened.shutdown()
    bus.shutdown()
    assert controller.buses == []


def test_fail_send_and_clear(faulty):
    controller, bus, peer = faulty
    controller.fail_send('tx timeout')
    frame = can.Message(arbitration_id=0x000, data=b'\x01\x00', is_extended_id=False)
    for _ in range(2):
        with pytest.raises(can.CanOperationError, match='tx timeout'):
            bus.send(frame)
    assert peer.recv(0.05) is None
    assert (controller.send_failures, controller.sent) == (2, [])
    controller.clear()
    bus.send(frame)
    assert peer.recv(10.0).arbitration_id == 0x000 and len(controller.sent) == 1


def test_fail_open_and_clear(faulty):
    controller, bus, peer = faulty
    controller.fail_open('no device')
    for _ in range(3):
        with pytest.raises(can.CanInitializationError, match='no device'):
            can.Bus(interface='faulty', channel=controller.channel)
    assert (controller.open_count, controller.open_failures) == (1, 3)
    controller.clear()
    second = can.Bus(interface='faulty', channel=controller.channel)
    second.shutdown()
    assert controller.open_count == 2


def test_bus_off_delivers_an_error_frame(faulty):
    controller, bus, peer = faulty
    waiting = recv_in_thread(bus, 1.0)
    assert controller.bus_off() == 1
    waiting['thread'].join(1.0)
    frame = waiting.get('message')
    assert frame is not None and frame.is_error_frame, waiting
    assert frame.arbitration_id == CAN_ERR_BUSOFF
    assert peer.recv(0.05) is None  # the error frame is local, not a frame on the bus
