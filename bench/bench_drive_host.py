"""The helper processes of ``bench_drives.py``: simulated drives, a bare receiver, a bare relay.

As a process (``python bench_drive_host.py MODE ...``) each writes ``@@ {"ready": ...}`` once
up and then answers commands (one JSON object a line) on standard input until ``stop``:

* ``drives``: simulated CiA 402 drives (``DurandDrive``, the PDOs of
  ``default_drive_pdos(--transmission-type)``) on one udp_multicast bus, for the gateway or
  for python canopen's ``BaseNode402``. With ``--shared-socket``, ``{"op": "generate"}``
  hands their synchronous TPDOs to a raw frame generator from then on (see
  :class:`SharedSocket`);
* ``devices``: simulated devices (``SimulatedDevice``, every object of ``--eds``) on one
  udp_multicast bus, for ``bench_boot.py``; an NMT reset node sets every value back to the
  file's default. ``{"op": "stats"}`` answers how many SDO writes each device took so far;
* ``bootloader``: one simulated device with a bootloader (``BootloaderDevice``, CiA 302-3)
  at ``--nodes``, flashing and clearing at once (the device's own time is not what
  ``bench_program_download.py`` measures). ``{"op": "stats"}`` answers the size and CRC-32
  of the image it holds and how often it was started;
* ``reader``: a bare python-can receiver that takes every frame of the bus and counts it by
  kind, nothing else: the floor of receiving what the gateway receives.
  ``{"op": "stats"}`` answers the counts so far;
* ``relay``: a bare rclpy node that takes a ``std_msgs/Float64`` (subscribed best effort, as
  the gateway subscribes targets) and sends it as one CAN frame, laid out as a drive's RPDO 2
  (target velocity INTEGER32, target torque INTEGER16) on COB-ID 0x37F, which no simulated
  drive takes: the floor of the gateway's target path, between the same kinds of process;
* ``floor``: what any gateway of the control-rate row must do at the least, with no CANopen
  of its own: start the drives (NMT), send SYNC every ``--period`` s (python-can's periodic
  sending, as the gateway's), take every frame, publish one ``sensor_msgs/JointState`` of
  the drives' positions on ``--namespace``/joint_states once a SYNC's two TPDOs of every
  drive are in, and send each ``joint_commands`` message's positions as the drives' RPDO 1
  frames (controlword 0x0F, target, CSP). No checks, no state, no stops;
* ``enable-floor``: the least any ROS gateway does for an enable: ``--namespace``/
  drive_command (the gateway's ``DriveCommand`` type and service QoS), whose callback runs
  python canopen's ``BaseNode402`` (``enable``: OPERATION ENABLED, ``disable``: SWITCH ON
  DISABLED) on the drive ``--nodes`` of the bus, blocking the executor meanwhile; and
  ``drive_command_answered_later``, the same on a worker thread that answers when done, so
  the executor stays free, as a gateway's must.
"""

import argparse
import heapq
import itertools
import json
import queue
import struct
import sys
import threading
import time
from typing import Dict, List

from bench_util import exit_on_sigterm, import_retrying, progress, receive, send
import can

RELAY_COB_ID = 0x37F  # RPDO 2 of node 127: no simulated drive takes it
SYNC_COB_ID = 0x080


def frame_kind(cob_id: int) -> str:
    """Return what a frame is, by its COB-ID (CiA 301 predefined connection set)."""
    if cob_id == SYNC_COB_ID:
        return 'sync'
    function = cob_id & 0x780
    if function in (0x180, 0x280, 0x380, 0x480):
        return 'tpdo'
    if function in (0x200, 0x300, 0x400, 0x500):
        return 'rpdo'
    if function == 0x700:
        return 'heartbeat'
    if function in (0x580, 0x600):
        return 'sdo'
    if function == 0x080:
        return 'emcy'
    return 'other'


def _bus(args, bus_options: Dict):
    return can.Bus(interface='udp_multicast', channel=args.channel, **bus_options)


