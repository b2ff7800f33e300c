"""Raw CAN frame benchmarks: the gateway's raw bridge beside a bare bridge, in the same run.

Run by ``make bench`` (``make bench ARGS=--quick`` shortens it); writes ``raw.md`` and
``raw.json`` in ``bench/out/`` (``--output``). A script, not a test: a target that is not met
is reported, never fatal. Each row is measured twice, one after the other: through the
gateway, and through a bare bridge (a python-can receive loop publishing each frame as a
``can_msgs/msg/Frame``, the least any Python raw bridge does: no filters, no CANopen beside
it), so the cost of the gateway's way shows beside the floor of this machine.

1. Frames published, none lost, at 5,000 frames/s from four senders, the bridge and the
   senders in one process on python-can's ``virtual`` bus: the frames sent, the frames a
   subscriber in a process of its own got (a subscriber in the bridge's process competes for
   its interpreter lock, and falls behind the bridge, not the other way round).
2. Bus to subscriber at 2,000 frames/s, the bridge in its own process on ``udp_multicast``:
   the frame carries its send time (CLOCK_MONOTONIC, one clock for every process of the
   machine), the subscriber in this process takes the difference; p50 and p99.
3. The bridge process's CPU while those 2,000 frames/s flow, from /proc.
4. CANopen beside a flood: SDO reads of a simulated device (durand, a process of its own)
   through the node while four senders put 5,000 raw frames/s on ``udp_multicast`` and a
   subscriber (a process of its own) takes every one the node publishes: reads that failed.
"""

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import threading
import time
from typing import Dict, List, Optional
import uuid

from bench_util import (
    logs_to,
    MARK,
    OUTPUT,
    percentile,
    proc_cpu_seconds,
    progress,
    receive,
    ros_of_its_own,
    send,
    write_report,
)

START_TIMEOUT = 60.0
RAW_IDS = (0x7F0, 0x7F1, 0x7F2, 0x7F3)  # four senders, ids no CANopen service uses
FILTERS = ['7F0:7F0']


def _paced(buses: List, rate: float, seconds: float) -> int:
    """Send from ``buses`` in turn at ``rate`` frames/s for ``seconds``; return the count.

    Each frame carries its send time (``time.monotonic_ns()``) in its 8 bytes.
    """
    import can
    sent = 0
    start = time.monotonic()
    while True:
        now = time.monotonic()
        if now - start >= seconds:
            return sent
        due = int((now - start) * rate) + 1
        while sent < due:
            bus = buses[sent % len(buses)]
            bus.send(can.Message(arbitration_id=RAW_IDS[sent % len(RAW_IDS)],
                                 data=time.monotonic_ns().to_bytes(8, 'little'),
                                 is_extended_id=False))
            sent += 1
        time.sleep(0.0005)


class BareBridge:
    """The least a raw bridge does: receive a frame, publish it (``from_can_bus``)."""

    def __init__(self, node, bus):
        from can_msgs.msg import Frame

        from cbcan_ros.ros.raw_frames import RAW_QOS
        self._bus = bus
        self._publisher = node.create_publisher(Frame, '~/from_can_bus', RAW_QOS)
        self._message = Frame()
        self._running = True
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from builtin_interfaces.msg import Time
        out = self._message
        while self._running:
            message = self._bus.recv(0.1)
            if message is None:
                continue
            now = time.time()
            out.header.stamp = Time(sec=int(now), nanosec=int((now % 1) * 1e9))
            out.id = message.arbitration_id
            out.is_extended = message.is_extended_id
            out.dlc = message.dlc
            out.data = list(bytes(message.data).ljust(8, b'\0'))
            self._publisher.publish(out)

    def close(self) -> None:
        """Stop receiving and close the bus."""
        self._running = False
        self._thread.join()
        self._bus.shutdown()


