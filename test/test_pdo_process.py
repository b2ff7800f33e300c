"""PDOs, SYNC and their diagnostics through the installed ``cbcan_node`` in its own process.

Durand devices (not our CANopen stack) run in this test process on the node's udp_multicast
bus; this process subscribes to ``~/node_<id>/rpdo`` and ``/diagnostics`` and calls
``~/pdo_write`` as a robot's program would.
"""

import struct
import threading
import uuid

from diagnostic_msgs.msg import DiagnosticStatus
import pytest
from test_diagnostics import DiagnosticsRecorder, values

from cbcan_ros.msg import Pdo, PdoEntry
from cbcan_ros.ros.pdo import PDO_QOS
from cbcan_ros.simulation.durand.pdos import PdoConfig
from cbcan_ros.srv import NmtCommand, PdoWrite

from conftest import wait_until
from node_process import call, EDS, private_bus, service_client, START_TIMEOUT

DEVICES = (5, 6)
EVENT_TIMER = 50  # ms
PDOS = (PdoConfig('tpdo', 1, ((0x2001, 0), (0x2003, 0)), transmission_type=1),
        PdoConfig('tpdo', 2, ((0x2002, 0),), transmission_type=254, event_timer=EVENT_TIMER),
        PdoConfig('rpdo', 1, ((0x2000, 0), (0x2001, 0)), transmission_type=255))


@pytest.fixture
def devices(start_durand):
    """Return a factory ``devices(group, port)`` starting durand devices 5 and 6."""
    def factory(group: str, port: int):
        return {node_id: start_durand(node_id, interface='udp_multicast', channel=group,
                                      bus_options={'port': port}, pdos=PDOS)
                for node_id in DEVICES}
    return factory


def test_a_subscriber_in_another_process_gets_every_devices_pdos_and_can_send(
        start_node, client_node, devices):
    group, port = private_bus()
    namespace = f'/pdo{uuid.uuid4().hex[:8]}'
    name = f'{namespace}/cbcan'
    simulated = devices(group, port)
    node = start_node(['-r', f'__ns:={namespace}',
                       '-p', 'can.interface:=udp_multicast', '-p', f'can.channel:={group}',
                       '-p', f'nodes:=[{DEVICES[0]}, {DEVICES[1]}]',
                       '-p', f'pdo.nodes:=[{DEVICES[0]}, {DEVICES[1]}]',
                       '-p', f'node_{DEVICES[0]}.eds:={EDS}',
                       '-p', 'sync.period:=0.02', '-p', 'sync.counter_overflow:=10',
                       '-p', 'diagnostics_period:=0.2'], port)
    received = {node_id: [] for node_id in DEVICES}
    lock = threading.Lock()

    def keep(node_id, message):
        with lock:
            received[node_id].append(message)

    for node_id in DEVICES:
        client_node.create_subscription(Pdo, f'{name}/node_{node_id}/rpdo',
                                        lambda message, n=node_id: keep(n, message), PDO_QOS)
    recorder = DiagnosticsRecorder(client_node)
    nmt = service_client(client_node, NmtCommand, f'{name}/nmt_command', node)
    pdo_write = service_client(client_node, PdoWrite, f'{name}/pdo_write', node)

    def started() -> bool:
        # The mapping is read when each device is first heard; start them once it is.
        for node_id in DEVICES:
            call(nmt, NmtCommand.Request(node_id=node_id, command=1), 'nmt start', node)
        with lock:
            return all(any(message.pdo == 1 for message in received[node_id])
                       for node_id in DEVICES)
    wait_until(started, START_TIMEOUT, f'TPDO 1 of both devices\n{node.output()}')

    with lock:
        first = next(message for message in received[5] if message.pdo == 1)
        other = next(message for message in received[6] if message.pdo == 1)
    # Node 5 has an EDS: names and types; node 6 none: unsigned numbers of their length.
    assert [(entry.name, entry.value) for entry in first.entries] == [
        ('Demo UNSIGNED16', 0x1234), ('Demo INTEGER32', -2.0)]
    assert [(entry.name, entry.data_type, entry.value) for entry in other.entries] == [
        ('', 0, 0x1234), ('', 0, 0xFFFFFFFE)]

    answer = call(pdo_write, PdoWrite.Request(node_id=5, pdo=1, entries=[
        PdoEntry(index=0x2000, subindex=0, value=200.0),
        PdoEntry(index=0x2001, subindex=0, value=float(0xBEEF))]), 'pdo_write', node)
    assert answer.success, answer.message
    wait_until(lambda: simulated[5].value(0x2001) == struct.pack('<H', 0xBEEF), 5.0,
               'RPDO 1 applied by device 5')
    # Device 5 sends the new value in its next synchronous TPDO.
    wait_until(lambda: received[5][-1].pdo != 1 or
               received[5][-1].entries[0].value == 0xBEEF, 5.0, 'the new value in TPDO 1')

    # Diagnostics: PDOs per second both ways, and the period of the SYNCs the gateway's
    # thread sent (udp_multicast: the kernel drops them before the gateway hears them).
    device = recorder.wait_for(f'{name}: node 5', DiagnosticStatus.OK, timeout=10.0,
                               where=lambda v: float(v['PDOs received/s']) > 10
                               and int(v['PDOs sent']) > 0)
    assert int(values(device)['PDOs sent']) == 1
    assert values(device)['PDO frames too short'] == '0'
    sync = recorder.wait_for(f'{name}: SYNC', DiagnosticStatus.OK, timeout=10.0,
                             where=lambda v: v['Period measured (ms)'] != 'no SYNC heard')
    assert 10 < float(values(sync)['Period measured (ms)']) < 40
    assert values(sync)['SYNC frames heard'] == '0', 'the gateway took its own SYNCs back'
    assert values(sync)['Counter overflow'] == '10'

    # An event-driven TPDO silent for twice its event timer: WARN while operational.
    simulated[5].configure_pdos([PdoConfig('tpdo', 2, ((0x2002, 0),), 254, 0)])
    warned = recorder.wait_for(f'{name}: node 5', DiagnosticStatus.WARN, timeout=10.0)
    assert 'TPDO 2 silent' in warned.message and f'event timer {EVENT_TIMER} ms' in \
        warned.message, warned.message
