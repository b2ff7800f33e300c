"""PDO and SYNC benchmarks: the five targets of the PDO feature, one row each.

Run by ``make bench`` after ``bench_sdo.py`` (``make bench ARGS=--quick`` shortens it); writes
``pdo.md`` and ``pdo.json`` in ``bench/out/`` (``--output``). A script, not a test: a target
that is not met is reported, never fatal.

1. Received PDOs published, none lost: 32 devices, 5,000 frames/s in all, everything in one
   process on python-can's ``virtual`` bus (gateway node, a raw sender, the subscriber).
2. Frame to subscriber latency at 2,000 frames/s, the installed ``cbcan_node`` in its own
   process on ``udp_multicast``: the frame carries its send time (CLOCK_MONOTONIC is one clock
   for every process of the machine), the subscriber in this process takes the difference.
3. SYNC at 10 ms produced by that node: the period error between SYNCs at a raw receiver,
   by the kernel's receive timestamps of its socket (udp_multicast's message timestamps).
4. Topic to frame: a Pdo published on ``~/node_1/tpdo`` carrying its send time, until the RPDO
   frame arrives at a raw receiver.
5. The node's CPU while 8 devices send 2 TPDOs each at 100 Hz (1,600 frames/s), from /proc.

The devices whose mappings the gateway reads are durand devices (node ids 1..32, TPDO 1 and 2
and RPDO 1 of 64 bits each); they stay pre-operational, so the frames measured come from a raw
sender alone, at the rate given.
"""

import argparse
import json
import os
import random
import shutil
import subprocess
import sys
import threading
import time
from typing import Dict, List
import uuid

from bench_util import (
    logs_to,
    OUTPUT,
    percentile,
    proc_cpu_seconds,
    progress,
    ros_of_its_own,
    write_report,
)

START_TIMEOUT = 60.0
PDOS = None  # set in main() once the package is importable


def _devices(node_ids, interface, channel, options=None):
    from cbcan_ros.simulation.durand.device import DurandDevice
    devices = [DurandDevice(node_id, interface, channel, bus_options=options, pdos=PDOS)
               for node_id in node_ids]
    for device in devices:
        device.start()
    return devices


def _paced(bus, frames: List, rate: float, seconds: float, stamp: bool = False) -> int:
    """Send ``frames`` round robin at ``rate`` per second for ``seconds``; return the count."""
    import can
    sent = 0
    start = time.monotonic()
    while True:
        now = time.monotonic()
        if now - start >= seconds:
            return sent
        due = int((now - start) * rate) + 1
        while sent < due:
            cob_id = frames[sent % len(frames)]
            data = time.monotonic_ns().to_bytes(8, 'little') if stamp else \
                sent.to_bytes(8, 'little')
            bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))
            sent += 1
        time.sleep(0.0005)


def row_published_none_lost(seconds: float) -> Dict:
    """Row 1: 32 devices, 5,000 frames/s, one process on the virtual bus."""
    import can
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.experimental import EventsExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    from cbcan_ros.msg import Pdo
    from cbcan_ros.ros.node import CbcanNode

    channel = f'bench-pdo-{uuid.uuid4().hex[:8]}'
    node_ids = list(range(1, 33))
    devices = _devices(node_ids, 'virtual', channel)
    node = CbcanNode(parameter_overrides=[
        Parameter('can.interface', value='virtual'), Parameter('can.channel', value=channel),
        Parameter('pdo.nodes', value=node_ids)])
    listener = rclpy.create_node(f'bench_pdo_{uuid.uuid4().hex[:8]}')
    received = [0]
    # A subscriber that keeps up: deep history, its own EventsExecutor (as the node's).
    deep = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10_000,
                      reliability=ReliabilityPolicy.RELIABLE)
    for node_id in node_ids:
        listener.create_subscription(Pdo, f'/cbcan/node_{node_id}/rpdo',
                                     lambda _m: received.__setitem__(0, received[0] + 1),
                                     deep)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    listening = EventsExecutor()
    listening.add_node(listener)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    listening_done = threading.Event()

    def listen() -> None:
        while not listening_done.is_set():
            listening.spin_once(timeout_sec=0.1)
    listener_thread = threading.Thread(target=listen, daemon=True)
    listener_thread.start()
    pdo = node.interface.gateway.pdo
    deadline = time.monotonic() + START_TIMEOUT
    while not all(pdo.mappings(n)[0] for n in node_ids) and time.monotonic() < deadline:
        time.sleep(0.05)
    for device in devices:
        device.stop()  # the raw sender alone makes the frames; nothing else on the bus
    time.sleep(1.0)  # subscriptions matched
    bus = can.Bus(interface='virtual', channel=channel)
    sent = _paced(bus, [0x180 + n for n in node_ids] + [0x280 + n for n in node_ids],
                  5000, seconds)
    deadline = time.monotonic() + 10.0
    while received[0] < sent and time.monotonic() < deadline:
        time.sleep(0.05)
    bus.shutdown()
    statistics = node.interface.gateway.pdo.statistics()
    decoded = sum(s.received for s in statistics.values())
    listening_done.set()
    listener_thread.join()
    executor.shutdown(timeout_sec=2.0)
    listener.destroy_node()
    node.destroy_node()
    return {'value': sent - received[0], 'unit': 'frames lost', 'sent': sent,
            'decoded': decoded, 'received': received[0], 'rate': sent / seconds}


