"""Control rate: 8 drives in cyclic synchronous position at 250 Hz (and 500 Hz), side by side.

Run by ``make bench`` after ``bench_drives.py`` (``--quick`` shortens the window); writes
``control_rate.md`` and ``control_rate.json`` in ``bench/out/`` (``--output``). A script, not
a test: a target that is not met is reported, never fatal.

Processes, each on one private udp_multicast bus: the installed ``cbcan_node`` (8 drives of
``drives.nodes`` in CSP, SYNC from the gateway, every PDO synchronous, the command timeout
at its default); the 8 simulated drives (``bench_drive_host.py drives``, one socket), whose
synchronous TPDOs come from a raw frame generator once the drives are enabled (the
simulation must not set the limit); a bare
python-can receiver process (``bench_drive_host.py reader``) that counts every frame and
records the SYNCs and the RPDOs with the kernel's receive timestamps; and this process, the
robot program: a controller that answers every ``~/joint_states`` message with a
``~/joint_commands`` message for the 8 joints, as a ros2_control loop does.

Measured over one window:
- node CPU beside the bare receiver's (both from /proc): the frames the node must take are
  the same the receiver takes; the node's CPU split by thread (named by py-spy);
- cycles missed: SYNC intervals in which a drive's RPDO did not come (at the receiver), and
  SYNCs whose TPDOs did not reach ``~/joint_states`` (SYNCs at the receiver against
  ``joint_states`` messages here);
- the SYNC period error, p99, at the receiver;
- ``joint_commands`` to RPDO: from the publication to the RPDO frame that carries its
  target (the synchronous RPDO waits for the next SYNC), and from that SYNC to the RPDO;
- the floor: the same set-up with, in the gateway's place, a process that does only what any
  gateway of this row must (``bench_drive_host.py floor``: SYNC, every frame taken,
  ``joint_states`` a SYNC, the RPDOs of each ``joint_commands``; no checks, no CANopen),
  its CPU beside the bare receiver's of its own run: how far under the receiver target
  Python, rclpy and python-can can go on this machine at all;
- where the node's time goes: a py-spy profile of the node (samples of the thread holding
  the GIL: its Python work, not its waits) right after the window (py-spy's own load would
  change what is measured),
  written beside the report (``control_rate_<hz>_profile.txt``), when py-spy is installed.
"""

import argparse
import json
import os
import re
import shutil
import struct
import subprocess
import sys
import threading
import time
from typing import Dict, List, Optional
import uuid

from bench_drives import (
    _stats,
    _until_no_sdo,
    bench_session,
    Caller,
    gateway_ready,
    NodeProcess,
    start_helper,
    UdpBus,
    wait_until,
)
from bench_sdo import Child, ChildFailed
from bench_util import OUTPUT, percentile, proc_cpu_seconds, progress

START_TIMEOUT = 60.0
CSP = 8
DRIVES = tuple(range(1, 9))
SYNC = 0x80
RPDO_1 = 0x200  # COMMAND: controlword, target position, mode (drive_pdos.COMMAND)
RATES = {'250': 0.004, '500': 0.002}
CPU_TARGET = 30.0  # % of a core
RECEIVER_TARGET = 1.5  # x the bare receiver
SYNC_ERROR_TARGET = 0.5  # ms, p99
LATENCY_TARGETS = (0.5, 2.0)  # ms, p50 and p99
RECORDED = ','.join(hex(cob_id) for cob_id in (SYNC, *(RPDO_1 + n for n in DRIVES)))