def _serve(extra=None, ops=None) -> None:
    """Answer commands until ``stop``: ``stats`` with ``extra()``, anything else with ok.

    ``ops``: further commands by name, each run before its answer.
    """
    send({'ready': True})
    while True:
        command = receive()
        if command.get('op') == 'stop':
            return
        (ops or {}).get(command.get('op'), lambda: None)()
        answer = {'ok': True, 'time': time.monotonic()}
        if extra is not None:
            answer.update(extra())
        send(answer)


class SharedSocket:
    """One udp_multicast socket for every simulated drive of this process.

    Each simulated drive opens a bus of its own, and on udp_multicast every socket receives
    (and unpacks) every frame: 8 drives cost 8 times the receiving, and on a busy machine
    they missed SYNCs and SDO requests. Here one socket receives and hands each drive, on a
    :class:`SharedUdpBus`, only the frames a drive takes (those a master sends it).

    Once told to ``generate``, the drives' synchronous TPDOs (``default_drive_pdos(1)``) come
    from a raw frame generator instead, so that the simulation does not set the limit of a
    control-rate measurement: each SYNC is answered with every drive's TPDO 1 as the drive
    last sent it (statusword, mode, torque) and its TPDO 2 with the target position of its
    last RPDO 1 as the actual position (velocity 0). The drives themselves still answer SDO,
    NMT and heartbeats, but take neither SYNC nor RPDOs any more.
    """

    def __init__(self, channel: str, bus_options: Dict, node_ids):
        self._bus = can.Bus(interface='udp_multicast', channel=channel, **bus_options)
        self._node_ids = set(node_ids)
        self._send_lock = threading.Lock()
        self._members: Dict[int, 'SharedUdpBus'] = {}
        self._sent: Dict[int, bytes] = {}  # COB-ID: the data a drive last sent on it
        self._targets: Dict[int, bytes] = {}  # node: target position of its last RPDO 1
        self._generating = False
        self._running = True
        self._thread = threading.Thread(target=self._receive, daemon=True)
        self._thread.start()

    def join(self, member: 'SharedUdpBus') -> None:
        """Hand ``member`` the frames for its node from now on."""
        self._members[member.node_id] = member

    def leave(self, member: 'SharedUdpBus') -> None:
        """Stop handing ``member`` frames."""
        self._members.pop(member.node_id, None)

    def send(self, message: can.Message) -> None:
        """Send a drive's frame."""
        with self._send_lock:
            self._sent[message.arbitration_id] = bytes(message.data)
            self._bus.send(message)

    def generate(self) -> None:
        """Answer SYNC with generated TPDOs from now on (see the class)."""
        self._generating = True

    def _answer_sync(self) -> None:
        for node_id in sorted(self._node_ids):
            status = self._sent.get(0x180 + node_id)
            if status is None:
                continue
            position = self._targets.get(node_id, self._sent.get(0x280 + node_id,
                                                                 bytes(8))[:4])
            for cob_id, data in ((0x180 + node_id, status),
                                 (0x280 + node_id, position + bytes(4))):
                self._bus.send(can.Message(arbitration_id=cob_id, data=data,
                                           is_extended_id=False))

    def close(self) -> None:
        """Stop receiving and close the socket."""
        self._running = False
        self._thread.join()
        self._bus.shutdown()

    def _receive(self) -> None:
        while self._running:
            message = self._bus.recv(0.05)
            if message is None:
                continue
            cob_id = message.arbitration_id
            if self._generating and cob_id == SYNC_COB_ID:
                with self._send_lock:
                    self._answer_sync()
                continue
            if self._generating and cob_id & 0x780 == 0x200:  # RPDO 1: taken here
                self._targets[cob_id & 0x7F] = bytes(message.data[2:6])
                continue
            if cob_id in (0x000, SYNC_COB_ID, 0x7E5):  # NMT, SYNC, LSS: every drive's
                members = list(self._members.values())
            elif 0x700 < cob_id < 0x780 and cob_id - 0x700 not in self._node_ids:
                members = list(self._members.values())  # a master's heartbeat
            elif (cob_id & 0x780) in (0x200, 0x300, 0x400, 0x500, 0x600):
                member = self._members.get(cob_id & 0x7F)  # its RPDOs and SDO requests
                members = [member] if member is not None else []
            else:
                continue  # what the drives send (udp_multicast hands them back)
            for member in members:
                member.queue.put(message)