def _drain(bus) -> None:
    """Drop the frames waiting in ``bus`` (udp_multicast hands a process its own back)."""
    while bus.recv(0) is not None:
        pass


class UdpNode:
    """The installed cbcan_node in its own process on a private udp_multicast bus."""

    def __init__(self, node_ids: List[int], log_path: str):
        self.group = f'239.{random.randint(1, 254)}.{random.randint(0, 255)}.' \
                     f'{random.randint(1, 254)}'
        self.port = random.randint(20000, 40000)
        self.name = f'/benchpdo{uuid.uuid4().hex[:8]}/cbcan'
        executable = shutil.which('cbcan_node')
        if not executable:
            raise SystemExit('cbcan_node is not on PATH (run through make bench)')
        self._log = open(log_path, 'w')
        self.process = subprocess.Popen(
            [executable, '--ros-args', '-r', f'__ns:={self.name.rpartition("/")[0]}',
             '-p', 'can.interface:=udp_multicast', '-p', f'can.channel:={self.group}',
             '-p', f'pdo.nodes:={node_ids}', '-p', 'sync.period:=0.01'],
            stdout=self._log, stderr=subprocess.STDOUT,
            env={**os.environ, 'CAN_CONFIG': json.dumps({'port': self.port})})

    def bus(self):
        """Return a raw python-can bus on the node's udp_multicast channel."""
        import can
        return can.Bus(interface='udp_multicast', channel=self.group, port=self.port)

    def close(self) -> None:
        """End the node process."""
        self.process.terminate()
        self.process.wait(10)
        self._log.close()


def rows_in_own_process(seconds: float, output: str) -> Dict[str, Dict]:
    """Rows 2-5 against the installed node on udp_multicast."""
    import rclpy
    from rclpy.experimental import EventsExecutor

    from cbcan_ros.msg import Pdo
    from cbcan_ros.ros.pdo import PDO_QOS

    node_ids = list(range(1, 9))
    node = UdpNode(node_ids, os.path.join(output, 'pdo_node.log'))
    devices = _devices(node_ids, 'udp_multicast', node.group, {'port': node.port})
    client = rclpy.create_node(f'bench_pdo_{uuid.uuid4().hex[:8]}')
    latencies: List[float] = []
    client.create_subscription(
        Pdo, f'{node.name}/node_1/rpdo',
        lambda m: latencies.append((time.monotonic_ns() -
                                    int.from_bytes(bytes(m.data), 'little')) / 1e9), PDO_QOS)
    publisher = client.create_publisher(Pdo, f'{node.name}/node_1/tpdo', PDO_QOS)
    executor = EventsExecutor()  # as the node's: the subscriber must not be the bottleneck
    executor.add_node(client)
    spinning = threading.Event()
    spinning.set()

    def spin() -> None:
        while spinning.is_set():
            executor.spin_once(timeout_sec=0.1)
    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    rows = {}
    bus = node.bus()
    try:
        # Mappings read, topics matched: a frame of node 1 arrives at the subscriber.
        deadline = time.monotonic() + START_TIMEOUT
        while not latencies and time.monotonic() < deadline:
            _paced(bus, [0x181], 20, 0.5, stamp=True)
        time.sleep(2.0)  # the other devices' mappings
        for device in devices:
            device.stop()  # each would receive every frame in this process
        latencies.clear()

        progress('PDO: SYNC period at a receiver')
        _drain(bus)
        syncs = []
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            message = bus.recv(0.1)
            if message is not None and message.arbitration_id == 0x80:
                # The socket's kernel receive time: when the SYNC reached this receiver, not
                # when this (loaded) process got round to reading it.
                syncs.append(message.timestamp)
        errors = [abs((b - a) - 0.01) for a, b in zip(syncs, syncs[1:], strict=False)]
        rows['sync'] = {'value': percentile(errors, 0.99) * 1000 if errors else None,
                        'unit': 'ms p99 period error', 'samples': len(errors)}

        progress('PDO: frame to subscriber at 2,000 frames/s')
        _paced(bus, [0x181], 2000, seconds, stamp=True)
        time.sleep(1.0)
        rows['latency'] = {'value': percentile(latencies, 0.99) * 1000 if latencies else None,
                           'unit': 'ms p99', 'p50': percentile(latencies, 0.5) * 1000
                           if latencies else None, 'samples': len(latencies)}

        progress('PDO: topic to frame')
        _drain(bus)
        to_frame = []
        for _ in range(int(200 * seconds / 5) or 50):
            sent = time.monotonic_ns()
            publisher.publish(Pdo(pdo=1, data=list(sent.to_bytes(8, 'little'))))
            wait = time.monotonic() + 1.0
            while time.monotonic() < wait:
                message = bus.recv(0.05)
                if message is not None and message.arbitration_id == 0x201:
                    to_frame.append((time.monotonic_ns() -
                                     int.from_bytes(message.data, 'little')) / 1e9)
                    break
            time.sleep(0.01)
        rows['topic_to_frame'] = {'value': percentile(to_frame, 0.5) * 1000
                                  if to_frame else None, 'unit': 'ms p50',
                                  'samples': len(to_frame)}

        progress('PDO: node CPU, 8 devices x 2 TPDOs at 100 Hz')
        before = proc_cpu_seconds(node.process.pid)
        started = time.monotonic()
        _paced(bus, [base + n for n in node_ids for base in (0x180, 0x280)], 1600, seconds)
        used = proc_cpu_seconds(node.process.pid) - before
        rows['cpu'] = {'value': 100 * used / (time.monotonic() - started),
                       'unit': '% of a core'}
    finally:
        bus.shutdown()
        spinning.clear()
        spinner.join()
        executor.shutdown(timeout_sec=2.0)
        client.destroy_node()
        for device in devices:
            device.stop()
        node.close()
    return rows


