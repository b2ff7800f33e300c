"""The ROS floor: a bare std_srvs/Trigger service, the least an rclpy service can do.

In-process it spins in a SingleThreadedExecutor of its own (as ``cbcan_node`` spins the
gateway); as a process (``python bench_trigger.py NAMESPACE``) it runs ``rclpy.spin``, rclpy's
default executor (a SingleThreadedExecutor as well). Its QoS is the gateway's SERVICE_QOS.

With ``--floor-bus '{"interface": ..., "channel": ...}'`` it serves instead the floor of an
``sdo_read``: ``<namespace>/floor_sdo_read``, the gateway's own ``SdoRead`` type, answered by a
raw python-canopen upload inside the callback, on the executor ``cbcan_node`` spins (rclpy's
EventsExecutor). That is the least any ROS gateway of a CAN bus does for a read (no checks, no
queue, no thread hand-over, the executor blocked meanwhile), so a target below it cannot be met
by a gateway of rclpy and python-canopen.
"""

import argparse
import json
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


class FloorSdoRead:
    """``<namespace>/floor_sdo_read``: a raw python-canopen upload inside an rclpy callback."""

    def __init__(self, namespace: str, service_qos, bus: dict):
        import canopen

        from cbcan_ros.srv import SdoRead
        self._canopen = canopen
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.05
        self.network.connect(**bus)
        self._remotes = {}
        self.node = rclpy.create_node('bench_floor_sdo_read', namespace=namespace)
        self.node.create_service(SdoRead, f'{namespace}/floor_sdo_read', self._on_read,
                                 qos_profile=service_qos)

    def _on_read(self, request, response):
        remote = self._remotes.get(request.node_id)
        if remote is None:
            remote = self._canopen.RemoteNode(request.node_id, self._canopen.ObjectDictionary())
            self.network.add_node(remote)
            self._remotes[request.node_id] = remote
        try:
            response.data = list(remote.sdo.upload(request.index, request.subindex))
            response.success = True
        except self._canopen.SdoError as error:
            response.message = str(error)
        return response

    def close(self) -> None:
        """Leave the bus."""
        self.network.disconnect()


def main(argv=None) -> int:
    """Serve ``<namespace>/trigger``, or the floor of a read, until SIGINT or SIGTERM."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('namespace')
    parser.add_argument('--floor-bus', help='python-can arguments as JSON: serve '
                                            'floor_sdo_read on that bus instead')
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    exit_on_sigterm()
    node_module, gateway_node = import_retrying('cbcan_ros.ros.interface', 'cbcan_ros.ros.node')
    rclpy.init()
    floor = None
    if args.floor_bus:
        floor = FloorSdoRead(args.namespace, node_module.SERVICE_QOS, json.loads(args.floor_bus))
        node, executor = floor.node, gateway_node.make_executor()
    else:
        node, executor = TriggerNode(args.namespace, node_module.SERVICE_QOS).node, None
    send({'ready': True})
    try:
        if executor is None:
            rclpy.spin(node)
        else:
            executor.add_node(node)
            while rclpy.ok():  # spin_once, as cbcan_node spins (see make_executor)
                executor.spin_once(timeout_sec=0.5)
    except (KeyboardInterrupt, SystemExit, ExternalShutdownException):
        pass
    finally:
        if floor is not None:
            floor.close()
        node.destroy_node()
        rclpy.try_shutdown()
    progress('trigger process done')
    return 0


if __name__ == '__main__':
    sys.exit(main())
