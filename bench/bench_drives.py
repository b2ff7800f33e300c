"""Drive (CiA 402) benchmarks: enable time, target latency, load; each beside its baseline.

Run by ``make bench`` after ``bench_pdo.py`` (``make bench ARGS=--quick`` shortens it); writes
``drives.md`` and ``drives.json`` in ``bench/out/`` (``--output``), the nodes' logs next to
them. A script, not a test: a target that is not met is reported, never fatal.
Every figure that has a target is a ratio to something measured side by side in the same run,
because the machine it runs on may be busy with other work.

Processes: the installed ``cbcan_node`` on a udp_multicast bus of its own; the simulated
drives (``DurandDrive``, ``bench_drive_host.py drives``) in a process of their own, so that
the node's CPU is the gateway's alone; this process, the ROS caller and python canopen.

1. Enable time, SWITCH_ON_DISABLED to OPERATION_ENABLED in CSV: ``~/drive_command enable``
   as a ROS caller sees it (the round trip) against python canopen's ``BaseNode402``
   (``node.state = 'OPERATION ENABLED'``, set up with ``setup_402_state_machine()`` as its
   documentation shows), on a second udp_multicast bus with a drive of the same kind in a
   drive process of its own, as the gateway's. One after the other, alternating which goes
   first, disabled between; both drives are already in CSV. A receiver process on each bus
   times the frames, to show where the time goes. Measured on the ``combined`` PDO layout
   and again on the ``vendor`` one (the controlword in every RPDO, as EPOS2 EDS files ship).
   Target: at most 1.0 x (BaseNode402 + a bare ``std_srvs/Trigger`` round trip). Beside
   them, the floor: BaseNode402 inside a bare rclpy ``DriveCommand`` callback on a third bus
   (``bench_drive_host.py enable-floor``), the least any ROS gateway of python canopen does;
   and the free floor: the same enable on a worker thread that answers when done, so the
   executor stays free meanwhile, as a gateway's must (its other calls and topics go on).
2. Target latency: a ``std_msgs/Float64`` published on ``~/node_1/target`` until the RPDO
   frame with that target velocity reaches a raw python-can receiver in this process (drive
   enabled in CSV, asynchronous RPDOs, ``drives.command_timeout`` 0). Beside it, alternating
   sample by sample: the same message through a bare rclpy relay process
   (``bench_drive_host.py relay``: subscription to ``bus.send``), and one frame sent and
   received on the same bus by this process.
3. Load: 8 drives, SYNC every 10 ms (``sync.period`` 0.01), synchronous TPDOs and RPDOs
   (``default_drive_pdos(1)``), all enabled in CSV: ``~/joint_states`` messages a second at
   this process, and the node's CPU beside a bare python-can receiver process's
   (``bench_drive_host.py reader``), both over the same window, from /proc. The 8 drives
   share one socket in their process (``--shared-socket``): with a socket each they missed
   SYNCs on a busy machine, and the row says so whenever fewer TPDOs come than SYNCs ask.
"""

import argparse
import contextlib
import json
import os
import random
import shutil
import struct
import sys
import threading
import time
from typing import Callable, Dict, List, Optional
import uuid

from bench_report import machine_info
from bench_sdo import Child, ChildFailed, python
from bench_util import logs_to, OUTPUT, percentile, proc_cpu_seconds, progress, ros_of_its_own

START_TIMEOUT = 60.0
CALL_TIMEOUT = 10.0
CSV = 9
NMT_START = 1
DRIVE = 1  # node id of the drive in rows 1 and 2
LOAD_DRIVES = tuple(range(1, 9))
TARGET_COB_ID = 0x300 + DRIVE  # RPDO 2 of the default mapping: target velocity, torque
RELAY_COB_ID = 0x37F  # bench_drive_host.RELAY_COB_ID
SYNC_PERIOD = 0.01
# The enable row's target: the round trip at most this times BaseNode402's enable of the same
# drive plus a bare std_srvs/Trigger round trip (the floor of any ROS call).
ENABLE_TARGET = 1.0


class UdpBus:
    """A private udp_multicast bus: a random group and port (unless given), as no other run has."""

    def __init__(self, group: Optional[str] = None, port: Optional[int] = None):
        self.group = group or (f'239.{random.randint(1, 254)}.{random.randint(0, 255)}.'
                               f'{random.randint(1, 254)}')
        self.port = port or random.randint(20000, 40000)

    def arguments(self) -> List[str]:
        """Return the bench_drive_host.py arguments naming this bus."""
        return ['--channel', self.group, '--bus-options', json.dumps({'port': self.port})]

    def open(self):
        """Return a raw python-can bus on it."""
        import can
        return can.Bus(interface='udp_multicast', channel=self.group, port=self.port)


def start_helper(name: str, mode: str, bus: UdpBus, *extra: str) -> Child:
    """Start ``bench_drive_host.py mode`` on ``bus``; return it once it says it is ready."""
    child = Child(name, python('bench_drive_host.py', mode, *bus.arguments(), *extra))
    try:
        child.expect('ready', START_TIMEOUT)
    except ChildFailed:
        print(child.output(), file=sys.stderr)
        raise
    return child


