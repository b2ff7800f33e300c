"""How many callers of a 3,000-call burst hear back when the gateway is stopped in the middle.

Run by ``make bench`` after the PDO rows (``python bench/bench_shutdown.py [--quick]``). The
installed ``cbcan_node`` runs in its own process on a private udp_multicast bus; this process
sends it 3,000 reads, writes and batches for devices nobody answers, and SIGINT once a third
are answered. The node answers every call it took ("shutting down") and keeps its services
``ANSWER_LINGER`` s for the answers to leave (the tests prove that much); how many of the
others arrive is DDS's: a request still on its way when the services go reaches nobody, and
answers still inside the middleware when the process ends are lost. This counts them, per
round. Writes ``shutdown.md`` and ``shutdown.json`` into ``bench/out/`` (``--output``).
"""

import argparse
import json
import os
import random
import re
import shutil
import signal
import statistics
import subprocess
import sys
import threading
import time
import uuid

from bench_util import logs_to, OUTPUT, progress, ros_of_its_own

CALLS = 3000
SILENT = range(10, 30)   # node ids nobody answers
CALL_TIMEOUT = 30.0      # beyond each round: only shutdown answers these calls
START_TIMEOUT = 60.0
SETTLE = 3.0             # s without a new answer after the node exited: the count is final
ANSWERED = re.compile(r'shutdown: (\d+) calls answered while shutting down')


def wait_for(condition, timeout: float) -> bool:
    """Wait until ``condition()``; return whether it came within ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def burst(clients: dict) -> list:
    """Send the 3,000 calls; return their futures (one in three each of read, write, batch)."""
    from cbcan_ros.msg import SdoAccess
    from cbcan_ros.srv import SdoBatch, SdoRead, SdoWrite
    futures = []
    for number in range(CALLS):
        node_id = SILENT[number % len(SILENT)]
        data = list(number.to_bytes(4, 'little'))
        request = (SdoRead.Request(node_id=node_id, index=0x1000, timeout=CALL_TIMEOUT),
                   SdoWrite.Request(node_id=node_id, index=0x2002, data=data,
                                    timeout=CALL_TIMEOUT),
                   SdoBatch.Request(accesses=[SdoAccess(node_id=node_id, index=0x1000)],
                                    timeout=CALL_TIMEOUT))[number % 3]
        futures.append(clients[type(request)].call_async(request))
    return futures


def one_round(client_node, output: str, number: int) -> dict:
    """Start a node, burst, SIGINT; return what reached this process and what the node said."""
    from cbcan_ros.ros.interface import SERVICE_QOS
    from cbcan_ros.srv import SdoBatch, SdoRead, SdoWrite
    group = f'239.{random.randint(1, 254)}.{random.randint(0, 255)}.{random.randint(1, 254)}'
    name = f'/benchstop{uuid.uuid4().hex[:8]}/cbcan'
    log_path = os.path.join(output, f'shutdown_node_{number}.log')
    with open(log_path, 'w') as log:
        node = subprocess.Popen(
            [shutil.which('cbcan_node'), '--ros-args', '-r',
             f'__ns:={name.rpartition("/")[0]}', '-p', 'can.interface:=udp_multicast',
             '-p', f'can.channel:={group}'],
            stdout=log, stderr=subprocess.STDOUT,
            env={**os.environ,
                 'CAN_CONFIG': json.dumps({'port': random.randint(20000, 40000)})})
    clients = {}
    try:
        for service, service_name in ((SdoRead, 'sdo_read'), (SdoWrite, 'sdo_write'),
                                      (SdoBatch, 'sdo_batch')):
            client = client_node.create_client(service, f'{name}/{service_name}',
                                               qos_profile=SERVICE_QOS)
            if not client.wait_for_service(timeout_sec=START_TIMEOUT):
                raise RuntimeError(f'{name} did not come up (see {log_path})')
            clients[service.Request] = client
        futures = burst(clients)
        wait_for(lambda: sum(f.done() for f in futures) >= CALLS // 3, CALL_TIMEOUT)
        before = sum(f.done() for f in futures)
        signalled = time.monotonic()
        node.send_signal(signal.SIGINT)
        status = node.wait(CALL_TIMEOUT)
        exited = time.monotonic() - signalled
        count = -1
        while count != sum(f.done() for f in futures):
            count = sum(f.done() for f in futures)
            wait_for(lambda c=count: sum(f.done() for f in futures) > c, SETTLE)
    finally:
        if node.poll() is None:
            node.kill()
            node.wait()
        for client in clients.values():
            client_node.destroy_client(client)
    said = ANSWERED.search(open(log_path).read())
    return {'answered': count, 'answered_before_signal': before, 'exit_status': status,
            'exit_s': round(exited, 2),
            'node_answered_while_shutting_down': int(said.group(1)) if said else None}


def main(argv=None) -> int:
    """Measure the rounds, print and write the row."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--quick', action='store_true', help='one round instead of three')
    parser.add_argument('--output', default=OUTPUT,
                        help='folder of shutdown.md, shutdown.json and node logs '
                             '(default %(default)s)')
    args = parser.parse_args(argv)
    logs_to(os.path.join(args.output, 'shutdown_logs.txt'))
    ros_of_its_own()
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    rclpy.init()
    client_node = rclpy.create_node(f'bench_shutdown_{uuid.uuid4().hex[:8]}')
    executor = SingleThreadedExecutor()
    executor.add_node(client_node)
    spinning = threading.Event()
    spinning.set()

    def spin():
        while spinning.is_set():
            executor.spin_once(timeout_sec=0.05)

    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    rounds = []
    try:
        for number in range(1 if args.quick else 3):
            progress(f'shutdown: round {number + 1}, {CALLS:,} calls, SIGINT at a third')
            rounds.append(one_round(client_node, args.output, number + 1))
    except KeyboardInterrupt:
        progress('interrupted')
    finally:
        spinning.clear()
        spinner.join()
        executor.shutdown()
        client_node.destroy_node()
        rclpy.try_shutdown()
    answered = [r['answered'] for r in rounds]
    shown = (f'{statistics.median(answered):,.0f} of {CALLS:,} (rounds: '
             f'{", ".join(f"{a:,}" for a in answered)})' if rounds else 'not measured')
    table = ('| row | measured |\n|---|---|\n'
             f'| calls answered after SIGINT in the middle of a {CALLS:,}-call burst '
             f'(counted, no target: DDS decides) | {shown} |')
    print(table)
    with open(os.path.join(args.output, 'shutdown.md'), 'w') as out:
        out.write(f'# Shutdown in the middle of a burst\n\n{table}\n')
    with open(os.path.join(args.output, 'shutdown.json'), 'w') as out:
        json.dump(rounds, out, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
