"""The installed ``cbcan_node`` as a child process, and calling its services from this one.

python-can's udp_multicast sockets bind to the port on every address: on Linux a socket hears
every group any socket of the machine joined on that port. A random group alone therefore does
not keep parallel runs apart; a random port does. The node has no parameter for the port, so
the child gets it through python-can's own environment configuration (``CAN_CONFIG``).
"""

import json
import os
import pathlib
import random
import shutil
import signal
import subprocess
import tempfile
from typing import Optional

from conftest import wait_for_future

ROOT = pathlib.Path(__file__).resolve().parent.parent
EDS = str(ROOT / 'config' / 'simulated_device.eds')
START_TIMEOUT = 15.0  # process start, parameter check, bus and DDS discovery
STOP_TIMEOUT = 5.0


def executable(name: str) -> str:
    """Return the path of an installed executable (tools/ros-env puts them on PATH)."""
    path = shutil.which(name)
    assert path, f'{name} is not on PATH: run the tests through tools/ros-env after make build'
    return path


def random_bus():
    """Return (IPv4 multicast group, UDP port) for this test run only."""
    group = f'239.{random.randint(1, 254)}.{random.randint(0, 255)}.{random.randint(1, 254)}'
    return group, random.randint(20000, 40000)


class NodeProcess:
    """A gateway node in a child process; its output goes to a file, read on failure."""

    def __init__(self, arguments, port: Optional[int] = None, program: str = 'cbcan_node'):
        self._output = tempfile.TemporaryFile(mode='w+')
        env = dict(os.environ)
        if port is not None:
            env['CAN_CONFIG'] = json.dumps({'port': port})
        self.process = subprocess.Popen([executable(program), '--ros-args', *arguments],
                                        stdout=self._output, stderr=subprocess.STDOUT,
                                        env=env, text=True)

    def output(self) -> str:
        """Return everything the process printed so far."""
        self._output.flush()
        self._output.seek(0)
        return self._output.read()

    def wait(self, timeout: float) -> int:
        """Wait for the process to end by itself; fail the test after ``timeout`` seconds."""
        try:
            return self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f'cbcan_node still running after {timeout} s:\n'
                                 f'{self.output()}') from None

    def stop(self) -> None:
        """Interrupt the process as Ctrl-C does, then kill it if it does not end in time."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(STOP_TIMEOUT)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(STOP_TIMEOUT)

    def close(self) -> None:
        """Stop the process and drop its output."""
        self.stop()
        self._output.close()


def call(client, request, what: str, gateway: NodeProcess, timeout: float = 10.0):
    """Call a service and return the response, with the node's output on failure."""
    try:
        return wait_for_future(client.call_async(request), timeout)
    except AssertionError as error:
        raise AssertionError(f'{what}: {error}\ncbcan_node output:\n{gateway.output()}') \
            from None


def service_client(client_node, service_type, name: str, gateway: NodeProcess):
    """Return a client of the child's service ``name``, failing with its output if absent."""
    from cbcan_ros.ros.interface import SERVICE_QOS
    made = client_node.create_client(service_type, name, qos_profile=SERVICE_QOS)
    if not made.wait_for_service(timeout_sec=START_TIMEOUT):
        raise AssertionError(f'{name} did not appear within {START_TIMEOUT} s (exit status '
                             f'{gateway.process.poll()}):\n{gateway.output()}')
    return made
