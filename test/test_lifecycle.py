"""The managed node ``cbcan_lifecycle_node``, driven through its lifecycle services.

The node runs as a separate process with a simulated device on a udp_multicast bus; this
process plays ``ros2 lifecycle set`` (lifecycle_msgs/ChangeState) and the robot's callers.
"""

import uuid

from diagnostic_msgs.msg import DiagnosticArray
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rcl_interfaces.msg import Parameter as ParameterMessage
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters

from cbcan_ros.msg import LssIdentity, NodeStates, SdoAccess
from cbcan_ros.ros.interface import NODE_STATES_QOS
from cbcan_ros.srv import (
    LssConfigure,
    LssInquire,
    LssScan,
    NmtCommand,
    NmtState,
    PdoWrite,
    RegisterMailbox,
    SdoBatch,
    SdoRead,
    SdoWrite,
)

from conftest import wait_until
from node_process import call, random_bus, service_client

INACTIVE_ABORT = 0x08000022
DEVICE = 2


def test_transitions_open_serve_refuse_and_close_the_bus(start_node, client_node):
    group, port = random_bus()
    namespace = f'/life{uuid.uuid4().hex[:8]}'
    name = f'{namespace}/cbcan'
    node = start_node(['-r', f'__ns:={namespace}',
                       '-p', 'can.interface:=not_an_interface',  # fixed before configure
                       '-p', f'can.channel:={group}',
                       '-p', f'simulation.devices:=[{DEVICE}]',
                       '-p', f'nodes:=[{DEVICE}]',
                       '-p', f'pdo.nodes:=[{DEVICE}]',
                       '-p', 'state_publish_period:=0.2',
                       '-p', 'diagnostics_period:=0.1'], port, 'cbcan_lifecycle_node')

    def client(service_type, service: str):
        return service_client(client_node, service_type, f'{name}/{service}', node)

    change_state = client(ChangeState, 'change_state')
    get_state = client(GetState, 'get_state')
    set_parameters = client(SetParameters, 'set_parameters')

    def state() -> str:
        return call(get_state, GetState.Request(), 'get_state', node).current_state.label

    def transition(transition_id: int) -> bool:
        request = ChangeState.Request(transition=Transition(id=transition_id))
        return call(change_state, request, f'transition {transition_id}', node).success

    states, diagnostics = [], []
    client_node.create_subscription(NodeStates, f'{name}/node_states', states.append,
                                    NODE_STATES_QOS)

    def ours(array: DiagnosticArray) -> None:
        if any(status.name.startswith(f'{name}:') for status in array.status):
            diagnostics.append(array)

    client_node.create_subscription(DiagnosticArray, '/diagnostics', ours, 10)
    assert state() == 'unconfigured'
    service_names = [n for n, _ in client_node.get_service_names_and_types()]
    assert f'{name}/sdo_read' not in service_names

    # A wrong parameter fails configure, named in the log; fixed, configure succeeds.
    assert not transition(Transition.TRANSITION_CONFIGURE)
    assert state() == 'unconfigured'
    wait_until(lambda: 'parameter can.interface' in node.output(), 5.0,
               f'the configure failure naming the parameter in:\n{node.output()}')
    fixed = ParameterMessage(name='can.interface', value=ParameterValue(
        type=ParameterType.PARAMETER_STRING, string_value='udp_multicast'))
    result = call(set_parameters, SetParameters.Request(parameters=[fixed]), 'set', node)
    assert result.results[0].successful, result.results[0].reason
    assert transition(Transition.TRANSITION_CONFIGURE)
    assert state() == 'inactive'

    sdo_read = client(SdoRead, 'sdo_read')
    read = SdoRead.Request(node_id=DEVICE, index=0x1000, timeout=2.0)

    def refused_while_inactive() -> None:
        answer = call(sdo_read, read, 'sdo_read while inactive', node)
        assert not answer.success
        assert answer.abort_code == INACTIVE_ABORT
        assert 'inactive' in answer.message
        answer = call(client(SdoWrite, 'sdo_write'), SdoWrite.Request(
            node_id=DEVICE, index=0x2002, data=[1, 2, 3, 4]), 'sdo_write', node)
        assert (answer.success, answer.abort_code) == (False, INACTIVE_ABORT)
        batch = call(client(SdoBatch, 'sdo_batch'), SdoBatch.Request(
            accesses=[SdoAccess(node_id=DEVICE, index=0x1000)] * 2), 'sdo_batch', node)
        assert [(r.success, r.abort_code) for r in batch.results] == \
            [(False, INACTIVE_ABORT)] * 2
        answer = call(client(NmtCommand, 'nmt_command'), NmtCommand.Request(
            node_id=DEVICE, command=1), 'nmt_command', node)
        assert not answer.success and 'inactive' in answer.message
        assert answer.abort_code == INACTIVE_ABORT
        answer = call(client(NmtState, 'nmt_state'), NmtState.Request(node_id=DEVICE),
                      'nmt_state', node)
        assert not answer.success and 'inactive' in answer.message
        assert answer.abort_code == INACTIVE_ABORT
        registers = [0] * 26
        answer = call(client(RegisterMailbox, 'plc_mailbox'), RegisterMailbox.Request(
            format='cbcan', registers=registers), 'plc_mailbox', node)
        assert list(answer.registers) == registers and 'inactive' in answer.message
        for service_type, service, request in (
                (LssScan, 'lss_scan', LssScan.Request(first_node_id=10)),
                (LssConfigure, 'lss_configure', LssConfigure.Request(
                    identity=LssIdentity(serial=7), node_id=10)),
                (LssInquire, 'lss_inquire', LssInquire.Request(identity=LssIdentity()))):
            answer = call(client(service_type, service), request, service, node)
            assert not answer.success and 'inactive' in answer.message
        answer = call(client(PdoWrite, 'pdo_write'), PdoWrite.Request(
            node_id=DEVICE, pdo=1, data=[1, 2, 3]), 'pdo_write', node)
        assert (answer.success, answer.abort_code) == (False, INACTIVE_ABORT)

    refused_while_inactive()
    assert not states and not diagnostics, 'nothing is published before activate'

    assert transition(Transition.TRANSITION_ACTIVATE)
    assert state() == 'active'
    answer = call(sdo_read, read, 'sdo_read while active', node)
    assert answer.success, answer.message
    assert bytes(answer.data) == bytes([0x92, 0x01, 0x02, 0x00])
    wait_until(lambda: states and [n.node_id for n in states[-1].nodes] == [DEVICE], 5.0,
               'node_states published once active')
    wait_until(lambda: diagnostics, 5.0, '/diagnostics published once active')

    assert transition(Transition.TRANSITION_DEACTIVATE)
    assert state() == 'inactive'
    refused_while_inactive()

    # Cleanup closes the bus; configure and activate open it again.
    assert transition(Transition.TRANSITION_CLEANUP)
    assert state() == 'unconfigured'
    wait_until(lambda: 'is closed' in node.output(), 5.0, 'the bus closed by cleanup')
    assert transition(Transition.TRANSITION_CONFIGURE)
    assert transition(Transition.TRANSITION_ACTIVATE)
    answer = call(sdo_read, read, 'sdo_read after a second configure', node)
    assert answer.success, answer.message

    assert transition(Transition.TRANSITION_ACTIVE_SHUTDOWN)
    assert state() == 'finalized'
    node.stop()
    assert node.process.returncode == 0, node.output()
    assert node.output().count('is closed') == 2
