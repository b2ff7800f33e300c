"""The installed ``cbcan_node`` as a child process, and calling its services from this one.

python-can's udp_multicast sockets bind to the port on every address: on Linux a socket hears
every group any socket of the machine joined on that port. A group of its own therefore does
not keep parallel runs apart; a port of its own does: each test process takes its ports from a
block that belongs to its ROS domain id, which no other running test process holds
(conftest.claim_domain_id). The node has no parameter for the port, so the child gets it
through python-can's own environment configuration (``CAN_CONFIG``).
"""

import itertools
import json
import os
import pathlib
import shutil
import signal
import subprocess
import tempfile
import threading
import time
from typing import Optional
import uuid

import can

from cbcan_ros.core.python_can_gaps.receive_buffer import deepen_receive_buffer
from cbcan_ros.msg import NodeStates
from cbcan_ros.ros.interface import NODE_STATES_QOS
from cbcan_ros.ros.node import SHUTDOWN_LIMIT

from conftest import DOMAIN_ID, DOMAIN_IDS, wait_for_future, wait_until

ROOT = pathlib.Path(__file__).resolve().parent.parent
EDS = str(ROOT / 'config' / 'simulated_device.eds')
# Ceilings for what only a defect makes slow (a quiet machine needs a few seconds at most):
# a process start (Python, rclpy, the parameter check, the bus, DDS discovery) with two
# test workers and other work on 2 cores, and the end of a process after its signal (the
# node's own promise, SHUTDOWN_LIMIT, plus the time to see it gone).
START_TIMEOUT = 60.0
STOP_TIMEOUT = SHUTDOWN_LIMIT + 5.0


def executable(name: str) -> str:
    """Return the path of an installed executable (tools/ros-env puts them on PATH)."""
    path = shutil.which(name)
    assert path, f'{name} is not on PATH: run the tests through tools/ros-env after make build'
    return path


# UDP ports of the buses: above Linux's ephemeral range (32768..60999) and the DDS ports of
# every domain id, a block per domain id.
PORTS = 61000
PORTS_PER_DOMAIN = (65536 - PORTS) // DOMAIN_IDS.stop
_buses = itertools.count()


def namespace() -> str:
    """Return a ROS namespace no other test uses."""
    return f'/proc{uuid.uuid4().hex[:8]}'


def arguments(name: str, *more: str) -> list:
    """Return the node's command line arguments for the node name ``/<namespace>/cbcan``."""
    return ['-r', f'__ns:={name.rsplit("/", 1)[0]}', *more]


def private_bus():
    """Return (IPv4 multicast group, UDP port) no other test or test process uses now.

    A test process uses its ports one after another, round the block: a port comes back
    only after PORTS_PER_DOMAIN more buses, long after the test that had it ended.
    """
    number = next(_buses) % PORTS_PER_DOMAIN
    return f'239.192.{DOMAIN_ID}.{number + 1}', PORTS + PORTS_PER_DOMAIN * DOMAIN_ID + number


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


class BusRecorder:
    """Every frame on a udp_multicast bus, with the time it arrived here.

    Its socket gets the gateway's deep receive buffer: with the default one (some 250
    frames) a recording thread held up 0.1 s on a loaded machine loses frames of a burst of
    a few thousand a second, and a test then misses a frame that was on the bus.
    """

    def __init__(self, group: str, port: int):
        self._bus = can.Bus(interface='udp_multicast', channel=group, port=port)
        deepen_receive_buffer(self._bus)
        self.frames = []
        self._running = True
        self._thread = threading.Thread(target=self._record, daemon=True)
        self._thread.start()

    def _record(self) -> None:
        while self._running:
            message = self._bus.recv(0.05)
            if message is not None:
                self.frames.append((time.monotonic(), message))

    def dropped(self) -> int:
        """Return how many datagrams the kernel dropped for the recording socket."""
        inode = str(os.fstat(self._bus.fileno()).st_ino)
        for line in pathlib.Path('/proc/net/udp').read_text().splitlines()[1:]:
            fields = line.split()
            if fields[9] == inode:
                return int(fields[-1])
        return 0

    def close(self) -> None:
        """Stop recording and close the bus."""
        self._running = False
        self._thread.join()
        self._bus.shutdown()


class StateWatcher:
    """The node_states topic of a gateway, as a subscriber in this process sees it."""

    def __init__(self, client_node, gateway_name: str):
        self.messages = []
        client_node.create_subscription(NodeStates, f'{gateway_name}/node_states',
                                        self.messages.append, NODE_STATES_QOS)

    def latest(self) -> dict:
        """Return {node_id: state_name} of the latest message."""
        return {n.node_id: n.state_name for n in self.messages[-1].nodes} \
            if self.messages else {}

    def wait_for(self, expected: dict, timeout: float) -> None:
        """Wait until the latest message shows exactly ``expected``."""
        wait_until(lambda: self.latest() == expected, timeout,
                   f'node states {expected} (last {self.latest()})')
