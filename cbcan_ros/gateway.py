"""The gateway core: one CAN bus, one canopen Network, SDO channels, NMT and node states.

Knows nothing of ROS. The ROS node (``node.py``) and the PLC mailbox (``mailbox.py``) are
both thin layers over :class:`Gateway`, so there is exactly one SDO and one NMT code path.
"""

from concurrent.futures import Future
from dataclasses import dataclass, field
import logging
import threading
from typing import Dict, Tuple

import canopen
from canopen import objectdictionary as od

from . import nmt
from .sdo import (
    check_node_id,
    check_request,
    check_size,
    resolved,
    run_guarded,
    SdoChannel,
    SdoResult,
)

LOGGER = logging.getLogger(__name__)

VERSION = '0.1.0'

# canopen's notifier thread polls the bus once a second by default, and closing the
# network waits for that poll: a shorter cycle lets the node shut down at once.
NOTIFIER_CYCLE = 0.05


@dataclass(frozen=True)
class GatewayConfig:
    """Everything the core needs to know; the ROS node fills it from parameters."""

    interface: str = 'virtual'
    channel: str = 'cbcan'
    bitrate: int = 0
    sdo_timeout: float = 0.5
    block_transfer: bool = False
    heartbeat_timeout: float = 3.0
    expected_nodes: Tuple[int, ...] = ()
    guarded_nodes: Tuple[int, ...] = ()
    guard_period: float = 1.0
    bus_options: Dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class NmtResult:
    """The answer to an NMT command."""

    success: bool
    message: str = ''


def _variable(name, index, subindex, data_type, access, default):
    variable = od.ODVariable(name, index, subindex)
    variable.data_type = data_type
    variable.access_type = access
    variable.default = default
    return variable


def own_dictionary() -> canopen.LocalNode:
    """Build the gateway's own object dictionary (node id 0 in the services).

    It is not on the bus: the gateway has no node id of its own. 0x1017 is writable as
    CiA 301 requires and keeps its value, but no heartbeat is produced from it.
    """
    dictionary = od.ObjectDictionary()
    dictionary.add_object(_variable('Device type', 0x1000, 0, od.UNSIGNED32, 'ro', 0))
    dictionary.add_object(_variable('Error register', 0x1001, 0, od.UNSIGNED8, 'ro', 0))
    dictionary.add_object(_variable('Manufacturer device name', 0x1008, 0,
                                    od.VISIBLE_STRING, 'const', 'cbcan_ros gateway'))
    dictionary.add_object(_variable('Manufacturer software version', 0x100A, 0,
                                    od.VISIBLE_STRING, 'const', VERSION))
    dictionary.add_object(_variable('Producer heartbeat time', 0x1017, 0,
                                    od.UNSIGNED16, 'rw', 0))
    identity = od.ODRecord('Identity object', 0x1018)
    for subindex, name, data_type, value in (
            (0, 'Highest sub-index supported', od.UNSIGNED8, 4),
            (1, 'Vendor-ID', od.UNSIGNED32, 0),
            (2, 'Product code', od.UNSIGNED32, 0xCBCA),
            (3, 'Revision number', od.UNSIGNED32, 0x00010000),
            (4, 'Serial number', od.UNSIGNED32, 0)):
        identity.add_member(_variable(name, 0x1018, subindex, data_type,
                                      'const' if subindex == 0 else 'ro', value))
    dictionary.add_object(identity)
    dictionary.node_id = 0  # canopen reads a node id of 0 as "take it from the dictionary"
    node = canopen.LocalNode(0, dictionary)
    # LocalNode starts a heartbeat producer when 0x1017 is written; this dictionary has no bus.
    node._write_callbacks.remove(node.nmt.on_write)
    return node