class Controller:
    """This process as a robot's control loop: every joint state answered with commands.

    Each command's 8 positions are the drive's start position plus a counter (one count
    a cycle, position_scale 1: one count a joint unit), so the RPDO that carries it names
    the command it came from.
    """

    def __init__(self, caller: Caller, gateway: str):
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        self._message = JointState
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                         reliability=ReliabilityPolicy.RELIABLE)
        self._node = caller.node
        self._lock = threading.Lock()
        self.states = 0
        self.incomplete = 0
        self.counter = 0
        self.base: Optional[Dict[str, float]] = None
        self.sent: Dict[int, float] = {}  # counter: time.time() of its publication
        self.running = False
        self._publisher = caller.node.create_publisher(JointState, f'{gateway}/joint_commands',
                                                       qos)
        # Last: the caller's executor spins already, and the first message may come at once.
        self._subscription = caller.node.create_subscription(
            JointState, f'{gateway}/joint_states', self._on_states, qos)

    def _on_states(self, message) -> None:
        with self._lock:
            self.states += 1
            if len(message.name) != len(DRIVES):
                self.incomplete += 1
            if self.base is None:
                self.base = dict(zip(message.name, message.position, strict=True))
            if not self.running:
                return
            self.counter += 1
            counter = self.counter
        command = self._message(name=list(self.base),
                                position=[value + counter for value in self.base.values()])
        stamp = time.time()
        self._publisher.publish(command)
        with self._lock:
            self.sent[counter] = stamp

    def close(self) -> None:
        """Stop answering."""
        self.running = False
        self._node.destroy_subscription(self._subscription)
        self._node.destroy_publisher(self._publisher)


def profile(pid: int, seconds: float, path: str) -> Optional[str]:
    """Sample the node with py-spy for ``seconds``; return why not, or None."""
    spy = shutil.which('py-spy')
    if spy is None:
        return 'py-spy is not installed: no profile'
    done = subprocess.run([spy, 'record', '--pid', str(pid), '--duration', str(int(seconds)),
                           '--format', 'raw', '--threads', '--gil', '--output', path,
                           '--nonblocking'],
                          capture_output=True, text=True, timeout=seconds + 60)
    if done.returncode:
        return f'py-spy failed: {done.stderr.strip()[-300:]}'
    return None


def thread_names(pid: int) -> Dict[int, str]:
    """Return the node's Python thread names by native thread id (py-spy), {} without it."""
    spy = shutil.which('py-spy')
    if spy is None:
        return {}
    names: Dict[int, str] = {}
    for _ in range(5):  # a dump of a process busy in native code may fail: try again
        dump = subprocess.run([spy, 'dump', '--pid', str(pid), '--nonblocking'],
                              capture_output=True, text=True, timeout=60)
        names = {int(tid): name for tid, name in re.findall(
            r'Thread (\d+) \(\w+\): "([^"]*)"', dump.stdout)}
        if names:
            break
        progress(f'py-spy dump of the node failed: {dump.stderr.strip()[-200:]}')
    return names


def thread_ticks(pid: int) -> Dict[int, int]:
    """Return utime + stime of every thread of ``pid``, in clock ticks, by thread id."""
    ticks = {}
    for tid in os.listdir(f'/proc/{pid}/task'):
        try:
            with open(f'/proc/{pid}/task/{tid}/stat') as stat:
                fields = stat.read().rsplit(')', 1)[1].split()
        except OSError:
            continue
        ticks[int(tid)] = int(fields[11]) + int(fields[12])
    return ticks


def summarise_profile(path: str, top: int = 25) -> List[str]:
    """Return the functions the node spent the most samples in (self and total), as text."""
    own: Dict[str, int] = {}
    total: Dict[str, int] = {}
    samples = 0
    with open(path) as file:
        for line in file:
            stack, _, count = line.rstrip('\n').rpartition(' ')
            if not count.isdigit():
                continue
            frames = stack.split(';')
            samples += int(count)
            own[frames[-1]] = own.get(frames[-1], 0) + int(count)
            for frame in set(frames):
                total[frame] = total.get(frame, 0) + int(count)
    lines = [f'{samples} samples']
    for title, table in (('self', own), ('total', total)):
        lines.append(f'-- by {title} samples')
        for frame, count in sorted(table.items(), key=lambda item: -item[1])[:top]:
            lines.append(f'{100 * count / max(samples, 1):5.1f} %  {frame}')
    return lines


