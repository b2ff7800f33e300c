"""Faults and shutdown with the installed ``cbcan_node`` as a separate process.

A robot's USB-CAN adapter speaks slcan: here python-can's real ``slcan`` driver in the node
talks to a fake adapter on a pseudo-terminal (test/fake_slcan.py), which is unplugged and
plugged back. Shutdown is tested with SIGINT and SIGTERM while calls wait for a silent device.
"""

import signal
import threading
import time
import uuid

import can
import pytest

from cbcan_ros.msg import NodeStates
from cbcan_ros.ros.interface import NODE_STATES_QOS
from cbcan_ros.simulation.canopen_device import SimulatedDevice
from cbcan_ros.srv import SdoRead, SdoWrite

from conftest import new_channel, wait_for_future, wait_until
from fake_slcan import FakeSlcanAdapter
from node_process import EDS, random_bus, service_client

RECOVERY = 10.0
SILENT = 9  # no device has this node id


def namespace() -> str:
    return f'/proc{uuid.uuid4().hex[:8]}'


class StateWatcher:
    """The node_states topic of a gateway, as a subscriber in this process sees it."""

    def __init__(self, client_node, gateway_name: str):
        self._messages = []
        client_node.create_subscription(NodeStates, f'{gateway_name}/node_states',
                                        self._messages.append, NODE_STATES_QOS)

    def latest(self) -> dict:
        """Return {node_id: state_name} of the latest message."""
        return {n.node_id: n.state_name for n in self._messages[-1].nodes} \
            if self._messages else {}

    def wait_for(self, expected: dict, timeout: float) -> None:
        """Wait until the latest message shows exactly ``expected``."""
        wait_until(lambda: self.latest() == expected, timeout,
                   f'node states {expected} (last {self.latest()})')


def test_slcan_adapter_plugged_in_late_unplugged_and_plugged_back(
        start_node, client_node, tmp_path):
    channel = new_channel()
    device = SimulatedDevice(2, EDS, 'virtual', channel)
    device.start()
    link = tmp_path / 'usb-can0'
    adapter = FakeSlcanAdapter(link, channel, plugged=False)
    name = f'{namespace()}/cbcan'
    try:
        gateway = start_node(['-r', f'__ns:={name.rsplit("/", 1)[0]}',
                              '-p', 'can.interface:=slcan', '-p', f'can.channel:={link}',
                              '-p', 'can.bitrate:=500000',
                              '-p', 'can.options:=[sleep_after_open=0]',
                              '-p', 'nodes:=[2]', '-p', 'heartbeat.timeout:=0.5',
                              '-p', 'state_publish_period:=0.1'])
        states = StateWatcher(client_node, name)
        sdo_read = service_client(client_node, SdoRead, f'{name}/sdo_read', gateway)
        request = SdoRead.Request(node_id=2, index=0x1000, subindex=0)

        # Started before the adapter was plugged in: honest errors, no exit.
        answer = wait_for_future(sdo_read.call_async(request), 5.0)
        assert not answer.success
        assert 'CAN bus is down' in answer.message and 'cannot open' in answer.message
        assert gateway.process.poll() is None

        adapter.plug()
        wait_until(lambda: wait_for_future(sdo_read.call_async(request), 5.0).success,
                   RECOVERY, 'SDO through the adapter once plugged in')
        states.wait_for({2: 'PRE_OPERATIONAL'}, RECOVERY)

        adapter.unplug()
        states.wait_for({2: 'NOT_DETECTED'}, 3.0)
        answer = wait_for_future(sdo_read.call_async(request), 5.0)
        assert not answer.success and 'CAN bus is down' in answer.message, answer.message

        adapter.plug()
        wait_until(lambda: wait_for_future(sdo_read.call_async(request), 5.0).success,
                   RECOVERY, 'SDO again after the adapter came back')
        states.wait_for({2: 'PRE_OPERATIONAL'}, RECOVERY)
        assert bytes(wait_for_future(sdo_read.call_async(request), 5.0).data) == bytes(
            [0x92, 0x01, 0x02, 0x00])
        gateway.stop()
        output = gateway.output()
        assert gateway.process.returncode == 0, output
        # One line per fault: the first failed open and the unplug, not one per attempt.
        assert output.count('is down') == 2, output
        assert output.count('up again') == 1, output
    finally:
        adapter.close()
        device.stop()


