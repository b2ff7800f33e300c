"""Where the time of an SDO read goes: raw canopen, the gateway core, rclpy, the gateway service.

Run with ``make bench`` (or ``tools/ros-env python bench/bench_sdo.py --count 2000``). All
rows are measured in one run, against the same simulated devices on one python-can
``virtual`` bus:

* raw     python-canopen ``RemoteNode.sdo.upload(0x1000, 0)``, in the server process
* core    ``Gateway.sdo_read(node, 0x1000, 0).result()`` of the running gateway node
* trigger a bare rclpy std_srvs/Trigger service (the floor of any rclpy service call)
* service ``sdo_read`` of 0x1000 through the gateway node (CbcanNode)

Setup of trigger and service, identical for both: the server process hosts the CbcanNode
and a bare Trigger node, each in its own SingleThreadedExecutor spinning in its own thread
(the executor ``cbcan_node`` uses). The client is a separate process (as the CLI and other
nodes are): one node, one SingleThreadedExecutor, ``call_async`` then ``spin_once`` until
the future is done, SERVICE_QOS. The client alternates trigger and service calls,
and the server alternates raw and core reads, so drift of the machine hits both alike.

Throughput: bursts of concurrent calls spread over devices 2, 3 and 5, all sent at once
and awaited together; calls/s = calls / time until the last answer.
"""

import argparse
import json
import os
import random
import subprocess
import sys
import threading
import time
import uuid

import canopen
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from cbcan_ros.node import CbcanNode, SERVICE_QOS
from cbcan_ros.srv import SdoRead

DEVICES = (2, 3, 5)
DEVICE_TYPE = bytes([0x92, 0x01, 0x02, 0x00])  # 0x1000 of config/simulated_device.eds
WARMUP = 50
MAX_BURST = 250  # SERVICE_QOS keeps 256 requests; a larger burst would lose some


def percentile(samples, fraction: float) -> float:
    """Return the ``fraction`` quantile of ``samples`` (linear interpolation)."""
    ordered = sorted(samples)
    position = (len(ordered) - 1) * fraction
    low = int(position)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (position - low)


def summary(samples) -> dict:
    """Return p50 and p90 of ``samples`` (seconds) in milliseconds."""
    return {'p50': percentile(samples, 0.5) * 1e3, 'p90': percentile(samples, 0.9) * 1e3,
            'n': len(samples)}


# ---------------------------------------------------------------- client process

def progress(text: str) -> None:
    """Say on stderr what the benchmark is doing."""
    print(f'bench: {text}', file=sys.stderr, flush=True)


def run_client(namespace: str, count: int, burst: int, rounds: int) -> None:
    """Measure trigger and service from this (separate) process; print JSON results."""
    rclpy.init()
    node = rclpy.create_node(f'bench_client_{uuid.uuid4().hex[:8]}')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    trigger = node.create_client(Trigger, f'{namespace}/trigger', qos_profile=SERVICE_QOS)
    sdo_read = node.create_client(SdoRead, f'{namespace}/cbcan/sdo_read',
                                  qos_profile=SERVICE_QOS)
    for client in (trigger, sdo_read):
        if not client.wait_for_service(timeout_sec=20.0):
            raise SystemExit(f'bench client: {client.srv_name} not found')

    failures = []
    progress('client: services found, measuring latency')

    def call(client, request, timeout: float = 5.0):
        # Not executor.spin_until_future_complete: in rclpy 7.1.6 (Jazzy) every call leaves
        # about three finished-callback tasks in the executor, and each later spin walks
        # them all: repeated calls get slower without bound (3.8 ms per call after 300 calls,
        # 78 ms after 1500; ros2/rclpy#1374). spin_once leaves nothing behind.
        future = client.call_async(request)
        deadline = time.monotonic() + timeout
        while not future.done():
            if time.monotonic() > deadline:
                raise SystemExit(f'bench client: no answer from {client.srv_name}')
            executor.spin_once(timeout_sec=0.1)
        return future.result()

    def read_request(node_id: int = 5):
        return SdoRead.Request(node_id=node_id, index=0x1000, subindex=0)

    def check(response) -> None:
        if not response.success or bytes(response.data) != DEVICE_TYPE:
            failures.append(response.message or bytes(response.data).hex())

    for _ in range(WARMUP):
        call(trigger, Trigger.Request())
        check(call(sdo_read, read_request()))

    trigger_times, service_times = [], []
    for _ in range(count):
        start = time.perf_counter()
        call(trigger, Trigger.Request())
        middle = time.perf_counter()
        check(call(sdo_read, read_request()))
        end = time.perf_counter()
        trigger_times.append(middle - start)
        service_times.append(end - middle)

    def throughput(client, make_request, is_sdo: bool) -> float:
        total_calls, total_time = 0, 0.0
        for _ in range(rounds):
            start = time.perf_counter()
            futures = [client.call_async(make_request(i)) for i in range(burst)]
            deadline = start + 30.0
            while not all(future.done() for future in futures):
                if time.perf_counter() > deadline:
                    raise SystemExit(f'bench client: burst on {client.srv_name} unanswered')
                executor.spin_once(timeout_sec=0.05)
            total_time += time.perf_counter() - start
            total_calls += burst
            if is_sdo:
                for future in futures:
                    check(future.result())
        return total_calls / total_time

    progress('client: measuring throughput')
    results = {
        'trigger': summary(trigger_times),
        'service': summary(service_times),
        'service_throughput': throughput(
            sdo_read, lambda i: read_request(DEVICES[i % len(DEVICES)]), True),
        'trigger_throughput': throughput(trigger, lambda i: Trigger.Request(), False),
        'failures': failures[:5],
        'failure_count': len(failures),
    }
    executor.shutdown(timeout_sec=1.0)
    node.destroy_node()
    rclpy.try_shutdown()
    print(json.dumps(results), flush=True)


