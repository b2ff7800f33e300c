"""Program download benchmark: a 256 KiB image into one device, through the gateway and raw.

Run by ``make bench`` after ``bench_boot.py`` (``make bench ARGS=--quick`` shortens it);
writes ``program_download.md`` and ``program_download.json`` in ``bench/out/``
(``--output``), the node's log next to them. A script, not a test: a target that is not met
is reported, never fatal.

One simulated device with a bootloader (``BootloaderDevice``, durand, block download with
CRC; ``bench_drive_host.py bootloader``, in a process of its own, clearing and flashing at
once) on a udp_multicast bus, and, taking turns with it, round by round:

* the gateway: the installed ``cbcan_node``; this process sends a ``~/program_download``
  goal (``start: false``) and times it from the goal sent to the result received: the whole
  action, stop and clear before the image and the flash status after it included;
* the baseline: python canopen in this process writing the same image into 0x1F50:1 with its
  block download stream (``sdo.open(..., block_transfer=True)``), timed around the transfer
  alone (the device is stopped and cleared before, untimed).

The figure is KiB/s of the image (262,144 bytes) over that time; the target is the gateway's
whole action at least 0.9 x the baseline's bare transfer. The download phase alone (the rate
the last DOWNLOADING feedback tells) is shown beside it.
"""

import argparse
import os
import statistics
import sys
import threading
import time
from typing import Dict, List
import zlib

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
from bench_util import OUTPUT, progress, write_report

NODE = 12
IMAGE_SIZE = 256 * 1024
TARGET = 0.9
ROUND_TIMEOUT = 60.0
PROGRAM_DATA, PROGRAM_CONTROL = 0x1F50, 0x1F51
STOP, CLEAR = b'\x00', b'\x03'


class GatewaySide:
    """The installed cbcan_node with the device, and this process's action client."""

    def __init__(self, bus: UdpBus, caller: Caller, output: str):
        from rclpy.action import ActionClient

        from cbcan_ros.action import ProgramDownload
        self._goal_type = ProgramDownload.Goal
        self.node = NodeProcess(bus, {'nodes': f'[{NODE}]'},
                                os.path.join(output, 'program_download_node.log'))
        self.action = ActionClient(caller.node, ProgramDownload,
                                   f'{self.node.name}/program_download')
        if not self.action.wait_for_server(timeout_sec=START_TIMEOUT):
            raise RuntimeError('the gateway offers no program_download action')

    def run(self, path: str) -> Dict:
        """Run one goal; return its KiB/s (whole action) and the download phase's."""
        feedback = []
        done = threading.Event()
        started = time.monotonic()
        sent = self.action.send_goal_async(
            self._goal_type(node_id=NODE, file=path, start=False),
            feedback_callback=lambda message: feedback.append(message.feedback))
        wait_until(sent.done, ROUND_TIMEOUT, 'the goal taken')
        answer = sent.result().get_result_async()
        answer.add_done_callback(lambda _future: done.set())
        # done() checked too: rclpy can complete a future without running its callback.
        wait_until(lambda: done.is_set() or answer.done(), ROUND_TIMEOUT, 'the result')
        elapsed = time.monotonic() - started
        result = answer.result().result
        if not result.success:
            raise RuntimeError(f'the download failed: {result.message}')
        phase = [f.bytes_per_second for f in feedback if f.phase == 'DOWNLOADING']
        return {'kib_s': IMAGE_SIZE / 1024 / elapsed,
                'download_phase_kib_s': phase[-1] / 1024 if phase else float('nan')}

    def close(self) -> None:
        """Stop the node."""
        self.action.destroy()
        self.node.close()


class CanopenSide:
    """python canopen in this process: its block download stream into 0x1F50:1."""

    def __init__(self, bus: UdpBus):
        import canopen
        self.network = canopen_network(bus)
        self.node = canopen.RemoteNode(NODE, canopen.ObjectDictionary())
        self.network.add_node(self.node)

    def run(self, image: bytes) -> Dict:
        """Stop and clear the program (untimed), then time the block download alone."""
        self.node.sdo.download(PROGRAM_CONTROL, 1, STOP)
        self.node.sdo.download(PROGRAM_CONTROL, 1, CLEAR)
        started = time.monotonic()
        with self.node.sdo.open(PROGRAM_DATA, 1, 'wb', buffering=0, size=len(image),
                                block_transfer=True) as stream:
            view, position = memoryview(image), 0
            while position < len(image):  # a raw stream takes 7 bytes a write
                position += stream.write(view[position:position + 7])
        return {'kib_s': IMAGE_SIZE / 1024 / (time.monotonic() - started)}

    def close(self) -> None:
        """Leave the network."""
        self.network.disconnect()


