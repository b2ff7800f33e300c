"""Frames waiting to be handed to canopen: what a backlog between receipt and dispatch does.

The bus supervisor's receive thread takes each frame from the driver and stamps it. It hands
a frame to canopen's subscribers itself only when all of them are marked prompt and nothing
waits; other frames go to a dispatch thread, and every frame behind them waits there too
(``core/bus.py``). Whenever that dispatch is behind (a burst of frames, a busy machine, a
handler that takes its time), frames wait between the two threads. These tests hold the
dispatch on purpose, with a handler on a COB-ID no CANopen service uses that returns when
the test says, and look at what a user then sees: node states, heartbeat ages, EMCY times
and the gateway's memory.
"""

import sys
import threading
import time

import can
import pytest

from cbcan_ros.core.bus import prompt
from cbcan_ros.core.gateway import Gateway, GatewayConfig

from conftest import new_channel, wait_until
import faulty_bus

NODE = 5
HOLD_ID = 0x7F0  # no CANopen service and nobody on the bus listens to it
HELD = 1.0  # seconds the dispatch is held after the frame under test was received

faulty_bus.register()


def frame(arbitration_id: int, data: bytes) -> can.Message:
    """Return a classic CAN frame with an 11-bit identifier."""
    return can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False)


class HeldDispatch:
    """Holds the gateway's dispatch thread inside a frame handler until released."""

    def __init__(self, gateway: Gateway, device: can.BusABC):
        self._entered = threading.Event()
        self._release = threading.Event()
        gateway.network.subscribe(HOLD_ID, self._handler)
        device.send(frame(HOLD_ID, b'\x00'))
        wait_until(self._entered.is_set, 10.0, 'the dispatch thread in the holding handler')

    def _handler(self, *_frame) -> None:
        self._entered.set()
        self._release.wait(30.0)

    def release(self) -> None:
        """Let the dispatch go on."""
        self._release.set()


@pytest.fixture
def bus_with_gateway():
    """Yield ``(gateway, device, controller)``: a core gateway on a faulty bus, a raw peer."""
    channel = new_channel()
    device = can.Bus(interface='virtual', channel=channel)
    gateway = Gateway(GatewayConfig(interface=faulty_bus.INTERFACE_NAME, channel=channel,
                                    heartbeat_timeout=10.0))
    gateway.start()
    held = []
    yield gateway, device, faulty_bus.FaultController.get(channel), held
    for hold in held:
        hold.release()
    gateway.stop()
    device.shutdown()
    faulty_bus.FaultController.forget(channel)


def hold(setup) -> HeldDispatch:
    """Hold the dispatch of the gateway of ``setup`` (released at the end of the test)."""
    gateway, device, _, held = setup
    holding = HeldDispatch(gateway, device)
    held.append(holding)
    return holding


def send_and_wait_received(gateway: Gateway, device: can.BusABC, *frames) -> float:
    """Send ``frames``; return time.monotonic() once the receive thread has taken them all."""
    before = gateway.bus_status.frames_received
    for message in frames:
        device.send(message)
    wait_until(lambda: gateway.bus_status.frames_received >= before + len(frames), 10.0,
               f'{len(frames)} frame(s) taken by the receive thread')
    return time.monotonic()


def test_heartbeats_waiting_for_dispatch_do_not_revive_nodes_once_the_bus_is_down(
        bus_with_gateway):
    """A user sees a node OPERATIONAL again while the bus is down (unplugged adapter).

    Node 5 beats; a heartbeat of it is received but still waits for dispatch when the adapter
    is unplugged. The gateway reports the bus down and every node NOT_DETECTED; then the
    waiting heartbeat is dispatched and node 5 is OPERATIONAL, "seen just now", on a bus
    that is down, until its heartbeat timeout runs out. Expected: NOT_DETECTED while down.
    """
    gateway, device, controller, _ = bus_with_gateway
    device.send(frame(0x700 + NODE, b'\x05'))
    wait_until(lambda: gateway.monitor.status(NODE).state_name == 'OPERATIONAL', 10.0,
               'node 5 OPERATIONAL')
    holding = hold(bus_with_gateway)
    dispatched = threading.Event()
    gateway.network.subscribe(HOLD_ID + 1, lambda *_: dispatched.set())
    send_and_wait_received(gateway, device, frame(0x700 + NODE, b'\x05'),
                           frame(HOLD_ID + 1, b'\x00'))
    controller.fail_open('adapter unplugged')
    controller.fail_receive('adapter unplugged')
    wait_until(lambda: not gateway.bus_status.up, 10.0, 'the bus reported down')
    wait_until(lambda: gateway.monitor.status(NODE).state_name == 'NOT_DETECTED', 10.0,
               'node 5 NOT_DETECTED once the bus is down')
    holding.release()
    wait_until(dispatched.is_set, 10.0, 'the frames received before the fault dispatched')
    assert not gateway.bus_status.up
    status = gateway.monitor.status(NODE)
    assert status.state_name == 'NOT_DETECTED', (
        f'node {NODE} is {status.state_name}, last seen {status.last_seen_age:.3f} s ago, '
        f'while the bus is down: {gateway.bus_status.reason}')