class BusRecorder:
    """Every frame on a udp_multicast bus, with the time it arrived here."""

    def __init__(self, group: str, port: int):
        self._bus = can.Bus(interface='udp_multicast', channel=group, port=port)
        self.frames = []
        self._running = True
        self._thread = threading.Thread(target=self._record, daemon=True)
        self._thread.start()

    def _record(self) -> None:
        while self._running:
            message = self._bus.recv(0.05)
            if message is not None:
                self.frames.append((time.monotonic(), message))

    def close(self) -> None:
        """Stop recording and close the bus."""
        self._running = False
        self._thread.join()
        self._bus.shutdown()


@pytest.mark.parametrize('signum', [signal.SIGINT, signal.SIGTERM])
def test_signal_answers_every_waiting_call_and_sends_no_request(
        start_node, client_node, signum):
    group, port = random_bus()
    recorder = BusRecorder(group, port)
    name = f'{namespace()}/cbcan'
    try:
        gateway = start_node(['-r', f'__ns:={name.rsplit("/", 1)[0]}',
                              '-p', 'can.interface:=udp_multicast',
                              '-p', f'can.channel:={group}'], port)
        sdo_read = service_client(client_node, SdoRead, f'{name}/sdo_read', gateway)
        sdo_write = service_client(client_node, SdoWrite, f'{name}/sdo_write', gateway)
        calls = []
        for i in range(6):
            calls.append(sdo_read.call_async(SdoRead.Request(
                node_id=SILENT, index=0x1000, subindex=0, timeout=30.0)))
            calls.append(sdo_write.call_async(SdoWrite.Request(
                node_id=SILENT, index=0x2002, subindex=0, data=[i, 0, 0, 0], timeout=30.0)))
        requests = 0x600 + SILENT
        wait_until(lambda: any(m.arbitration_id == requests for _, m in recorder.frames),
                   10.0, 'the first request on the bus')
        signalled = time.monotonic()
        gateway.process.send_signal(signum)
        answers = [wait_for_future(call, 2.0) for call in calls]
        answered = time.monotonic() - signalled
        status = gateway.wait(2.0)
        exited = time.monotonic() - signalled
        time.sleep(0.2)  # let frames still in flight reach the recorder
    finally:
        recorder.close()
    output = gateway.output()
    assert status == 0, output
    assert exited < 2.0 and answered < 2.0, (answered, exited)
    assert 'Traceback' not in output, output
    for answer in answers:
        assert not answer.success
        assert 'shutting down' in answer.message, answer.message
    sent = [(t, m) for t, m in recorder.frames if m.arbitration_id == requests]
    after = [m for t, m in sent if t > signalled]
    assert all(m.data[0] == 0x80 for m in after), [m.data.hex() for m in after]
    assert [m.data[0] for _, m in sent].count(0x40) == 1, 'only the first request went out'
    assert not any(m.data[0] & 0xE0 == 0x20 for _, m in sent), 'no write went out'


def test_second_signal_ends_the_node_at_once_without_a_traceback(start_node, client_node):
    name = f'{namespace()}/cbcan'
    gateway = start_node(['-r', f'__ns:={name.rsplit("/", 1)[0]}',
                          '-p', f'can.channel:={new_channel()}'])
    service_client(client_node, SdoRead, f'{name}/sdo_read', gateway)
    gateway.process.send_signal(signal.SIGINT)
    # Two signals sent at once may reach Python as one: the second goes once the first is in.
    wait_until(lambda: 'shutting down' in gateway.output() or gateway.process.poll() is not None,
               5.0, 'the first signal taken')
    if gateway.process.poll() is None:
        gateway.process.send_signal(signal.SIGINT)
    status = gateway.wait(1.0)
    output = gateway.output()
    assert status in (0, 128 + signal.SIGINT), output
    assert 'Traceback' not in output, output
