"""The benchmark's report: the table (Markdown, printed and written), the ratios and a chart."""

from importlib import metadata
import json
import math
import os
import platform
import time
from typing import Dict, List, Optional

from bench_util import (
    BATCH_DEVICES,
    BLOCK_DEVICE,
    LATENCY_DEVICE,
    LOCAL_DEVICES,
    SEGMENTED_DEVICE,
    STATE_DEVICE,
    STATE_DEVICE_HEARTBEAT_MS,
)

COLUMNS = ('virtual', 'udp_multicast')
COLUMN_TITLES = {'virtual': 'virtual (1 process)', 'udp_multicast': 'udp_multicast (processes)'}

# 1 Mbit/s; a CAN 2.0A data frame of 8 bytes is 111 bits with the 3-bit interframe space, and
# 111-135 with stuff bits: an expedited SDO (request + answer) is 222-270 bits on the wire.
BITRATE = 1_000_000
BITS_PER_EXCHANGE = 250
WIRE_LIMIT = BITRATE / BITS_PER_EXCHANGE  # 4,000 SDO/s

ROWS = (
    ('1', 'raw', 'raw python-canopen upload of 0x1000 (expedited), the anchor'),
    ('2', 'trigger', 'bare rclpy std_srvs/Trigger round trip, the ROS floor'),
    ('2', 'floor_sdo_read', 'the floor of a read: a bare rclpy `SdoRead` service whose callback '
                            'makes the raw upload'),
    ('3', 'sdo_read', '`sdo_read` of 0x1000 through the gateway, sequential'),
    ('3', 'burst_trigger_150', 'Trigger, bursts of 150 concurrent calls'),
    ('3', 'burst_sdo_150', '`sdo_read`, bursts of 150 concurrent calls over 10 devices'),
    ('3', 'burst_trigger_600', 'Trigger, bursts of 600 concurrent calls'),
    ('3', 'burst_sdo_600', '`sdo_read`, bursts of 600 concurrent calls over 10 devices'),
    ('4', 'batch_raw_3', 'raw python-canopen, 999 uploads over the 3 batch devices, one thread '
                         'each: the ceiling of these devices'),
    ('4', 'batch_1', '`sdo_batch` of 1,000 reads, 1 device'),
    ('4', 'batch_3', '`sdo_batch` of 1,000 reads, 3 devices'),
    ('4', 'batch_8', '`sdo_batch` of 1,000 reads, 8 devices'),
    ('5', 'segmented_raw', '64 KiB segmented read, raw python-canopen'),
    ('5', 'segmented_service', '64 KiB segmented read, `sdo_read`'),
    ('5', 'block_raw', '64 KiB block read, raw python-canopen'),
    ('5', 'block_service', '64 KiB block read, `sdo_read`'),
    ('6', 'states_frame', 'heartbeat frame with the new state -> `node_states` message'),
    ('6', 'states_command', f'NMT command -> `node_states` (includes the device heartbeat of '
                            f'{STATE_DEVICE_HEARTBEAT_MS} ms)'),
)

LOAD_ROWS = (
    ('load_base', '1 device (node 1), heartbeat 200 ms: the unloaded reference'),
    ('load_32', '32 devices, heartbeat every 100 ms'),
    ('load_127', '127 devices, heartbeat every 10 ms'),
)


def machine_info() -> Dict:
    """Return what the run ran on: CPU, cores, Python, kernel, library versions, load."""
    model = 'unknown'
    try:
        with open('/proc/cpuinfo') as cpuinfo:
            for line in cpuinfo:
                if line.startswith('model name'):
                    model = line.split(':', 1)[1].strip()
                    break
    except OSError:
        pass
    versions = {}
    for name in ('ros-jazzy-rclpy', 'python-can', 'canopen', 'durand'):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = '?'
    return {'cpu': model, 'cores': os.cpu_count(), 'python': platform.python_version(),
            'kernel': f'{platform.system()} {platform.release()}', 'versions': versions,
            'date': time.strftime('%Y-%m-%d %H:%M %Z'),
            'load_before': ' '.join(f'{v:.2f}' for v in os.getloadavg())}