# ---------------------------------------------------------------- server process

class TriggerNode:
    """A bare std_srvs/Trigger server: the least an rclpy service can do."""

    def __init__(self, namespace: str):
        self.node = rclpy.create_node('bench_trigger', namespace=namespace)
        self.node.create_service(Trigger, f'{namespace}/trigger', self._on_trigger,
                                 qos_profile=SERVICE_QOS)

    @staticmethod
    def _on_trigger(_request, response):
        response.success = True
        return response


def spin_in_thread(node) -> tuple:
    """Spin ``node`` in its own SingleThreadedExecutor on a thread of its own."""
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    return executor, thread


def measure_in_process(gateway, channel: str, count: int, burst: int, rounds: int) -> dict:
    """Measure raw canopen uploads and core reads, alternating, on the gateway's bus."""
    network = canopen.Network()
    network.connect(interface='virtual', channel=channel)
    remote = canopen.RemoteNode(5, canopen.ObjectDictionary())
    network.add_node(remote)
    failures = []
    try:
        def raw():
            if remote.sdo.upload(0x1000, 0) != DEVICE_TYPE:
                failures.append('raw upload returned other bytes')

        def core(node_id: int = 5):
            result = gateway.sdo_read(node_id, 0x1000, 0).result()
            if not result.success or result.data != DEVICE_TYPE:
                failures.append(result.message or result.data.hex())

        for _ in range(WARMUP):
            raw()
            core()
        raw_times, core_times = [], []
        for _ in range(count):
            start = time.perf_counter()
            raw()
            middle = time.perf_counter()
            core()
            end = time.perf_counter()
            raw_times.append(middle - start)
            core_times.append(end - middle)

        total_calls, total_time = 0, 0.0
        for _ in range(rounds):
            start = time.perf_counter()
            futures = [gateway.sdo_read(DEVICES[i % len(DEVICES)], 0x1000, 0)
                       for i in range(burst)]
            results = [future.result(timeout=30.0) for future in futures]
            total_time += time.perf_counter() - start
            total_calls += burst
            failures.extend(r.message for r in results if not r.success)
    finally:
        network.disconnect()
    return {'raw': summary(raw_times), 'core': summary(core_times),
            'core_throughput': total_calls / total_time, 'failures': failures[:5],
            'failure_count': len(failures)}