@contextlib.contextmanager
def bench_session(output: str, name: str, quick: bool):
    """Run a bench script's measurements as a ROS program; yield ``(caller, machine)``.

    Its nodes' logs go to ``<output>/<name>_logs.txt``, its processes to a ROS domain of
    their own; rclpy is started with a :class:`Caller`. Ctrl-C ends the measurements (the
    report then says so in ``machine['interrupted']``); on the way out every child process
    is stopped, rclpy shut down, and the load after, the duration and ``quick`` are added to
    ``machine`` (this machine, as the report shows it).
    """
    logs_to(os.path.join(output, f'{name}_logs.txt'))
    ros_of_its_own()
    import rclpy
    machine = machine_info()
    started = time.monotonic()
    rclpy.init()
    caller = Caller()
    try:
        yield caller, machine
    except KeyboardInterrupt:
        machine['interrupted'] = 'Ctrl-C: the rows after that point are missing'
        progress('interrupted')
    finally:
        Child.stop_all()
        caller.close()
        rclpy.try_shutdown()
        machine['load_after'] = ' '.join(f'{v:.2f}' for v in os.getloadavg())
        machine['duration_s'] = round(time.monotonic() - started, 1)
        machine['quick'] = quick


class NodeProcess:
    """The installed cbcan_node in its own process on ``bus``, its log in ``log_path``."""

    def __init__(self, bus: UdpBus, parameters: Dict[str, str], log_path: str):
        import subprocess
        self.name = f'/benchdrive{uuid.uuid4().hex[:8]}/cbcan'
        executable = shutil.which('cbcan_node')
        if not executable:
            raise SystemExit('cbcan_node is not on PATH (run through make bench)')
        arguments = [executable, '--ros-args', '-r', f'__ns:={self.name.rpartition("/")[0]}',
                     '-p', 'can.interface:=udp_multicast', '-p', f'can.channel:={bus.group}']
        for name, value in parameters.items():
            arguments += ['-p', f'{name}:={value}']
        self._log = open(log_path, 'w')
        self.process = subprocess.Popen(
            arguments, stdout=self._log, stderr=subprocess.STDOUT,
            env={**os.environ, 'CAN_CONFIG': json.dumps({'port': bus.port})})

    @property
    def pid(self) -> int:
        """Return the process id."""
        return self.process.pid

    def close(self) -> None:
        """End the node process (SIGTERM, as a launch file stops it)."""
        self.process.terminate()
        try:
            self.process.wait(15)
        except Exception:  # noqa: BLE001 - whatever it is, it must not outlive the bench
            self.process.kill()
            self.process.wait(5)
        self._log.close()


class Caller:
    """This process as a ROS program: service clients and topics, an executor spinning."""

    def __init__(self):
        import rclpy
        from rclpy.experimental import EventsExecutor
        self.node = rclpy.create_node(f'bench_drives_{uuid.uuid4().hex[:8]}')
        self._executor = EventsExecutor()  # as the gateway's: the caller is no bottleneck
        self._executor.add_node(self.node)
        self._spinning = threading.Event()
        self._spinning.set()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()
        self._clients = {}

    def _spin(self) -> None:
        while self._spinning.is_set():
            self._executor.spin_once(timeout_sec=0.1)

    def call(self, service_type, name: str, timeout: float = CALL_TIMEOUT, **fields):
        """Call ``name`` and return the response (None on timeout), waiting on done()."""
        client = self._clients.get(name)
        if client is None:
            client = self._clients[name] = self.node.create_client(service_type, name)
            if not client.wait_for_service(timeout_sec=START_TIMEOUT):
                raise RuntimeError(f'{name} is not offered')
        future = client.call_async(service_type.Request(**fields))
        answered = threading.Event()
        future.add_done_callback(lambda _future: answered.set())
        deadline = time.monotonic() + timeout
        # done() checked too: rclpy can complete a future without running a callback added
        # meanwhile (ROS_ON_THIS_MACHINE.md); then the answer is seen within a millisecond.
        while not future.done():
            if time.monotonic() > deadline:
                client.remove_pending_request(future)
                return None
            answered.wait(0.001)
        return future.result()

    def close(self) -> None:
        """Stop spinning and destroy the node."""
        self._spinning.clear()
        self._thread.join()
        self._executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()


