"""What every process of the benchmark shares: statistics, messages between processes, setup.

The benchmark's processes talk in lines of JSON. A child writes ``@@ {...}`` lines on its
standard output (results and requests); everything else it prints goes to standard error.
"""

import importlib
import json
import os
import random
import signal
import sys
import time
from typing import Dict, Iterable, List, Optional

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EDS = os.path.join(ROOT, 'config', 'simulated_device.eds')

MARK = '@@ '

# Where a run writes its reports and the nodes' logs (ignored by git; `make bench` passes it
# as --output). The results committed for comparison are in bench/reference/.
OUTPUT = os.path.join(ROOT, 'bench', 'out')

# The simulated devices (python-canopen LocalNodes from config/simulated_device.eds).
LOCAL_DEVICES = tuple(range(1, 11))    # bursts spread over all ten: 60 calls each at most
BATCH_DEVICES = {1: (1,), 3: (1, 2, 3), 8: tuple(range(1, 9))}
LATENCY_DEVICE = 1                     # sequential reads, raw and through the gateway
STATE_DEVICE = 9                       # the one whose NMT state changes (node_states rows)
SEGMENTED_DEVICE = 10                  # a LocalNode: segmented transfers only
BLOCK_DEVICE = 20                      # a DurandDevice: block transfer
STATE_DEVICE_HEARTBEAT_MS = 50
DEVICE_TYPE = bytes([0x92, 0x01, 0x02, 0x00])  # 0x1000 of config/simulated_device.eds
DOMAIN_INDEX = 0x2020
DOMAIN_SIZE = 64 * 1024
DOMAIN_DATA = bytes((i * 7 + (i >> 8)) & 0xFF for i in range(DOMAIN_SIZE))
BIG_TIMEOUT = 30.0                     # s: a 64 KiB transfer or a batch of 1000 reads

# NMT states and commands (CiA 301)
OPERATIONAL = 5
PRE_OPERATIONAL = 127
NMT_START = 1
NMT_ENTER_PRE_OPERATIONAL = 128


_terminal = None  # standard error as it was before logs_to()


def ros_of_its_own() -> None:
    """Put this process (and the processes it starts) in a ROS domain of its own, this host only.

    ``BENCH_ROS_DOMAIN_ID`` names the domain; without it one of 101..200 at random, so two runs
    on one machine, and other ROS work on it, do not hear each other.
    """
    os.environ['ROS_DOMAIN_ID'] = os.environ.get('BENCH_ROS_DOMAIN_ID',
                                                 str(random.randint(101, 200)))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'


def progress(text: str) -> None:
    """Say on standard error what this process is doing."""
    print(f'bench: {text}', file=_terminal or sys.stderr, flush=True)


def logs_to(path: str) -> None:
    """Send what this process prints on standard error (its nodes' logs) to ``path``.

    Progress lines still reach the terminal, so the report stays free of node logs.
    """
    global _terminal
    os.makedirs(os.path.dirname(path), exist_ok=True)
    _terminal = os.fdopen(os.dup(2), 'w', buffering=1)
    with open(path, 'w') as log:
        os.dup2(log.fileno(), 2)
    progress(f'node logs: {path}')


def send(message: Dict) -> None:
    """Write one message for the benchmark's main process on standard output."""
    sys.stdout.write(MARK + json.dumps(message) + '\n')
    sys.stdout.flush()


def receive() -> Dict:
    """Read the next message of the main process from standard input."""
    line = sys.stdin.readline()
    if not line:
        raise SystemExit('bench: the main process went away')
    return json.loads(line)


def percentile(samples: Iterable[float], fraction: float) -> float:
    """Return the ``fraction`` quantile of ``samples`` (linear interpolation)."""
    ordered = sorted(samples)
    if not ordered:
        return float('nan')
    position = (len(ordered) - 1) * fraction
    low = int(position)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (position - low)


def latency(samples_s: List[float], **extra) -> Dict:
    """Return p50, p99 and max of ``samples_s`` (seconds) in milliseconds."""
    return {'kind': 'ms', 'p50': percentile(samples_s, 0.5) * 1e3,
            'p99': percentile(samples_s, 0.99) * 1e3,
            'max': max(samples_s) * 1e3 if samples_s else float('nan'),
            'n': len(samples_s), **extra}


def rate(rates: List[float], unit: str, **extra) -> Dict:
    """Return the median and the worst of per-round rates (higher is better)."""
    return {'kind': unit, 'p50': percentile(rates, 0.5),
            'worst': min(rates) if rates else float('nan'), 'n': len(rates), **extra}


