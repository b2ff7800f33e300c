"""Where the time of the gateway goes: every row side by side, in one run, on this machine.

Run with ``make bench`` (``make bench ARGS=--quick`` for a shorter run). Two columns, measured
one after the other, each with its rows alternating call by call or round by round:

* ``virtual``: ONE process on a python-can ``virtual`` bus: simulated devices, the gateway
  node (CbcanNode), a bare Trigger node, raw python-canopen and the client
  (``bench_client.py virtual``);
* ``udp_multicast``: separate processes, as users run it: the simulated devices
  (``bench_devices.py``), a bare Trigger server (``bench_trigger.py``), the installed
  ``cbcan_node``, and the client (``bench_client.py udp_multicast``), which also does the raw
  python-canopen rows against the device process. For the load rows the device process makes
  way for a load process (node 1 plus the heartbeats of further nodes) and a bare python-can
  receiver shows what receiving the frames alone costs.

This script starts and stops every process, measures CPU and RSS from /proc, prints the
table and writes ``latest.md`` and ``latest.png`` into ``bench/out/`` (``--output``). It is a
script, not a test: a target that is not met is reported, never fatal. Ctrl-C stops every
child process and reports what was measured so far.
"""

import argparse
import ctypes
import json
import os
import queue
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from typing import Dict, List, Optional
import uuid

from bench_report import machine_info, write_report
from bench_util import (
    BLOCK_DEVICE,
    dropped_between,
    MARK,
    OUTPUT,
    proc_cpu_seconds,
    proc_rss_mb,
    proc_udp_drops,
    progress,
    ros_of_its_own,
    udp_receive_drops,
)

HERE = os.path.dirname(os.path.abspath(__file__))
COLUMN_TIMEOUT = 400.0    # s without any message from a column's client: it is stuck
START_TIMEOUT = 60.0      # s for a helper process to say it is ready
STOP_TIMEOUT = 5.0
PR_SET_PDEATHSIG = 1

try:
    _prctl = ctypes.CDLL('libc.so.6', use_errno=True).prctl
except OSError:  # not Linux: children then rely on the cleanup below alone
    _prctl = None


def _die_with_parent() -> None:
    # Runs in the child before exec: if this script is killed outright, its children follow.
    if _prctl is not None:
        _prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


class ChildFailed(Exception):
    """A child process ended, or said nothing in time."""


class Child:
    """A child process in a session of its own; its ``@@`` lines arrive on a queue.

    Everything else it prints goes to a log file, shown when something fails.
    """

    running: List['Child'] = []

    def __init__(self, name: str, argv: List[str], env: Optional[Dict] = None):
        self.name = name
        self.messages: 'queue.Queue[Optional[dict]]' = queue.Queue()
        self.log = tempfile.TemporaryFile(mode='w+')
        self.process = subprocess.Popen(
            argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True, env=env, start_new_session=True, preexec_fn=_die_with_parent)
        self._log_lock = threading.Lock()
        Child.running.append(self)
        threading.Thread(target=self._read, daemon=True).start()
        threading.Thread(target=self._read_errors, daemon=True).start()

    @property
    def pid(self) -> int:
        """Return the process id."""
        return self.process.pid

    def _keep(self, line: str) -> None:
        with self._log_lock:
            self.log.write(line)

    def _read(self) -> None:
        for line in self.process.stdout:
            if line.startswith(MARK):
                try:
                    self.messages.put(json.loads(line[len(MARK):]))
                    continue
                except ValueError:
                    pass
            self._keep(line)
        self.messages.put(None)

    def _read_errors(self) -> None:
        for line in self.process.stderr:
            if line.startswith('bench: '):
                sys.stderr.write(line)  # progress, shown as it happens
            self._keep(line)

    def next(self, timeout: float) -> dict:
        """Return the next message; raise ChildFailed if the child ended or stayed silent."""
        try:
            message = self.messages.get(timeout=timeout)
        except queue.Empty:
            raise ChildFailed(f'{self.name} said nothing for {timeout:g} s') from None
        if message is None:
            self.messages.put(None)  # later calls see the end too
            raise ChildFailed(f'{self.name} ended (status {self.process.wait()})')
        return message

    def expect(self, key: str, timeout: float) -> dict:
        """Return the next message holding ``key`` (others are dropped)."""
        deadline = time.monotonic() + timeout
        while True:
            message = self.next(max(0.01, deadline - time.monotonic()))
            if key in message:
                return message

    def tell(self, message: dict) -> None:
        """Send one message on the child's standard input."""
        try:
            self.process.stdin.write(json.dumps(message) + '\n')
            self.process.stdin.flush()
        except (BrokenPipeError, ValueError) as error:
            raise ChildFailed(f'{self.name} does not listen any more: {error}') from None

    def output(self, lines: int = 25) -> str:
        """Return the last ``lines`` lines the child printed."""
        with self._log_lock:
            self.log.flush()
            self.log.seek(0)
            text = self.log.read().splitlines()[-lines:]
            self.log.seek(0, os.SEEK_END)
        return '\n'.join(f'    {self.name}| {line}' for line in text)

    def stop(self) -> None:
        """Stop the child: SIGINT (as Ctrl-C), then SIGTERM, then SIGKILL, by its pid."""
        if self.process.poll() is None:
            for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
                try:
                    self.process.send_signal(signum)
                    self.process.wait(STOP_TIMEOUT)
                    break
                except subprocess.TimeoutExpired:
                    continue
                except ProcessLookupError:
                    break
        if self.process.stdin:
            try:
                self.process.stdin.close()
            except OSError:
                pass
        if self in Child.running:
            Child.running.remove(self)

    @classmethod
    def stop_all(cls) -> None:
        """Stop every child still running, newest first."""
        for child in reversed(list(cls.running)):
            child.stop()