SHARED_SOCKETS: Dict[str, SharedSocket] = {}
SHARED_INTERFACE = 'bench_shared_udp'


class SharedUdpBus(can.BusABC):
    """A simulated drive's bus on the process's :class:`SharedSocket` ``channel``."""

    def __init__(self, channel: str, node_id: int, **kwargs):
        self.node_id = node_id
        self.queue: 'queue.SimpleQueue[can.Message]' = queue.SimpleQueue()
        self._socket = SHARED_SOCKETS[channel]
        super().__init__(channel=channel, **kwargs)
        self.channel_info = f'shared udp_multicast {channel}, node {node_id}'
        self._socket.join(self)

    def _recv_internal(self, timeout):
        try:
            return self.queue.get(timeout=timeout), False
        except queue.Empty:
            return None, False

    def send(self, msg: can.Message, timeout=None) -> None:
        """Send ``msg`` on the shared socket."""
        self._socket.send(msg)

    def shutdown(self) -> None:
        """Leave the shared socket."""
        self._socket.leave(self)
        super().shutdown()


def run_drives(args, bus_options: Dict) -> None:
    """Host simulated drives ``--nodes`` until told to stop (``--shared-socket``: on one)."""
    drive_module, pdo_module = import_retrying('cbcan_ros.simulation.durand.drive',
                                               'cbcan_ros.simulation.durand.drive_pdos')
    pdos = (pdo_module.default_drive_pdos(args.transmission_type) if args.transmission_type
            else pdo_module.drive_pdos(args.layout))
    shared = None
    if args.shared_socket:
        # python-can finds a bus class by its interface name in BACKENDS (the entry point
        # of interface plugins); ignore_config skips its check of the name against the list
        # made at import.
        can.interfaces.BACKENDS[SHARED_INTERFACE] = (__name__, 'SharedUdpBus')
        shared = SHARED_SOCKETS[args.channel] = SharedSocket(args.channel, bus_options,
                                                             args.nodes)
        drives = [drive_module.DurandDrive(
            node_id, interface=SHARED_INTERFACE, channel=args.channel,
            bus_options={'node_id': node_id, 'ignore_config': True}, pdos=pdos)
            for node_id in args.nodes]
    else:
        drives = [drive_module.DurandDrive(node_id, interface='udp_multicast',
                                           channel=args.channel, bus_options=bus_options,
                                           pdos=pdos)
                  for node_id in args.nodes]
    for drive in drives:
        drive.start()
    try:
        _serve(lambda: {'states': {drive.node_id: drive.drive_state for drive in drives}},
               {'generate': shared.generate} if shared is not None else None)
    finally:
        for drive in drives:
            drive.stop()
        if shared is not None:
            shared.close()


class LateAnswers:
    """Sends each device's SDO answers ``delay`` s after they are ready, devices apart.

    A real device takes about a millisecond to answer an SDO request; the simulated ones
    answer at once, on the CPU the master needs too. One thread sends every answer at its
    time, so one device's wait never holds up another's.
    """

    def __init__(self, delay: float):
        self._delay = delay
        self._due: List = []
        self._order = itertools.count()
        self._changed = threading.Condition()
        threading.Thread(target=self._run, daemon=True, name='late answers').start()

    def wrap(self, send):
        """Return ``send`` (one answer frame) delayed."""
        def later(response) -> None:
            with self._changed:
                heapq.heappush(self._due, (time.monotonic() + self._delay, next(self._order),
                                           send, bytes(response)))
                self._changed.notify()
        return later

    def _run(self) -> None:
        with self._changed:
            while True:
                now = time.monotonic()
                if self._due and self._due[0][0] <= now:
                    _, _, send, response = heapq.heappop(self._due)
                    self._changed.release()
                    try:
                        send(response)
                    finally:
                        self._changed.acquire()
                    continue
                self._changed.wait(self._due[0][0] - now if self._due else None)


