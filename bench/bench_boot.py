"""Boot configuration benchmark: 8 devices booting at once, 50 writes each, until all started.

Run by ``make bench`` last, after ``bench_shutdown.py`` (``make bench ARGS=--quick`` shortens it);
writes ``boot.md`` and ``boot.json`` in ``bench/out/`` (``--output``), the node's log next to
them. A script, not a test: a target that is not met is reported, never fatal.

The row: 8 simulated devices (``SimulatedDevice``, ``bench_drive_host.py devices``, in a
process of their own so that the node's CPU is the gateway's alone) boot at once, after one
NMT reset node to all of them (0x000 [0x81, 0]) sent by this process, and are configured with
the same 50 values each (UNSIGNED32 objects 0x3000-0x3031, a DCF written at run time from
``config/simulated_device.eds``), then started:

* the gateway: the installed ``cbcan_node`` with a ``bus_config`` naming the 8 devices with
  that DCF; the boot-ups start its boots (device type, identity, the DCF's ``ParameterValue``
  entries written and read back, a heartbeat awaited, NMT start), the 8 side by side;
* the baseline: python canopen in this process, on a second udp_multicast bus with 8 devices
  of the same kind in a process of their own: after the same reset, for node 1..8 one after
  the other, ``RemoteNode(node_id, dcf).load_configuration()`` and an NMT start.

Each round is timed from the reset frame to the last NMT start frame, both taken by the
kernel's receive timestamps at a bare receiver process on each bus (``bench_drive_host.py
reader``), the same measure for both sides; the same receiver counts each side's SDO
transfers and shows where the time goes. The gateway's ``~/boot_states`` showing all 8
``BOOTED`` again is timed too (at this process's subscriber). Rounds alternate which side goes
first. The DCF has no PDO objects: ``load_configuration()`` writes every PDO of its file
(``pdo.read(from_od=True)``, ``pdo.save()``), the gateway only those the file gives values,
so without them both write the same 50 objects. Every device counts the writes it took, and
the report shows them. Target: the gateway at most 0.5 x the baseline.

The row is measured twice: with the simulated devices answering each SDO request at once,
and answering after 1 ms (``--answer-delay``), as real devices take about that. Answering at
once, every transfer is CPU work of the two processes on the same 2 cores, so boots side by
side cannot overlap anything the baseline waits for; answering after 1 ms, they overlap the
devices' time, as on a real bus.
"""

import argparse
import configparser
from itertools import pairwise
import os
import re
import statistics
import sys
import threading
import time
from typing import Dict, List, Tuple

from bench_drives import (
    bench_session,
    Caller,
    canopen_network,
    NodeProcess,
    start_helper,
    START_TIMEOUT,
    UdpBus,
    wait_until,
)
from bench_sdo import Child, ChildFailed
from bench_util import (
    EDS,
    OUTPUT,
    proc_cpu_seconds,
    proc_udp_drops,
    progress,
    write_report,
)

DEVICES = tuple(range(1, 9))
OBJECTS = 50
FIRST_INDEX = 0x3000
TARGET = 0.5
ANSWER_DELAYS = (0.0, 0.001)  # s a simulated device takes to answer an SDO request
NMT_RESET_NODE, NMT_START = 0x81, 0x01
PDO_OBJECTS = range(0x1400, 0x1C00)
ROUND_TIMEOUT = 30.0
SETTLE = 0.3  # s after a round: every frame of it has reached the receiver
# The frames the receivers keep: NMT, SDO answers and requests, boot-ups and heartbeats.
RECORDED = ','.join(f'0x{cob_id:X}' for cob_id in
                    [0x000] + [base + node_id for base in (0x580, 0x600, 0x700)
                               for node_id in DEVICES])


def value_of(number: int) -> int:
    """Return the value written to object ``FIRST_INDEX + number``: distinct, never 0."""
    return 0x10000000 + number * 0x01010101


