"""Shared test harness: the gateway node in-process on a private virtual bus, with rclpy clients.

Every gateway gets its own python-can ``virtual`` channel, and every test process its own
ROS_DOMAIN_ID (set before rclpy starts, held with a lock for the life of the process), so
parallel workers and parallel runs of the suite never hear each other.
"""

import fcntl
import os
import pathlib
import tempfile
import threading
import time
import uuid

# ROS domain ids a test process may take. 0 is every ROS system's default; up to 101 the
# DDS ports of a domain stay below Linux's ephemeral port range (ROS 2's "domain ID" page).
DOMAIN_IDS = range(1, 102)
DOMAIN_LOCKS = pathlib.Path(tempfile.gettempdir()) / 'cbcan_ros-test-domains'


def claim_domain_id() -> int:
    """Return the first ROS domain id no other running test process holds, and hold it.

    The lock (flock on one file per id) lasts as long as this process and ends with it,
    however it ends; a random id would let two workers or two clones meet by chance.
    """
    DOMAIN_LOCKS.mkdir(mode=0o1777, exist_ok=True)
    for domain in DOMAIN_IDS:
        lock = os.open(DOMAIN_LOCKS / f'{domain}.lock', os.O_RDONLY | os.O_CREAT, 0o666)
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(lock)
            continue
        return domain  # the descriptor stays open (and is not inherited by children)
    raise RuntimeError(f'every ROS domain id {DOMAIN_IDS.start}..{DOMAIN_IDS.stop - 1} is held '
                       f'by another test process (locks in {DOMAIN_LOCKS})')


DOMAIN_ID = claim_domain_id()
os.environ['ROS_DOMAIN_ID'] = str(DOMAIN_ID)
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

import can  # noqa: E402
import pytest  # noqa: E402
import rclpy  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from cbcan_ros.msg import NodeStates  # noqa: E402
from cbcan_ros.ros.interface import NODE_STATES_QOS, SERVICE_QOS  # noqa: E402
from cbcan_ros.ros.node import CbcanNode  # noqa: E402
from cbcan_ros.srv import (  # noqa: E402
    Boot,
    DriveCommand,
    LssConfigure,
    LssInquire,
    LssScan,
    NmtCommand,
    NmtState,
    PdoWrite,
    RegisterMailbox,
    SdoRead,
    SdoWrite,
    SendFrames,
)

SERVICE_TYPES = {
    'sdo_read': SdoRead,
    'sdo_write': SdoWrite,
    'nmt_command': NmtCommand,
    'nmt_state': NmtState,
    'plc_mailbox': RegisterMailbox,
    'lss_scan': LssScan,
    'lss_configure': LssConfigure,
    'lss_inquire': LssInquire,
    'pdo_write': PdoWrite,
    'drive_command': DriveCommand,
    'send_frames': SendFrames,
    'boot': Boot,
}

DEFAULT_DEVICES = [2, 3, 5]


# Tests that load both cores by themselves (bursts of a thousand calls, a 2,000-call
# shutdown, 66 concurrent callers, the soak): `make test` runs four workers with
# `--dist loadgroup`, which sends them all to one worker, so no two of them overlap and
# their time bounds stay fair.
HEAVY = pytest.mark.xdist_group('heavy')


def new_channel() -> str:
    """Return a python-can channel name no other test uses."""
    return f'test-{uuid.uuid4().hex[:8]}'


def frames_within(bus: can.BusABC, seconds: float) -> list:
    """Return the frames ``bus`` receives in the next ``seconds`` (what a command sent)."""
    frames, until = [], time.monotonic() + seconds
    while time.monotonic() < until:
        message = bus.recv(0.05)
        if message is not None:
            frames.append(message)
    return frames