def wait_until(condition: Callable[[], bool], timeout: float, what: str) -> None:
    """Wait for ``condition()``; raise RuntimeError naming ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise RuntimeError(f'timed out waiting for {what}')
        time.sleep(0.02)


def gateway_ready(caller: Caller, node: NodeProcess, node_ids, mode: int = CSV) -> None:
    """Start the drives (NMT), wait for the gateway to know them, enable each once in ``mode``.

    The first enable changes the mode (the drive boots in none), so every measured enable
    after it starts from SWITCH_ON_DISABLED with the mode already set, as BaseNode402's.
    """
    from cbcan_ros.srv import DriveCommand, NmtCommand
    response = caller.call(NmtCommand, f'{node.name}/nmt_command', node_id=0,
                           command=NMT_START)
    if response is None or not response.success:
        raise RuntimeError(f'NMT start failed: {response}')
    for node_id in node_ids:
        def enabled(node_id=node_id) -> bool:
            answer = caller.call(DriveCommand, f'{node.name}/drive_command', node_id=node_id,
                                 command='enable', mode=mode)
            return answer is not None and answer.success
        wait_until(enabled, START_TIMEOUT, f'drive {node_id} enabled through the gateway')


# Row 1: enable time against python canopen's BaseNode402.

# The drive's objects as an EDS would list them, for BaseNode402: the PDO parameters
# (communication: COB-ID, type, inhibit time, event timer; mapping: 8 entries) and CiA 402's.
DRIVE_OBJECTS = (
    (0x603F, 'UNSIGNED16'), (0x6040, 'UNSIGNED16'), (0x6041, 'UNSIGNED16'),
    (0x6060, 'INTEGER8'), (0x6061, 'INTEGER8'), (0x6064, 'INTEGER32'), (0x606C, 'INTEGER32'),
    (0x6071, 'INTEGER16'), (0x6077, 'INTEGER16'), (0x607A, 'INTEGER32'),
    (0x60FF, 'INTEGER32'), (0x6502, 'UNSIGNED32'),
)


def drive_dictionary():
    """Return the simulated drive's object dictionary for python canopen (no EDS ships)."""
    from canopen.objectdictionary import datatypes, ObjectDictionary, ODRecord, ODVariable

    def variable(name: str, index: int, subindex: int, kind: str) -> ODVariable:
        entry = ODVariable(name, index, subindex)
        entry.data_type = getattr(datatypes, kind)
        entry.access_type = 'rw'
        return entry

    od = ObjectDictionary()
    for base, communication in ((0x1400, 'RPDO'), (0x1800, 'TPDO')):
        for number in range(4):
            record = ODRecord(f'{communication} {number + 1} communication', base + number)
            for subindex, name, kind in ((0, 'count', 'UNSIGNED8'),
                                         (1, 'COB-ID', 'UNSIGNED32'),
                                         (2, 'transmission type', 'UNSIGNED8'),
                                         (3, 'inhibit time', 'UNSIGNED16'),
                                         (5, 'event timer', 'UNSIGNED16')):
                record.add_member(variable(name, base + number, subindex, kind))
            od.add_object(record)
            mapping = ODRecord(f'{communication} {number + 1} mapping', base + 0x200 + number)
            mapping.add_member(variable('count', base + 0x200 + number, 0, 'UNSIGNED8'))
            for subindex in range(1, 9):
                mapping.add_member(variable(f'entry {subindex}', base + 0x200 + number,
                                            subindex, 'UNSIGNED32'))
            od.add_object(mapping)
    for index, kind in DRIVE_OBJECTS:
        od.add_object(variable(f'0x{index:04X}', index, 0, kind))
    return od


def _sent_by_a_master(cob_id: int) -> bool:
    """Return whether a master sends frames with ``cob_id`` (NMT, SYNC, RPDOs, SDO requests)."""
    return cob_id in (0x000, 0x080) or 0x200 <= cob_id < 0x580 or 0x600 <= cob_id < 0x680


def canopen_network(bus: UdpBus):
    """Return a python canopen Network on ``bus`` that does not hear its own frames.

    udp_multicast hands a process its own frames back; a CAN controller does not. canopen's
    RPDO map would take its own frame as one received, note a period, and from then on count
    the RPDO periodic, and BaseNode402 would stop sending its controlword (it leaves a periodic
    RPDO to the SYNC). So frames only a master sends are dropped before canopen sees them.
    """
    import can
    import canopen
    from canopen.network import MessageListener

    class DeviceFramesOnly(can.Listener):
        def __init__(self, listener: can.Listener):
            self._listener = listener

        def on_message_received(self, message: can.Message) -> None:
            if not _sent_by_a_master(message.arbitration_id):
                self._listener.on_message_received(message)

    network = canopen.Network()
    network.bus = bus.open()
    network.listeners = [DeviceFramesOnly(MessageListener(network))]
    network.notifier = can.Notifier(network.bus, network.listeners, 0.05)
    return network


