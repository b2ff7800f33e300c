"""``/diagnostics`` of a gateway node in this process: bus and device levels as monitors see them.

The faults come from the fault-injecting python-can bus (test/faulty_bus.py) and from frames
forged on a raw bus of the gateway's channel; a subscriber reads ``/diagnostics``.
"""

import pathlib
import threading

import can
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
import pytest

from cbcan_ros.core import bus as bus_module
from cbcan_ros.ros import diagnostics as diagnostics_module
from cbcan_ros.ros.diagnostics import DIAGNOSTICS_QOS
from cbcan_ros.simulation.canopen_device import SimulatedDevice

from conftest import new_channel, wait_until
import faulty_bus
from faulty_bus import FaultController

UNUSED_ID = 0x7F0  # no CANopen service uses it: a handler there holds the dispatch

EDS = str(pathlib.Path(__file__).resolve().parent.parent / 'config' / 'simulated_device.eds')
OK, WARN, ERROR, STALE = (DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR,
                          DiagnosticStatus.STALE)
CAN_ERR_CRTL = 0x04  # linux/can/error.h: a controller problem (not bus-off)

faulty_bus.register()


class DiagnosticsRecorder:
    """Keeps the latest DiagnosticStatus of every status name seen on ``/diagnostics``."""

    def __init__(self, node):
        self._lock = threading.Lock()
        self._latest = {}
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_array,
                                 DIAGNOSTICS_QOS)

    def _on_array(self, array) -> None:
        with self._lock:
            for status in array.status:
                self._latest[status.name] = status

    def latest(self, name: str):
        """Return the latest status named ``name``, or None."""
        with self._lock:
            return self._latest.get(name)

    def wait_for(self, name: str, level, timeout: float = 10.0, where=lambda values: True):
        """Wait for a status ``name`` at ``level`` whose key-values satisfy ``where``."""
        def matches():
            status = self.latest(name)
            return status is not None and status.level == level and where(values(status))
        wait_until(matches, timeout, f'{name!r} at level {level!r} '
                                     f'(last seen {describe(self.latest(name))})')
        return self.latest(name)


def values(status) -> dict:
    """Return a status's key-values as a dict."""
    return {pair.key: pair.value for pair in status.values}


def describe(status) -> str:
    """Return a short text of a status, for failure messages."""
    if status is None:
        return 'nothing'
    return f'{status.level!r} {status.message!r} {values(status)}'


@pytest.fixture
def start_faulty(make_gateway):
    """Return ``start() -> (harness, faults, recorder)``: a gateway on the faulty interface.

    Devices 2 and 3 run on the plain virtual bus of the channel; the gateway expects 2, 3 and 9.
    """
    devices = []

    def factory():
        channel = new_channel()
        faults = FaultController.get(channel)
        for node_id in (2, 3):
            device = SimulatedDevice(node_id, EDS, 'virtual', channel)
            device.start()
            devices.append(device)
        harness = make_gateway(can__interface='faulty', can__channel=channel,
                               simulation__devices=None, nodes=[2, 3, 9],
                               heartbeat__timeout=0.5, diagnostics_period=0.1)
        return harness, faults, DiagnosticsRecorder(harness.client_node)

    yield factory
    for device in devices:
        device.stop()


def test_diagnostics_are_built_only_while_something_subscribes(make_gateway, monkeypatch):
    # With 127 devices an array is about 2,000 key-values each period: issue 39's idle node
    # must not pay for messages nobody reads. A subscriber that comes gets them at once.
    periods, arrays = [], []
    diagnostics = diagnostics_module.Diagnostics
    publish, build = diagnostics.publish, diagnostics._bus_status  # the first status built

    def counted_publish(self):
        periods.append(1)
        publish(self)

    def counted_build(self, *args):
        arrays.append(1)
        return build(self, *args)

    monkeypatch.setattr(diagnostics, 'publish', counted_publish)
    monkeypatch.setattr(diagnostics, '_bus_status', counted_build)
    harness = make_gateway(diagnostics_period=0.05)
    wait_until(lambda: len(periods) >= 5, 10.0, 'five diagnostics periods')
    assert not arrays, 'an array was built while nothing subscribed to /diagnostics'
    recorder = DiagnosticsRecorder(harness.client_node)
    bus = recorder.wait_for('cbcan: CAN bus', OK)
    assert values(bus)['State'] == 'up'
    assert arrays