def wait_until(condition, timeout: float, what: str):
    """Wait for ``condition()`` to become truthy, failing the test after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f'timed out after {timeout} s waiting for {what}')
        time.sleep(0.005)


def wait_for_future(future, timeout: float):
    """Wait for an rclpy future: on its done-callback, and on done() for the known race."""
    finished = threading.Event()
    future.add_done_callback(lambda _: finished.set())
    deadline = time.monotonic() + timeout
    while not future.done():
        if time.monotonic() > deadline:
            raise AssertionError(f'no answer within {timeout} s')
        finished.wait(0.01)
    return future.result()


def frames_before_marker(gateway, bus: can.BusABC, timeout: float = 60.0):
    """Return the SDO request frames the gateway sent before a marker read of node 3.

    Frames arrive in order, so whatever an earlier call sent (a repeat included) is on the
    bus before the marker's request.
    """
    assert gateway.call('sdo_read', node_id=3, index=0x1000, subindex=0).success
    frames = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        message = bus.recv(0.1)
        if message is None or not 0x600 <= message.arbitration_id <= 0x67F:
            continue
        if message.arbitration_id == 0x603:
            return frames
        frames.append(message)
    raise AssertionError('the marker request was not seen on the bus')


class Spinning:
    """Spins ``executor`` in a thread of its own until :meth:`stop`.

    rclpy's ``Executor.shutdown`` waits for running callbacks only, not for a thread that is
    building its wait set; it then destroys the guard condition that thread is about to use
    (AttributeError in the spinning thread, seen on a busy machine). So the thread stops
    spinning first, and the executor is shut down after it has ended.
    """

    def __init__(self, executor):
        self.executor = executor
        self._stopping = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while not self._stopping.is_set():
            self.executor.spin_once(timeout_sec=0.05)

    def stop(self) -> None:
        """End the spinning thread, then shut the executor down."""
        self._stopping.set()
        self.thread.join(timeout=30.0)
        self.executor.shutdown()


class Harness:
    """The gateway node under test, its simulated devices, a raw view of the bus, clients."""

    def __init__(self, parameters: dict):
        self.channel = parameters.get('can.channel') or new_channel()
        overrides = {'can.interface': 'virtual', 'can.channel': self.channel,
                     'simulation.devices': DEFAULT_DEVICES}
        overrides.update(parameters)
        self.node = CbcanNode(parameter_overrides=[
            Parameter(name, value=value) for name, value in overrides.items()
            if value is not None])  # None leaves a parameter at its default
        self.client_node = rclpy.create_node(f'test_client_{uuid.uuid4().hex[:8]}')
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.executor.add_node(self.client_node)
        self._clients = {}
        self.states = []
        self._states_lock = threading.Lock()
        self.client_node.create_subscription(NodeStates, '/cbcan/node_states',
                                             self._on_states, NODE_STATES_QOS)
        self._spinning = Spinning(self.executor)

    def device(self, node_id: int):
        """Return the simulated device with ``node_id``."""
        return next(d for d in self.node.interface.simulated_devices if d.node_id == node_id)

    def client(self, service: str):
        """Return (creating once) a client of the gateway's ``service``."""
        if service not in self._clients:
            client = self.client_node.create_client(SERVICE_TYPES[service],
                                                    f'/cbcan/{service}', qos_profile=SERVICE_QOS)
            assert client.wait_for_service(timeout_sec=10.0), f'{service} not available'
            self._clients[service] = client
        return self._clients[service]

    def call(self, service: str, wait: float = 30.0, **fields):
        """Call a gateway service with the request ``fields`` and return the response."""
        request = SERVICE_TYPES[service].Request(**fields)
        return wait_for_future(self.client(service).call_async(request), wait)

    def call_async(self, service: str, **fields):
        """Send a request without waiting; returns the rclpy future."""
        return self.client(service).call_async(SERVICE_TYPES[service].Request(**fields))

    def raw_bus(self) -> can.BusABC:
        """Open a raw python-can bus on the gateway's virtual channel (caller shuts it down)."""
        return can.Bus(interface='virtual', channel=self.channel)

    def _on_states(self, message) -> None:
        with self._states_lock:
            self.states.append(message)

    def latest_states(self):
        """Return {node_id: state_name} of the latest NodeStates message, or None."""
        with self._states_lock:
            if not self.states:
                return None
            return {n.node_id: n.state_name for n in self.states[-1].nodes}

    def wait_for_states(self, expected: dict, timeout: float = 10.0):
        """Wait until the topic shows every node in ``expected`` ({id: state_name})."""
        def matches():
            latest = self.latest_states()
            return latest is not None and all(
                latest.get(node_id) == name for node_id, name in expected.items())
        return wait_until(matches, timeout, f'node states {expected} on the topic '
                                            f'(last seen {self.latest_states()})')

    def close(self) -> None:
        """Stop spinning, destroy the nodes and close the bus."""
        self._spinning.stop()
        self.client_node.destroy_node()
        self.node.destroy_node()


