"""What another program sends to the gateway's udp_multicast group does not take its bus.

Another program on the same group and port (or a scan) sends datagrams python-can cannot
unpack, frames it unpacks whatever their field types (msgpack carries floats; python-can's
check lets an error frame with the id 0.5 through), and error frames, which on a group are
another program's (no adapter reports to it). Once defects, each: a datagram that did not
unpack took the bus down and failed the transfers under way; the float id ended the bus
thread (the gateway deaf for good, /diagnostics saying the bus is up); a bus-off error frame
took the bus down. Now each is dropped, counted in /diagnostics and logged once.
"""

import socket
import time
import uuid

from diagnostic_msgs.msg import DiagnosticStatus
import msgpack
from test_diagnostics import DiagnosticsRecorder, values

from cbcan_ros.srv import SdoRead

from conftest import wait_until
from node_process import call, private_bus, service_client, StateWatcher

DEVICE = 5
DATAGRAMS = 20


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


def _send(group, port, frame) -> None:
    """Send ``frame`` (a dict, packed as python-can packs one; bytes as they are)."""
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sender.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
        sender.sendto(frame if isinstance(frame, bytes) else msgpack.packb(
            {'timestamp': 0.0, **frame}, use_bin_type=True), (group, port))
    finally:
        sender.close()


def test_datagrams_that_are_no_frames_are_counted_and_sdo_goes_on(start_node, client_node,
                                                                  start_durand):
    group, port, name, node, sdo_read, request = _gateway(start_node, client_node, start_durand)
    recorder = DiagnosticsRecorder(client_node)
    for number in range(DATAGRAMS):
        # Not msgpack at all, and msgpack that is no frame.
        _send(group, port, b'not a CAN frame' if number % 2 else b'\x93\x01\x02\x03')
        answer = call(sdo_read, request, 'sdo_read', node)
        assert answer.success, f'read after datagram {number}: {answer.message}'
    bus = recorder.wait_for(f'{name}: CAN bus', DiagnosticStatus.OK, timeout=10.0,
                            where=lambda v: int(v['Datagrams dropped']) == DATAGRAMS)
    assert values(bus)['Reopen count'] == '0', values(bus)
    assert node.output().count('held no CAN frame') == 1, node.output()[-3000:]


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


# A heartbeat of node 9 saying OPERATIONAL, as python-can's pack_message lays a frame out.
HEARTBEAT = {'arbitration_id': 0x709, 'is_extended_id': False, 'is_remote_frame': False,
             'is_error_frame': False, 'channel': None, 'dlc': 1, 'data': b'\x05',
             'is_fd': False, 'bitrate_switch': False, 'error_state_indicator': False}
FLAGS = ('is_extended_id', 'is_remote_frame', 'is_error_frame', 'is_fd', 'bitrate_switch',
         'error_state_indicator', 'is_rx')
# Each is a frame python-can 4.6.1 takes whatever its field types: a flag of another type
# (its check takes 1 for True), a CAN FD frame (the driver opens for FD by default; CANopen
# here runs on classic CAN), a dlc of 1.0 or True, data that is no msgpack bin (python-can
# makes bytes of it: 1 becomes b'\x00', a boot-up; [5] an OPERATIONAL heartbeat).
ODD_HEARTBEATS = ([{**HEARTBEAT, flag: 0} for flag in FLAGS] + [
    {**HEARTBEAT, 'is_fd': True},
    {**HEARTBEAT, 'is_fd': True, 'dlc': 64, 'data': b'\x05' * 64},
    {**HEARTBEAT, 'dlc': 1.0},
    {**HEARTBEAT, 'dlc': True},
    {**HEARTBEAT, 'data': 1},
    {**HEARTBEAT, 'data': [5]},
    {**HEARTBEAT, 'data': [True]},
])
WELL_FORMED = 0x760  # node 96's heartbeat: once it shows, every odd one before it was taken


def test_frames_of_other_types_are_dropped_counted_and_show_no_node(start_node, client_node,
                                                                    start_durand):
    group, port, name, node, sdo_read, request = _gateway(start_node, client_node, start_durand)
    recorder = DiagnosticsRecorder(client_node)
    states = StateWatcher(client_node, name)
    for frame in ODD_HEARTBEATS:
        _send(group, port, frame)
        answer = call(sdo_read, request, 'sdo_read', node)
        assert answer.success, f'sdo_read after {frame}: {answer.message}'
    _send(group, port, {**HEARTBEAT, 'arbitration_id': WELL_FORMED})
    wait_until(lambda: 96 in states.latest(), 10.0, 'the well-formed heartbeat shown')
    assert 9 not in states.latest(), f'an odd frame showed node 9: {states.latest()}'
    bus = recorder.wait_for(f'{name}: CAN bus', DiagnosticStatus.OK, timeout=10.0,
                            where=lambda v: int(v['Datagrams dropped']) == len(ODD_HEARTBEATS))
    assert values(bus)['Reopen count'] == '0', values(bus)
