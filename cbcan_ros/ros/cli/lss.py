"""The LSS commands of ``cbcan_cli``: lss-scan, lss-configure and lss-inquire (CiA 305)."""

import argparse
import sys

from ...core.lss import requests as lss
from ...core.protocol import MAX_NODE_ID
from ...msg import LssIdentity
from ...srv import LssConfigure, LssInquire, LssScan
from ..service_caller import ANSWER_MARGIN
from .arguments import bounded_seconds, ranged
from .standalone_client import Client


def _lss_identity(args) -> LssIdentity:
    return LssIdentity(vendor_id=args.vendor, product_code=args.product, revision=args.revision,
                       serial=args.serial)


def _lss_answer_within(timeout: float) -> float:
    return (timeout or lss.MAX_TIMEOUT) + ANSWER_MARGIN


def _identity_text(identity) -> str:
    return (f'vendor 0x{identity.vendor_id:08X} product 0x{identity.product_code:08X} '
            f'revision 0x{identity.revision:08X} serial 0x{identity.serial:08X}')


def cmd_lss_scan(client: Client, args) -> int:
    """Find unconfigured devices (LSS Fastscan) and, with --assign-from, number them."""
    response = client.call(LssScan, 'lss_scan', LssScan.Request(
        first_node_id=args.assign_from, store=args.store, timeout=args.timeout),
        _lss_answer_within(args.timeout))
    for identity, node_id in zip(response.devices, response.node_ids, strict=True):
        given = f'  -> node {node_id}' if node_id else '  (left unconfigured)'
        print(f'{_identity_text(identity)}{given}')
    if not response.success:
        print(f'error: {response.message}', file=sys.stderr)
        return 1
    print(response.message)
    return 0


def cmd_lss_configure(client: Client, args) -> int:
    """Give one device a node id and/or bit rate (LSS), stored if asked."""
    response = client.call(LssConfigure, 'lss_configure', LssConfigure.Request(
        identity=_lss_identity(args), node_id=args.node_id, bitrate=args.bitrate,
        store=args.store, timeout=args.timeout), _lss_answer_within(args.timeout))
    if not response.success:
        code = f' (LSS error code {response.error_code})' if response.error_code else ''
        print(f'error: {response.message}{code}', file=sys.stderr)
        return 1
    print(f'ok: {response.message}')
    return 0


def cmd_lss_inquire(client: Client, args) -> int:
    """Print the node id of one device, found by its identity (LSS)."""
    response = client.call(LssInquire, 'lss_inquire', LssInquire.Request(
        identity=_lss_identity(args), timeout=args.timeout), _lss_answer_within(args.timeout))
    if not response.success:
        print(f'error: {response.message}', file=sys.stderr)
        return 1
    shown = 'unconfigured (255)' if response.node_id == lss.UNCONFIGURED else response.node_id
    print(f'node id: {shown}')
    return 0


_lss_seconds = bounded_seconds(lss.MAX_TIMEOUT, 'the default')


def _lss_arguments(command: argparse.ArgumentParser, identity: bool, default: str) -> None:
    """Add the device's identity (VENDOR PRODUCT REVISION SERIAL) and --timeout."""
    if identity:
        for name, meaning in (('vendor', 'vendor id, 0x1018:1'),
                              ('product', 'product code, 0x1018:2'),
                              ('revision', 'revision number, 0x1018:3'),
                              ('serial', 'serial number, 0x1018:4')):
            command.add_argument(name, type=ranged(name, 0, 0xFFFFFFFF, 8),
                                 metavar=name.upper(), help=meaning)
    command.add_argument('--timeout', type=_lss_seconds, default=0.0, metavar='S',
                         help=f'seconds for the whole call (default 0: {default})')


def add_commands(commands) -> None:
    """Add lss-scan, lss-configure and lss-inquire."""
    scan = commands.add_parser(
        'lss-scan', help='find unconfigured devices (LSS Fastscan) and number them',
        description='Find the devices without a node id (LSS Fastscan, CiA 305). With '
                    '--assign-from, give each a node id from ID upward, skipping ids heard on '
                    "the bus or listed in the gateway's nodes; each then boots with its id. "
                    'Without, report one device found and leave it unconfigured.')
    scan.add_argument('--assign-from', type=ranged('assign-from', 1, MAX_NODE_ID),
                      default=0, metavar='ID', help='first node id to give (1..127)')
    scan.add_argument('--store', action='store_true',
                      help='store the ids in the devices (kept after power-off)')
    _lss_arguments(scan, False, 'a default that fits the bus')
    scan.set_defaults(run=cmd_lss_scan)

    configure = commands.add_parser(
        'lss-configure', help="set one device's node id and/or bit rate (LSS)",
        description='Give the device with this identity a node id and/or bit rate (LSS '
                    'selective switch, CiA 305); also renumbers a configured device, which '
                    'takes the id at its next NMT reset communication.')
    _lss_arguments(configure, True, '5 s')
    configure.add_argument('--node-id', type=ranged('node-id', 1, MAX_NODE_ID), default=0,
                           metavar='ID', help='new node id 1..127')
    configure.add_argument('--bitrate', type=ranged('bitrate', 0, 0xFFFFFFFF), default=0,
                           metavar='BPS',
                           help=f'new bit rate in bit/s ({", ".join(map(str, lss.BIT_TIMING))}'
                                f'); needs --store, takes effect at the next power-on')
    configure.add_argument('--store', action='store_true',
                           help='store the configuration in the device')
    configure.set_defaults(run=cmd_lss_configure)

    inquire = commands.add_parser(
        'lss-inquire', help='ask one device for its node id (LSS)',
        description='Print the node id of the device with this identity (255: '
                    'unconfigured).')
    _lss_arguments(inquire, True, '5 s')
    inquire.set_defaults(run=cmd_lss_inquire)