def test_a_late_subscriber_is_not_shown_old_errors_as_the_last_periods(make_gateway,
                                                                          monkeypatch):
    periods = []
    publish = diagnostics_module.Diagnostics.publish

    def counted_publish(self):
        periods.append(1)
        publish(self)

    monkeypatch.setattr(diagnostics_module.Diagnostics, 'publish', counted_publish)
    channel = new_channel()
    harness = make_gateway(can__interface='faulty', can__channel=channel,
                           simulation__devices=None, diagnostics_period=0.05)
    raw = harness.raw_bus()
    try:
        raw.send(can.Message(arbitration_id=CAN_ERR_CRTL, is_error_frame=True))
    finally:
        raw.shutdown()
    gateway = harness.node.gateway
    wait_until(lambda: gateway.bus_status.error_frames == 1, 10.0, 'the error frame taken')
    seen = len(periods)
    wait_until(lambda: len(periods) >= seen + 3, 10.0, 'three periods without a subscriber')
    first = []
    harness.client_node.create_subscription(
        DiagnosticArray, '/diagnostics',
        lambda array: first or first.extend(s for s in array.status if s.name.endswith(
            ': CAN bus')), DIAGNOSTICS_QOS)
    wait_until(lambda: first, 10.0, 'the first array at the new subscriber')
    assert first[0].level == OK, describe(first[0])
    assert values(first[0])['Error frames'] == '1'


def test_devices_are_ok_an_expected_silent_one_is_error(start_faulty):
    harness, _faults, recorder = start_faulty()
    hardware = f'faulty:{harness.channel}'
    two = recorder.wait_for('cbcan: node 2', OK, where=lambda v: v['NMT state'] ==
                            'PRE_OPERATIONAL')
    assert two.hardware_id == f'canopen node 2 on {hardware}'
    assert two.message == 'PRE_OPERATIONAL'
    assert values(two)['Expected'] == 'yes'
    # Seconds since its last heartbeat: alive (heartbeat.timeout 0.5 s) means recent, with
    # room for a loaded machine; a timestamp or milliseconds would be far off.
    assert 0 <= float(values(two)['Last heartbeat age (s)']) < 3.0
    nine = recorder.wait_for('cbcan: node 9', ERROR)
    assert nine.message == 'expected but never heard', describe(nine)
    bus = recorder.wait_for('cbcan: CAN bus', OK,
                            where=lambda v: float(v['Frames received/s']) > 0)
    assert bus.hardware_id == hardware
    assert bus.message == 'up'
    assert values(bus)['State'] == 'up'


def test_error_frames_warn_and_a_bus_down_is_an_error(start_faulty):
    harness, faults, recorder = start_faulty()
    recorder.wait_for('cbcan: CAN bus', OK)
    raw = harness.raw_bus()  # a plain virtual bus: its frames reach the gateway's adapter
    try:
        raw.send(can.Message(arbitration_id=CAN_ERR_CRTL, is_error_frame=True))
    finally:
        raw.shutdown()
    warned = recorder.wait_for('cbcan: CAN bus', WARN)
    assert warned.message.startswith('up; 1 error frame in the last'), describe(warned)
    assert values(warned)['Error frames'] == '1'
    recorder.wait_for('cbcan: CAN bus', OK)  # no new error frames: OK again

    faults.fail_open('adapter gone')
    faults.fail_receive('adapter unplugged')
    down = recorder.wait_for('cbcan: CAN bus', ERROR)
    assert 'adapter unplugged' in down.message, describe(down)
    assert values(down)['State'] == 'down'
    two = recorder.wait_for('cbcan: node 2', ERROR)
    assert 'the CAN bus is down' in two.message, describe(two)

    faults.clear()
    up = recorder.wait_for('cbcan: CAN bus', OK, timeout=10.0)
    assert values(up)['Reopen count'] == '1'
    recorder.wait_for('cbcan: node 2', OK, timeout=10.0)


def test_frames_dropped_for_a_full_backlog_warn(start_faulty, monkeypatch):
    monkeypatch.setattr(bus_module, 'DISPATCH_BACKLOG', 5)
    harness, _faults, recorder = start_faulty()
    recorder.wait_for('cbcan: CAN bus', OK)
    entered, release = threading.Event(), threading.Event()

    def hold(*_frame):
        entered.set()
        release.wait(10.0)
    harness.node.gateway.network.subscribe(UNUSED_ID, hold)
    raw = harness.raw_bus()
    try:
        raw.send(can.Message(arbitration_id=UNUSED_ID, data=b'\x00', is_extended_id=False))
        wait_until(entered.is_set, 10.0, 'the dispatch held in a handler')
        for _ in range(20):
            raw.send(can.Message(arbitration_id=UNUSED_ID, data=b'\x01', is_extended_id=False))
        warned = recorder.wait_for('cbcan: CAN bus', WARN)
    finally:
        release.set()
        raw.shutdown()
    assert 'dropped' in warned.message, describe(warned)
    assert int(values(warned)['Frames dropped']) > 0, describe(warned)