class Canopen402:
    """python canopen's BaseNode402 on its own network, set up as its documentation shows."""

    def __init__(self, bus: UdpBus, node_id: int):
        from canopen.profiles.p402 import BaseNode402
        self.network = canopen_network(bus)
        self.node = BaseNode402(node_id, drive_dictionary())
        self.network.add_node(self.node)
        self.node.nmt.wait_for_heartbeat(START_TIMEOUT)
        self.node.setup_402_state_machine()  # reads the PDO mapping by SDO
        self.node.nmt.state = 'OPERATIONAL'
        wait_until(lambda: self.node.nmt.state == 'OPERATIONAL', START_TIMEOUT,
                   'the BaseNode402 drive OPERATIONAL')
        wait_until(lambda: self.node.tpdo_values.get(0x6041), START_TIMEOUT,
                   'a statusword in a TPDO')
        # The mode is set by SDO and read back by SDO: BaseNode402's op_mode setter swallows
        # its errors, and its getter trusts a TPDO value it may not have taken yet (on the
        # vendor layout it showed NO MODE for good). Only the enable is measured.
        self.node.sdo[0x6060].raw = CSV
        wait_until(lambda: self.node.sdo[0x6061].raw == CSV, 5.0, 'the drive in CSV')

    def enable(self) -> None:
        """Enable the drive as BaseNode402 does (it raises RuntimeError on a timeout)."""
        self.node.state = 'OPERATION ENABLED'

    def disable(self) -> None:
        """Back to SWITCH ON DISABLED."""
        self.node.state = 'SWITCH ON DISABLED'

    def close(self) -> None:
        """Leave the network."""
        self.network.disconnect()


STATUS_COB_ID = 0x180 + DRIVE  # TPDO 1: the statusword
COMMAND_COB_ID = 0x200 + DRIVE  # RPDO 1: the controlword
RECORDED = f'0x{STATUS_COB_ID:X},0x{COMMAND_COB_ID:X},0x{TARGET_COB_ID:X}'
OPERATION_ENABLED = (0x6F, 0x27)  # statusword mask and value


def steps(frames: List, started: float, answered: float) -> Dict[str, List[float]]:
    """Return where one enable's time went, from the frames a reader recorded (wall clock, s).

    ``first``: from the call to the first frame the master sent; ``master``: from each
    statusword that showed a transition to the next controlword; ``drive``: from each
    controlword to the drive's next statusword; ``answer``: from the statusword showing
    OPERATION_ENABLED to the caller having the answer.
    """
    frames = [(at, cob_id, bytes.fromhex(data)) for at, cob_id, data in frames
              if started <= at <= answered]
    sent = [frame for frame in frames if frame[1] in (COMMAND_COB_ID, TARGET_COB_ID)]
    words = [frame for frame in frames if frame[1] == COMMAND_COB_ID]
    result: Dict[str, List[float]] = {'first': [], 'master': [], 'drive': [], 'answer': []}
    if sent:
        result['first'].append(sent[0][0] - started)
    for number, (at, _cob_id, _data) in enumerate(words):
        status = next((frame for frame in frames
                       if frame[1] == STATUS_COB_ID and frame[0] > at), None)
        if status is None:
            continue
        result['drive'].append(status[0] - at)
        if number + 1 < len(words):
            result['master'].append(words[number + 1][0] - status[0])
        elif status[2] and status[2][0] & OPERATION_ENABLED[0] == OPERATION_ENABLED[1]:
            result['answer'].append(answered - status[0])
    return result


def row_enable(caller: Caller, node: NodeProcess, reference: Canopen402,
               readers: Dict[str, Child], trigger: str, floor: str, repetitions: int) -> Dict:
    """Row 1: enable round trips, the gateway's, BaseNode402's and the floor's, alternating.

    ``readers`` (one a bus, recording) show where the time went: the master's reaction to
    each statusword, the drive's, and the way in and out. A bare ``std_srvs/Trigger`` round
    trip (service ``trigger``, a process of its own) is timed in the same rounds, and the
    floor (service ``floor``, ``bench_drive_host.py enable-floor``): BaseNode402 inside a
    bare rclpy ``DriveCommand`` callback, the least any ROS gateway of python canopen does;
    and the same answered later from a worker thread (``floor`` + ``_answered_later``).
    """
    from std_srvs.srv import Trigger

    from cbcan_ros.srv import DriveCommand

    def command(service: str, who: str, name: str, **fields) -> Callable[[], None]:
        def call() -> None:
            answer = caller.call(DriveCommand, service, node_id=DRIVE, command=name, **fields)
            if answer is None or not answer.success:
                raise RuntimeError(f'{who} {name} failed: {answer}')
        return call

    def trigger_call() -> None:
        if caller.call(Trigger, trigger) is None:
            raise RuntimeError('the bare Trigger service did not answer')

    gateway = f'{node.name}/drive_command'
    contenders = (('gateway', command(gateway, 'gateway', 'enable', mode=CSV),
                   command(gateway, 'gateway', 'disable')),
                  ('basenode402', reference.enable, reference.disable),
                  ('trigger', trigger_call, lambda: None),
                  ('floor', command(floor, 'the floor', 'enable'),
                   command(floor, 'the floor', 'disable')),
                  ('floor_free', command(f'{floor}_answered_later', 'the free floor', 'enable'),
                   command(f'{floor}_answered_later', 'the free floor', 'disable')))
    readers = {**readers, 'floor_free': readers['floor']}  # one after the other, one bus
    for _name, _enable, disable in contenders:
        disable()  # both drives start from SWITCH ON DISABLED, in CSV
    times: Dict[str, List[float]] = {name: [] for name, _enable, _disable in contenders}
    parts = {name: {'first': [], 'master': [], 'drive': [], 'answer': []} for name in readers}
    for repetition in range(repetitions):
        order = contenders if repetition % 2 == 0 else contenders[::-1]
        for name, enable, disable in order:
            time.sleep(0.05)  # the last transition's frames settled
            if name in readers:
                _stats(readers[name])  # forget the frames before
            started, wall = time.perf_counter(), time.time()  # frames are stamped wall time
            enable()
            answered = time.perf_counter()
            times[name].append(answered - started)
            if name in readers:
                time.sleep(0.002)
                for part, values in steps(_stats(readers[name])['frames'], wall,
                                          wall + answered - started).items():
                    parts[name][part] += values
            disable()
    row = {'repetitions': repetitions, 'unit': 'gateway / BaseNode402 (p50)'}
    for name, values in times.items():
        row[f'{name}_ms'] = percentile(values, 0.5) * 1e3
        row[f'{name}_max_ms'] = max(values) * 1e3
    for name in readers:
        row[f'{name}_steps_ms'] = {part: percentile(values, 0.5) * 1e3
                                   for part, values in parts[name].items()}
    row['value'] = row['gateway_ms'] / row['basenode402_ms']
    sum_of_parts = row['basenode402_ms'] + row['trigger_ms']
    row['ratio_to_floor'] = row['gateway_ms'] / sum_of_parts
    row['floor_to_parts'] = row['floor_ms'] / sum_of_parts
    row['gateway_to_floor'] = row['gateway_ms'] / row['floor_ms']
    row['floor_free_to_parts'] = row['floor_free_ms'] / sum_of_parts
    row['gateway_to_floor_free'] = row['gateway_ms'] / row['floor_free_ms']
    return row