def exit_on_sigterm() -> None:
    """Turn SIGTERM into SystemExit, so ``finally`` blocks clean up as on Ctrl-C."""
    def on_term(signum, _frame):
        raise SystemExit(128 + signum)
    signal.signal(signal.SIGTERM, on_term)


def import_retrying(*names: str, attempts: int = 15, pause: float = 2.0) -> List:
    """Import modules, retrying: another engineer may be rebuilding the package meanwhile."""
    for attempt in range(attempts):
        try:
            return [importlib.import_module(name) for name in names]
        except ImportError as error:
            if attempt == attempts - 1:
                raise
            progress(f'import failed ({error}); retrying in {pause:g} s')
            for name in [m for m in sys.modules if m == 'cbcan_ros' or
                         m.startswith('cbcan_ros.')]:
                del sys.modules[name]
            importlib.invalidate_caches()
            time.sleep(pause)
    return []


def proc_cpu_seconds(pid: int) -> Optional[float]:
    """Return utime + stime of process ``pid`` in seconds (None if it is gone)."""
    try:
        with open(f'/proc/{pid}/stat') as stat:
            fields = stat.read().rsplit(')', 1)[1].split()
    except OSError:
        return None
    # fields[0] is field 3 (state): utime and stime are fields 14 and 15.
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def proc_rss_mb(pid: int) -> Optional[float]:
    """Return the resident set size of process ``pid`` in MB (10^6 bytes; None if gone)."""
    try:
        with open(f'/proc/{pid}/status') as status:
            for line in status:
                if line.startswith('VmRSS:'):
                    return int(line.split()[1]) * 1024 / 1e6
    except OSError:
        return None
    return None


def udp_receive_drops() -> Optional[int]:
    """Return how many UDP datagrams this machine dropped for full receive buffers so far."""
    try:
        with open('/proc/net/snmp') as snmp:
            rows = [line.split() for line in snmp if line.startswith('Udp:')]
        return int(rows[1][rows[0].index('RcvbufErrors')])
    except (OSError, ValueError, IndexError):
        return None


def dropped_between(before: Dict[str, Optional[int]],
                    after: Dict[str, Optional[int]]) -> Dict[str, int]:
    """Return the datagrams each counter of ``udp_drops`` gained from ``before`` to ``after``.

    The node's socket also counts the echoes of its own frames that its kernel filter drops
    (cbcan_ros/core/python_can_gaps/own_frames.py): only the machine's count of datagrams
    dropped for a full buffer (``system``) bounds what it lost, so its count is capped there.
    """
    gained = {key: after[key] - before[key] for key in before
              if before[key] is not None and after.get(key) is not None}
    if 'node' in gained and 'system' in gained:
        gained['node'] = min(gained['node'], gained['system'])
    return gained


def proc_udp_drops(pid: int, port: int) -> Optional[int]:
    """Return the datagrams dropped so far by the UDP sockets of ``pid`` bound to ``port``.

    /proc/net/udp counts drops per socket (full receive buffer): the sockets are matched to
    the process by their inodes in /proc/<pid>/fd.
    """
    try:
        inodes = set()
        for name in os.listdir(f'/proc/{pid}/fd'):
            try:
                target = os.readlink(f'/proc/{pid}/fd/{name}')
            except OSError:
                continue
            if target.startswith('socket:['):
                inodes.add(target[8:-1])
        total = 0
        for table in ('/proc/net/udp', '/proc/net/udp6'):
            with open(table) as sockets:
                next(sockets)
                for line in sockets:
                    fields = line.split()
                    local_port = int(fields[1].rsplit(':', 1)[1], 16)
                    if local_port == port and fields[9] in inodes:
                        total += int(fields[-1])
        return total
    except (OSError, ValueError, IndexError):
        return None


def write_report(output: str, name: str, title: str, table: str, rows: Dict) -> None:
    """Write ``<name>.md`` (``title``, ``table`` and the load after) and ``<name>.json``."""
    os.makedirs(output, exist_ok=True)
    with open(os.path.join(output, f'{name}.md'), 'w') as file:
        file.write(f'# {title}\n\n{table}\n\nLoad after: '
                   f'{" ".join(f"{v:.2f}" for v in os.getloadavg())}\n')
    with open(os.path.join(output, f'{name}.json'), 'w') as file:
        json.dump(rows, file, indent=1)