def write_files(folder: str) -> Tuple[str, str, str]:
    """Write the devices' EDS, the DCF that configures them and the bus description.

    The EDS is ``config/simulated_device.eds`` with ``OBJECTS`` UNSIGNED32 rw objects from
    ``FIRST_INDEX`` (default 0); the DCF is that EDS without its PDO objects, the new objects
    given ``ParameterValue``s. Return the three paths.
    """
    os.makedirs(folder, exist_ok=True)
    eds = configparser.RawConfigParser()
    eds.optionxform = str  # keys as the file spells them
    eds.read(EDS)
    new = [FIRST_INDEX + number for number in range(OBJECTS)]
    manufacturer = [int(eds.get('ManufacturerObjects', key), 0)
                    for key in eds.options('ManufacturerObjects') if key.isdigit()]
    _list_objects(eds, 'ManufacturerObjects', manufacturer + new)
    for number, index in enumerate(new):
        section = f'{index:04X}'
        eds.add_section(section)
        for key, value in (('ParameterName', f'Bench parameter {number + 1}'),
                           ('ObjectType', '0x7'), ('DataType', '0x0007'),
                           ('AccessType', 'rw'), ('DefaultValue', '0'), ('PDOMapping', '0')):
            eds.set(section, key, value)
    eds_path = os.path.join(folder, 'boot_device.eds')
    with open(eds_path, 'w') as file:
        eds.write(file, space_around_delimiters=False)

    for section in [name for name in eds.sections()
                    if re.fullmatch(r'[0-9A-Fa-f]{4}(sub[0-9A-Fa-f]+)?', name)
                    and int(name[:4], 16) in PDO_OBJECTS]:
        eds.remove_section(section)
    optional = [int(eds.get('OptionalObjects', key), 0)
                for key in eds.options('OptionalObjects') if key.isdigit()]
    _list_objects(eds, 'OptionalObjects', [i for i in optional if i not in PDO_OBJECTS])
    for number, index in enumerate(new):
        eds.set(f'{index:04X}', 'ParameterValue', f'0x{value_of(number):08X}')
    eds.set('FileInfo', 'FileName', 'boot_device.dcf')
    eds.set('FileInfo', 'Description', f'bench_boot.py: {OBJECTS} values to write, no PDOs')
    dcf_path = os.path.join(folder, 'boot_device.dcf')
    with open(dcf_path, 'w') as file:
        eds.write(file, space_around_delimiters=False)

    bus_path = os.path.join(folder, 'bus.yml')
    with open(bus_path, 'w') as file:
        file.write('# bench_boot.py: the devices the gateway boots\nnodes:\n')
        for node_id in DEVICES:
            file.write(f'  device_{node_id}:\n    node_id: {node_id}\n'
                       f'    dcf: boot_device.dcf\n')
    return eds_path, dcf_path, bus_path


def _list_objects(eds: configparser.RawConfigParser, section: str, indices: List[int]) -> None:
    for key in eds.options(section):
        eds.remove_option(section, key)
    eds.set(section, 'SupportedObjects', str(len(indices)))
    for number, index in enumerate(indices, 1):
        eds.set(section, str(number), f'0x{index:04X}')


# Where a round's time went, from the frames a receiver recorded.