def python(script: str, *arguments: str) -> List[str]:
    """Return the command line running one of the benchmark's scripts."""
    return [sys.executable, os.path.join(HERE, script), *arguments]


class Run:
    """One benchmark run: the columns, their rows, what went wrong."""

    def __init__(self, args):
        self.args = args
        self.rows: Dict[str, Dict[str, dict]] = {'virtual': {}, 'udp_multicast': {}}
        self.problems: List[str] = []

    def _collect(self, client: Child, column: str, on_request=None) -> None:
        """Take the client's rows (and serve its requests) until it is done."""
        while True:
            message = client.next(COLUMN_TIMEOUT)
            if 'row' in message:
                self.rows[column][message['row']] = message['data']
            elif 'request' in message and on_request is not None:
                client.tell(on_request(message['request']))
            elif message.get('done'):
                return

    def _quick(self) -> List[str]:
        return ['--quick'] if self.args.quick else []

    def column(self, name: str, measure) -> None:
        """Measure one column; retry once if it failed before measuring anything."""
        for attempt in (1, 2):
            try:
                measure()
                return
            except ChildFailed as error:
                logs = '\n'.join(child.output() for child in Child.running)
                Child.stop_all()
                measured = bool(self.rows[name])
                problem = f'{name}: {error}'
                progress(f'{problem}\n{logs}')
                if measured or attempt == 2:
                    self.problems.append(problem + ('' if measured else
                                                    ' (retried once; nothing measured)'))
                    return
                progress(f'{name}: retrying once (the package may have been rebuilding)')
            finally:
                Child.stop_all()

    def virtual(self) -> None:
        """Measure the virtual column: one process."""
        progress('column virtual: everything in one process')
        client = Child('virtual', python('bench_client.py', 'virtual', *self._quick()))
        self._collect(client, 'virtual')
        client.stop()

    def udp(self) -> None:
        """Measure the udp_multicast column: devices, Trigger, cbcan_node, client."""
        group = f'239.{random.randint(1, 254)}.{random.randint(0, 255)}.{random.randint(1, 254)}'
        options = {'port': random.randint(20000, 40000)}
        bus = ['--channel', group, '--bus-options', json.dumps(options)]
        namespace = f'/bench_{uuid.uuid4().hex[:8]}'
        progress(f'column udp_multicast: group {group} port {options["port"]}; '
                 'devices, Trigger, cbcan_node and client are separate processes')
        devices = Child('devices', python('bench_devices.py', 'devices', '--durand',
                                          str(BLOCK_DEVICE), *bus))
        devices.expect('ready', START_TIMEOUT)
        trigger = Child('trigger', python('bench_trigger.py', namespace))
        trigger.expect('ready', START_TIMEOUT)
        floor = Child('floor', python(
            'bench_trigger.py', namespace, '--floor-bus',
            json.dumps({'interface': 'udp_multicast', 'channel': group, **options})))
        floor.expect('ready', START_TIMEOUT)
        node_executable = shutil.which('cbcan_node')
        if node_executable is None:
            raise ChildFailed('cbcan_node is not on PATH (run through make bench)')
        node = Child('cbcan_node', [
            node_executable, '--ros-args', '-r', f'__ns:={namespace}',
            '-p', 'can.interface:=udp_multicast', '-p', f'can.channel:={group}',
            '-p', 'sdo.block_transfer:=true'],
            env={**os.environ, 'CAN_CONFIG': json.dumps(options)})
        client = Child('client', python('bench_client.py', 'udp_multicast', '--namespace',
                                         namespace, *bus, *self._quick()))
        helpers: Dict[str, Child] = {'devices': devices}
        port = options['port']

        def drops() -> dict:
            device = helpers.get('devices') or helpers.get('load-device')
            return {'system': udp_receive_drops(), 'node': proc_udp_drops(node.pid, port),
                    'device': proc_udp_drops(device.pid, port) if device else None,
                    'client': proc_udp_drops(client.pid, port)}

        def on_request(request: dict) -> dict:
            if request['op'] == 'start_load':
                helpers.pop('devices').stop()
                for mode in ('load-device', 'heartbeats'):
                    helpers[mode] = Child(mode, python('bench_devices.py', mode, *bus))
                    helpers[mode].expect('ready', START_TIMEOUT)
                return {'ok': True}
            if request['op'] == 'load':
                helpers['load-device'].tell(request)
                helpers['load-device'].expect('ok', START_TIMEOUT)
                helpers['heartbeats'].tell(request)
                return helpers['heartbeats'].expect('ok', START_TIMEOUT)
            if request['op'] == 'cpu':
                return self._cpu_window(request['seconds'], node, helpers, client, bus, drops)
            if request['op'] == 'udp_drops':
                return drops()
            return {'error': f'unknown request {request}'}

        self._collect(client, 'udp_multicast', on_request)
        client.stop()
        for helper in helpers.values():
            helper.stop()

    @staticmethod
    def _cpu_window(seconds: float, node: Child, helpers: Dict[str, Child], client: Child,
                    bus: List[str], drops) -> dict:
        """Measure CPU shares (of one core) over ``seconds``, the node's RSS, dropped frames.

        Then a second, shorter window with a bare python-can receiver on the bus: what
        receiving the frames alone costs (apart, so it does not compete with the node).
        """
        heartbeats = helpers['heartbeats']

        def window(pids: Dict[str, int], length: float) -> dict:
            heartbeats.tell({'op': 'stats'})
            before_stats = heartbeats.expect('ok', START_TIMEOUT)
            dropped = drops()
            before = {name: proc_cpu_seconds(pid) for name, pid in pids.items()}
            started = time.monotonic()
            time.sleep(length)
            after = {name: proc_cpu_seconds(pid) for name, pid in pids.items()}
            elapsed = time.monotonic() - started
            dropped_after = drops()
            heartbeats.tell({'op': 'stats'})
            after_stats = heartbeats.expect('ok', START_TIMEOUT)
            result = {f'cpu_{name}': (after[name] - before[name]) / elapsed * 100
                      if after[name] is not None and before[name] is not None else None
                      for name in pids}
            gained = dropped_between(dropped, dropped_after)
            result.update({f'drops_{name}': gained.get(name) for name in dropped})
            sent = after_stats['sent'] - before_stats['sent']
            result['frames_per_s'] = sent / (after_stats['time'] - before_stats['time'])
            result['late_cycles'] = after_stats['late_cycles'] - before_stats['late_cycles']
            result['window_s'] = elapsed
            return result

        measured = window({'node': node.pid, 'device': helpers['load-device'].pid,
                           'heartbeats': heartbeats.pid, 'client': client.pid}, seconds)
        measured['rss_mb'] = proc_rss_mb(node.pid)
        reader = Child('reader', python('bench_devices.py', 'reader', *bus))
        try:
            reader.expect('ready', START_TIMEOUT)
            bare = window({'reader': reader.pid}, min(seconds, 3.0))
        finally:
            reader.stop()
        measured['cpu_reader'] = bare['cpu_reader']
        measured['reader_frames_per_s'] = bare['frames_per_s']
        return measured