def _number(value: Optional[float], digits: int = 0) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return 'n/a'
    return f'{value:,.{digits}f}'


def _with(value: Optional[float], digits: int, unit: str) -> str:
    return 'n/a' if value is None else f'{_number(value, digits)}{unit}'


def _value(row: Optional[dict], key: str) -> Optional[float]:
    if not row:
        return None
    value = row.get(key)
    return None if value is None or (isinstance(value, float) and math.isnan(value)) else value


def _cells(row: Optional[dict]) -> List[str]:
    """Return the median cell and the p99-or-worst cell of a row."""
    if not row:
        return ['not measured', '']
    if row['kind'] == 'ms':
        return [f'{_number(row["p50"], 3)} ms', f'{_number(row["p99"], 3)} ms']
    unit = row['kind']
    median = f'{_number(row["p50"])} {unit}'
    if unit == 'SDO/s':
        median += f' ({_number(row["p50"] / WIRE_LIMIT * 100)} % of wire)'
    return [median, f'{_number(row["worst"])} {unit}']


def _right(row: Optional[dict]) -> str:
    if not row:
        return '-'
    text = f'{row.get("right", "?")}/{row.get("calls", "?")}'
    if 'answered' in row and row['answered'] != row.get('calls'):
        text += f' ({row["answered"]} answered)'
    return text


def _ratio(rows: Dict[str, dict], numerator: str, denominators: List[str]) -> Optional[float]:
    top = _value(rows.get(numerator), 'p50')
    bottom = [_value(rows.get(name), 'p50') for name in denominators]
    if top is None or None in bottom or not sum(bottom):
        return None
    return top / sum(bottom)


def _dropped_share(row: Optional[dict]) -> Optional[float]:
    """Return the share of the bus's frames the node's socket dropped in the CPU window."""
    frames, dropped = _value(row, 'frames_per_s'), _value(row, 'drops_node')
    if frames is None or dropped is None:
        return None
    total = (frames + 1000 / row['period_ms']) * row['window_s']
    return dropped / total if total else None


def _cpu_for_all_frames(row: Optional[dict]) -> tuple:
    """Return (CPU share judged, text): a node that dropped frames did not pay for them.

    Its CPU is then scaled up to every frame on the bus, and the text says so.
    """
    cpu = _value(row, 'cpu_node')
    if cpu is None:
        return None, 'n/a'
    share = _dropped_share(row) or 0.0
    if share <= 0.01:
        return cpu, f'{cpu:.1f} %'
    everything = cpu / max(1e-6, 1.0 - share)
    return everything, (f'{cpu:.1f} % while its socket dropped {share * 100:.0f} % of the '
                        f'frames: ~{everything:.0f} % for all of them')