def analyse(frames: List, node_ids=DEVICES) -> Dict:
    """Return a round's figures from its frames (kernel timestamps, s; ``reader --record``).

    ``total_ms``: the reset frame to the last NMT start frame. Per device: the boot-up, its
    first SDO request, its last SDO answer and its NMT start, relative to the reset. Per
    transfer, over every device: the device's answer after the request (``answer_ms``) and
    the master's next request after an answer (``turnaround_ms``), p50.
    """
    frames = sorted(frames)
    resets = [time for time, cob_id, data in frames
              if cob_id == 0 and data == f'{NMT_RESET_NODE:02x}00']
    if not resets:
        raise RuntimeError('the receiver did not see the NMT reset')
    reset = resets[-1]
    after = [(time - reset, cob_id, data) for time, cob_id, data in frames if time >= reset]
    devices = {}
    answer_s: List[float] = []
    turnaround_s: List[float] = []
    for node_id in node_ids:
        sdo = [(time, cob_id) for time, cob_id, _ in after
               if cob_id in (0x600 + node_id, 0x580 + node_id)]
        for (sent, first), (came, second) in pairwise(sdo):
            if (first, second) == (0x600 + node_id, 0x580 + node_id):
                answer_s.append(came - sent)
            elif (first, second) == (0x580 + node_id, 0x600 + node_id):
                turnaround_s.append(came - sent)
        boot_up = next((t for t, cob_id, data in after
                        if cob_id == 0x700 + node_id and data == '00'), None)
        requests = [t for t, cob_id, _ in after if cob_id == 0x600 + node_id]
        answers = [t for t, cob_id, _ in after if cob_id == 0x580 + node_id]
        start = next((t for t, cob_id, data in after if cob_id == 0 and
                      data in (f'{NMT_START:02x}{node_id:02x}', f'{NMT_START:02x}00')), None)
        missing = [name for name, seen in (('boot-up', boot_up is not None),
                                           ('SDO request', requests), ('SDO answer', answers),
                                           ('NMT start', start is not None)) if not seen]
        if missing:
            raise RuntimeError(f'node {node_id}: the receiver saw no {", ".join(missing)} '
                               f'after the reset')
        devices[node_id] = {'boot_up': boot_up, 'first_request': requests[0],
                            'last_answer': answers[-1], 'start': start,
                            'sdo_transfers': len(requests), 'sdo_answers': len(answers)}
    ms = {name: [device[name] * 1e3 for device in devices.values()]
          for name in ('boot_up', 'first_request', 'last_answer', 'start')}
    return {
        'total_ms': max(ms['start']),
        'last_boot_up_ms': max(ms['boot_up']),
        'last_answer_ms': max(ms['last_answer']),  # every device configured (and verified)
        'sdo_transfers': sum(device['sdo_transfers'] for device in devices.values()),
        'sdo_answers': sum(device['sdo_answers'] for device in devices.values()),
        'sdo_transfers_per_device': {node_id: device['sdo_transfers']
                                     for node_id, device in devices.items()},
        # per device, the median over the devices
        'boot_up_to_first_sdo_ms': statistics.median(
            d['first_request'] - d['boot_up'] for d in devices.values()) * 1e3,
        'sdo_span_ms': statistics.median(
            d['last_answer'] - d['first_request'] for d in devices.values()) * 1e3,
        'last_answer_to_start_ms': statistics.median(
            d['start'] - d['last_answer'] for d in devices.values()) * 1e3,
        'sdo_round_trip_ms': statistics.median(
            (d['last_answer'] - d['first_request']) / max(1, d['sdo_transfers'] - 1)
            for d in devices.values()) * 1e3,
        'answer_ms': statistics.median(answer_s) * 1e3 if answer_s else float('nan'),
        'turnaround_ms': statistics.median(turnaround_s) * 1e3 if turnaround_s else float('nan'),
    }


def _stats(child: Child) -> dict:
    child.tell({'op': 'stats'})
    return child.expect('ok', START_TIMEOUT)


class Side:
    """One bus with its devices' process and its receiver; ``run()`` measures one round."""

    def __init__(self, name: str, eds_path: str, answer_delay: float):
        self.name = name
        self.bus = UdpBus()
        self.devices = start_helper(f'{name} devices', 'devices', self.bus, '--eds', eds_path,
                                    '--nodes', ','.join(map(str, DEVICES)), '--shared-socket',
                                    '--answer-delay', str(answer_delay))
        self.reader = start_helper(f'{name} reader', 'reader', self.bus, '--record', RECORDED)
        self.rounds: List[Dict] = []
        self.retries: List[str] = []
        self.devices_cpu_s = 0.0
        self.master_cpu_s = 0.0
        self.master_pid = os.getpid()  # the process that configures the devices
        self.busy_s = 0.0

    def measure(self) -> Dict:
        """Run one round; run it again (at most twice) when the receiver missed frames.

        The receiver is a python process on a loaded machine: when its socket's buffer is
        full the kernel drops frames (counted, /proc/net/udp), and a round without its
        NMT start frames cannot be timed. Such rounds are counted in the report.
        """
        for attempt in range(3):
            try:
                return self._measure_once()
            except RuntimeError as error:
                self.retries.append(str(error))
                if attempt == 2:
                    raise
                progress(f'boot: {error}; the round again')
        return {}

    def _measure_once(self) -> Dict:
        _stats(self.reader)  # forget the frames so far
        drops_before = proc_udp_drops(self.reader.pid, self.bus.port) or 0
        writes_before = _stats(self.devices)['writes']
        cpu_before = [proc_cpu_seconds(pid) for pid in (self.devices.pid, self.master_pid)]
        started = time.monotonic()
        extra = self.run()
        cpu_after = [proc_cpu_seconds(pid) for pid in (self.devices.pid, self.master_pid)]
        self.busy_s += time.monotonic() - started
        self.devices_cpu_s += cpu_after[0] - cpu_before[0]
        self.master_cpu_s += cpu_after[1] - cpu_before[1]
        time.sleep(SETTLE)
        frames = _stats(self.reader)['frames']
        drops = (proc_udp_drops(self.reader.pid, self.bus.port) or 0) - drops_before
        try:
            figures = analyse(frames)
        except RuntimeError as error:
            raise RuntimeError(f'{self.name}: {error} ({drops} frames dropped at the '
                               f'receiver in this round)') from None
        figures['receiver_drops'] = drops
        writes = _stats(self.devices)['writes']
        figures['writes'] = {int(node_id): writes[node_id] - writes_before[node_id]
                             for node_id in writes}
        figures.update(extra)
        self.rounds.append(figures)
        return figures

    def run(self) -> Dict:
        """Reset every device and wait until each is configured and started."""
        raise NotImplementedError

    def close(self) -> None:
        """Stop the processes of this side."""
        for child in (self.reader, self.devices):
            child.stop()


