"""The installed ``cbcan_node`` as a separate process, as users run it, over udp_multicast.

The simulated devices run in this test process on the same udp_multicast channel, so every
SDO, NMT and heartbeat frame crosses a process boundary, and so does every service call.
"""

import os
import subprocess
import time
import uuid

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
import pytest

from cbcan_ros.msg import NodeStates
from cbcan_ros.ros.interface import NODE_STATES_QOS
from cbcan_ros.simulation.canopen_device import SimulatedDevice
from cbcan_ros.srv import NmtCommand, NmtState, SdoRead, SdoWrite

from conftest import new_channel, wait_for_future, wait_until
from node_process import (
    arguments,
    call,
    EDS,
    executable,
    namespace,
    private_bus,
    service_client,
    START_TIMEOUT,
)

DEVICES = (2, 5)


@pytest.fixture
def devices():
    """Return a factory ``devices(group, port)`` starting simulated devices 2 and 5."""
    started = []

    def factory(group: str, port: int):
        for node_id in DEVICES:
            device = SimulatedDevice(node_id, EDS, 'udp_multicast', group,
                                     bus_options={'port': port})
            device.start()
            started.append(device)
        return {device.node_id: device for device in started}

    yield factory
    for device in started:
        device.stop()


def test_installed_node_serves_sdo_nmt_and_the_cli_over_udp_multicast(
        start_node, client_node, devices, tmp_path):
    group, port = private_bus()
    namespace = f'/proc{uuid.uuid4().hex[:8]}'
    gateway_name = f'{namespace}/cbcan'
    simulated = devices(group, port)
    gateway = start_node(['-r', f'__ns:={namespace}',
                          '-p', 'can.interface:=udp_multicast',
                          '-p', f'can.channel:={group}',
                          '-p', 'nodes:=[2, 5]',
                          '-p', 'heartbeat.timeout:=1.0',
                          '-p', 'state_publish_period:=0.2'], port)

    states = []
    client_node.create_subscription(NodeStates, f'{gateway_name}/node_states',
                                    states.append, NODE_STATES_QOS)

    def client(service_type, service: str):
        return service_client(client_node, service_type, f'{gateway_name}/{service}', gateway)

    def latest_states():
        return {n.node_id: n.state_name for n in states[-1].nodes} if states else {}

    sdo_read = client(SdoRead, 'sdo_read')
    sdo_write = client(SdoWrite, 'sdo_write')
    nmt_command = client(NmtCommand, 'nmt_command')
    nmt_state = client(NmtState, 'nmt_state')

    # Heartbeats of the devices in this process reach the gateway in the other one.
    wait_until(lambda: latest_states() == {2: 'PRE_OPERATIONAL', 5: 'PRE_OPERATIONAL'},
               10.0, f'both devices PRE_OPERATIONAL on the topic (last {latest_states()})')

    response = call(sdo_read, SdoRead.Request(node_id=5, index=0x1000),
                    'sdo_read 5 0x1000', gateway)
    assert response.success, response.message
    assert bytes(response.data) == bytes([0x92, 0x01, 0x02, 0x00])

    written = bytes([0xEF, 0xBE, 0xAD, 0xDE])
    response = call(sdo_write, SdoWrite.Request(
        node_id=5, index=0x2002, subindex=0, data=list(written)), 'sdo_write 5 0x2002', gateway)
    assert response.success, response.message
    assert simulated[5].node.sdo[0x2002].raw == 0xDEADBEEF  # it reached the device itself
    response = call(sdo_read, SdoRead.Request(node_id=5, index=0x2002),
                    'sdo_read 5 0x2002', gateway)
    assert (response.success, bytes(response.data)) == (True, written), response.message

    response = call(nmt_command, NmtCommand.Request(
        node_id=5, command=NmtCommand.Request.START), 'nmt_command 5 START', gateway)
    assert response.success, response.message
    wait_until(lambda: latest_states() == {2: 'PRE_OPERATIONAL', 5: 'OPERATIONAL'}, 10.0,
               f'node 5 OPERATIONAL on the topic (last {latest_states()})')
    response = call(nmt_state, NmtState.Request(node_id=5), 'nmt_state 5',
                    gateway)
    assert (response.success, response.state_name) == (True, 'OPERATIONAL')
    assert simulated[5].state == NmtState.Response.OPERATIONAL

    cli = subprocess.run([executable('cbcan_cli'), '--gateway', gateway_name,
                          '--wait', str(START_TIMEOUT), 'sdo-read', '5', '0x1000'],
                         capture_output=True, text=True, timeout=START_TIMEOUT + 30)
    assert cli.returncode == 0, cli.stdout + cli.stderr
    assert '92 01 02 00' in cli.stdout and '0x00020192' in cli.stdout, cli.stdout

    accesses = tmp_path / 'accesses.txt'
    accesses.write_text('# a comment, then a read of what the arguments wrote\nr:5:0x2001\n')
    cli = subprocess.run([executable('cbcan_cli'), '--gateway', gateway_name,
                          '--wait', str(START_TIMEOUT), 'sdo-batch', 'r:5:0x1000',
                          'w:5:0x2001:0:3412', 'r:5:0x6000', '--file', str(accesses)],
                         capture_output=True, text=True, timeout=START_TIMEOUT + 30)
    assert cli.returncode == 1, cli.stdout + cli.stderr  # one access failed
    lines = cli.stdout.splitlines()
    assert lines[0].endswith('read  node 5 0x1000:00  ok  92 01 02 00'), lines
    assert lines[1].endswith('write node 5 0x2001:00  ok'), lines
    assert 'error: 0x06020000 NOT_EXIST' in lines[2], lines
    assert lines[3].endswith('read  node 5 0x2001:00  ok  34 12'), lines

    gateway.stop()
    assert gateway.process.returncode == 0, 'cbcan_node did not end cleanly on SIGINT'