def run_server(args) -> int:
    """Host the gateway and the Trigger node, measure raw and core, start the client."""
    os.environ.setdefault('ROS_DOMAIN_ID', str(random.randint(101, 200)))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    started = time.monotonic()
    namespace = f'/bench_{uuid.uuid4().hex[:8]}'
    channel = f'bench-{uuid.uuid4().hex[:8]}'
    rclpy.init()
    gateway_node = CbcanNode(namespace=namespace, parameter_overrides=[
        Parameter('can.interface', value='virtual'),
        Parameter('can.channel', value=channel),
        Parameter('simulation.devices', value=list(DEVICES))])
    trigger = TriggerNode(namespace)
    spinners = [spin_in_thread(gateway_node), spin_in_thread(trigger.node)]
    try:
        progress('measuring raw canopen and the core in process')
        local = measure_in_process(gateway_node.gateway, channel, args.count, args.burst,
                                   args.rounds)
        progress('starting the client process')
        client = subprocess.run(
            [sys.executable, os.path.abspath(__file__), '--client-of', namespace,
             '--count', str(args.count), '--burst', str(args.burst),
             '--rounds', str(args.rounds)],
            stdout=subprocess.PIPE, text=True, timeout=120)
        if client.returncode != 0:
            print(f'bench: the client process failed (status {client.returncode})',
                  file=sys.stderr)
            return 1
        remote = json.loads(client.stdout.strip().splitlines()[-1])
    finally:
        for executor, thread in spinners:
            executor.shutdown(timeout_sec=2.0)
            thread.join(timeout=5.0)
        trigger.node.destroy_node()
        gateway_node.destroy_node()
        rclpy.try_shutdown()
    report(args, local, remote, time.monotonic() - started)
    return 0


def report(args, local: dict, remote: dict, elapsed: float) -> None:
    """Print the table and the ratios."""
    raw, core = local['raw'], local['core']
    trigger, service = remote['trigger'], remote['service']
    print()
    print(f'SDO read of 0x1000 (4 bytes, expedited), {args.count} calls per row after '
          f'{WARMUP} warm-up calls; python-can virtual bus, simulated devices {DEVICES}')
    print('trigger and service: server process = CbcanNode and a bare Trigger node, each in '
          'its own')
    print('  SingleThreadedExecutor thread; client = a separate process, '
          'SingleThreadedExecutor,')
    print('  call_async + spin_once until done, SERVICE_QOS, trigger and service calls '
          'alternating.')
    print()
    print(f'{"row":<44} {"p50 ms":>8} {"p90 ms":>8}')
    for name, row in (('(a) raw    canopen RemoteNode.sdo.upload', raw),
                      ('    core   Gateway.sdo_read().result()', core),
                      ('(b) trigger rclpy std_srvs/Trigger round trip', trigger),
                      ('(c) service sdo_read through the gateway', service)):
        print(f'{name:<44} {row["p50"]:>8.3f} {row["p90"]:>8.3f}')
    print()
    print(f'(d) throughput, bursts of {args.burst} concurrent calls over nodes '
          f'{", ".join(map(str, DEVICES))}, {args.rounds} bursts:')
    print(f'    service sdo_read      {remote["service_throughput"]:>8.0f} calls/s')
    print(f'    trigger (no SDO)      {remote["trigger_throughput"]:>8.0f} calls/s')
    print(f'    core Gateway.sdo_read {local["core_throughput"]:>8.0f} calls/s')
    print()
    print('ratios of p50:')
    print(f'    service/trigger = {service["p50"] / trigger["p50"]:.2f}   '
          f'service/raw = {service["p50"] / raw["p50"]:.2f}   '
          f'core/raw = {core["p50"] / raw["p50"]:.2f}')
    print(f'    service - trigger = {service["p50"] - trigger["p50"]:.3f} ms   '
          f'(gateway cost above a bare rclpy call; core - raw = '
          f'{core["p50"] - raw["p50"]:.3f} ms)')
    failures = local['failure_count'] + remote['failure_count']
    if failures:
        print(f'\n{failures} reads failed or returned other bytes, e.g. '
              f'{(local["failures"] + remote["failures"])[:3]}')
    print(f'\ntotal {elapsed:.1f} s')


def main(argv=None) -> int:
    """Run the benchmark (or, with --client-of, its client process)."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('--count', type=int, default=1000,
                        help='calls per latency row (default %(default)s)')
    parser.add_argument('--burst', type=int, default=150,
                        help=f'concurrent calls per throughput burst, at most {MAX_BURST} '
                             f'(default %(default)s)')
    parser.add_argument('--rounds', type=int, default=5,
                        help='throughput bursts per row (default %(default)s)')
    parser.add_argument('--client-of', metavar='NAMESPACE', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.count < 1 or not 1 <= args.burst <= MAX_BURST or args.rounds < 1:
        parser.error(f'--count and --rounds must be at least 1, --burst 1..{MAX_BURST}')
    if args.client_of:
        run_client(args.client_of, args.count, args.burst, args.rounds)
        return 0
    return run_server(args)


if __name__ == '__main__':
    sys.exit(main())