def ratios(rows: Dict[str, dict]) -> List[tuple]:
    """Return (name, target text, value text, met or None) for one column's rows."""
    def check(value, good, text):
        return (text, None) if value is None else (text, good(value))

    out = []
    value = _ratio(rows, 'sdo_read', ['raw', 'trigger'])
    out.append(('sdo_read p50 / (raw p50 + Trigger p50)', '<= 1.1',
                *check(value, lambda v: v <= 1.1, _number(value, 2))))
    value = _ratio(rows, 'floor_sdo_read', ['raw', 'trigger'])
    out.append(('the floor of a read / (raw p50 + Trigger p50) (not a target: what any gateway '
                'of rclpy and python-canopen pays)', '-', _number(value, 2), None))
    value = _ratio(rows, 'sdo_read', ['floor_sdo_read'])
    out.append(('sdo_read p50 / the floor of a read', '-', _number(value, 2), None))
    for size in (150, 600):
        value = _ratio(rows, f'burst_sdo_{size}', [f'burst_trigger_{size}'])
        out.append((f'burst {size}: sdo_read calls/s / Trigger calls/s', '>= 0.8',
                    *check(value, lambda v: v >= 0.8, _number(value, 2))))
    value = _value(rows.get('batch_3'), 'p50')
    out.append(('sdo_batch over 3 devices, SDO/s', '>= 4,000',
                *check(value, lambda v: v >= 4000,
                       f'{_number(value)} ({_number((value or 0) / WIRE_LIMIT * 100)} % '
                       'of wire)' if value else 'n/a')))
    value = _ratio(rows, 'batch_3', ['batch_raw_3'])
    out.append(('sdo_batch over 3 devices / raw python-canopen on them (not a target: '
                'what the simulated devices allow)', '-', _number(value, 2), None))
    for kind in ('segmented', 'block'):
        value = _ratio(rows, f'{kind}_service', [f'{kind}_raw'])
        out.append((f'64 KiB {kind}: service KiB/s / raw KiB/s', '>= 0.8',
                    *check(value, lambda v: v >= 0.8, _number(value, 2))))
    row = rows.get('states_frame')
    value = _value(row, 'p50')
    out.append(('heartbeat -> node_states latency, p50 (p99)', '<= 50 ms',
                *check(value, lambda v: v <= 50,
                       f'{_number(value, 1)} ms ({_number(_value(row, "p99"), 1)} ms)'
                       if value is not None else 'n/a')))
    load32, load127, base = rows.get('load_32'), rows.get('load_127'), rows.get('load_base')
    value, text = _cpu_for_all_frames(load32)
    out.append(('idle node CPU, 32 devices @ 100 ms', '< 5 % of a core',
                *check(value, lambda v: v < 5, text)))
    value = _value(load32, 'rss_mb')
    out.append(('idle node RSS, 32 devices @ 100 ms', '< 150 MB',
                *check(value, lambda v: v < 150, _with(value, 0, ' MB'))))
    value, text = _cpu_for_all_frames(load127)
    out.append(('idle node CPU, 127 devices @ 10 ms', '< 35 % of a core',
                *check(value, lambda v: v < 35, text)))
    reader = _value(load127, 'cpu_reader')
    value = value / reader if value is not None and reader else None
    out.append(('idle node CPU, 127 devices @ 10 ms / a bare python-can receiver of them',
                '<= 1.3', *check(value, lambda v: v <= 1.3,
                                 f'{_number(value, 2)} (receiver {_number(reader, 1)} %)'
                                 if value else 'n/a')))
    loaded, unloaded = _value(load127, 'p50'), _value(base, 'p50')
    value = loaded / unloaded if loaded is not None and unloaded else None
    out.append(('sdo_read p50 under 127 devices @ 10 ms / unloaded', '<= 2',
                *check(value, lambda v: v <= 2,
                       f'{_number(value, 2)} ({_number(loaded, 2)} / {_number(unloaded, 2)} ms)'
                       if value else 'n/a')))
    return out


def _verdict(met: Optional[bool]) -> str:
    return {None: '', True: ' met', False: ' **not met**'}[met]