def _until_sigterm() -> None:
    """Return when this process is sent SIGTERM (how the benchmark ends its helpers)."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    stop.wait()


def run_bare_bridge(group: str, port: int, namespace: str) -> int:
    """Run a bare bridge as its own process until SIGTERM (``--bare-bridge``)."""
    import can
    import rclpy
    rclpy.init()
    node = rclpy.create_node('bare_bridge', namespace=namespace)
    bridge = BareBridge(node, can.Bus(interface='udp_multicast', channel=group, port=port))
    _until_sigterm()
    bridge.close()
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def _subscriber(topic: str, on_frame):
    """Return (node, stop) of a subscriber that keeps up: deep history, an EventsExecutor."""
    from can_msgs.msg import Frame
    import rclpy
    from rclpy.experimental import EventsExecutor
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    node = rclpy.create_node(f'bench_raw_{uuid.uuid4().hex[:8]}')
    node.create_subscription(Frame, topic, on_frame, QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=10_000, reliability=ReliabilityPolicy.RELIABLE))
    executor = EventsExecutor()
    executor.add_node(node)
    running = threading.Event()
    running.set()

    def spin() -> None:
        while running.is_set():
            executor.spin_once(timeout_sec=0.1)
    thread = threading.Thread(target=spin, daemon=True)
    thread.start()

    def stop() -> None:
        running.clear()
        thread.join()
        executor.shutdown(timeout_sec=2.0)
        node.destroy_node()
    return node, stop


def run_counter(topic: str) -> int:
    """Count the frames of ``topic`` in a process of its own (``--count-frames``).

    Says ``ready`` once matched, then, told how many were sent, how many it got.
    """
    import rclpy
    rclpy.init()
    received = [0]
    node, stop = _subscriber(topic, lambda _m: received.__setitem__(0, received[0] + 1))
    _wait_matched(node, topic)
    send({'ready': True})
    expected = receive()['sent']
    deadline = time.monotonic() + 10.0
    while received[0] < expected and time.monotonic() < deadline:
        time.sleep(0.05)
    send({'received': received[0]})
    stop()
    rclpy.try_shutdown()
    return 0


class Counter:
    """The counting subscriber's process (:func:`run_counter`)."""

    def __init__(self, topic: str):
        self.process = subprocess.Popen(
            [sys.executable, os.path.abspath(__file__), '--count-frames', topic],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    def message(self) -> Dict:
        """Return the next message of the counter."""
        for line in self.process.stdout:
            if line.startswith(MARK):
                return json.loads(line[len(MARK):])
        raise RuntimeError('the counting subscriber ended')

    def received(self, sent: int) -> int:
        """Tell the counter how many frames were sent; return how many it got."""
        self.process.stdin.write(json.dumps({'sent': sent}) + '\n')
        self.process.stdin.flush()
        received = self.message()['received']
        self.process.wait(10)
        return received


def _wait_matched(node, topic: str) -> None:
    deadline = time.monotonic() + START_TIMEOUT
    while not node.count_publishers(topic) and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(1.0)  # the publisher's side of the match, too


def row_published(seconds: float, bare: bool) -> Dict:
    """Row 1, one process on the virtual bus: through the gateway node, or a bare bridge."""
    import can
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from cbcan_ros.ros.node import CbcanNode
    channel = f'bench-raw-{uuid.uuid4().hex[:8]}'
    if bare:
        bridge_node = rclpy.create_node('cbcan')
        gateway = BareBridge(bridge_node, can.Bus(interface='virtual', channel=channel))
        topic = '/cbcan/from_can_bus'
    else:
        bridge_node = CbcanNode(parameter_overrides=[
            Parameter('can.interface', value='virtual'), Parameter('can.channel', value=channel),
            Parameter('raw.filters', value=FILTERS)])
        topic = '/cbcan/from_can_bus'
        executor = SingleThreadedExecutor()
        executor.add_node(bridge_node)
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()
    counter = Counter(topic)
    counter.message()  # matched
    time.sleep(1.0)  # the publisher's side of the match, too
    senders = [can.Bus(interface='virtual', channel=channel) for _ in RAW_IDS]
    sent = _paced(senders, 5000, seconds)
    received = counter.received(sent)
    for bus in senders:
        bus.shutdown()
    taken = None  # the frames the gateway's bus thread took and passed the filters
    if bare:
        gateway.close()
    else:
        taken = bridge_node.interface.gateway.raw.statistics().received
        executor.shutdown(timeout_sec=2.0)
    bridge_node.destroy_node()
    return {'value': sent - received, 'unit': 'frames lost', 'sent': sent,
            'received': received, 'rate': sent / seconds, 'taken': taken}


def run_flood(group: str, port: int, seconds: float) -> int:
    """Send 5,000 frames/s from four buses for ``seconds``; say how many (``--flood``)."""
    import can
    senders = [can.Bus(interface='udp_multicast', channel=group, port=port) for _ in RAW_IDS]
    sent = _paced(senders, 5000, seconds)
    for bus in senders:
        bus.shutdown()
    send({'sent': sent})
    return 0


def run_device(group: str, port: int) -> int:
    """Run simulated device 2 on ``udp_multicast`` until SIGTERM (``--device``)."""
    from cbcan_ros.simulation.durand.device import DurandDevice
    device = DurandDevice(2, interface='udp_multicast', channel=group,
                          bus_options={'port': port})
    device.start()
    _until_sigterm()
    device.stop()
    return 0


class Bridge:
    """The installed cbcan_node, or a bare bridge, in its own process on udp_multicast."""

    def __init__(self, bare: bool, log_path: str, parameters=()):
        import can
        self.group = f'239.{random.randint(1, 254)}.{random.randint(0, 255)}.' \
                     f'{random.randint(1, 254)}'
        self.port = random.randint(20000, 40000)
        namespace = f'/benchraw{uuid.uuid4().hex[:8]}'
        self._log = open(log_path, 'w')
        if bare:
            self.topic = f'{namespace}/bare_bridge/from_can_bus'
            command = [sys.executable, os.path.abspath(__file__), '--bare-bridge', self.group,
                       str(self.port), namespace]
        else:
            self.topic = f'{namespace}/cbcan/from_can_bus'
            executable = shutil.which('cbcan_node')
            if not executable:
                raise SystemExit('cbcan_node is not on PATH (run through make bench)')
            command = [executable, '--ros-args', '-r', f'__ns:={namespace}',
                       '-p', 'can.interface:=udp_multicast', '-p', f'can.channel:={self.group}',
                       '-p', f'raw.filters:={FILTERS}', *parameters]
        self.process = subprocess.Popen(
            command, stdout=self._log, stderr=subprocess.STDOUT,
            env={**os.environ, 'CAN_CONFIG': json.dumps({'port': self.port})})
        self.bus = can.Bus(interface='udp_multicast', channel=self.group, port=self.port)

    def close(self) -> None:
        """End the bridge process."""
        self.bus.shutdown()
        self.process.terminate()
        self.process.wait(10)
        self._log.close()


def rows_in_own_process(seconds: float, bare: bool, output: str) -> Dict[str, Dict]:
    """Rows 2 and 3: 2,000 frames/s through a bridge in its own process."""
    bridge = Bridge(bare, os.path.join(output, f'raw_{"bare" if bare else "node"}.log'))
    latencies: List[float] = []
    listener, stop_listening = _subscriber(bridge.topic, lambda m: latencies.append(
        (time.monotonic_ns() - int.from_bytes(bytes(m.data), 'little')) / 1e9))
    rows = {}
    try:
        deadline = time.monotonic() + START_TIMEOUT
        while not latencies and time.monotonic() < deadline:
            _paced([bridge.bus], 20, 0.5)
        latencies.clear()
        before = proc_cpu_seconds(bridge.process.pid)
        started = time.monotonic()
        sent = _paced([bridge.bus], 2000, seconds)
        used = proc_cpu_seconds(bridge.process.pid) - before
        elapsed = time.monotonic() - started
        time.sleep(1.0)
        rows['latency'] = {'value': percentile(latencies, 0.99) * 1000 if latencies else None,
                           'unit': 'ms p99', 'p50': percentile(latencies, 0.5) * 1000
                           if latencies else None, 'samples': len(latencies), 'sent': sent}
        rows['cpu'] = {'value': 100 * used / elapsed, 'unit': '% of a core'}
    finally:
        stop_listening()
        bridge.close()
    return rows


def row_canopen_under_flood(seconds: float, output: str) -> Dict:
    """Row 4: SDO reads through the node while 5,000 raw frames/s are published."""
    from rclpy.executors import SingleThreadedExecutor
    import rclpy.node

    from cbcan_ros.srv import SdoRead
    bridge = Bridge(False, os.path.join(output, 'raw_flood_node.log'),
                    ('-p', 'nodes:=[2]', '-p', 'sdo.timeout:=0.5'))
    device = subprocess.Popen([sys.executable, os.path.abspath(__file__), '--device',
                               bridge.group, str(bridge.port)])
    counter = Counter(bridge.topic)
    node = rclpy.node.Node(f'bench_flood_{uuid.uuid4().hex[:8]}')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    client = node.create_client(SdoRead, bridge.topic.replace('from_can_bus', 'sdo_read'))

    def read() -> bool:
        future = client.call_async(SdoRead.Request(node_id=2, index=0x1000))
        executor.spin_until_future_complete(future, timeout_sec=5.0)
        return future.done() and future.result().success

    try:
        counter.message()  # matched
        client.wait_for_service(timeout_sec=START_TIMEOUT)
        deadline = time.monotonic() + START_TIMEOUT
        while not read() and time.monotonic() < deadline:
            time.sleep(0.2)
        # The senders in a process of their own: here they would wait for this one's reads.
        flood = subprocess.Popen(
            [sys.executable, os.path.abspath(__file__), '--flood', bridge.group,
             str(bridge.port), str(seconds)], stdout=subprocess.PIPE, text=True)
        reads = failed = 0
        while flood.poll() is None:
            reads += 1
            failed += not read()
        sent = json.loads(flood.stdout.read().split(MARK)[-1])['sent']
        received = counter.received(sent)
    finally:
        device.terminate()
        device.wait(10)
        node.destroy_node()
        bridge.close()
    return {'value': failed, 'unit': 'reads failed', 'reads': reads, 'sent': sent,
            'received': received}


# (row, title, target, met(gateway's value, bare bridge's value or None))
TARGETS = (
    ('published', 'raw frames published, 4 senders, 5,000 frames/s, virtual',
     'none lost', lambda v, _bare: v == 0),
    ('latency', 'bus to subscriber at 2,000 frames/s, bridge in its own process (udp)',
     'p99 <= 5 ms', lambda v, _bare: v <= 5),
    # The gateway does more than a bare bridge (filters, its own frames told apart, CANopen
    # beside it): the target is what that may cost.
    ('cpu', "bridge process's CPU, 2,000 raw frames/s (udp)", '<= 1.5 x the bare bridge',
     lambda v, bare: bare is not None and v <= 1.5 * bare),
    ('flood', 'SDO reads during a 5,000 frames/s published raw flood (udp)', 'none fails',
     lambda v, _bare: v == 0),
)


def _shown(row: Optional[Dict]) -> str:
    value = (row or {}).get('value')
    if value is None:
        return 'not measured'
    extra = f' (p50 {row["p50"]:.3g} ms)' if row.get('p50') is not None else ''
    if row.get('reads') is not None:
        extra = (f' of {row["reads"]} ({row["sent"]:,} raw frames sent, '
                 f'{row["received"]:,} received by the subscriber)')
    if row.get('rate') is not None:
        extra = f' of {row["sent"]} ({row["rate"]:,.0f} frames/s sent)'
    return f'{value:.3g} {row.get("unit", "")}{extra}'


def report(rows: Dict[str, Dict], output: str) -> str:
    """Write raw.md and raw.json; return the table."""
    lines = ['| row | target | gateway | met | bare bridge |', '|---|---|---|---|---|']
    for key, title, target, met in TARGETS:
        row = rows.get(key) or {}
        value = row.get('value')
        bare = (rows.get('bare_' + key) or {}).get('value')
        verdict = '' if value is None else ('yes' if met(value, bare) else '**no**')
        lines.append(f'| {title} | {target} | {_shown(row)} | {verdict} | '
                     f'{_shown(rows.get("bare_" + key))} |')
    table = '\n'.join(lines)
    write_report(output, 'raw', 'Raw CAN frame benchmark', table, rows)
    return table


def main(argv=None) -> int:
    """Run the raw frame rows, gateway and bare bridge, and report them."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--quick', action='store_true', help='shorter measurements')
    parser.add_argument('--only', help='ignored (bench_sdo.py option)')
    parser.add_argument('--output', default=OUTPUT,
                        help="folder of raw.md, raw.json and the bridges' logs (default "
                             '%(default)s)')
    parser.add_argument('--bare-bridge', nargs=3, metavar=('GROUP', 'PORT', 'NAMESPACE'),
                        help=argparse.SUPPRESS)
    parser.add_argument('--count-frames', metavar='TOPIC', help=argparse.SUPPRESS)
    parser.add_argument('--flood', nargs=3, help=argparse.SUPPRESS)
    parser.add_argument('--device', nargs=2, metavar=('GROUP', 'PORT'), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.flood:
        return run_flood(args.flood[0], int(args.flood[1]), float(args.flood[2]))
    if args.device:
        return run_device(args.device[0], int(args.device[1]))
    if args.count_frames:
        return run_counter(args.count_frames)
    if args.bare_bridge:
        group, port, namespace = args.bare_bridge
        return run_bare_bridge(group, int(port), namespace)
    logs_to(os.path.join(args.output, 'raw_logs.txt'))
    seconds = 2.0 if args.quick else 5.0
    ros_of_its_own()
    import rclpy
    rclpy.init()
    rows: Dict[str, Dict] = {}
    try:
        for bare in (False, True):
            prefix = 'bare_' if bare else ''
            who = 'bare bridge' if bare else 'gateway'
            progress(f'raw: {who}, 5,000 frames/s, one process')
            rows[f'{prefix}published'] = row_published(seconds, bare)
            progress(f'raw: {who} in its own process, 2,000 frames/s')
            rows.update({f'{prefix}{key}': row for key, row in
                         rows_in_own_process(seconds, bare, args.output).items()})
        progress('raw: SDO reads through the gateway during a 5,000 frames/s flood')
        rows['flood'] = row_canopen_under_flood(2 * seconds, args.output)
    except KeyboardInterrupt:
        progress('interrupted')
    finally:
        rclpy.try_shutdown()
    print(report(rows, args.output))
    return 0


if __name__ == '__main__':
    sys.exit(main())
