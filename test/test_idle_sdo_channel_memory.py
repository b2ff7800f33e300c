"""Frames on a device's SDO response COB-ID while no transfer runs are not kept.

Once the gateway has talked to a device, it listens to the device's SDO responses (0x580 +
node id) for good. Between two transfers such frames answer nothing: a late answer, or the
device answering another SDO client on the same channel (a service tool, a second master, a
PLC polling the same device). Each of them must be dropped, not kept until the next
transfer to that device, which may never come.
"""

import struct
import sys
import time
import uuid

import can
from test_soak import rss_kb

from cbcan_ros.core.gateway import Gateway, GatewayConfig
from cbcan_ros.srv import NmtState, SdoRead

from conftest import new_channel, wait_until
from node_process import call, private_bus, service_client

SILENT = 9  # nobody answers it: only the frames the test sends are on its COB-IDs
MARKER = 10  # a heartbeat of this node, sent after the flood, tells it was all dispatched
TIMEOUT = 0x05040000
# What another SDO client's traffic looks like on the response COB-ID: download acks.
OTHER_CLIENTS_ANSWER = can.Message(arbitration_id=0x580 + SILENT, is_extended_id=False,
                                   data=struct.pack('<BHB4x', 0x60, 0x2002, 0))
MARKER_HEARTBEAT = can.Message(arbitration_id=0x700 + MARKER, is_extended_id=False,
                               data=b'\x05')


def test_sdo_frames_between_transfers_are_not_kept_by_the_core():
    """The core keeps every frame on 0x589 that arrives after its last transfer with node 9.

    30,000 such frames (4 s of a saturated 1 Mbit/s bus) after one read of node 9: the
    Python memory blocks they leave behind are counted.
    """
    channel = new_channel()
    peer = can.Bus(interface='virtual', channel=channel)
    gateway = Gateway(GatewayConfig(channel=channel))
    gateway.start()
    try:
        assert gateway.sdo_read(SILENT, 0x1000, 0, timeout=0.1).result(10.0).abort_code == \
            TIMEOUT
        before = sys.getallocatedblocks()
        base = gateway.bus_status.frames_received
        for sent in range(1, 30_001):
            peer.send(OTHER_CLIENTS_ANSWER)
            if sent % 5000 == 0:  # the virtual bus keeps a queue per receiver: let it drain
                wait_until(lambda n=sent: gateway.bus_status.frames_received >= base + n,
                           30.0, f'{sent} frames taken')
        peer.send(MARKER_HEARTBEAT)
        wait_until(lambda: gateway.monitor.status(MARKER).detected, 30.0,
                   'every frame dispatched')
        kept = sys.getallocatedblocks() - before
        assert kept < 10_000, (
            f'{kept} Python memory blocks more after 30000 SDO frames for no transfer: each '
            f'one is kept')
    finally:
        gateway.stop()
        peer.shutdown()


FLOOD = 60_000
ALLOWED_GROWTH_KB = 2_000  # 60,000 frames on an id nobody subscribes: +0.1 MB


def test_another_sdo_client_on_the_bus_does_not_grow_the_node_s_memory(start_node,
                                                                       client_node, measured):
    """A user sees cbcan_node's memory grow while a service tool talks to a device.

    The installed node reads node 9 once; then 60,000 frames on 0x589 (the device answering
    another SDO client) pass on the bus. Expected: the node's RSS stays flat.
    """
    group, port = private_bus()
    name = f'/idle{uuid.uuid4().hex[:8]}/cbcan'
    gateway = start_node(['-r', f'__ns:={name.rsplit("/", 1)[0]}',
                          '-p', 'can.interface:=udp_multicast', '-p', f'can.channel:={group}'],
                         port)
    sdo_read = service_client(client_node, SdoRead, f'{name}/sdo_read', gateway)
    nmt_state = service_client(client_node, NmtState, f'{name}/nmt_state', gateway)
    answer = call(sdo_read, SdoRead.Request(node_id=SILENT, index=0x1000, timeout=0.1),
                  'read', gateway)
    assert answer.abort_code == TIMEOUT, answer.message
    bus = can.Bus(interface='udp_multicast', channel=group, port=port)
    try:
        before = rss_kb(gateway.process.pid)
        started = time.monotonic()
        for _ in range(FLOOD):
            bus.send(OTHER_CLIENTS_ANSWER)
        elapsed = time.monotonic() - started

        def marker_seen():
            bus.send(MARKER_HEARTBEAT)
            return call(nmt_state, NmtState.Request(node_id=MARKER), 'state',
                        gateway).state_name == 'OPERATIONAL'
        wait_until(marker_seen, 20.0, 'the frames after the flood dispatched')
        after = rss_kb(gateway.process.pid)
    finally:
        bus.shutdown()
    measured(f'cbcan_node RSS {before} -> {after} kB over {FLOOD} frames on 0x589 '
             f'({FLOOD / elapsed:.0f} frames/s)')
    assert after - before < ALLOWED_GROWTH_KB, (
        f'cbcan_node grew {after - before} kB while {FLOOD} SDO frames for no transfer of '
        f'its own passed on the bus')