def cycles(frames: List, commands: Dict[int, float], base: float) -> Dict:
    """Work out missed cycles, the SYNC period error and the command to RPDO latencies.

    ``base``: the first drive's position the controller's counter is added to.
    """
    syncs = sorted(stamp for stamp, cob_id, _ in frames if cob_id == SYNC)
    rpdos = sorted((stamp, cob_id, data) for stamp, cob_id, data in frames if cob_id != SYNC)
    missed = 0
    position = 0
    for start, end in zip(syncs[:-1], syncs[1:], strict=True):
        seen = set()
        while position < len(rpdos) and rpdos[position][0] < end:
            if rpdos[position][0] >= start:
                seen.add(rpdos[position][1] - RPDO_1)
            position += 1
        missed += len(DRIVES) - len(seen & set(DRIVES))
    periods = [1e3 * (b - a) for a, b in zip(syncs[:-1], syncs[1:], strict=True)]
    latencies, after_sync = [], []
    first = {}
    for stamp, cob_id, data in rpdos:
        if cob_id - RPDO_1 != DRIVES[0]:
            continue
        target = struct.unpack_from('<i', bytes.fromhex(data), 2)[0]
        first.setdefault(target, stamp)
    for target, stamp in first.items():
        sent = commands.get(target - round(base))
        if sent is not None and stamp >= sent:
            latencies.append(1e3 * (stamp - sent))
            before = [s for s in syncs if s <= stamp]
            if before:
                after_sync.append(1e3 * (stamp - before[-1]))
    return {'syncs': len(syncs), 'intervals': max(len(syncs) - 1, 0), 'rpdo_missing': missed,
            'periods_ms': periods, 'latencies_ms': latencies, 'after_sync_ms': after_sync}


def start_drives_and_reader(helpers: Dict[str, Child], bus: UdpBus, label: str) -> None:
    """Start the 8 drives (synchronous PDOs, one socket) and the recording receiver on ``bus``.

    Each goes into ``helpers`` as it starts, so the caller stops what did start.
    """
    helpers['drives'] = start_helper(
        f'{label} drives', 'drives', bus, '--nodes', ','.join(map(str, DRIVES)),
        '--transmission-type', '1', '--shared-socket')
    helpers['reader'] = start_helper(f'{label} reader', 'reader', bus, '--record', RECORDED)


def cpu_over(pids: Dict[str, int], seconds: float):
    """Return ({name: % of a core} of the processes ``pids`` over ``seconds``, the window)."""
    before = {name: proc_cpu_seconds(pid) for name, pid in pids.items()}
    started = time.monotonic()
    time.sleep(seconds)
    after = {name: proc_cpu_seconds(pid) for name, pid in pids.items()}
    elapsed = time.monotonic() - started
    return {name: 100 * (after[name] - before[name]) / elapsed for name in pids}, elapsed


