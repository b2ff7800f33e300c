"""Command-line client of the gateway services, for machines without the ``ros2`` CLI.

Examples (the gateway started by ``make run`` is ``/can0/cbcan``)::

    cbcan_cli sdo-read 5 0x1000
    cbcan_cli sdo-read 5 0x2003 --type i32
    cbcan_cli sdo-read 5 "Producer heartbeat time"        # named in node 5's EDS
    cbcan_cli sdo-read 5 "Identity object.Vendor-ID"
    cbcan_cli sdo-write 5 "Producer heartbeat time" 1000   # typed by the EDS
    cbcan_cli sdo-write 5 0x2002 0 0x12345678 --type u32
    cbcan_cli sdo-write 5 0x2021 0 hello --type str
    cbcan_cli nmt 5 start
    cbcan_cli state 5
    cbcan_cli states
    cbcan_cli boot 5                                      # check, configure, start node 5 again
    cbcan_cli boot-states                                 # how each device's last boot ended
    cbcan_cli program-download 5 firmware.bin --expect 0x00010203   # new firmware, CiA 302-3
    cbcan_cli --gateway /robot/can1/cbcan mailbox cbcan 0x0001 ...
    cbcan_cli sdo-batch r:5:0x1000 w:5:0x2002:0:78563412 r:3:0x1008
    cbcan_cli sdo-batch --file accesses.txt
    cbcan_cli lss-scan --assign-from 10 --store
    cbcan_cli lss-inquire 0x319 0x51 0x10000 7
    cbcan_cli lss-configure 0x319 0x51 0x10000 7 --node-id 12 --store
    cbcan_cli pdo-echo 5                                  # what node 5 sends (its TPDOs)
    cbcan_cli pdo-write 5 1 "Demo UNSIGNED8=7" 0x2001=300  # node 5's RPDO 1
    cbcan_cli drive 7 enable --mode csv                   # a CiA 402 drive of drives.nodes
    cbcan_cli target 7 1.5                                # its target in CSV, joint units/s
    cbcan_cli drive 7 set-mode --mode pp
    cbcan_cli move 7 2.0 --velocity 0.5                   # Ctrl-C cancels: the drive halts
    cbcan_cli drives                                      # every drive's state
    cbcan_cli dump 7F0:7F0                                 # raw CAN frames, as candump
    cbcan_cli send 7F0#DEADBEEF 18FF0001#01.02            # as cansend
    cbcan_cli lifecycle configure                         # a managed gateway's transition

Objects are given by index (a number) or by the name the node's EDS or DCF file gives them.
The file is the gateway's parameter ``node_<id>.eds`` (asked of the running gateway) or
``--eds FILE``.

Exit status: 0 on success, 1 when the gateway answered with an error (an SDO abort, a
refused request) or the answer does not fit the value type, 2 when there is no usable
gateway (not running, no answer) or the command line is wrong (an unknown name, a value that
does not fit its type); 130 when Ctrl-C ended it (a move or a program download is cancelled
first).
"""

import argparse
import sys
from typing import Optional, Sequence

from ..client import DEFAULT_GATEWAY, DEFAULT_WAIT, RequestFailed
from ..service_caller import GatewayUnavailable
from . import boot, drive, lifecycle, lss, mailbox, move, nmt, pdo, program, raw, sdo
from .arguments import positive_seconds
from .errors import print_refusal, UsageError
from .standalone_client import Client

# The command groups, each a module with add_commands(commands), in the order --help lists
# their commands.
COMMAND_GROUPS = (sdo, nmt, boot, program, mailbox, lss, pdo, drive, move, raw, lifecycle)


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``cbcan_cli``."""
    parser = argparse.ArgumentParser(
        prog='cbcan_cli',
        description='Call the services of a cbcan_ros CANopen gateway. Numbers take '
                    'decimal or 0x hex.',
        epilog='Exit status: 0 ok, 1 the gateway answered with an error, 2 no gateway or a '
               'wrong command line, 130 ended by Ctrl-C.')
    parser.add_argument('--gateway', default=DEFAULT_GATEWAY,
                        help='the gateway node: namespace and name (default %(default)s)')
    parser.add_argument('--wait', type=positive_seconds, default=DEFAULT_WAIT,
                        help='seconds to wait for the gateway to be found (default '
                             '%(default)g)')
    commands = parser.add_subparsers(dest='command', required=True, metavar='COMMAND')
    for group in COMMAND_GROUPS:
        group.add_commands(commands)
    return parser


def run(client: Client, args: argparse.Namespace) -> int:
    """Run one parsed command through ``client`` (several may share one); return the status."""
    try:
        return args.run(client, args)
    except RequestFailed as error:
        return print_refusal(error.response, error.what)
    except (GatewayUnavailable, UsageError) as error:
        print(f'error: {error}', file=sys.stderr)
        return 2


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run one command of ``cbcan_cli``; return the exit status."""
    args = build_parser().parse_args(argv)
    client = None
    try:
        client = Client(args.gateway, args.wait)
        return run(client, args)
    except KeyboardInterrupt:
        return 130
    finally:
        if client is not None:
            client.close()