# Row 2: target to frame.

def _frame_with(bus, cob_id: int, value: int, timeout: float = 1.0) -> Optional[float]:
    """Return when (perf_counter) the frame ``cob_id`` carrying INTEGER32 ``value`` arrived."""
    deadline = time.perf_counter() + timeout
    while True:
        left = deadline - time.perf_counter()
        if left <= 0:
            return None
        message = bus.recv(left)
        if (message is not None and message.arbitration_id == cob_id
                and len(message.data) >= 4
                and struct.unpack_from('<i', message.data)[0] == value):
            return time.perf_counter()


def _drain(bus) -> None:
    while bus.recv(0) is not None:
        pass


def row_target(caller: Caller, node: NodeProcess, bus: UdpBus, relay_topic: str,
               samples: int) -> Dict:
    """Row 2: Float64 on ~/node_1/target to its RPDO frame; a bare relay and a CAN hop beside."""
    import can
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Float64
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                     reliability=ReliabilityPolicy.BEST_EFFORT)
    to_gateway = caller.node.create_publisher(Float64, f'{node.name}/node_{DRIVE}/target', qos)
    to_relay = caller.node.create_publisher(Float64, relay_topic, qos)
    receiver, sender = bus.open(), bus.open()
    latencies: Dict[str, List[float]] = {'gateway': [], 'relay': [], 'can': []}
    lost = {'gateway': 0, 'relay': 0, 'can': 0}
    try:
        # Matched: a target that arrives at each (best effort drops what goes before).
        for publisher, cob_id, name in ((to_gateway, TARGET_COB_ID, 'the gateway'),
                                        (to_relay, RELAY_COB_ID, 'the relay')):
            def arrives(publisher=publisher, cob_id=cob_id) -> bool:
                publisher.publish(Float64(data=-1.0))
                return _frame_with(receiver, cob_id, -1, 0.2) is not None
            wait_until(arrives, START_TIMEOUT, f'a target through {name}')
        time.sleep(0.2)
        for sample in range(1, samples + 1):
            for name, send in (('gateway', lambda v: to_gateway.publish(Float64(data=v))),
                               ('relay', lambda v: to_relay.publish(Float64(data=v))),
                               ('can', lambda v: sender.send(can.Message(
                                   arbitration_id=RELAY_COB_ID, is_extended_id=False,
                                   data=struct.pack('<ih', round(v), 0))))):
                cob_id = TARGET_COB_ID if name == 'gateway' else RELAY_COB_ID
                value = sample * 3 + ('gateway', 'relay', 'can').index(name)
                _drain(receiver)
                started = time.perf_counter()
                send(float(value))
                arrived = _frame_with(receiver, cob_id, value)
                if arrived is None:
                    lost[name] += 1
                else:
                    latencies[name].append(arrived - started)
                time.sleep(0.005)
    finally:
        receiver.shutdown()
        sender.shutdown()
        caller.node.destroy_publisher(to_gateway)
        caller.node.destroy_publisher(to_relay)
    row = {'unit': 'ms', 'samples': samples, 'lost': lost}
    for name, values in latencies.items():
        row[f'{name}_p50_ms'] = percentile(values, 0.5) * 1e3
        row[f'{name}_p99_ms'] = percentile(values, 0.99) * 1e3
    row['value'] = row['gateway_p50_ms']
    row['ratio_to_relay'] = row['gateway_p50_ms'] / row['relay_p50_ms']
    return row