def run_devices(args, bus_options: Dict) -> None:
    """Host ``SimulatedDevice`` s of ``--eds`` at ``--nodes`` (``--shared-socket``: on one).

    Each counts the SDO writes it takes (``stats``), so a boot that wrote less than it
    should shows in the report.
    """
    device_module, = import_retrying('cbcan_ros.simulation.canopen_device')
    shared = None
    if args.shared_socket:
        can.interfaces.BACKENDS[SHARED_INTERFACE] = (__name__, 'SharedUdpBus')
        shared = SHARED_SOCKETS[args.channel] = SharedSocket(args.channel, bus_options,
                                                             args.nodes)
    devices = []
    writes = dict.fromkeys(args.nodes, 0)
    late = LateAnswers(args.answer_delay) if args.answer_delay else None
    for node_id in args.nodes:
        if shared is not None:
            device = device_module.SimulatedDevice(
                node_id, args.eds, interface=SHARED_INTERFACE, channel=args.channel,
                bus_options={'node_id': node_id, 'ignore_config': True})
        else:
            device = device_module.SimulatedDevice(node_id, args.eds, interface='udp_multicast',
                                                   channel=args.channel,
                                                   bus_options=bus_options)

        def count(node_id=node_id, **_access) -> None:
            writes[node_id] += 1

        device.node.add_write_callback(count)
        if late is not None:
            device.node.sdo.send_response = late.wrap(device.node.sdo.send_response)
        devices.append(device)
    for device in devices:
        device.start()
    try:
        _serve(lambda: {'writes': dict(writes),
                        'states': {device.node_id: device.state for device in devices}})
    finally:
        for device in devices:
            device.stop()
        if shared is not None:
            shared.close()


def run_bootloader(args, bus_options: Dict) -> None:
    """Host one ``BootloaderDevice`` at the first of ``--nodes``, clearing and flashing at once."""
    bootloader, = import_retrying('cbcan_ros.simulation.durand.bootloader')
    device = bootloader.BootloaderDevice(args.nodes[0], interface='udp_multicast',
                                         channel=args.channel, bus_options=bus_options,
                                         flash_time=0.0, clear_time=0.0)
    device.start()
    try:
        _serve(lambda: {'image_size': len(device.image), 'software_id': device.software_id,
                        'starts': device.starts})
    finally:
        device.stop()


def run_reader(args, bus_options: Dict) -> None:
    """Receive and count every frame, by kind: the floor of receiving them.

    With ``--record``, frames of those COB-IDs are also kept with the time they reached the
    socket (the kernel's receive timestamp, wall clock: not when this process got round to
    them) and handed over, and forgotten, on ``{"op": "stats"}``.
    """
    bus = _bus(args, bus_options)
    counts = dict.fromkeys(('sync', 'tpdo', 'rpdo', 'sdo', 'heartbeat', 'emcy', 'other'), 0)
    recorded = []
    lock = threading.Lock()
    done = threading.Event()

    def count() -> None:
        while not done.is_set():
            message = bus.recv(0.5)
            if message is not None:
                kind = frame_kind(message.arbitration_id)
                with lock:
                    counts[kind] += 1
                    if message.arbitration_id in args.record:
                        recorded.append((message.timestamp, message.arbitration_id,
                                         bytes(message.data).hex()))

    def stats() -> dict:
        with lock:
            frames = list(recorded)
            recorded.clear()
            return {'counts': dict(counts), 'frames': frames}

    thread = threading.Thread(target=count, daemon=True)
    thread.start()
    try:
        _serve(stats)
    finally:
        done.set()
        thread.join()
        bus.shutdown()