def floor_row(args, caller: Caller, hertz: str) -> Dict:
    """Measure the floor beside a rate: the least any gateway does (``floor`` helper).

    The same drives, frame generator, bare receiver and controller as the rate's row, with
    the floor process in the gateway's place; its CPU and the receiver's over a window as
    long.
    """
    bus = UdpBus()
    helpers: Dict[str, Child] = {}
    controller = None
    namespace = f'/benchfloor{uuid.uuid4().hex[:8]}'
    try:
        start_drives_and_reader(helpers, bus, f'{hertz} Hz floor')
        helpers['floor'] = start_helper(
            f'{hertz} Hz floor', 'floor', bus, '--nodes', ','.join(map(str, DRIVES)),
            '--namespace', namespace, '--period', str(RATES[hertz]))
        controller = Controller(caller, namespace)
        wait_until(lambda: controller.base is not None, START_TIMEOUT,
                   "the floor's joint_states")
        helpers['drives'].tell({'op': 'generate'})
        helpers['drives'].expect('ok', START_TIMEOUT)
        controller.running = True
        _stats(helpers['reader'])  # forget what was recorded before the window
        states_before = controller.states
        cpu, elapsed = cpu_over({'floor': helpers['floor'].pid,
                                 'reader': helpers['reader'].pid}, args.seconds)
        states = controller.states - states_before
        recorded = _stats(helpers['reader'])
        with controller._lock:
            commands = dict(controller.sent)
        base = controller.base[f'node_{DRIVES[0]}']
    finally:
        if controller is not None:
            controller.close()
        for helper in reversed(list(helpers.values())):
            helper.stop()
    found = cycles(recorded['frames'], commands, base)
    return {'floor_cpu': cpu['floor'], 'floor_reader_cpu': cpu['reader'],
            'floor_ratio': cpu['floor'] / cpu['reader'] if cpu['reader'] else None,
            'floor_joint_states': states, 'floor_syncs': found['syncs'],
            'floor_rpdo_missing': found['rpdo_missing'],
            'floor_sync_error_p99_ms': _sync_error_p99(found, RATES[hertz]),
            'floor_latency_p50_ms': percentile(found['latencies_ms'], 0.5)
            if found['latencies_ms'] else None}


def _sync_error_p99(found: Dict, period: float) -> Optional[float]:
    return (percentile([abs(p - period * 1e3) for p in found['periods_ms']], 0.99)
            if found['periods_ms'] else None)


def row(args, caller: Caller, hertz: str) -> Dict:
    """One rate: 8 drives in CSP, SYNC every 1/hertz, the controller answering each cycle."""
    period = RATES[hertz]
    bus = UdpBus()
    helpers: Dict[str, Child] = {}
    node = controller = None
    try:
        start_drives_and_reader(helpers, bus, f'{hertz} Hz')
        node = NodeProcess(bus, {'drives.nodes': f'[{",".join(map(str, DRIVES))}]',
                                 'sync.period': str(period)},
                           os.path.join(args.output, f'control_rate_{hertz}_node.log'))
        progress(f'control rate: {len(DRIVES)} drives in CSP, SYNC {period * 1e3:g} ms')
        gateway_ready(caller, node, DRIVES, mode=CSP)
        controller = Controller(caller, node.name)
        wait_until(lambda: controller.base is not None, START_TIMEOUT, 'joint_states')
        helpers['drives'].tell({'op': 'generate'})
        helpers['drives'].expect('ok', START_TIMEOUT)
        controller.running = True
        _until_no_sdo(helpers['reader'])
        _stats(helpers['reader'])  # forget what was recorded before the window
        pids = {'node': node.pid, 'reader': helpers['reader'].pid,
                'drives': helpers['drives'].pid}
        names = thread_names(node.pid)
        states_before = controller.states
        threads_before = thread_ticks(node.pid)
        cpu, elapsed = cpu_over(pids, args.seconds)
        threads_after = thread_ticks(node.pid)
        states = controller.states - states_before
        recorded = _stats(helpers['reader'])
        with controller._lock:
            commands = dict(controller.sent)
        incomplete = controller.incomplete
        base = controller.base[f'node_{DRIVES[0]}']
        # After the window: py-spy takes a core's share of the machine itself.
        profiled = None
        if args.profile:
            profiled = profile(node.pid, min(args.seconds, 20.0),
                               os.path.join(args.output, f'control_rate_{hertz}_profile.raw'))
    finally:
        if controller is not None:
            controller.close()
        if node is not None:
            node.close()
        for helper in reversed(list(helpers.values())):
            helper.stop()
    by_thread: Dict[str, float] = {}
    for tid, ticks in threads_after.items():
        name = names.get(tid, 'native (rclpy, DDS)')
        by_thread[name] = by_thread.get(name, 0.0) + 100 * (
            ticks - threads_before.get(tid, 0)) / os.sysconf('SC_CLK_TCK') / elapsed
    found = cycles(recorded['frames'], commands, base)
    result = {
        'hertz': int(hertz), 'window_s': elapsed, 'node_cpu': cpu['node'],
        'reader_cpu': cpu['reader'], 'drives_cpu': cpu['drives'],
        'ratio': cpu['node'] / cpu['reader'] if cpu['reader'] else None,
        'syncs': found['syncs'], 'joint_states': states, 'incomplete_states': incomplete,
        'tpdo_cycles_missed': max(0, found['syncs'] - states),
        'rpdo_missing': found['rpdo_missing'], 'intervals': found['intervals'],
        'sync_error_p99_ms': _sync_error_p99(found, period),
        'latency_p50_ms': percentile(found['latencies_ms'], 0.5) if found['latencies_ms']
        else None,
        'latency_p99_ms': percentile(found['latencies_ms'], 0.99) if found['latencies_ms']
        else None,
        'after_sync_p50_ms': percentile(found['after_sync_ms'], 0.5) if found['after_sync_ms']
        else None,
        'after_sync_p99_ms': percentile(found['after_sync_ms'], 0.99)
        if found['after_sync_ms'] else None,
        'latency_samples': len(found['latencies_ms']),
        'node_threads': {name: round(value, 1) for name, value in sorted(
            by_thread.items(), key=lambda item: -item[1]) if value >= 0.05},
        'profile': profiled,
    }
    raw = os.path.join(args.output, f'control_rate_{hertz}_profile.raw')
    if args.profile and profiled is None and os.path.exists(raw):
        with open(os.path.join(args.output, f'control_rate_{hertz}_profile.txt'), 'w') as file:
            file.write('\n'.join(summarise_profile(raw)) + '\n')
    return result