class GatewaySide(Side):
    """The installed cbcan_node booting the devices of ``bus.yml``."""

    def __init__(self, eds_path: str, bus_path: str, caller: Caller, output: str,
                 answer_delay: float):
        from cbcan_ros.msg import BootStates
        from cbcan_ros.ros.boot import BOOT_STATES_QOS
        super().__init__('gateway', eds_path, answer_delay)
        self.node = None
        self.subscription = None
        self._caller = caller
        self._states: List[Tuple[float, Dict[int, Tuple[str, int]]]] = []
        self._lock = threading.Lock()
        self._raw = self.bus.open()
        self.node = NodeProcess(self.bus, {'bus_config': bus_path},
                                os.path.join(output, 'boot_node.log'))
        self.master_pid = self.node.pid
        self.subscription = caller.node.create_subscription(
            BootStates, f'{self.node.name}/boot_states', self._on_states, BOOT_STATES_QOS)
        progress('boot: the gateway boots its 8 devices once (at its start)')
        wait_until(lambda: self._all_booted(1), START_TIMEOUT, 'the first boot of every device')

    def _on_states(self, message) -> None:
        now = time.monotonic()
        with self._lock:
            self._states.append((now, {state.node_id: (state.state, state.boots)
                                       for state in message.states}))

    def _latest(self) -> Dict[int, Tuple[str, int]]:
        with self._lock:
            return self._states[-1][1] if self._states else {}

    def _all_booted(self, boots: int) -> bool:
        latest = self._latest()
        return all(latest.get(node_id, ('', 0))[0] == 'BOOTED' and
                   latest[node_id][1] >= boots for node_id in DEVICES)

    def run(self) -> Dict:
        """Reset every device; wait for ~/boot_states to show each BOOTED once more."""
        import can
        boots = max(boots for _state, boots in self._latest().values()) + 1
        with self._lock:
            self._states.clear()
        reset = can.Message(arbitration_id=0, data=[NMT_RESET_NODE, 0], is_extended_id=False)
        sent = time.monotonic()
        self._raw.send(reset)
        wait_until(lambda: self._all_booted(boots), ROUND_TIMEOUT, 'every device BOOTED again')
        with self._lock:
            shown = next(moment for moment, states in self._states
                         if all(states.get(node_id, ('', 0)) == ('BOOTED', boots)
                                for node_id in DEVICES))
        return {'boot_states_ms': (shown - sent) * 1e3}

    def close(self) -> None:
        """Stop the node, then the devices and the receiver."""
        if self.subscription is not None:
            self._caller.node.destroy_subscription(self.subscription)
        if self.node is not None:
            self.node.close()
        self._raw.shutdown()
        super().close()


class CanopenSide(Side):
    """python canopen in this process: ``load_configuration()`` one device after the other."""

    def __init__(self, eds_path: str, dcf_path: str, answer_delay: float):
        import canopen
        super().__init__('python canopen', eds_path, answer_delay)
        self.network = canopen_network(self.bus)
        self.nodes = [canopen.RemoteNode(node_id, dcf_path) for node_id in DEVICES]
        self._booted = {node_id: threading.Event() for node_id in DEVICES}
        for node in self.nodes:
            self.network.add_node(node)
            self.network.subscribe(0x700 + node.id, self._on_heartbeat)

    def _on_heartbeat(self, cob_id: int, data: bytearray, _timestamp: float) -> None:
        if data and data[0] == 0:  # a boot-up
            self._booted[cob_id - 0x700].set()

    def run(self) -> Dict:
        """Reset every device; then each: await its boot-up, load its DCF, start it."""
        for booted in self._booted.values():
            booted.clear()
        self.network.send_message(0, [NMT_RESET_NODE, 0])
        for node in self.nodes:
            if not self._booted[node.id].wait(ROUND_TIMEOUT):
                raise RuntimeError(f'node {node.id} sent no boot-up after the reset')
            node.load_configuration()
            node.nmt.send_command(NMT_START)
        return {}

    def close(self) -> None:
        """Leave the network, stop the devices and the receiver."""
        self.network.disconnect()
        super().close()