def test_prompt_handlers_see_frames_in_the_order_received_whichever_thread_hands_them_on(
        bus_with_gateway):
    """A user sees node 5 in the state of an older heartbeat than its last one.

    Heartbeats are handled by the receive thread itself while nothing waits for dispatch.
    Three heartbeats arrive while an earlier frame holds the dispatch: they must wait behind
    it, not overtake it; the one after the release must come after them, not before.
    """
    gateway, device, _, _ = bus_with_gateway
    seen = []
    gateway.network.subscribe(0x700 + NODE, prompt(lambda _id, data, _stamp: seen.append(
        (data[0], threading.current_thread().name))))
    holding = hold(bus_with_gateway)
    send_and_wait_received(gateway, device, *(frame(0x700 + NODE, bytes([state]))
                                              for state in (0x7F, 0x05, 0x04)))
    assert seen == [], 'heartbeats overtook a frame received before them'
    holding.release()
    wait_until(lambda: len(seen) == 3, 10.0, 'the three waiting heartbeats')
    device.send(frame(0x700 + NODE, b'\x05'))
    wait_until(lambda: len(seen) == 4, 10.0, 'the heartbeat after the release')
    assert [state for state, _ in seen] == [0x7F, 0x05, 0x04, 0x05]
    assert {thread for _, thread in seen[:3]} == {'can-dispatch'}
    assert seen[3][1] == 'can-bus', 'with nothing waiting, a prompt frame is not queued'
    assert gateway.monitor.status(NODE).state_name == 'OPERATIONAL'


def test_a_heartbeat_s_age_counts_from_its_receipt_not_its_dispatch(bus_with_gateway):
    """A user sees a node "last seen 0.0 s ago" that last spoke seconds ago.

    The heartbeat is received, then waits ``HELD`` s for dispatch. Its age (nmt_state's
    last_seen_age) and time (node_states' last_seen) must count from its receipt, as the
    frame's stamp says; the monitor takes the time again when the frame is dispatched.
    """
    gateway, device, _, _ = bus_with_gateway
    holding = hold(bus_with_gateway)
    received = send_and_wait_received(gateway, device, frame(0x700 + NODE, b'\x05'))
    received_wall = time.time()
    wait_until(lambda: time.monotonic() - received >= HELD, 2 * HELD + 5.0, 'the hold')
    holding.release()
    wait_until(lambda: gateway.monitor.status(NODE).detected, 10.0, 'node 5 detected')
    asked = time.monotonic()
    status = gateway.monitor.status(NODE)
    assert status.last_seen_age >= asked - received, (
        f'last_seen_age {status.last_seen_age:.3f} s, but the heartbeat was received '
        f'{asked - received:.3f} s before')
    assert status.last_seen <= received_wall + 0.05, (
        f'last_seen is {status.last_seen - received_wall:.3f} s after the heartbeat was '
        f'received')


def test_a_heartbeat_keeps_its_time_when_the_wall_clock_is_stepped(bus_with_gateway,
                                                                    monkeypatch):
    """A user sees node_states' last_seen of one and the same heartbeat change.

    The wall clock is stepped (NTP, a user setting the date) between two looks at a node
    that has not beaten again: its last_seen must stay the time the heartbeat arrived.
    """
    gateway, device, _, _ = bus_with_gateway
    device.send(frame(0x700 + NODE, b'\x05'))
    wait_until(lambda: gateway.monitor.status(NODE).detected, 10.0, 'node 5 detected')
    before = gateway.monitor.status(NODE)
    wall = time.time
    monkeypatch.setattr(time, 'time', lambda: wall() + 3600.0)
    after = gateway.monitor.status(NODE)
    assert after.last_seen == before.last_seen, (
        f'last_seen moved by {after.last_seen - before.last_seen:.1f} s with the clock')


def test_an_emcy_s_time_is_its_receipt_not_its_dispatch(bus_with_gateway):
    """A user sees an EMCY stamped later than the device sent it (its time of dispatch).

    The emcy topic and diagnostics carry ``Emergency.received``, "time.time() when the
    gateway received it"; after a wait for dispatch it is the time of dispatch instead.
    """
    gateway, device, _, _ = bus_with_gateway
    holding = hold(bus_with_gateway)
    received = send_and_wait_received(
        gateway, device, frame(0x80 + NODE, bytes([0x10, 0x32, 0x04, 1, 2, 3, 4, 5])))
    received_wall = time.time()
    wait_until(lambda: time.monotonic() - received >= HELD, 2 * HELD + 5.0, 'the hold')
    holding.release()
    emergency = wait_until(lambda: gateway.emcy.status(NODE).last, 10.0, 'the EMCY')
    assert emergency.received <= received_wall + 0.05, (
        f'the EMCY is stamped {emergency.received - received_wall:.3f} s after it was '
        f'received')


