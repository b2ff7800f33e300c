"""A datagram on the udp_multicast group that holds no frame does not take the bus down.

Another program on the same group and port, or a scan, sends datagrams python-can cannot
unpack. Once a defect: each took the gateway's bus down (python-can raises from ``recv``),
failed the transfers under way, and a few in a row kept it down for seconds. Now each is
dropped and counted in ``/diagnostics``, and SDO goes on.
"""

import socket
import uuid

from diagnostic_msgs.msg import DiagnosticStatus
from test_diagnostics import DiagnosticsRecorder, values

from cbcan_ros.srv import SdoRead

from conftest import wait_until
from node_process import call, private_bus, service_client

DEVICE = 5
DATAGRAMS = 20


def test_datagrams_that_are_no_frames_are_counted_and_sdo_goes_on(start_node, client_node,
                                                                  start_durand):
    group, port = private_bus()
    name = f'/junk{uuid.uuid4().hex[:8]}/cbcan'
    start_durand(DEVICE, interface='udp_multicast', channel=group, bus_options={'port': port})
    node = start_node(['-r', f'__ns:={name.rpartition("/")[0]}',
                       '-p', 'can.interface:=udp_multicast', '-p', f'can.channel:={group}',
                       '-p', 'diagnostics_period:=0.2'], port)
    recorder = DiagnosticsRecorder(client_node)
    sdo_read = service_client(client_node, SdoRead, f'{name}/sdo_read', node)
    request = SdoRead.Request(node_id=DEVICE, index=0x1000, subindex=0, timeout=2.0)
    wait_until(lambda: call(sdo_read, request, 'sdo_read', node).success, 20.0,
               'the device answering')
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sender.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
        for number in range(DATAGRAMS):
            # Not msgpack at all, and msgpack that is no frame.
            sender.sendto(b'not a CAN frame' if number % 2 else b'\x93\x01\x02\x03',
                          (group, port))
            answer = call(sdo_read, request, 'sdo_read', node)
            assert answer.success, f'read after datagram {number}: {answer.message}'
    finally:
        sender.close()
    bus = recorder.wait_for(f'{name}: CAN bus', DiagnosticStatus.OK, timeout=10.0,
                            where=lambda v: int(v['Datagrams dropped']) == DATAGRAMS)
    assert values(bus)['Reopen count'] == '0', values(bus)
    assert node.output().count('held no CAN frame') == 1, node.output()[-3000:]