def main(argv=None) -> int:
    """Run both columns, then print and write the report."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('--quick', action='store_true',
                        help='fewer calls and rounds (about a third of the time)')
    parser.add_argument('--only', choices=('virtual', 'udp_multicast'),
                        help='measure one column only')
    parser.add_argument('--output', default=OUTPUT,
                        help='folder of latest.md and latest.png (default %(default)s)')
    args = parser.parse_args(argv)

    def on_term(signum, _frame):
        raise KeyboardInterrupt(f'signal {signum}')
    signal.signal(signal.SIGTERM, on_term)
    # Ctrl-C stops the run even when started where SIGINT was ignored (a background job).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    ros_of_its_own()
    machine = machine_info()
    started = time.monotonic()
    run = Run(args)
    interrupted = False
    try:
        if args.only in (None, 'virtual'):
            run.column('virtual', run.virtual)
        if args.only in (None, 'udp_multicast'):
            run.column('udp_multicast', run.udp)
    except KeyboardInterrupt:
        interrupted = True
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # the cleanup below takes seconds
        progress('interrupted: stopping every child process')
    finally:
        Child.stop_all()
    machine['load_after'] = ' '.join(f'{v:.2f}' for v in os.getloadavg())
    machine['duration_s'] = time.monotonic() - started
    machine['quick'] = args.quick
    if interrupted:
        run.problems.append('interrupted (Ctrl-C): the rows after that point are missing')
    write_report(run.rows, run.problems, machine, args.output)
    return 0


if __name__ == '__main__':
    sys.exit(main())