def measure(args, caller: Caller, answer_delay: float) -> Dict:
    """Set both sides up, run the rounds alternating which goes first; return the row."""
    eds_path, dcf_path, bus_path = write_files(os.path.join(args.output, 'boot_files'))
    sides: Dict[str, Side] = {}
    try:
        progress(f'boot: set up (gateway, python canopen), 8 devices each, answering after '
                 f'{answer_delay * 1e3:g} ms')
        sides['gateway'] = GatewaySide(eds_path, bus_path, caller, args.output, answer_delay)
        sides['canopen'] = CanopenSide(eds_path, dcf_path, answer_delay)
        sides['canopen'].measure()  # a first round: canopen's imports and SDO setup
        sides['canopen'].rounds.clear()
        for number in range(args.repetitions):
            order = ('gateway', 'canopen') if number % 2 == 0 else ('canopen', 'gateway')
            for name in order:
                figures = sides[name].measure()
                progress(f'boot: round {number + 1} {name}: {figures["total_ms"]:.0f} ms, '
                         f'{figures["sdo_transfers"]} SDO transfers')
        row = {'repetitions': args.repetitions, 'devices': len(DEVICES), 'objects': OBJECTS,
               'answer_delay_ms': answer_delay * 1e3}
        for name, side in sides.items():
            row[name] = summary(side)
        row['ratio'] = row['gateway']['total_ms'] / row['canopen']['total_ms']
        row['gateway']['boot_states_ms'] = statistics.median(
            r['boot_states_ms'] for r in sides['gateway'].rounds)
        return row
    finally:
        for side in sides.values():
            side.close()


def summary(side: Side) -> Dict:
    """Return the median of each figure over the side's rounds, and the writes seen."""
    rounds = side.rounds
    figures = {key: statistics.median(r[key] for r in rounds)
               for key in ('total_ms', 'last_boot_up_ms', 'last_answer_ms',
                           'boot_up_to_first_sdo_ms', 'sdo_span_ms', 'last_answer_to_start_ms',
                           'sdo_round_trip_ms', 'answer_ms', 'turnaround_ms')}
    # Transfers are counted in the rounds whose every frame reached the receiver.
    whole = [r['sdo_transfers'] for r in rounds if not r['receiver_drops']]
    figures['sdo_transfers'] = statistics.median(whole) if whole else float('nan')
    figures['rounds_with_drops'] = len(rounds) - len(whole)
    figures['rounds_again'] = side.retries
    figures['total_ms_all'] = [round(r['total_ms'], 1) for r in rounds]
    figures['rounds'] = rounds  # every figure of every round, for the JSON
    writes = [w for r in rounds for w in r['writes'].values()]
    figures['writes_per_device'] = (min(writes), max(writes))
    figures['devices_cpu_percent'] = 100 * side.devices_cpu_s / side.busy_s
    figures['master_cpu_percent'] = 100 * side.master_cpu_s / side.busy_s
    return figures


def table(rows: List[Dict]) -> str:
    """Return the rows as a Markdown table: the figure, its baseline, the ratio, the target."""
    lines = ['| row | measured | beside it (same run) | ratio | target | met |',
             '|---|---|---|---|---|---|']
    if not rows:
        return '\n'.join(lines + ['| boot | not measured | | | | |'])
    return '\n'.join(lines + [_line(row) for row in rows])