FLOOD = 100_000
KEPT_BLOCKS = 60_000  # what ~20,000 waiting frames (2.5 s of a saturated 1 Mbit/s bus) take


def taken(gateway: Gateway) -> int:
    """Return the frames the receive thread took: kept for dispatch or dropped."""
    status = gateway.bus_status
    return status.frames_received + status.frames_dropped


def test_frames_waiting_for_dispatch_do_not_grow_memory_without_bound(bus_with_gateway):
    """A user sees the node's memory grow by every frame on the bus while dispatch is held.

    While the dispatch is held, the receive thread keeps taking frames (heartbeats of
    another node here) and every one is kept: about 160 bytes a frame, 1 MB a second of a
    saturated bus, without limit. Expected: a bounded backlog (the frames beyond it dropped
    and counted, as a driver's receive buffer does), so memory stays flat.
    """
    gateway, device, _, _ = bus_with_gateway
    holding = hold(bus_with_gateway)
    send_and_wait_received(gateway, device, frame(0x700 + NODE, b'\x05'))
    base = taken(gateway)
    before = sys.getallocatedblocks()
    heartbeat = frame(0x700 + NODE + 1, b'\x05')
    sent = 0
    while sent < FLOOD:
        device.send(heartbeat)
        sent += 1
        if sent % 5000 == 0:  # the virtual bus keeps a queue per receiver: let it drain
            wait_until(lambda goal=base + sent: taken(gateway) >= goal,
                       30.0,
                       f'{sent} flood frames taken')
    kept = sys.getallocatedblocks() - before
    holding.release()
    assert gateway.bus_status.frames_dropped > 0, 'the frames beyond the backlog are counted'
    assert kept < KEPT_BLOCKS, (
        f'{kept} Python memory blocks more after {FLOOD} frames arrived during a held '
        f'dispatch: every frame is kept')


@pytest.mark.parametrize('marked', [False, True], ids=['dispatch_thread', 'receive_thread'])
def test_a_handler_that_raises_is_logged_once_and_the_others_still_get_their_frames(
        bus_with_gateway, caplog, marked):
    """A frame handler failing on every frame costs one log line; states and SDO go on."""
    gateway, device, _, _ = bus_with_gateway
    failures = []

    def failing(*_frame):
        failures.append(1)
        raise ValueError('a broken handler')
    gateway.network.subscribe(HOLD_ID, prompt(failing) if marked else failing)
    for _ in range(50):
        device.send(frame(HOLD_ID, b'\x00'))
    device.send(frame(0x700 + NODE, b'\x05'))
    wait_until(lambda: gateway.monitor.status(NODE).state_name == 'OPERATIONAL', 10.0,
               'node 5 OPERATIONAL after the failing frames')
    assert len(failures) == 50
    logged = [record for record in caplog.records if 'frame handler failed' in record.message]
    assert len(logged) == 1, [record.message for record in logged]


def test_shutdown_with_a_held_dispatch_answers_every_call_and_sends_only_aborts(
        bus_with_gateway):
    """Shutdown while frames wait for dispatch: every call answered, then nothing but aborts.

    The dispatch thread ends once its handler returns.
    """
    gateway, device, _, _ = bus_with_gateway
    holding = hold(bus_with_gateway)
    silent = 9
    calls = [gateway.sdo_read(silent, 0x1000, 0, timeout=30.0) for _ in range(5)]
    first = wait_until(lambda: device.recv(0.1), 10.0, 'the first request on the bus')
    assert first.arbitration_id == 0x600 + silent
    for _ in range(20):  # frames received and waiting for dispatch at shutdown
        device.send(frame(0x700 + NODE, b'\x05'))
    gateway.stop()
    assert all(call.done() for call in calls)
    answers = [call.result() for call in calls]
    assert not any(answer.success for answer in answers), answers
    holding.release()
    wait_until(lambda: not gateway.bus._dispatcher.is_alive(), 10.0,
               'the dispatch thread to end')
    after = []
    while (message := device.recv(0.2)) is not None:
        after.append((hex(message.arbitration_id), bytes(message.data).hex()))
    assert all(can_id == hex(0x600 + silent) and data.startswith('80')
               for can_id, data in after), after
    assert len(after) == 1, after  # the running transfer's abort
