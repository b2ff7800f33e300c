"""The simulated devices of the benchmark, in-process or as a process of their own.

:class:`DeviceHost` puts python-canopen ``LocalNode`` devices built from
``config/simulated_device.eds`` (as ``SimulatedDevice`` of ``cbcan_ros.simulation`` does) on ONE
canopen Network, so the device side opens one bus socket, and adds a ``DurandDevice`` (the
independent device stack, which does block transfer). On ``udp_multicast`` every socket of
the machine receives every frame: ten devices with a socket each would multiply the cost of
every frame by ten, in the process that also has to answer.

As a process (``python bench_devices.py MODE ...``) it writes ``@@ {"ready": ...}`` once up
and then answers commands (one JSON object a line) on standard input:

* ``devices``: the DeviceHost (the rows measured against devices 1..10 and 20);
* ``load-device``: one LocalNode (node 1, answering SDO), its heartbeat period set by
  ``{"op": "load", "period_ms": P}``;
* ``heartbeats``: the heartbeats of nodes 2..N every P ms, from one thread that never
  receives, ``{"op": "load", "nodes": N, "period_ms": P}``; ``{"op": "stats"}`` counts them;
* ``reader``: a bare python-can receiver counting frames, the floor of receiving them.

The load is split in two processes so that node 1's answers do not wait for the sender's
GIL. The sender packs each frame once, as python-can's udp_multicast does, and sends the
datagram on a socket of its own (``UdpMulticastBus.send`` would pack it again for every
frame): the frames on the bus are the same, and one core can send 12,700 of them a second.
"""

import argparse
import ipaddress
import json
import socket
import struct
import sys
import threading
import time
from typing import Dict, Optional, Sequence

from bench_util import (
    DOMAIN_DATA,
    DOMAIN_INDEX,
    EDS,
    exit_on_sigterm,
    import_retrying,
    progress,
    receive,
    send,
    STATE_DEVICE,
    STATE_DEVICE_HEARTBEAT_MS,
)
import can
from can.interfaces.udp_multicast.utils import pack_message
import canopen

NOTIFIER_CYCLE = 0.05
RESET_NODE = 129
ENTER_PRE_OPERATIONAL = 128
UDP_DEFAULT_PORT = 43113  # python-can's udp_multicast default


def _boot(node: canopen.LocalNode) -> None:
    node.data_store.setdefault(DOMAIN_INDEX, {})[0] = DOMAIN_DATA
    node.nmt.send_command(RESET_NODE)  # state 0, the boot-up message
    node.nmt.send_command(ENTER_PRE_OPERATIONAL)  # starts the heartbeat (0x1017, 200 ms)


class DeviceHost:
    """LocalNodes on one canopen Network plus, optionally, one DurandDevice."""

    def __init__(self, interface: str, channel: str, bus_options: Dict,
                 local_ids: Sequence[int], durand_id: Optional[int] = None):
        self._bus = dict(interface=interface, channel=channel, **bus_options)
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = NOTIFIER_CYCLE
        self.local_ids = tuple(local_ids)
        self.durand_id = durand_id
        self.nodes: Dict[int, canopen.LocalNode] = {}
        self.durand = None

    def start(self) -> None:
        """Connect, boot every device, give the state device a short heartbeat."""
        self.network.connect(**self._bus)
        for node_id in self.local_ids:
            node = canopen.LocalNode(node_id, EDS)
            self.network.add_node(node)
            _boot(node)
            self.nodes[node_id] = node
        if STATE_DEVICE in self.nodes:
            self.nodes[STATE_DEVICE].sdo[0x1017].raw = STATE_DEVICE_HEARTBEAT_MS
        if self.durand_id is not None:
            durand_device, = import_retrying('cbcan_ros.simulation.durand.device')
            options = {k: v for k, v in self._bus.items() if k not in ('interface', 'channel')}
            self.durand = durand_device.DurandDevice(
                self.durand_id, self._bus['interface'], self._bus['channel'], options)
            self.durand.start()
            self.durand.set_value(DOMAIN_INDEX, 0, DOMAIN_DATA)

    def set_heartbeat(self, period_ms: int) -> None:
        """Set the producer heartbeat time (0x1017) of every LocalNode."""
        for node in self.nodes.values():
            node.sdo[0x1017].raw = period_ms

    def stop(self) -> None:
        """Stop heartbeats and leave the bus."""
        for node in self.nodes.values():
            node.nmt.stop_heartbeat()
        if self.durand is not None:
            self.durand.stop()
        self.network.disconnect()