def _ms(value) -> str:
    return 'not measured' if value is None else f'{value:.2f} ms'


def _met(condition: bool) -> str:
    return 'yes' if condition else '**no**'


def table(rows: Dict[str, Dict]) -> str:
    """Return the rows as a Markdown table: each figure, its baseline, its target."""
    lines = ['| row | measured | beside it (same run) | ratio | target | met |',
             '|---|---|---|---|---|---|']
    for hertz, result in rows.items():
        title = f'{len(DRIVES)} drives CSP, SYNC {1000 / result["hertz"]:g} ms ({hertz} Hz)'
        cpu_met = result['node_cpu'] < CPU_TARGET and (result['ratio'] or 99) <= \
            RECEIVER_TARGET
        lines.append(f'| {title}: node CPU | {result["node_cpu"]:.1f} % of a core | bare '
                     f'python-can receiver {result["reader_cpu"]:.1f} % | '
                     f'{result["ratio"]:.2f} | < {CPU_TARGET:g} % and <= {RECEIVER_TARGET} x '
                     f'| {_met(cpu_met)} |')
        if result.get('floor_ratio') is not None:
            lines.append(
                f'| {title}: the floor, the least any gateway does (SYNC, take the frames, '
                f'joint_states a SYNC, RPDOs from joint_commands; no checks) | '
                f'{result["floor_cpu"]:.1f} % of a core | bare python-can receiver '
                f'{result["floor_reader_cpu"]:.1f} % (its own run) | '
                f'{result["floor_ratio"]:.2f}; node to floor '
                f'{result["node_cpu"] / result["floor_cpu"]:.2f} | (<= {RECEIVER_TARGET} x '
                f'the receiver) | {_met(result["floor_ratio"] <= RECEIVER_TARGET)} |')
            lines.append(
                f'| {title}: the floor\'s cycles | RPDOs missing {result["floor_rpdo_missing"]} '
                f'of {max(result["floor_syncs"] - 1, 0) * len(DRIVES)}; SYNC period error p99 '
                f'{_ms(result["floor_sync_error_p99_ms"])}; joint_commands to RPDO p50 '
                f'{_ms(result["floor_latency_p50_ms"])} | | | (0; <= {SYNC_ERROR_TARGET} ms; '
                f'<= {LATENCY_TARGETS[0]} ms) | |')
        missed = result['rpdo_missing'] + result['tpdo_cycles_missed']
        lines.append(f'| {title}: cycles missed in {result["window_s"]:.0f} s | RPDOs missing '
                     f'{result["rpdo_missing"]} of {result["intervals"] * len(DRIVES)}; SYNCs '
                     f'without joint_states {result["tpdo_cycles_missed"]} of '
                     f'{result["syncs"]} | | | 0 | {_met(missed == 0)} |')
        error = result['sync_error_p99_ms']
        lines.append(f'| {title}: SYNC period error p99 at a receiver | {_ms(error)} | | | '
                     f'<= {SYNC_ERROR_TARGET} ms | '
                     f'{_met(error is not None and error <= SYNC_ERROR_TARGET)} |')
        p50, p99 = result['latency_p50_ms'], result['latency_p99_ms']
        fast = p50 is not None and p50 <= LATENCY_TARGETS[0] and p99 <= LATENCY_TARGETS[1]
        lines.append(f'| {title}: joint_commands to RPDO, p50 (p99) of '
                     f'{result["latency_samples"]} | {_ms(p50)} ({_ms(p99)}) | of which the '
                     f'SYNC before the RPDO to the RPDO {_ms(result["after_sync_p50_ms"])} '
                     f'({_ms(result["after_sync_p99_ms"])}) | | p50 <= {LATENCY_TARGETS[0]} '
                     f'ms, p99 <= {LATENCY_TARGETS[1]} ms | '
                     f'{_met(fast)} |')
    return '\n'.join(lines)