def markdown(rows: Dict[str, Dict[str, dict]], problems: List[str], machine: Dict) -> str:
    """Return the whole report as Markdown."""
    lines = ['# cbcan_ros benchmark (`make bench`)', '']
    lines += [f'{machine["date"]}; {machine["cpu"]}, {machine["cores"]} cores; Python '
              f'{machine["python"]}; {machine["kernel"]}; '
              + ', '.join(f'{k} {v}' for k, v in machine['versions'].items())
              + f'; load average {machine["load_before"]} before, '
              f'{machine.get("load_after", "?")} after; '
              f'{"--quick, " if machine.get("quick") else ""}'
              f'{_number(machine.get("duration_s"))} s in all. Other work shares this '
              'machine: the numbers are noisy, compare rows of one run.', '']
    if problems:
        lines += ['**Problems in this run:** ' + '; '.join(problems), '']
    drops = rows['udp_multicast'].get('udp_drops')
    if drops:
        lines += ['udp_multicast frames dropped for a full socket receive buffer, per phase '
                  '(node, device process, client; /proc/net/udp; the node capped by the '
                  "machine's count), and UDP datagrams the whole "
                  'machine dropped (/proc/net/snmp, DDS and other work included): '
                  + '; '.join(f'{phase} {counts.get("node", "?")}, {counts.get("device", "?")}'
                              f', {counts.get("client", "?")} ({counts.get("system", "?")})'
                              for phase, counts in drops['phases'].items()) + '.', '']
    failed = [f'{column} {key}: {row["errors"][0]}' for column in COLUMNS
              for key, row in rows[column].items() if row.get('errors')]
    if failed:
        lines += ['**Calls that failed** (first error of each row): ' + '; '.join(failed), '']
    lines += ['| # | row | ' + ' | '.join(f'{COLUMN_TITLES[c]}: median | p99 / worst'
                                           for c in COLUMNS) + ' | right (virtual; udp) |',
              '|---|---|' + '---:|---:|' * len(COLUMNS) + '---|']
    for number, key, title in ROWS:
        cells = []
        for column in COLUMNS:
            cells += _cells(rows[column].get(key))
        right = '; '.join(_right(rows[column].get(key)) for column in COLUMNS)
        lines.append(f'| {number} | {title} | ' + ' | '.join(cells) + f' | {right} |')
    lines += ['', '**Load** (udp_multicast only). CPU in % of one core from /proc/<pid>/stat '
              'utime+stime over the window, while nothing calls the node; "dropped" = frames '
              'its socket dropped for a full receive buffer (/proc/net/udp, capped by the '
              "machine's count: the socket also counts the echoes of its own frames its "
              'filter drops), i.e. frames it '
              'never paid for; then `sdo_read` of node 1 under the same load:', '',
              '| load | frames/s on the bus | node CPU | node dropped | node RSS | '
              '`sdo_read` p50 | p99 | right | dropped during the calls (node; device) | '
              'device process CPU | sender CPU | bare receiver CPU |',
              '|---|---:|---:|---:|---:|---:|---:|---|---|---:|---:|---:|']
    for key, title in LOAD_ROWS:
        row = rows['udp_multicast'].get(key)
        if not row:
            lines.append(f'| {title} | not measured |' + ' |' * 10)
            continue
        frames = _value(row, 'frames_per_s')
        dropped = _value(row, 'drops_node')
        share = _dropped_share(row)
        if frames is not None:
            frames += 1000 / row['period_ms']  # node 1's own heartbeat
        share = '' if share is None else f' ({share * 100:.0f} %)'
        lines.append(
            f'| {title} | {_number(frames)} | {_number(row.get("cpu_node"), 1)} % | '
            f'{_number(dropped)}{share} | {_number(row.get("rss_mb"))} MB | '
            f'{_number(row["p50"], 3)} ms | {_number(row["p99"], 3)} ms | {_right(row)} | '
            f'{_number(row.get("calls_drops_node"))}; {_number(row.get("calls_drops_device"))} '
            f'| {_number(row.get("cpu_device"), 1)} % | {_number(row.get("cpu_heartbeats"), 1)} '
            f'% | {_number(row.get("cpu_reader"), 1)} % |')
    lines += ['', '**Ratios and targets** (medians):', '',
              '| ratio | target | ' + ' | '.join(COLUMN_TITLES[c] for c in COLUMNS) + ' |',
              '|---|---|' + '---|' * len(COLUMNS)]
    per_column = {column: ratios(rows[column]) for column in COLUMNS}
    for position, (name, target, *_rest) in enumerate(per_column[COLUMNS[0]]):
        cells = []
        for column in COLUMNS:
            _name, _target, text, met = per_column[column][position]
            if text == 'n/a' and column == 'virtual' and 'devices @' in name + target:
                text = 'n/a (udp only)'
            cells.append(text + _verdict(met))
        lines.append(f'| {name} | {target} | ' + ' | '.join(cells) + ' |')
    lines += ['', '**How it was measured**', '',
              '- *virtual*: one process: the devices, the gateway (CbcanNode on an '
              'EventsExecutor thread, as `cbcan_node` spins it), a bare Trigger node '
              '(its own SingleThreadedExecutor thread), raw python-canopen and the client '
              '(SingleThreadedExecutor on the main thread). *udp_multicast*: the device '
              'process, a Trigger server process (`rclpy.spin`, the default executor), the '
              'installed `cbcan_node` (CAN_CONFIG gives the random port) and the client '
              'process, which also does the raw rows against the device process.',
              f'- Devices: python-canopen LocalNodes {LOCAL_DEVICES[0]}..{LOCAL_DEVICES[-1]} '
              'from config/simulated_device.eds on one canopen Network (one bus socket: on '
              'udp_multicast every socket pays for every frame), and a DurandDevice '
              f'{BLOCK_DEVICE} (block transfer). Sequential reads: node {LATENCY_DEVICE}; '
              f'segmented: node {SEGMENTED_DEVICE}; block: node {BLOCK_DEVICE}; batches: nodes '
              + ', '.join(f'{n}: {list(ids)}' for n, ids in BATCH_DEVICES.items())
              + f'; state changes: node {STATE_DEVICE} (heartbeat {STATE_DEVICE_HEARTBEAT_MS} '
              'ms, NMT start / enter pre-operational sent by the client).',
              '- Gateway parameters: defaults (sdo.timeout 0.5 s, sdo.queue_limit 64, '
              'state_publish_period 1 s) except `sdo.block_transfer: true`; LocalNodes refuse '
              'block transfer once during warm-up and get segmented/expedited transfers from '
              'then on. 64 KiB calls and batches carry a 30 s timeout.',
              '- Clients: one node, SingleThreadedExecutor, `call_async` + `spin_once` until '
              '`future.done()`, SERVICE_QOS (reliable, depth 4096) for both Trigger and the '
              'gateway. '
              'Latency rows alternate call by call (the order rotates); bursts, batches and '
              '64 KiB reads alternate round by round. Bursts: all calls sent at once, calls/s '
              '= calls / time until the last answer. "p99 / worst" is the p99 for latencies '
              'and the slowest round for rates; "right" counts answers with the right bytes.',
              f'- Wire limit: 1 Mbit/s; an expedited SDO is two 8-byte frames, 222-270 bits '
              f'with stuffing: assumed {BITS_PER_EXCHANGE} bits, so '
              f'{WIRE_LIMIT:,.0f} SDO/s is 100 %.',
              '- Load: the device process leaves; a device process holds node 1 (LocalNode, '
              'answers SDO, heartbeat at the period of the load) and a sender process sends '
              'the heartbeats of nodes 2..N from one thread (never receiving; each datagram '
              'packed once). A bare python-can receiver '
              'process, in a window of its own after that of the node, shows what receiving the '
              'frames alone costs on udp_multicast (msgpack over a UDP socket; SocketCAN would '
              'cost less).', '']
    return '\n'.join(lines)