class HeartbeatLoad:
    """The heartbeats of many nodes, sent from one thread.

    On udp_multicast the frames leave through a send-only socket: a python-can bus would also
    join the group, and a member that never reads fills its buffer and drops every frame, which
    would hide the drops of the real receivers in the machine's UDP counters.
    """

    def __init__(self, interface: str, channel: str, options: Dict):
        self._bus = None
        self._socket = None
        if interface == 'udp_multicast':
            group = ipaddress.ip_address(channel)
            family = socket.AF_INET if group.version == 4 else socket.AF_INET6
            self._socket = socket.socket(family, socket.SOCK_DGRAM)
            if group.version == 4:
                self._socket.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL,
                                        struct.pack('@I', 1))
            else:
                self._socket.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_HOPS,
                                        struct.pack('@I', 1))
            self._destination = (channel, options.get('port', UDP_DEFAULT_PORT))
        else:
            self._bus = can.Bus(interface=interface, channel=channel, **options)
        self._lock = threading.Lock()
        self._frames: list = []
        self._period = 1.0
        self._restart = False
        self.sent = 0
        self.late_cycles = 0
        self._running = True
        self._thread = threading.Thread(target=self._run, name='heartbeat-load', daemon=True)
        self._thread.start()

    def _sender(self, message: can.Message):
        """Return a function sending ``message`` (on udp_multicast: its datagram, packed once)."""
        if self._socket is None:
            return lambda: self._bus.send(message)
        datagram = pack_message(message)
        return lambda: self._socket.sendto(datagram, self._destination)

    def configure(self, node_ids: Sequence[int], period_ms: float, state: int = 5) -> None:
        """Send the heartbeat ``state`` of ``node_ids`` every ``period_ms``, from now on."""
        with self._lock:
            self._frames = [self._sender(can.Message(
                arbitration_id=0x700 + node_id, data=[state], is_extended_id=False))
                for node_id in node_ids]
            self._period = period_ms / 1000.0
            self._restart = True

    def stop(self) -> None:
        """Stop sending and close the bus."""
        self._running = False
        self._thread.join(2.0)
        if self._socket is not None:
            self._socket.close()
        else:
            self._bus.shutdown()

    def _run(self) -> None:
        next_cycle = time.monotonic()
        while self._running:
            with self._lock:
                frames, period = self._frames, self._period
                if self._restart:
                    next_cycle, self._restart = time.monotonic(), False
            now = time.monotonic()
            if now < next_cycle:
                time.sleep(min(next_cycle - now, 0.1))
                continue
            for send_frame in frames:
                send_frame()
            self.sent += len(frames)
            next_cycle += period
            if next_cycle < time.monotonic() - period:
                self.late_cycles += 1
                next_cycle = time.monotonic()  # cannot keep up: never burst to catch up


def run_devices(args, bus_options: Dict) -> None:
    """Host devices 1..10 (LocalNode) and a DurandDevice until told to stop."""
    host = DeviceHost(args.interface, args.channel, bus_options, range(1, 11), args.durand)
    host.start()
    try:
        send({'ready': True})
        while receive().get('op') != 'stop':
            send({'ok': True})
    finally:
        host.stop()


def run_load_device(args, bus_options: Dict) -> None:
    """Host node 1 (LocalNode), its heartbeat period as told."""
    host = DeviceHost(args.interface, args.channel, bus_options, (1,))
    host.start()
    try:
        send({'ready': True})
        while True:
            command = receive()
            if command['op'] == 'stop':
                break
            if command['op'] == 'load':
                host.set_heartbeat(command['period_ms'])
            send({'ok': True})
    finally:
        host.stop()


def run_heartbeats(args, bus_options: Dict) -> None:
    """Send the heartbeats of nodes 2..N every P ms, as told."""
    load = HeartbeatLoad(args.interface, args.channel, bus_options)
    try:
        send({'ready': True})
        while True:
            command = receive()
            if command['op'] == 'stop':
                break
            if command['op'] == 'load':
                load.configure(range(2, command['nodes'] + 1), command['period_ms'])
            send({'ok': True, 'sent': load.sent, 'late_cycles': load.late_cycles,
                  'time': time.monotonic()})
    finally:
        load.stop()


def run_reader(args, bus_options: Dict) -> None:
    """Receive and count every frame, nothing else: the floor of receiving them."""
    bus = can.Bus(interface=args.interface, channel=args.channel, **bus_options)
    count = 0
    try:
        send({'ready': True})
        while True:
            if bus.recv(0.5) is not None:
                count += 1
    finally:
        bus.shutdown()


MODES = {'devices': run_devices, 'load-device': run_load_device,
         'heartbeats': run_heartbeats, 'reader': run_reader}


def main(argv=None) -> int:
    """Run one of the device processes until stdin closes or a signal arrives."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('mode', choices=MODES)
    parser.add_argument('--interface', default='udp_multicast')
    parser.add_argument('--channel', required=True)
    parser.add_argument('--bus-options', default='{}', help='JSON, e.g. {"port": 30001}')
    parser.add_argument('--durand', type=int, default=None,
                        help='node id of a DurandDevice (devices mode)')
    args = parser.parse_args(argv)
    exit_on_sigterm()
    bus_options = json.loads(args.bus_options)
    try:
        MODES[args.mode](args, bus_options)
    except (KeyboardInterrupt, SystemExit):
        pass
    progress(f'{args.mode} process done')
    return 0


if __name__ == '__main__':
    sys.exit(main())