def run_relay(args, bus_options: Dict) -> None:
    """Send every Float64 of ``--topic`` as one frame on the bus, from the subscription."""
    import rclpy
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Float64

    bus = _bus(args, bus_options)
    rclpy.init()
    node = rclpy.create_node('bench_relay')
    best_effort = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                             reliability=ReliabilityPolicy.BEST_EFFORT)

    def relay(message: Float64) -> None:
        data = struct.pack('<ih', round(message.data), 0)
        bus.send(can.Message(arbitration_id=RELAY_COB_ID, data=data, is_extended_id=False))

    node.create_subscription(Float64, args.topic, relay, best_effort)
    try:
        _spin_and_serve(node, threading.Event())
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        bus.shutdown()


def _spin_and_serve(node, done: threading.Event) -> None:
    """Spin ``node`` as the gateway's node spins, answering commands until ``stop``.

    ``done`` is set on the way out, before the executor is shut down.
    """
    from rclpy.executors import ExternalShutdownException
    from rclpy.experimental import EventsExecutor

    executor = EventsExecutor()
    executor.add_node(node)

    def spin() -> None:
        # spin_once in a loop: EventsExecutor.spin() on a thread of its own took a core here
        # and ran no callback.
        while not done.is_set():
            executor.spin_once(timeout_sec=0.1)

    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    try:
        _serve()
    except ExternalShutdownException:
        pass
    finally:
        done.set()
        spinner.join()
        executor.shutdown(timeout_sec=2.0)


def run_floor(args, bus_options: Dict) -> None:
    """Do the least a gateway of the control-rate row must do (see the module's text)."""
    import rclpy
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState

    bus = _bus(args, bus_options)
    rclpy.init()
    node = rclpy.create_node('floor', namespace=args.namespace)
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                     reliability=ReliabilityPolicy.RELIABLE)
    states = node.create_publisher(JointState, 'joint_states', qos)
    drives = sorted(args.nodes)
    names = [f'node_{node_id}' for node_id in drives]
    rpdos = {name: 0x200 + node_id for name, node_id in zip(names, drives, strict=True)}
    positions = dict.fromkeys(drives, 0)

    def command(message: JointState) -> None:
        for name, position in zip(message.name, message.position, strict=False):
            bus.send(can.Message(arbitration_id=rpdos[name], is_extended_id=False,
                                 data=struct.pack('<Hib', 0x0F, round(position), 8)))

    node.create_subscription(JointState, 'joint_commands', command, qos)
    done = threading.Event()

    def take() -> None:
        tpdos = 0
        while not done.is_set():
            message = bus.recv(0.5)
            if message is None:
                continue
            cob_id = message.arbitration_id
            if cob_id == SYNC_COB_ID:
                tpdos = 0
            elif cob_id & 0x780 in (0x180, 0x280) and cob_id & 0x7F in positions:
                if cob_id & 0x780 == 0x280:
                    positions[cob_id & 0x7F] = struct.unpack_from('<i', message.data)[0]
                tpdos += 1
                if tpdos == 2 * len(drives):
                    states.publish(JointState(name=names, position=[
                        float(positions[node_id]) for node_id in drives]))

    bus.send(can.Message(arbitration_id=0x000, data=bytes([1, 0]), is_extended_id=False))
    sync = bus.send_periodic(can.Message(arbitration_id=SYNC_COB_ID, data=b'',
                                         is_extended_id=False), args.period)
    taker = threading.Thread(target=take, daemon=True)
    taker.start()
    try:
        _spin_and_serve(node, done)
    finally:
        sync.stop()
        taker.join()
        node.destroy_node()
        rclpy.try_shutdown()
        bus.shutdown()