def rows_enable_and_target(args, caller: Caller, rows: Dict[str, Dict],
                           layout: str = 'combined') -> None:
    """Rows 1 and 2 into ``rows``: a drive for the gateway, one for BaseNode402, own buses.

    ``layout``: the drives' PDO layout; other than ``combined``, only the enable row, kept
    as ``enable_<layout>``.
    """
    gateway_bus, reference_bus, floor_bus = UdpBus(), UdpBus(), UdpBus()
    helpers: List[Child] = []
    node = None
    reference = None
    try:
        for name, bus in (('drives', gateway_bus), ('reference drives', reference_bus),
                          ('floor drives', floor_bus)):
            helpers.append(start_helper(name, 'drives', bus, '--nodes', str(DRIVE),
                                        '--layout', layout))
        readers = {'gateway': start_helper('reader', 'reader', gateway_bus,
                                           '--record', RECORDED),
                   'basenode402': start_helper('reference reader', 'reader', reference_bus,
                                               '--record', RECORDED),
                   'floor': start_helper('floor reader', 'reader', floor_bus,
                                         '--record', RECORDED)}
        helpers += readers.values()
        floor_namespace = f'/benchfloor{uuid.uuid4().hex[:8]}'
        helpers.append(start_helper('enable floor', 'enable-floor', floor_bus,
                                    '--nodes', str(DRIVE), '--namespace', floor_namespace))
        trigger_namespace = f'/benchtrigger{uuid.uuid4().hex[:8]}'
        trigger = Child('trigger', python('bench_trigger.py', trigger_namespace))
        helpers.append(trigger)
        trigger.expect('ready', START_TIMEOUT)
        relay_topic = f'/benchrelay{uuid.uuid4().hex[:8]}/target'
        helpers.append(start_helper('relay', 'relay', gateway_bus, '--topic', relay_topic))
        node = NodeProcess(gateway_bus, {'drives.nodes': f'[{DRIVE}]',
                                         'drives.command_timeout': '0.0'},
                           os.path.join(args.output, 'drives_node.log'))
        progress('drives: set up (gateway, BaseNode402)')
        gateway_ready(caller, node, [DRIVE])
        reference = Canopen402(reference_bus, DRIVE)
        if 'enable' in args.rows:
            progress(f'drives: enable time, gateway against BaseNode402 ({layout} layout)')
            rows['enable' if layout == 'combined' else f'enable_{layout}'] = row_enable(
                caller, node, reference, readers, f'{trigger_namespace}/trigger',
                f'{floor_namespace}/drive_command', args.repetitions)
        if 'target' in args.rows and layout == 'combined':
            progress('drives: target to RPDO frame')
            gateway_ready(caller, node, [DRIVE])  # enabled in CSV again
            rows['target'] = row_target(caller, node, gateway_bus, relay_topic, args.samples)
    finally:
        if reference is not None:
            reference.close()
        if node is not None:
            node.close()
        for helper in reversed(helpers):
            helper.stop()


# Row 3: load.

def row_load(args, caller: Caller) -> Dict:
    """Row 3: 8 drives, SYNC 10 ms: joint_states a second, node CPU beside a bare receiver."""
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    bus = UdpBus()
    helpers: Dict[str, Child] = {}
    node = None
    subscription = None
    try:
        helpers['drives'] = start_helper(
            'load drives', 'drives', bus, '--nodes', ','.join(map(str, LOAD_DRIVES)),
            '--transmission-type', '1', '--shared-socket')
        helpers['reader'] = start_helper('reader', 'reader', bus)
        node = NodeProcess(bus, {'drives.nodes': f'[{",".join(map(str, LOAD_DRIVES))}]',
                                 'drives.command_timeout': '0.0',
                                 'sync.period': str(SYNC_PERIOD)},
                           os.path.join(args.output, 'drives_load_node.log'))
        progress(f'drives: load, {len(LOAD_DRIVES)} drives enabled in CSV, SYNC '
                 f'{SYNC_PERIOD * 1e3:g} ms')
        gateway_ready(caller, node, LOAD_DRIVES)
        received = [0]
        subscription = caller.node.create_subscription(
            JointState, f'{node.name}/joint_states',
            lambda _message: received.__setitem__(0, received[0] + 1),
            QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                       reliability=ReliabilityPolicy.RELIABLE))
        wait_until(lambda: received[0] > 10, START_TIMEOUT, 'joint_states')
        _until_no_sdo(helpers['reader'])
        pids = {'node': node.pid, 'reader': helpers['reader'].pid,
                'drives': helpers['drives'].pid}
        reader_before = _stats(helpers['reader'])
        cpu_before = {name: proc_cpu_seconds(pid) for name, pid in pids.items()}
        messages_before, started = received[0], time.monotonic()
        time.sleep(args.seconds)
        cpu_after = {name: proc_cpu_seconds(pid) for name, pid in pids.items()}
        messages, elapsed = received[0] - messages_before, time.monotonic() - started
        reader_after = _stats(helpers['reader'])
        frames = {kind: (reader_after['counts'][kind] - reader_before['counts'][kind]) /
                  (reader_after['time'] - reader_before['time'])
                  for kind in reader_after['counts']}
    finally:
        if subscription is not None:
            caller.node.destroy_subscription(subscription)
        if node is not None:
            node.close()
        for helper in reversed(list(helpers.values())):
            helper.stop()
    cpu = {name: 100 * (cpu_after[name] - cpu_before[name]) / elapsed for name in pids}
    tpdos_per_sync = frames['tpdo'] / frames['sync'] if frames['sync'] else 0.0
    expected = 2 * len(LOAD_DRIVES)
    return {'value': cpu['node'] / cpu['reader'], 'unit': 'node CPU / bare receiver CPU',
            'node_cpu': cpu['node'], 'reader_cpu': cpu['reader'], 'drives_cpu': cpu['drives'],
            'joint_states_per_s': messages / elapsed, 'frames_per_s': frames,
            'tpdos_per_sync': tpdos_per_sync, 'tpdos_per_sync_expected': expected,
            'simulation_keeps_up': tpdos_per_sync >= 0.95 * expected,
            'window_s': elapsed}