def test_out_of_range_node_id_parameter_ends_the_node_with_a_message(start_node):
    group, port = private_bus()
    gateway = start_node(['-r', f'__ns:=/proc{uuid.uuid4().hex[:8]}',
                          '-p', 'can.interface:=udp_multicast',
                          '-p', f'can.channel:={group}',
                          '-p', 'nodes:=[2, 200]'], port)
    status = gateway.wait(START_TIMEOUT)
    output = gateway.output()
    assert status != 0, f'cbcan_node exited with status 0 on a bad parameter:\n{output}'
    assert 'nodes' in output and '200' in output and '1..127' in output, output


def cpu_seconds(pid: int) -> float:
    """Return the user + system CPU time a process used so far."""
    fields = open(f'/proc/{pid}/stat').read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def test_idle_nodes_do_not_spin(start_node, client_node):
    # EventsExecutor.spin() was reported to busy-wait; both nodes idle near 0 % of a core.
    plain_name = f'{namespace()}/cbcan'
    plain = start_node(arguments(plain_name, '-p', f'can.channel:={new_channel()}'))
    managed_name = f'{namespace()}/cbcan'
    managed = start_node(arguments(managed_name, '-p', f'can.channel:={new_channel()}'),
                         program='cbcan_lifecycle_node')
    service_client(client_node, SdoRead, f'{plain_name}/sdo_read', plain)
    change_state = service_client(client_node, ChangeState, f'{managed_name}/change_state',
                                  managed)
    for transition in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE):
        assert wait_for_future(change_state.call_async(ChangeState.Request(
            transition=Transition(id=transition))), 30.0).success
    time.sleep(0.5)
    before = {p: cpu_seconds(p.process.pid) for p in (plain, managed)}
    time.sleep(2.0)
    used = {p: (cpu_seconds(p.process.pid) - before[p]) / 2.0 for p in (plain, managed)}
    # A busy-wait takes what it gets of a core (half of one on a loaded machine); an idle
    # node next to nothing.
    assert used[plain] < 0.25 and used[managed] < 0.25, \
        f'idle CPU: cbcan_node {used[plain]:.0%}, cbcan_lifecycle_node {used[managed]:.0%}'