def run_enable_floor(args, bus_options: Dict) -> None:
    """Serve ``--namespace``/drive_command with BaseNode402 inside the callback (module text).

    And ``drive_command_answered_later``: the same enable run on a worker thread, answered from
    there (``rclpy_gaps.intercept_responses``, as the gateway answers), so the executor is free
    while the drive steps: the least a ROS gateway of python canopen does that must go on
    serving other calls and publishing meanwhile.
    """
    import queue

    from bench_drives import Canopen402, UdpBus
    import rclpy

    from cbcan_ros.ros.interface import SERVICE_QOS
    from cbcan_ros.ros.rclpy_gaps import intercept_responses
    from cbcan_ros.srv import DriveCommand

    drive = Canopen402(UdpBus(args.channel, bus_options['port']), args.nodes[0])
    rclpy.init()
    node = rclpy.create_node('enable_floor', namespace=args.namespace)
    steps = {'enable': drive.enable, 'disable': drive.disable}

    def command(request, response):
        try:
            steps[request.command]()
            response.success = True
        except (KeyError, RuntimeError) as error:
            response.message = f'{request.command}: {error!r}'
        return response

    node.create_service(DriveCommand, 'drive_command', command, qos_profile=SERVICE_QOS)
    requests: queue.Queue = queue.Queue()  # a request, then the header of its answer

    def take(request, response):
        requests.put((request, response))
        return response  # a placeholder: the worker answers it

    def answer_later(response, header) -> None:
        requests.put((None, (response, header)))

    send = intercept_responses(node.create_service(
        DriveCommand, 'drive_command_answered_later', take, qos_profile=SERVICE_QOS),
        answer_later)

    def work() -> None:
        taken = {}  # the request of each placeholder response, until its header comes
        while True:
            request, response = requests.get()
            if request is not None:
                taken[id(response)] = request
                continue
            if response is None:
                return
            response, header = response
            send(command(taken.pop(id(response)), response), header)

    worker = threading.Thread(target=work, daemon=True)
    worker.start()
    try:
        _spin_and_serve(node, threading.Event())
    finally:
        requests.put((None, None))
        worker.join()
        node.destroy_node()
        rclpy.try_shutdown()
        drive.close()


MODES = {'drives': run_drives, 'devices': run_devices, 'bootloader': run_bootloader,
         'reader': run_reader, 'relay': run_relay, 'floor': run_floor,
         'enable-floor': run_enable_floor}


def main(argv=None) -> int:
    """Run one of the helper processes until told to stop, stdin closes or a signal arrives."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('mode', choices=MODES)
    parser.add_argument('--channel', required=True, help='udp_multicast group')
    parser.add_argument('--bus-options', default='{}', help='JSON, e.g. {"port": 30001}')
    parser.add_argument('--nodes', type=lambda text: [int(n) for n in text.split(',')],
                        default=[1], help='node ids of the drives or devices, e.g. 1,2,3')
    parser.add_argument('--transmission-type', type=int, default=0,
                        help="0: the drives' default PDOs (asynchronous); 1: every SYNC")
    parser.add_argument('--layout', default='combined',
                        help="the drives' PDO layout (simulated_drives.LAYOUTS), without "
                             '--transmission-type')
    parser.add_argument('--shared-socket', action='store_true',
                        help='drives and devices modes: one udp_multicast socket for all')
    parser.add_argument('--eds', help='devices mode: the EDS the simulated devices serve')
    parser.add_argument('--answer-delay', type=float, default=0.0,
                        help='devices mode: seconds each SDO answer takes, as on a real '
                             'device (0: at once)')
    parser.add_argument('--record', type=lambda text: {int(i, 0) for i in text.split(',')},
                        default=set(), help='reader mode: COB-IDs whose frames are kept, '
                                            'e.g. 0x181,0x201')
    parser.add_argument('--topic', default='/bench_relay/target', help='relay mode')
    parser.add_argument('--namespace', default='/bench_floor',
                        help='floor and enable-floor modes')
    parser.add_argument('--period', type=float, default=0.004,
                        help='floor mode: the SYNC period, seconds')
    args = parser.parse_args(argv)
    exit_on_sigterm()
    try:
        MODES[args.mode](args, json.loads(args.bus_options))
    except (KeyboardInterrupt, SystemExit):
        pass
    progress(f'{args.mode} process done')
    return 0


if __name__ == '__main__':
    sys.exit(main())