def _until_no_sdo(reader: Child) -> None:
    """Wait for a second without SDO frames: every mapping read, every feedback in a TPDO.

    A drive whose mapping could not be read yet (its SDO answers late on a busy machine) is
    run by SDO meanwhile, and that traffic would be measured as load.
    """
    before = _stats(reader)
    deadline = time.monotonic() + START_TIMEOUT
    while True:
        time.sleep(1.0)
        after = _stats(reader)
        if after['counts']['sdo'] == before['counts']['sdo']:
            return
        if time.monotonic() > deadline:
            raise RuntimeError('the gateway still reads the drives by SDO after '
                               f'{START_TIMEOUT:g} s: a mapping was never read?')
        before = after


def _stats(child: Child) -> dict:
    child.tell({'op': 'stats'})
    return child.expect('ok', START_TIMEOUT)


# The report.

def _ms(value) -> str:
    return 'not measured' if value is None else f'{value:.2f} ms'


def table(rows: Dict[str, Dict]) -> str:
    """Return the rows as a Markdown table: the figure, its baseline, the ratio, the target."""
    lines = ['| row | measured | beside it (same run) | ratio | target | met |',
             '|---|---|---|---|---|---|']
    for key, layout in (('enable', 'combined'), ('enable_vendor', 'vendor')):
        enable = rows.get(key)
        if not enable:
            continue
        met = 'yes' if enable['ratio_to_floor'] <= ENABLE_TARGET else '**no**'
        lines.append(
            f'| enable, SWITCH_ON_DISABLED to OPERATION_ENABLED (CSV), {layout} PDO layout, '
            f'p50 of {enable["repetitions"]} | drive_command enable (ROS round trip) '
            f'{_ms(enable["gateway_ms"])} | BaseNode402 `state = \'OPERATION ENABLED\'` '
            f'{_ms(enable["basenode402_ms"])}; bare Trigger round trip '
            f'{_ms(enable["trigger_ms"])} | {enable["ratio_to_floor"]:.2f} (to BaseNode402 + '
            f'Trigger); {enable["value"]:.2f} (to BaseNode402) | <= {ENABLE_TARGET} | {met} |')
        lines.append(
            f'| the floor of an enable, {layout} layout: BaseNode402 inside a bare rclpy '
            f'`DriveCommand` callback | {_ms(enable["floor_ms"])} | BaseNode402 + Trigger as '
            f'above | {enable["floor_to_parts"]:.2f} (floor to BaseNode402 + Trigger); '
            f'gateway to floor {enable["gateway_to_floor"]:.2f} | not a target: what any '
            f'ROS gateway of python canopen pays | - |')
        lines.append(
            f'| the floor of an enable that keeps the executor free, {layout} layout: the '
            f'same BaseNode402 enable on a worker thread, answered from there | '
            f'{_ms(enable["floor_free_ms"])} | BaseNode402 + Trigger as above | '
            f'{enable["floor_free_to_parts"]:.2f} (to BaseNode402 + Trigger); gateway to it '
            f'{enable["gateway_to_floor_free"]:.2f} | not a target: what a ROS gateway that '
            f'serves other calls during an enable pays at the least | - |')
    target = rows.get('target')
    if target:
        met = 'yes' if target['gateway_p50_ms'] <= 1 else '**no**'
        lines.append(
            f'| target: Float64 on ~/node_1/target to RPDO frame, p50 (p99) of '
            f'{target["samples"]} | {_ms(target["gateway_p50_ms"])} '
            f'({_ms(target["gateway_p99_ms"])}) | bare rclpy relay process (subscription to '
            f'bus.send) {_ms(target["relay_p50_ms"])} ({_ms(target["relay_p99_ms"])}); one '
            f'CAN frame on the bus {_ms(target["can_p50_ms"])} ({_ms(target["can_p99_ms"])}) '
            f'| {target["ratio_to_relay"]:.2f} (to the relay) | p50 <= 1 ms | {met} |')
    load = rows.get('load')
    if load:
        met = 'yes' if load['node_cpu'] < 30 else '**no**'
        lines.append(
            f'| load: {len(LOAD_DRIVES)} drives in CSV, SYNC 10 ms, synchronous PDOs: node '
            f'CPU ({load["joint_states_per_s"]:.1f} joint_states/s received of 100, '
            f'{sum(load["frames_per_s"].values()):.0f} frames/s on the bus) | '
            f'{load["node_cpu"]:.1f} % of a core | bare python-can receiver process '
            f'{load["reader_cpu"]:.1f} % | {load["value"]:.2f} | node < 30 % of a core '
            f'| {met} |')
    return '\n'.join(lines)


