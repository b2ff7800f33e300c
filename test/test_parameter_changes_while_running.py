"""A parameter set while the gateway runs is refused, not taken and ignored.

The gateway reads its parameters when it starts (a managed node: at configure). rclpy would
accept a change of any of them and keep the new value, which the gateway never reads: a
user told by a message to set one (``program_download.restart_timeout``) would see it set
and nothing change.
"""

from rclpy.parameter import Parameter

from conftest import Harness


def test_a_parameter_set_while_the_node_runs_is_refused_and_keeps_its_value(ros_context):
    harness = Harness({'simulation.devices': None})
    try:
        node = harness.node
        result, = node.set_parameters([Parameter('program_download.restart_timeout',
                                                 value=5.0)])
        assert not result.successful
        assert 'reads its parameters when it starts' in result.reason, result.reason
        assert node.get_parameter('program_download.restart_timeout').value == 0.0
        assert node.gateway.config.program.restart_timeout == 0.0
    finally:
        harness.close()
