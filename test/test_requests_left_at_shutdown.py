"""Requests that reached the gateway but that no executor took are answered when it goes.

A robot's caller whose request sits in the node's service queue when the node shuts down
(the executor stopped, or was busy with a lifecycle transition) must still get its one
answer, "shutting down", rather than wait for ever. Here no executor ever spins the gateway
node, so every request stays in that queue until ``destroy_node``.
"""

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.parameter import Parameter

from cbcan_ros.ros.interface import SERVICE_QOS
from cbcan_ros.ros.node import CbcanNode
from cbcan_ros.srv import SdoRead

from conftest import new_channel, wait_until

SILENT = 40  # a node id nobody answers
CALLS = 50
DELIVERY = 10.0  # ceiling for answers handed to ROS on their way to this process


def waiting_in(service, context) -> bool:
    """Return whether ``service`` holds a request nobody has taken."""
    wait_set = _rclpy.WaitSet(0, 0, 0, 0, 1, 0, context.handle)
    with service.handle:
        wait_set.add_service(service.handle)
        wait_set.wait(0)
        return bool(wait_set.get_ready_entities('service'))


def test_requests_no_executor_took_are_answered_shutting_down(client_node):
    node = CbcanNode(parameter_overrides=[
        Parameter('can.interface', value='virtual'),
        Parameter('can.channel', value=new_channel())])
    destroyed = False
    try:
        client = client_node.create_client(SdoRead, f'{node.get_fully_qualified_name()}/sdo_read',
                                           qos_profile=SERVICE_QOS)
        assert client.wait_for_service(timeout_sec=DELIVERY)
        calls = [client.call_async(SdoRead.Request(node_id=SILENT, index=0x1000))
                 for _ in range(CALLS)]
        service = next(s for s in node.services if s.srv_name.endswith('/sdo_read'))
        wait_until(lambda: waiting_in(service, node.context), DELIVERY,
                   'a request waiting in the service')
        node.destroy_node()
        destroyed = True
        wait_until(lambda: any(call.done() for call in calls), DELIVERY, 'the first answer')
    finally:
        if not destroyed:
            node.destroy_node()
    answers = [call.result() for call in calls if call.done()]
    for answer in answers:
        assert not answer.success and 'shutting down' in answer.message, answer.message