def measure(args, caller: Caller) -> Dict:
    """Set the device and both sides up, run the rounds alternating; return the row."""
    bus = UdpBus()
    image = os.urandom(IMAGE_SIZE)
    os.makedirs(args.output, exist_ok=True)
    path = os.path.join(args.output, 'program_download_image.bin')
    with open(path, 'wb') as file:
        file.write(image)
    device = start_helper('bootloader', 'bootloader', bus, '--nodes', str(NODE))
    sides = {}
    try:
        sides['gateway'] = GatewaySide(bus, caller, args.output)
        sides['canopen'] = CanopenSide(bus)
        rounds: Dict[str, List[Dict]] = {'gateway': [], 'canopen': []}
        runs = {'gateway': lambda: sides['gateway'].run(path),
                'canopen': lambda: sides['canopen'].run(image)}
        wait_until(lambda: _try(runs['gateway']), START_TIMEOUT, 'a first download')
        for number in range(args.repetitions):
            order = ('gateway', 'canopen') if number % 2 == 0 else ('canopen', 'gateway')
            for name in order:
                figures = runs[name]()
                held = _stats(device)
                if held['image_size'] != IMAGE_SIZE or held['software_id'] != zlib.crc32(image):
                    raise RuntimeError(f'{name}: the device holds {held["image_size"]} bytes, '
                                       f'not the image')
                rounds[name].append(figures)
                progress(f'program download: round {number + 1} {name}: '
                         f'{figures["kib_s"]:.1f} KiB/s')
        row = {'repetitions': args.repetitions, 'image_bytes': IMAGE_SIZE}
        for name, kept in rounds.items():
            row[name] = {key: statistics.median(r[key] for r in kept) for key in kept[0]}
            row[name]['all_kib_s'] = [round(r['kib_s'], 1) for r in kept]
        row['ratio'] = row['gateway']['kib_s'] / row['canopen']['kib_s']
        return row
    finally:
        for side in sides.values():
            side.close()
        device.stop()


def _try(run) -> bool:
    """Run a first download (the node's discovery and imports); False while it fails."""
    try:
        run()
    except RuntimeError as error:
        progress(f'program download: not yet ({error})')
        return False
    return True


def _stats(child: Child) -> Dict:
    child.tell({'op': 'stats'})
    return child.expect('ok', START_TIMEOUT)


def table(row: Dict) -> str:
    """Return the row as a Markdown table: the figure, its baseline, the ratio, the target."""
    lines = ['| row | measured | beside it (same run) | ratio | target | met |',
             '|---|---|---|---|---|---|']
    if not row:
        return '\n'.join(lines + ['| program download | not measured | | | | |'])
    gateway, canopen = row['gateway'], row['canopen']
    met = 'yes' if row['ratio'] >= TARGET else '**no**'
    return '\n'.join(lines + [
        f'| program download: {row["image_bytes"] // 1024} KiB image into 0x1F50:1 of a '
        f'durand device (block transfer with CRC), p50 of {row["repetitions"]} | gateway '
        f'`~/program_download` (start false; stop, clear, image, flash status), goal to '
        f'result: {gateway["kib_s"]:.1f} KiB/s (its download phase '
        f'{gateway["download_phase_kib_s"]:.1f} KiB/s) | python canopen block download '
        f'stream, the transfer alone: {canopen["kib_s"]:.1f} KiB/s | {row["ratio"]:.2f} '
        f'| >= {TARGET} | {met} |'])


def main(argv=None) -> int:
    """Measure the program download row and report it."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--quick', action='store_true', help='fewer rounds')
    parser.add_argument('--output', default=OUTPUT, help='folder of program_download.md, '
                                                         '.json and the logs (default '
                                                         '%(default)s)')
    args = parser.parse_args(argv)
    args.repetitions = 3 if args.quick else 7
    row: Dict = {}
    problems: List[str] = []
    with bench_session(args.output, 'program_download', args.quick) as (caller, machine):
        try:
            row = measure(args, caller)
        except (RuntimeError, ChildFailed) as error:
            problems.append(f'program download: {error}')
            progress(f'program download failed: {error}')
    text = table(row)
    described = ', '.join(f'{key}: {value}' for key, value in machine.items())
    notes = [f'Every round (KiB/s): gateway {row["gateway"]["all_kib_s"]}, python canopen '
             f'{row["canopen"]["all_kib_s"]}.'] if row else []
    write_report(args.output, 'program_download', 'Program download benchmark (make bench)',
                 '\n\n'.join([described, text, *notes, *problems]),
                 {'row': row, 'problems': problems, 'machine': machine})
    print(text)
    for line in notes + problems:
        print(line)
    return 0


if __name__ == '__main__':
    sys.exit(main())
