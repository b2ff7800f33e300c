"""The ROS floor: a bare std_srvs/Trigger service, the least an rclpy service can do.

In-process it spins in a SingleThreadedExecutor of its own (as ``cbcan_node`` spins the
gateway); as a process (``python bench_trigger.py NAMESPACE``) it runs ``rclpy.spin``, rclpy's
default executor (a SingleThreadedExecutor as well). Its QoS is the gateway's SERVICE_QOS.
"""

import sys

from bench_util import exit_on_sigterm, import_retrying, progress, send
import rclpy
from rclpy.executors import ExternalShutdownException
from std_srvs.srv import Trigger


class TriggerNode:
    """A node with one Trigger service at ``<namespace>/trigger``."""

    def __init__(self, namespace: str, service_qos):
        self.node = rclpy.create_node('bench_trigger', namespace=namespace)
        self.node.create_service(Trigger, f'{namespace}/trigger', self._on_trigger,
                                 qos_profile=service_qos)

    @staticmethod
    def _on_trigger(_request, response):
        response.success = True
        return response


def main(argv=None) -> int:
    """Serve ``<namespace>/trigger`` until SIGINT or SIGTERM."""
    argv = sys.argv[1:] if argv is None else argv
    exit_on_sigterm()
    node_module, = import_retrying('cbcan_ros.ros.interface')
    rclpy.init()
    server = TriggerNode(argv[0], node_module.SERVICE_QOS)
    send({'ready': True})
    try:
        rclpy.spin(server.node)
    except (KeyboardInterrupt, SystemExit, ExternalShutdownException):
        pass
    finally:
        server.node.destroy_node()
        rclpy.try_shutdown()
    progress('trigger process done')
    return 0


if __name__ == '__main__':
    sys.exit(main())
