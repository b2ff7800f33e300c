"""Frames that python-can DOES unpack, sent by another program on the udp_multicast group.

The gateway drops datagrams that hold no frame (test_undecodable_datagrams). A datagram that
python-can unpacks into a frame with ``check=True`` is taken as a frame, whatever its field
types: msgpack carries floats, and python-can's check accepts an arbitration id of 0.5 on an
error frame. The gateway's bus thread then computes ``arbitration_id & CAN_ERR_BUSOFF`` outside
any guard (core/bus.py ``_receive``), the TypeError ends the bus thread, and the gateway is
deaf for good while /diagnostics goes on saying the bus is up.

Also: an error frame on a udp_multicast group is another program's (there is no adapter): one
with the bus-off class bit takes the gateway's bus down, and it fails the SDO under way.
"""

import socket
import time
import uuid

from diagnostic_msgs.msg import DiagnosticStatus
import msgpack
from test_diagnostics import DiagnosticsRecorder, values

from cbcan_ros.srv import SdoRead

from conftest import wait_until
from node_process import call, private_bus, service_client

DEVICE = 5


def _gateway(start_node, client_node, start_durand):
    group, port = private_bus()
    name = f'/odd{uuid.uuid4().hex[:8]}/cbcan'
    start_durand(DEVICE, interface='udp_multicast', channel=group, bus_options={'port': port})
    node = start_node(['-r', f'__ns:={name.rpartition("/")[0]}',
                       '-p', 'can.interface:=udp_multicast', '-p', f'can.channel:={group}',
                       '-p', 'diagnostics_period:=0.2'], port)
    sdo_read = service_client(client_node, SdoRead, f'{name}/sdo_read', node)
    request = SdoRead.Request(node_id=DEVICE, index=0x1000, subindex=0, timeout=1.0)
    wait_until(lambda: call(sdo_read, request, 'sdo_read', node).success, 20.0,
               'the device answering')
    return group, port, name, node, sdo_read, request


def _send(group, port, frame: dict) -> None:
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sender.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
        sender.sendto(msgpack.packb({'timestamp': 0.0, **frame}, use_bin_type=True),
                      (group, port))
    finally:
        sender.close()


def test_an_error_frame_with_a_float_id_does_not_make_the_gateway_deaf(start_node, client_node,
                                                                       start_durand):
    group, port, name, node, sdo_read, request = _gateway(start_node, client_node, start_durand)
    recorder = DiagnosticsRecorder(client_node)
    _send(group, port, {'arbitration_id': 0.5, 'is_error_frame': True})
    time.sleep(0.5)
    failures = []
    for _ in range(5):  # the bus must be up again within a few seconds at the latest
        answer = call(sdo_read, request, 'sdo_read', node)
        if answer.success:
            break
        failures.append(answer.message)
        time.sleep(1.0)
    else:
        wait_until(lambda: recorder.latest(f'{name}: CAN bus') is not None, 5.0, 'diagnostics')
        bus = recorder.latest(f'{name}: CAN bus')
        raise AssertionError(f'sdo_read fails for good after one odd error frame: {failures}; '
                             f'/diagnostics says {values(bus)}; log: {node.output()[-1500:]}')


def test_an_error_frame_of_another_program_does_not_take_the_bus_down(start_node, client_node,
                                                                      start_durand):
    group, port, name, node, sdo_read, request = _gateway(start_node, client_node, start_durand)
    recorder = DiagnosticsRecorder(client_node)
    for _ in range(3):
        _send(group, port, {'arbitration_id': 0x40, 'is_error_frame': True})  # CAN_ERR_BUSOFF
        answer = call(sdo_read, request, 'sdo_read', node)
        assert answer.success, f"sdo_read after another program's error frame: {answer.message}"
    bus = recorder.wait_for(f'{name}: CAN bus', DiagnosticStatus.OK, timeout=5.0)
    assert values(bus)['Reopen count'] == '0', values(bus)