def chart(rows: Dict[str, Dict[str, dict]], path: str) -> Optional[str]:
    """Draw the chart to ``path``; return why not if matplotlib is missing."""
    try:
        import matplotlib
        matplotlib.use('Agg')
        from matplotlib import ticker
        import matplotlib.pyplot as plt
    except ImportError as error:
        return f'no chart: {error}'

    figure, axes = plt.subplots(2, 3, figsize=(16, 9))
    colors = {'virtual': '#4C72B0', 'udp_multicast': '#DD8452'}
    width = 0.38

    def bars(axis, keys, labels, title, unit, error_key=None, line=None, line_label=''):
        for offset, column in enumerate(COLUMNS):
            values = [_value(rows[column].get(k), 'p50') or 0 for k in keys]
            errors = None
            if error_key:
                errors = [[0] * len(keys),
                          [max(0.0, (_value(rows[column].get(k), error_key) or 0) - v)
                           for k, v in zip(keys, values, strict=True)]]
            positions = [i + (offset - 0.5) * width for i in range(len(keys))]
            axis.bar(positions, values, width, yerr=errors, capsize=3,
                     label=COLUMN_TITLES[column], color=colors[column])
        if line is not None:
            axis.axhline(line, color='#C44E52', linestyle='--', linewidth=1, label=line_label)
        axis.set_xticks(range(len(keys)))
        axis.set_xticklabels(labels, fontsize=8)
        axis.set_title(title, fontsize=10)
        axis.set_ylabel(unit)
        axis.legend(fontsize=7)

    bars(axes[0][0], ['raw', 'trigger', 'sdo_read', 'states_frame'],
         ['raw upload', 'Trigger', 'sdo_read', 'heartbeat->\nnode_states'],
         'Latency: median, whisker to p99', 'ms', error_key='p99')
    bars(axes[0][1], ['burst_trigger_150', 'burst_sdo_150', 'burst_trigger_600',
                      'burst_sdo_600'],
         ['Trigger\n150', 'sdo_read\n150', 'Trigger\n600', 'sdo_read\n600'],
         'Bursts of concurrent calls', 'calls/s')
    bars(axes[0][2], ['batch_1', 'batch_3', 'batch_8'], ['1 device', '3 devices', '8 devices'],
         'sdo_batch of 1,000 reads', 'SDO/s', line=WIRE_LIMIT,
         line_label=f'1 Mbit/s wire limit ({BITS_PER_EXCHANGE} bit/SDO)')
    bars(axes[1][0], ['segmented_raw', 'segmented_service', 'block_raw', 'block_service'],
         ['segmented\nraw', 'segmented\nsdo_read', 'block\nraw', 'block\nsdo_read'],
         '64 KiB reads', 'KiB/s')
    loads = [rows['udp_multicast'].get(key) for key, _title in LOAD_ROWS]
    labels = ['1 @ 200 ms', '32 @ 100 ms', '127 @ 10 ms']
    axis = axes[1][1]
    axis.bar(labels, [_value(r, 'cpu_node') or 0 for r in loads], color=colors['udp_multicast'],
             label='node CPU')
    axis.bar(labels, [_value(r, 'cpu_reader') or 0 for r in loads], width=0.3, color='#8C8C8C',
             label='bare python-can receiver')
    axis.axhline(5, color='#55A868', linestyle=':', label='target 32 devices (5 %)')
    axis.axhline(35, color='#C44E52', linestyle='--', label='target 127 devices (35 %)')
    axis.set_title('Idle node CPU under heartbeat load (udp_multicast)', fontsize=10)
    axis.set_ylabel('% of one core')
    axis.legend(fontsize=7)
    axis = axes[1][2]
    medians = [_value(r, 'p50') or 0 for r in loads]
    p99s = [max(0.0, (_value(r, 'p99') or 0) - m) for r, m in zip(loads, medians, strict=True)]
    axis.bar(labels, medians, yerr=[[0] * 3, p99s], capsize=3, color=colors['udp_multicast'])
    if medians[0]:
        axis.axhline(2 * medians[0], color='#C44E52', linestyle='--',
                     label='target: 2 x unloaded')
        axis.legend(fontsize=7)
    axis.set_title('sdo_read under heartbeat load: median, whisker to p99', fontsize=10)
    axis.set_ylabel('ms (log scale)')
    if any(medians):
        axis.set_yscale('log')
        axis.yaxis.set_major_locator(ticker.LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        axis.yaxis.set_major_formatter(ticker.FormatStrFormatter('%g'))
        axis.yaxis.set_minor_formatter(ticker.NullFormatter())
    figure.suptitle('cbcan_ros make bench', fontsize=12)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return None


def write_report(rows: Dict[str, Dict[str, dict]], problems: List[str], machine: Dict,
                 folder: str) -> None:
    """Print the report and write latest.md and latest.png into ``folder``."""
    os.makedirs(folder, exist_ok=True)
    text = markdown(rows, problems, machine)
    with open(os.path.join(folder, 'latest.md'), 'w') as output:
        output.write(text)
    with open(os.path.join(folder, 'latest.json'), 'w') as output:
        json.dump({'machine': machine, 'problems': problems, 'rows': rows}, output, indent=1)
    problem = chart(rows, os.path.join(folder, 'latest.png'))
    print()
    print(text)
    print(f'written: {os.path.join(folder, "latest.md")}'
          + (f' ({problem})' if problem else f', {os.path.join(folder, "latest.png")}'))