def main(argv=None) -> int:
    """Measure the rates and report them."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--quick', action='store_true', help='a shorter window')
    parser.add_argument('--rates', type=lambda text: text.split(','), default=list(RATES),
                        help='rates to measure, of 250,500 (default both)')
    parser.add_argument('--no-profile', dest='profile', action='store_false',
                        help='no py-spy profile of the node')
    parser.add_argument('--output', default=OUTPUT, help='folder of the report')
    args = parser.parse_args(argv)
    args.seconds = 10.0 if args.quick else 60.0
    rows: Dict[str, Dict] = {}
    problems: List[str] = []
    with bench_session(args.output, 'control_rate', args.quick) as (caller, machine):
        for hertz in args.rates:
            try:
                rows[hertz] = row(args, caller, hertz)
                progress(f'control rate: the floor at {hertz} Hz')
                rows[hertz].update(floor_row(args, caller, hertz))
            except (RuntimeError, ChildFailed) as error:
                problems.append(f'{hertz} Hz: {error}')
                progress(f'control rate: {hertz} Hz failed: {error}')
    text = table(rows)
    described = ', '.join(f'{key}: {value}' for key, value in machine.items())
    with open(os.path.join(args.output, 'control_rate.md'), 'w') as file:
        file.write(f'# Control rate benchmark (make bench)\n\n{described}\n\n{text}\n')
        for hertz, result in rows.items():
            file.write(f'\n{hertz} Hz: simulated drives {result["drives_cpu"]:.1f} % of a '
                       f'core; joint_states with fewer than 8 joints: '
                       f'{result["incomplete_states"]}; profile: '
                       f'{result["profile"] or f"control_rate_{hertz}_profile.txt"}\n')
            threads = ', '.join(f'{name} {value:.1f} %'
                                for name, value in result['node_threads'].items())
            file.write(f'\n{hertz} Hz: node CPU by thread (% of a core): {threads}\n')
        for line in problems:
            file.write(f'\n{line}\n')
    with open(os.path.join(args.output, 'control_rate.json'), 'w') as file:
        json.dump({'rows': rows, 'problems': problems, 'machine': machine}, file, indent=1)
    print(text)
    for line in problems:
        print(line)
    return 0


if __name__ == '__main__':
    sys.exit(main())