TARGETS = (
    ('published', 'received PDOs published, 32 devices, 5,000 frames/s, virtual, one process',
     'none lost', lambda v: v == 0),
    ('latency', 'frame to subscriber at 2,000 frames/s, node in its own process (udp)',
     'p99 <= 5 ms', lambda v: v <= 5),
    ('sync', 'SYNC at 10 ms, period error at a receiver (udp)', 'p99 <= 1 ms',
     lambda v: v <= 1),
    ('topic_to_frame', 'tpdo topic to RPDO frame (udp)', 'p50 <= 1 ms', lambda v: v <= 1),
    ('cpu', 'node CPU, 8 devices x 2 TPDOs at 100 Hz (udp)', '< 30 % of a core',
     lambda v: v < 30),
)


def report(rows: Dict[str, Dict], output: str) -> str:
    """Write pdo.md and pdo.json; return the table."""
    lines = ['| row | target | measured | met |', '|---|---|---|---|']
    for key, title, target, met in TARGETS:
        row = rows.get(key) or {}
        value = row.get('value')
        shown = 'not measured' if value is None else f'{value:.3g} {row.get("unit", "")}'
        verdict = '' if value is None else ('yes' if met(value) else '**no**')
        lines.append(f'| {title} | {target} | {shown} | {verdict} |')
    table = '\n'.join(lines)
    write_report(output, 'pdo', 'PDO and SYNC benchmark', table, rows)
    return table


def main(argv=None) -> int:
    """Run the PDO rows and report them."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--quick', action='store_true', help='shorter measurements')
    parser.add_argument('--only', help='ignored (bench_sdo.py option)')
    parser.add_argument('--output', default=OUTPUT,
                        help='folder of pdo.md, pdo.json and the node logs (default %(default)s)')
    args = parser.parse_args(argv)
    logs_to(os.path.join(args.output, 'pdo_logs.txt'))
    seconds = 2.0 if args.quick else 5.0
    ros_of_its_own()
    import rclpy

    from cbcan_ros.simulation.durand.pdos import PdoConfig
    global PDOS
    PDOS = (PdoConfig('tpdo', 1, ((0x2002, 0), (0x2003, 0)), 255),
            PdoConfig('tpdo', 2, ((0x2002, 0), (0x2003, 0)), 255),
            PdoConfig('rpdo', 1, ((0x2002, 0), (0x2003, 0)), 255))
    rclpy.init()
    rows = {}
    try:
        progress('PDO: 32 devices, 5,000 frames/s, one process')
        rows['published'] = row_published_none_lost(seconds)
        rows.update(rows_in_own_process(seconds, args.output))
    except KeyboardInterrupt:
        progress('interrupted')
    finally:
        rclpy.try_shutdown()
    print(report(rows, args.output))
    return 0


if __name__ == '__main__':
    sys.exit(main())
