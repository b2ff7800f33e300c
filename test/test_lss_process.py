"""Commissioning through the installed ``cbcan_node`` and ``cbcan_cli``, each a process.

Three new durand devices (LSS slaves without a node id) run in this test process on the
node's udp_multicast bus; the integrator's steps are run as written in docs/commissioning.md.
"""

import subprocess
import uuid

import pytest

from cbcan_ros.msg import NodeStates
from cbcan_ros.ros.cli import build_parser, Client, run
from cbcan_ros.ros.interface import NODE_STATES_QOS
from cbcan_ros.simulation.durand.device import DurandDevice

from conftest import wait_until
from node_process import executable, private_bus, START_TIMEOUT

VENDOR, PRODUCT, REVISION = 0x319, 0x51, 0x10000
SERIALS = (0x12, 0x7, 0x30)


@pytest.fixture
def commissioning(start_node, client_node):
    """Start three new devices and the node on a udp_multicast bus; yield (name, devices)."""
    group, port = private_bus()
    devices = [DurandDevice(255, 'udp_multicast', group, bus_options={'port': port}, lss=True,
                            identity=(VENDOR, PRODUCT, REVISION, serial))
               for serial in SERIALS]
    for device in devices:
        device.start()
    namespace = f'/lss{uuid.uuid4().hex[:8]}'
    process = start_node(['-r', f'__ns:={namespace}',
                          '-p', 'can.interface:=udp_multicast',
                          '-p', f'can.channel:={group}',
                          '-p', 'nodes:=[10]',
                          # The default 40 ms on a bus without a wire was too short for
                          # these devices' answers on a loaded machine.
                          '-p', 'lss.probe_timeout:=0.15'], port)
    yield f'{namespace}/cbcan', devices, process
    for device in devices:
        device.stop()


def test_integrator_scans_numbers_and_checks_new_devices_from_the_command_line(
        commissioning, client_node, capsys):
    name, devices, process = commissioning
    states = []
    client_node.create_subscription(NodeStates, f'{name}/node_states', states.append,
                                    NODE_STATES_QOS)
    scan = subprocess.run([executable('cbcan_cli'), '--gateway', name, '--wait',
                           str(START_TIMEOUT), 'lss-scan', '--assign-from', '10', '--store'],
                          capture_output=True, text=True, timeout=120)
    assert scan.returncode == 0, f'{scan.stdout}{scan.stderr}\n{process.output()}'
    lines = scan.stdout.splitlines()
    # Node 10 is listed in nodes: ids start at 11. Lowest identity first.
    for line, (serial, node_id) in zip(lines, ((0x7, 11), (0x12, 12), (0x30, 13)),
                                       strict=False):
        assert line == (f'vendor 0x{VENDOR:08X} product 0x{PRODUCT:08X} revision '
                        f'0x{REVISION:08X} serial 0x{serial:08X}  -> node {node_id}')
    assert 'found 3 unconfigured device(s)' in lines[3]
    assert sorted((d.identity[3], d.node_id, d.stored['node_id']) for d in devices) == [
        (0x7, 11, 11), (0x12, 12, 12), (0x30, 13, 13)]

    def booted():
        latest = {n.node_id: n.state_name for n in states[-1].nodes} if states else {}
        return all(latest.get(n) == 'PRE_OPERATIONAL' for n in (11, 12, 13))
    wait_until(booted, 10.0, 'nodes 11, 12, 13 PRE_OPERATIONAL on node_states')

    client = Client(name, START_TIMEOUT)
    try:
        def cli(*arguments):
            status = run(client, build_parser().parse_args(arguments))
            out, err = capsys.readouterr()
            return status, out, err
        identity = (hex(VENDOR), hex(PRODUCT), hex(REVISION), '0x12')
        assert cli('sdo-read', '12', '0x1018', '4') == (
            0, 'data:  12 00 00 00  (4 bytes)\nvalue: 0x00000012 = 18  (unsigned, '
               'little-endian)\n', '')
        assert cli('lss-inquire', *identity) == (0, 'node id: 12\n', '')
        status, out, err = cli('lss-configure', *identity, '--bitrate', '125000', '--store')
        assert status == 0, err
        assert out.startswith('ok: vendor 0x00000319'), out
        assert next(d for d in devices if d.identity[3] == 0x12).stored == {
            'bitrate': 125000, 'node_id': 12}
        status, out, err = cli('lss-configure', *identity, '--bitrate', '100000', '--store')
        assert (status, out) == (1, '')
        assert 'bitrate 100000 is not in the CiA 305 table' in err
        assert cli('lss-inquire', hex(VENDOR), hex(PRODUCT), hex(REVISION), '0x99')[0] == 1
    finally:
        client.close()