def notes(rows: Dict[str, Dict]) -> List[str]:
    """Return what a reader of the table needs to know about this run."""
    lines = []
    enable = rows.get('enable')
    if enable:
        described = []
        for name, shown in (('gateway', 'gateway'), ('basenode402', 'BaseNode402'),
                            ('floor', 'the floor'), ('floor_free', 'the free floor')):
            parts = enable[f'{name}_steps_ms']
            described.append(
                f'{shown}: call to its first frame {parts["first"]:.2f} ms, statusword to its '
                f'next controlword {parts["master"]:.2f} ms (2 an enable), controlword to the '
                f"drive's statusword {parts['drive']:.2f} ms (3 an enable), OPERATION_ENABLED "
                f'statusword to the answer {parts["answer"]:.2f} ms')
        lines.append('Where the enable time went (p50 of each step, frames timed by the '
                     "kernel's receive timestamps at a receiver process on each bus): "
                     + '; '.join(described) + ". The gateway's first frame sets the target "
                     'that holds the axis, before the shutdown controlword.')
    target = rows.get('target')
    if target and any(target['lost'].values()):
        lines.append(f'Targets whose frame never came (1 s): {target["lost"]}.')
    load = rows.get('load')
    if load:
        frames = ', '.join(f'{kind} {rate:.0f}' for kind, rate in load['frames_per_s'].items())
        lines.append(f'Load: frames/s at the bare receiver: {frames}; TPDOs per SYNC '
                     f'{load["tpdos_per_sync"]:.2f} (expected {load["tpdos_per_sync_expected"]})'
                     f'; the drive simulation process used {load["drives_cpu"]:.1f} % of a '
                     f'core.')
        if not load['simulation_keeps_up']:
            lines.append('**The simulated drives did not keep up** (fewer TPDOs per SYNC than '
                         'mapped): the simulation, not the gateway, is the bottleneck of the '
                         'load row in this run.')
    return lines


def report(rows: Dict[str, Dict], problems: List[str], machine: Dict, output: str) -> str:
    """Write drives.md and drives.json; return the table."""
    text = table(rows)
    described = ', '.join(f'{key}: {value}' for key, value in machine.items())
    os.makedirs(output, exist_ok=True)
    with open(os.path.join(output, 'drives.md'), 'w') as file:
        file.write(f'# Drive (CiA 402) benchmark (make bench)\n\n{described}\n\n{text}\n')
        for line in notes(rows) + problems:
            file.write(f'\n{line}\n')
    with open(os.path.join(output, 'drives.json'), 'w') as file:
        json.dump({'rows': rows, 'problems': problems, 'machine': machine}, file, indent=1)
    return text


def main(argv=None) -> int:
    """Run the drive rows and report them."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--quick', action='store_true', help='shorter measurements')
    parser.add_argument('--rows', type=lambda text: text.split(','),
                        default=['enable', 'target', 'load'],
                        help='rows to measure, of enable,target,load (default all)')
    parser.add_argument('--output', default=OUTPUT,
                        help='folder of drives.md, drives.json and the logs '
                             '(default %(default)s)')
    args = parser.parse_args(argv)
    args.repetitions = 10 if args.quick else 30
    args.samples = 100 if args.quick else 300
    args.seconds = 3.0 if args.quick else 8.0
    rows: Dict[str, Dict] = {}
    problems: List[str] = []
    with bench_session(args.output, 'drives', args.quick) as (caller, machine):
        measures = []
        if {'enable', 'target'} & set(args.rows):
            measures.append(('enable and target',
                             lambda: rows_enable_and_target(args, caller, rows)))
        if 'enable' in args.rows:
            measures.append(('enable on the vendor layout',
                             lambda: rows_enable_and_target(args, caller, rows, 'vendor')))
        if 'load' in args.rows:
            measures.append(('load', lambda: rows.__setitem__('load', row_load(args, caller))))
        for name, measure in measures:
            try:
                measure()
            except (RuntimeError, ChildFailed) as error:
                problems.append(f'{name}: {error}')
                progress(f'drives: {name} failed: {error}')
    print(report(rows, problems, machine, args.output))
    for line in notes(rows) + problems:
        print(line)
    return 0


if __name__ == '__main__':
    sys.exit(main())
