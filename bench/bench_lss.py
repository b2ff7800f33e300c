"""How long LSS Fastscan takes: a scan that finds nothing, and one that numbers three devices.

Run by ``make bench`` after the SDO rows (``python bench/bench_lss.py [--quick]``). One
process on a python-can ``virtual`` bus: the gateway's core (what ``~/lss_scan`` calls) and
new durand devices without a node id (LSS slaves of a stack that is not ours). Each round of
the three-device rows starts three new devices. Two identity sets: the simulation's (few
1 bits) and random serial numbers as on real devices (every 1 bit is a probe nobody
answers, so it costs a whole probe wait). Writes ``lss.md`` and ``lss.json`` into
``bench/out/`` (``--output``); a target not met is reported, never fatal.
"""

import argparse
import json
import os
import random
import statistics
import sys
import time
import uuid

from bench_report import machine_info
from bench_util import logs_to, OUTPUT

from cbcan_ros.core.gateway import Gateway, GatewayConfig
from cbcan_ros.simulation.durand.device import DurandDevice

VENDOR, PRODUCT, REVISION = 0x319, 0x51, 0x10000
NONE_TARGET = 0.5
THREE_TARGET = 5.0


def scan_rounds(rounds: int, serials_of_round) -> list:
    """Return the seconds of ``rounds`` scans, each over new devices with those serials."""
    seconds = []
    for number in range(rounds):
        channel = f'bench-lss-{uuid.uuid4().hex[:8]}'
        gateway = Gateway(GatewayConfig(channel=channel))
        gateway.start()
        devices = [DurandDevice(255, channel=channel, lss=True,
                                identity=(VENDOR, PRODUCT, REVISION, serial))
                   for serial in serials_of_round(number)]
        for device in devices:
            device.start()
        try:
            started = time.monotonic()
            result = gateway.lss.scan(1, False, 0.0).result()
            seconds.append(time.monotonic() - started)
            if not result.success or len(result.devices) != len(devices):
                raise SystemExit(f'scan failed: {result.message}')
        finally:
            gateway.stop()
            for device in devices:
                device.stop()
    return seconds


def row(name: str, seconds: list, target: float) -> dict:
    """Return one row of the table: median, worst, and whether the target holds."""
    median, worst = statistics.median(seconds), max(seconds)
    return {'row': name, 'rounds': len(seconds), 'median_s': round(median, 3),
            'max_s': round(worst, 3), 'target_s': target, 'met': worst <= target}


def main(argv=None) -> int:
    """Measure, print and write the LSS rows."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--quick', action='store_true', help='fewer rounds')
    parser.add_argument('--output', default=OUTPUT,
                        help='folder of lss.md and lss.json (default %(default)s)')
    args = parser.parse_args(argv)
    logs_to(os.path.join(args.output, 'lss_logs.txt'))
    rounds = 3 if args.quick else 10
    generator = random.Random(305)
    rows = [
        row('scan, no device', scan_rounds(rounds, lambda _: ()), NONE_TARGET),
        row("scan, 3 devices (the simulation's serials 7, 0x12, 0x30)",
            scan_rounds(rounds, lambda _: (0x7, 0x12, 0x30)), THREE_TARGET),
        row('scan, 3 devices (random 32-bit serials)',
            scan_rounds(rounds, lambda _: generator.sample(range(2 ** 32), 3)), THREE_TARGET),
    ]
    machine = machine_info()
    lines = ['# LSS Fastscan (make bench)', '',
             ', '.join(f'{key}: {value}' for key, value in machine.items()), '',
             '| row | rounds | median | worst | target | |', '|---|---|---|---|---|---|']
    for r in rows:
        lines.append(f"| {r['row']} | {r['rounds']} | {r['median_s']:.3f} s | "
                     f"{r['max_s']:.3f} s | <= {r['target_s']:g} s | "
                     f"{'met' if r['met'] else '**not met**'} |")
    text = '\n'.join(lines) + '\n'
    print(text)
    with open(os.path.join(args.output, 'lss.md'), 'w') as out:
        out.write(text)
    with open(os.path.join(args.output, 'lss.json'), 'w') as out:
        json.dump({'machine': machine, 'rows': rows}, out, indent=1, default=str)
    return 0


if __name__ == '__main__':
    sys.exit(main())