def _line(row: Dict) -> str:
    gateway, canopen = row['gateway'], row['canopen']
    met = 'yes' if row['ratio'] <= TARGET else '**no**'
    answering = (f'answering each SDO request after {row["answer_delay_ms"]:g} ms'
                 if row['answer_delay_ms'] else 'answering at once')
    return (
        f'| boot: {row["devices"]} devices {answering}, {row["objects"]} writes each, after one '
        f'NMT reset node to all: the reset to the last NMT start, p50 of {row["repetitions"]} '
        f'| gateway '
        f'(`bus_config`, boots side by side) {gateway["total_ms"]:.1f} ms, '
        f'{gateway["sdo_transfers"]:.0f} SDO transfers; `~/boot_states` all BOOTED after '
        f'{gateway["boot_states_ms"]:.1f} ms | python canopen `load_configuration()` + NMT '
        f'start, one device after the other, {canopen["total_ms"]:.1f} ms, '
        f'{canopen["sdo_transfers"]:.0f} SDO transfers | {row["ratio"]:.2f} | <= {TARGET} '
        f'| {met} |')


def notes(rows: List[Dict]) -> List[str]:
    """Return where the time went, and what each side wrote."""
    return [line for row in rows for line in _notes(row)]


def _notes(row: Dict) -> List[str]:
    lines = [f'Devices answering after {row["answer_delay_ms"]:g} ms:']
    master = {'gateway': 'the node process', 'canopen': 'this process'}
    for name, shown in (('gateway', 'gateway'), ('canopen', 'python canopen')):
        side = row[name]
        lines.append(
            f'{shown}: the last boot-up {side["last_boot_up_ms"]:.1f} ms after the reset; per '
            f'device (median) boot-up to its first SDO request '
            f'{side["boot_up_to_first_sdo_ms"]:.1f} ms, first request to last answer '
            f'{side["sdo_span_ms"]:.1f} ms ({side["sdo_round_trip_ms"]:.2f} ms a transfer: the '
            f'device answering {side["answer_ms"]:.2f} ms after a request, the next request '
            f'{side["turnaround_ms"]:.2f} ms after an answer, p50), '
            f'last answer to its NMT start {side["last_answer_to_start_ms"]:.1f} ms; the last '
            f'SDO answer of all {side["last_answer_ms"]:.1f} ms after the reset; writes '
            f'taken per device {side["writes_per_device"][0]}-{side["writes_per_device"][1]}; '
            f'while the rounds ran, the device process used '
            f'{side["devices_cpu_percent"]:.0f} % of a core, the master '
            f'({master[name]}) {side["master_cpu_percent"]:.0f} %; every '
            f'round (ms): {", ".join(f"{t:g}" for t in side["total_ms_all"])}.')
    dropped = {name: row[name]['rounds_with_drops'] for name in ('gateway', 'canopen')}
    again = {name: len(row[name]['rounds_again']) for name in ('gateway', 'canopen')}
    if any(dropped.values()) or any(again.values()):
        lines.append(f'The receivers dropped frames (full socket buffer) in {dropped} rounds '
                     f'(SDO transfers counted in the others; the times need only the reset and '
                     f'the starts), and {again} rounds ran again for a missing frame.')
    lines.append(
        "The gateway's SDO transfers per device: 0x1000, 0x1018:2 (the DCF's product code; "
        f'its vendor is 0: not checked), the {OBJECTS} writes, the {OBJECTS} read back and '
        "0x1017 (not written: read for the heartbeat wait); python canopen's: the "
        f'{OBJECTS} writes. Both count the requests this side sent (all expedited), at the '
        'receiver.')
    return lines


def main(argv=None) -> int:
    """Measure the boot row and report it."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--quick', action='store_true', help='fewer rounds')
    parser.add_argument('--output', default=OUTPUT,
                        help='folder of boot.md, boot.json and the logs (default %(default)s)')
    args = parser.parse_args(argv)
    args.repetitions = 4 if args.quick else 12
    rows: List[Dict] = []
    problems: List[str] = []
    with bench_session(args.output, 'boot', args.quick) as (caller, machine):
        for answer_delay in ANSWER_DELAYS:
            try:
                rows.append(measure(args, caller, answer_delay))
            except (RuntimeError, ChildFailed) as error:
                problems.append(f'boot, devices answering after {answer_delay * 1e3:g} ms: '
                                f'{error}')
                progress(f'boot failed: {error}')
    text = table(rows)
    described = ', '.join(f'{key}: {value}' for key, value in machine.items())
    write_report(args.output, 'boot', 'Boot configuration benchmark (make bench)',
                 '\n\n'.join([described, text, *notes(rows), *problems]),
                 {'rows': rows, 'problems': problems, 'machine': machine})
    print(text)
    for line in notes(rows) + problems:
        print(line)
    return 0


if __name__ == '__main__':
    sys.exit(main())
