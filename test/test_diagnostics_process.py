"""EMCY and ``/diagnostics`` of the installed ``cbcan_node``, seen from another process.

A durand device (a CANopen stack independent of the gateway's) runs in this test process on
the node's udp_multicast bus and sends real EMCYs through durand's EMCY producer; this
process's rclpy subscribers read ``~/emcy`` and ``/diagnostics`` as a robot's monitor would.
"""

import time
import uuid

from diagnostic_msgs.msg import DiagnosticStatus
import pytest
from test_diagnostics import describe, DiagnosticsRecorder, values

from cbcan_ros.msg import Emcy
from cbcan_ros.ros.emcy import EMCY_QOS
from cbcan_ros.simulation.durand.device import DurandDevice
from cbcan_ros.srv import SdoRead

from conftest import wait_until
from node_process import call, private_bus, service_client, START_TIMEOUT

DEVICE = 5
SILENT = 9  # expected by the gateway, never on the bus
NOT_EXIST = 0x06020000


@pytest.fixture
def device():
    """Return a factory ``device(group, port)`` starting durand device 5 on that bus."""
    started = []

    def factory(group: str, port: int) -> DurandDevice:
        simulated = DurandDevice(DEVICE, 'udp_multicast', group, bus_options={'port': port})
        simulated.start()
        started.append(simulated)
        return simulated

    yield factory
    for simulated in started:
        simulated.stop()


def test_emcy_and_diagnostics_reach_a_subscriber_in_another_process(start_node, client_node,
                                                                    device):
    group, port = private_bus()
    namespace = f'/diag{uuid.uuid4().hex[:8]}'
    gateway_name = f'{namespace}/cbcan'
    durand = device(group, port)
    gateway = start_node(['-r', f'__ns:={namespace}',
                          '-p', 'can.interface:=udp_multicast',
                          '-p', f'can.channel:={group}',
                          '-p', f'nodes:=[{DEVICE}, {SILENT}]',
                          '-p', 'heartbeat.timeout:=1.0',
                          '-p', 'diagnostics_period:=0.2'], port)
    emergencies = []
    client_node.create_subscription(Emcy, f'{gateway_name}/emcy', emergencies.append, EMCY_QOS)
    recorder = DiagnosticsRecorder(client_node)
    bus_name, device_name = f'{gateway_name}: CAN bus', f'{gateway_name}: node {DEVICE}'
    silent_name = f'{gateway_name}: node {SILENT}'

    def wait_for(name, level, **options):
        try:
            return recorder.wait_for(name, level, **options)
        except AssertionError as error:
            raise AssertionError(f'{error}\ncbcan_node output:\n{gateway.output()}') from None

    # The bus: up, the device's heartbeats (every 200 ms) counted as frames per second.
    bus = wait_for(bus_name, DiagnosticStatus.OK, timeout=START_TIMEOUT,
                   where=lambda v: float(v['Frames received/s']) >= 2)
    assert bus.hardware_id == f'udp_multicast:{group}'
    assert (values(bus)['State'], values(bus)['Reopen count']) == ('up', '0')
    assert int(values(bus)['Frames received']) > 0
    silent = wait_for(silent_name, DiagnosticStatus.ERROR)
    assert silent.message == 'expected but never heard', describe(silent)
    assert values(silent)['NMT state'] == 'NOT_DETECTED'
    ok = wait_for(device_name, DiagnosticStatus.OK)
    assert ok.hardware_id == f'canopen node {DEVICE} on udp_multicast:{group}'
    assert (ok.message, values(ok)['Active EMCY']) == ('PRE_OPERATIONAL', 'none')

    # SDO statistics: one answer, one abort (CiA 301 NOT_EXIST), with a latency.
    sdo_read = service_client(client_node, SdoRead, f'{gateway_name}/sdo_read', gateway)
    assert call(sdo_read, SdoRead.Request(node_id=DEVICE, index=0x1000), 'sdo_read',
                gateway).success
    answer = call(sdo_read, SdoRead.Request(node_id=DEVICE, index=0x6000), 'sdo_read', gateway)
    assert answer.abort_code == NOT_EXIST, answer.message
    counted = wait_for(device_name, DiagnosticStatus.OK,
                       where=lambda v: v['SDO requests'] == '2')
    assert (values(counted)['SDO aborts'], values(counted)['SDO timeouts']) == ('1', '0')
    assert 0 < float(values(counted)['SDO latency p50 (ms)']) < 500

    # A real EMCY from durand's producer: on ~/emcy, and the device WARN while it is active.
    sent = time.time()
    durand.emergency(0x3120, error_register=0x05, manufacturer=b'\xaa\xbb\xcc')
    wait_until(lambda: emergencies, 10.0, f'the EMCY on ~/emcy\n{gateway.output()}')
    seen = time.time()
    message = emergencies[0]
    assert (message.node_id, message.error_code, message.error_register) == (DEVICE, 0x3120, 5)
    assert bytes(message.manufacturer_data) == b'\xaa\xbb\xcc\x00\x00'
    assert message.description == 'Voltage'
    # Stamped when the node received it: after it was sent, before this process saw it.
    assert sent - 0.1 <= message.stamp.sec + message.stamp.nanosec * 1e-9 <= seen + 0.1
    warned = wait_for(device_name, DiagnosticStatus.WARN)
    assert warned.message == 'PRE_OPERATIONAL; active EMCY 0x3120 Voltage', describe(warned)
    assert values(warned)['Last EMCY error register'] == '0x05'
    assert values(warned)['Last EMCY manufacturer data'] == 'aa bb cc 00 00'

    # The error reset clears it: OK again, the reset is the last EMCY.
    durand.emergency(0)
    wait_until(lambda: len(emergencies) == 2, 10.0, f'the error reset on ~/emcy\n'
                                                   f'{gateway.output()}')
    assert (emergencies[1].error_code, emergencies[1].description) == (
        0, 'Error Reset / No Error')
    cleared = wait_for(device_name, DiagnosticStatus.OK)
    assert values(cleared)['Active EMCY'] == 'none'
    assert values(cleared)['Last EMCY'] == '0x0000 Error Reset / No Error'
    assert recorder.latest(silent_name).level == DiagnosticStatus.ERROR  # still silent

    gateway.stop()
    assert gateway.process.returncode == 0, gateway.output()