@pytest.fixture
def measured(record_property):
    """Return ``measured(text)``: a measurement shown at the end of every run's output.

    It travels as a property of the test's report, so it is shown with two workers too.
    """
    return lambda text: record_property('measured', text)


def pytest_terminal_summary(terminalreporter):
    """Print the measurements tests reported with the ``measured`` fixture."""
    lines = [f'{report.nodeid}: {value}'
             for reports in terminalreporter.stats.values() for report in reports
             if getattr(report, 'when', '') == 'call'
             for name, value in report.user_properties if name == 'measured']
    if lines:
        terminalreporter.section('measured')
        for line in lines:
            terminalreporter.write_line(line)


@pytest.fixture(scope='session', autouse=True)
def ros_context():
    """Start rclpy once for the whole session."""
    rclpy.init()
    yield
    rclpy.try_shutdown()


@pytest.fixture
def make_gateway():
    """Return a factory: ``make_gateway(**parameters)`` starts a gateway node on its own bus."""
    harnesses = []

    def factory(**parameters):
        harness = Harness({name.replace('__', '.'): value for name, value in parameters.items()})
        harnesses.append(harness)
        return harness

    yield factory
    for harness in harnesses:
        harness.close()


@pytest.fixture
def gateway(make_gateway):
    """Start a gateway node with simulated devices 2, 3 and 5 on a private virtual bus."""
    return make_gateway()


@pytest.fixture
def start_durand():
    """Return ``start_durand(node_id, kind=DurandDevice, **options)``: a started durand device.

    durand is the independent device stack (``DurandDevice`` and its options; ``kind`` may be
    a subclass, such as the drive); every device the factory started is stopped after the test.
    """
    from cbcan_ros.simulation.durand.device import DurandDevice
    started = []

    def factory(node_id: int, kind=DurandDevice, **options):
        device = kind(node_id, **options)
        device.start()
        started.append(device)
        return device

    yield factory
    for device in started:
        device.stop()


@pytest.fixture
def durand_device(start_durand):
    """Return a factory ``durand_device(interface, channel, **options)`` for a device 2.

    The device holds 64 KiB in its DOMAIN 0x2020.
    """
    def factory(interface: str, channel: str, **options):
        device = start_durand(2, interface=interface, channel=channel,
                              bus_options=options or None)
        device.set_value(0x2020, 0, bytes(range(256)) * 256)
        return device
    return factory


@pytest.fixture
def start_node():
    """Return a factory ``start_node(arguments, port=None, program='cbcan_node')``.

    Every process it starts is ended after the test.
    """
    import node_process  # it imports this module: a top-level import would be circular

    processes = []

    def factory(arguments, port=None, program='cbcan_node') -> 'node_process.NodeProcess':
        process = node_process.NodeProcess(arguments, port, program)
        processes.append(process)
        return process

    yield factory
    for process in processes:
        process.close()


@pytest.fixture
def client_node():
    """Yield an rclpy node of this process, spun by an executor in a thread of its own."""
    node = rclpy.create_node(f'process_test_{uuid.uuid4().hex[:8]}')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinning = Spinning(executor)
    yield node
    spinning.stop()
    node.destroy_node()