class Gateway:
    """One CAN bus with its CANopen devices, as seen by the master.

    SDO requests return ``concurrent.futures.Future`` objects that always resolve to an
    :class:`SdoResult`; they never raise and never block the caller.
    """

    def __init__(self, config: GatewayConfig):
        self.config = config
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = NOTIFIER_CYCLE
        self.dictionary = own_dictionary()
        self.monitor = nmt.HeartbeatMonitor(self.network, config.heartbeat_timeout,
                                            config.expected_nodes)
        self._guarding = nmt.NodeGuarding(self.network, config.guarded_nodes,
                                          config.guard_period)
        self._channels: Dict[int, SdoChannel] = {}
        self._channels_lock = threading.Lock()

    def start(self) -> None:
        """Open the bus and start watching node states."""
        options = dict(self.config.bus_options)
        if self.config.bitrate:
            options['bitrate'] = self.config.bitrate
        self.network.connect(interface=self.config.interface, channel=self.config.channel,
                             **options)
        self.monitor.start()
        self._guarding.start()

    def stop(self) -> None:
        """Stop every worker and close the bus."""
        self._guarding.stop()
        self.monitor.stop()
        with self._channels_lock:
            channels, self._channels = list(self._channels.values()), {}
        for channel in channels:
            channel.stop()
        self.network.disconnect()

    def sdo_read(self, node_id: int, index: int, subindex: int, max_size: int = 0,
                 timeout: float = 0.0) -> 'Future[SdoResult]':
        """Read ``index:subindex`` of ``node_id`` (0 = the gateway's own dictionary)."""
        problem = check_request(node_id, index, subindex, timeout)
        if problem:
            return resolved(SdoResult.invalid(problem))
        if not 0 <= max_size <= 0xFFFFFFFF:
            return resolved(SdoResult.invalid(
                f'max_size {max_size} is out of range: allowed 0 (no limit) to 4294967295'))
        if node_id == 0:
            return resolved(run_guarded(lambda: self._read_own(index, subindex, max_size)))
        return self._channel(node_id).read(index, subindex, max_size,
                                           timeout or self.config.sdo_timeout)

    def sdo_write(self, node_id: int, index: int, subindex: int, data: bytes,
                  timeout: float = 0.0) -> 'Future[SdoResult]':
        """Write ``data`` to ``index:subindex`` of ``node_id`` (0 = own dictionary)."""
        problem = check_request(node_id, index, subindex, timeout)
        if problem:
            return resolved(SdoResult.invalid(problem))
        if not data:
            return resolved(SdoResult.invalid('data is empty: write at least 1 byte'))
        data = bytes(data)
        if node_id == 0:
            return resolved(run_guarded(
                lambda: self.dictionary.set_data(index, subindex, data, check_writable=True)))
        return self._channel(node_id).write(index, subindex, data,
                                            timeout or self.config.sdo_timeout)

    def nmt_command(self, node_id: int, command: int) -> NmtResult:
        """Send NMT ``command`` to ``node_id`` (0 = all nodes); checked before sending."""
        problem = check_node_id(node_id, '0..127 (0 = all nodes)')
        if problem:
            return NmtResult(False, problem)
        if command not in nmt.COMMAND_NAMES:
            known = ', '.join(f'{code} {name}' for code, name in nmt.COMMAND_NAMES.items())
            return NmtResult(False, f'command {command} is not an NMT command: allowed {known}')
        try:
            self.network.send_message(0, bytes([command, node_id]))
        except Exception as error:  # noqa: BLE001 - a lost bus must become an answer
            return NmtResult(False, f'the NMT frame could not be sent: {error}')
        return NmtResult(True)

    def _read_own(self, index: int, subindex: int, max_size: int) -> bytes:
        data = self.dictionary.get_data(index, subindex, check_readable=True)
        check_size(len(data), max_size)
        return data

    def _channel(self, node_id: int) -> SdoChannel:
        with self._channels_lock:
            channel = self._channels.get(node_id)
            if channel is None:
                remote = canopen.RemoteNode(node_id, od.ObjectDictionary())
                self.network.add_node(remote)
                channel = SdoChannel(remote.sdo, f'sdo-node-{node_id}',
                                     self.config.block_transfer)
                self._channels[node_id] = channel
            return channel
