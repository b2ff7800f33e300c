"""``/diagnostics``: the CAN bus and every device, as diagnostic_updater would publish them.

diagnostic_updater has no wheel here, so the ``diagnostic_msgs/DiagnosticArray`` is built
directly, following the updater's conventions so that diagnostic_aggregator, rqt_robot_monitor
and the like work unchanged:

- the absolute topic ``/diagnostics``, reliable, volatile, depth 1, as the updater's publisher;
- status names ``<node name>: <what>``: ``cbcan: CAN bus``, ``cbcan: node 5``. A node in a
  namespace is named by its fully qualified name (``/can0/cbcan: node 5``), as the updater's
  ``use_fqn`` option does, so the gateways of two buses never share a status name;
- ``hardware_id`` names the adapter (``socketcan:can0``) or the device
  (``canopen node 5 on socketcan:can0``);
- levels OK, WARN, ERROR and STALE, and the details as key-values.
"""

import time
from typing import Dict, List, Optional

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..core.boot.service import BootState, FAILED, WAITING
from ..core.bus import BusStatus
from ..core.drives import cia402
from ..core.drives.status import DriveStatus
from ..core.emcy import EmcyStatus, Emergency
from ..core.gateway import Gateway
from ..core.nmt import NodeStatus
from ..core.pdo.service import PdoStatistics
from ..core.pdo.sync import SyncStatus
from ..core.program.download import DOWNLOADING, Progress
from ..core.sdo.channel import SdoStatistics
from .drive_parameters import Joint

DIAGNOSTICS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE)

OK, WARN, ERROR, STALE = (ord(level) for level in (
    DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR, DiagnosticStatus.STALE))


def _status(level: int, name: str, message: str, hardware_id: str,
            values: Dict[str, object]) -> DiagnosticStatus:
    return DiagnosticStatus(level=bytes([level]), name=name, message=message,
                            hardware_id=hardware_id,
                            values=[KeyValue(key=key, value=str(value))
                                    for key, value in values.items()])


def _emcy_text(emergency: Optional[Emergency]) -> str:
    return emergency.summary if emergency else 'none'


class Diagnostics:
    """Builds and publishes the gateway's ``DiagnosticArray``; the node calls :meth:`publish`.

    - ``<node>: CAN bus``: ERROR while the bus is down (the message says why), WARN when error
      frames arrived in the last period, else OK. Frame rates are taken over the last
      period. It also shows the gateway's own heartbeat (node id, period, state, frames
      sent), which the bus carries or not, and the raw CAN bridge's frames (received past
      raw.filters, sent, refused, and lost when publishing fell far behind) while it is on.
    - ``<node>: node <id>`` for every device that is expected (parameter ``nodes``), was
      heard, sent an EMCY or was sent an SDO request: ERROR when expected but silent
      (NOT_DETECTED), STALE when a device that is not expected fell silent, WARN while it has
      an active EMCY (one not cleared by an error reset) or, for a device of ``pdo.nodes``,
      while an event-driven TPDO has been silent for twice its event timer, else OK. Its
      PDOs received and sent per second and the frames shorter than their mapping. WARN
      while a program download runs for it ("being programmed", its phase and progress).
    - ``<node>: drive <id>`` for every drive: ERROR in FAULT (the error code and its
      meaning), WARN while not heard or when the last set-point of its last stream of PP
      targets was missed (shown until a later stream's is reached), else OK with its state.
    - ``<node>: SYNC`` while the gateway produces SYNC: ERROR while it is not on the bus,
      with the period configured and the one measured: between the SYNCs the gateway's
      thread sent, where it sends them, else between those heard on the bus (an adapter
      that does not echo its own frames shows none).
    """

    def __init__(self, node: Node, gateway: Gateway, joints: Dict[int, Joint]):
        self._node = node
        self._gateway = gateway
        self._joints = joints
        self._publisher = node.create_publisher(DiagnosticArray, '/diagnostics',
                                                DIAGNOSTICS_QOS)
        self._prefix = (node.get_name() if node.get_namespace() == '/'
                        else node.get_fully_qualified_name())
        self._bus_id = gateway.bus.description
        self._expected = frozenset(gateway.config.expected_nodes)
        self._previous = (time.monotonic(), gateway.bus_status)
        self._previous_pdo: Dict[int, PdoStatistics] = {}

    def publish(self) -> None:
        """Publish the status of the bus and of every device known, if anyone subscribes.

        With 127 devices the array is about 2,000 key-values, a few milliseconds of the
        executor every period: not built for nobody (see :meth:`skip`).
        """
        if not self._publisher.get_subscription_count():
            self.skip()
            return
        bus = self._gateway.bus_status
        array = DiagnosticArray()
        array.header.stamp = self._node.get_clock().now().to_msg()
        elapsed = max(time.monotonic() - self._previous[0], 1e-6)
        array.status = [self._bus_status(bus),
                        *self._device_statuses(bus.up, elapsed)]
        if self._gateway.sync.producing:
            array.status.append(self._sync_status(self._gateway.sync.status()))
        array.status += [self._drive_status(status)
                         for status in self._gateway.drives.statuses()]
        self._publisher.publish(array)

    def skip(self) -> None:
        """Let a period pass unpublished (no subscriber, or the node inactive).

        The counts the next array's rates and warnings compare with move on all the same, so
        that a subscriber that comes later, or a node activated again, is not shown the
        errors and rates of the time nothing was published as the last period's.
        """
        self._previous = (time.monotonic(), self._gateway.bus_status)
        self._previous_pdo = self._gateway.pdo.statistics()

    def destroy(self) -> None:
        """Take the publisher away."""
        self._node.destroy_publisher(self._publisher)

    def _bus_status(self, status: BusStatus) -> DiagnosticStatus:
        now = time.monotonic()
        then, before = self._previous
        self._previous = (now, status)
        elapsed = max(now - then, 1e-6)
        errors = status.error_frames - before.error_frames
        dropped = status.frames_dropped - before.frames_dropped
        if not status.up:
            level, message = ERROR, f'down: {status.reason}'
        elif dropped:
            level = WARN
            message = (f'up; {dropped} frame{"s" * (dropped > 1)} dropped in the last '
                       f'{elapsed:.1f} s: they came faster than the gateway handles them')
        elif errors:
            level = WARN
            message = f'up; {errors} error frame{"s" * (errors > 1)} in the last {elapsed:.1f} s'
        else:
            level, message = OK, 'up'
        return _status(level, f'{self._prefix}: CAN bus', message, self._bus_id, {
            'State': 'up' if status.up else 'down',
            'Reason down': status.reason,
            'Reopen count': status.reopen_count,
            'Frames received/s':
                f'{(status.frames_received - before.frames_received) / elapsed:.1f}',
            'Frames sent/s': f'{(status.frames_sent - before.frames_sent) / elapsed:.1f}',
            'Error frames/s': f'{errors / elapsed:.1f}',
            'Frames received': status.frames_received,
            'Frames sent': status.frames_sent,
            'Error frames': status.error_frames,
            'Frames dropped': status.frames_dropped,
            'Datagrams dropped': status.datagrams_dropped,
            **self._heartbeat_values(),
            **self._raw_values(),
        })

    def _raw_values(self) -> Dict[str, object]:
        """Return the raw CAN bridge's counts, while raw.filters or raw.send_allow is set."""
        raw = self._gateway.raw
        if not raw.receiving and raw.settings.send_allow.empty:
            return {}
        counts = raw.statistics()
        return {'Raw frames received': counts.received, 'Raw frames sent': counts.sent,
                'Raw frames refused': counts.refused, 'Raw frames lost': counts.lost}

    def _heartbeat_values(self) -> Dict[str, object]:
        heartbeat = self._gateway.heartbeat.status()
        if not heartbeat.node_id:
            return {'Own heartbeat': 'none (heartbeat.node_id is 0)'}
        return {'Own heartbeat': f'node {heartbeat.node_id} every {heartbeat.period * 1000:g} '
                                 f'ms, {heartbeat.state_name}',
                'Own heartbeats sent': heartbeat.sent}

    def _sync_status(self, sync: SyncStatus) -> DiagnosticStatus:
        if sync.running:
            level, message = OK, f'producing every {sync.period * 1000:g} ms'
        else:
            level, message = ERROR, 'not produced now (the CAN bus is down)'
        measured = sync.measured_period
        return _status(level, f'{self._prefix}: SYNC', message, self._bus_id, {
            'Period configured (ms)': f'{sync.period * 1000:g}',
            'Period measured (ms)':
                f'{measured * 1000:.3f}' if measured is not None else 'no SYNC heard',
            'Largest period error (ms)':
                f'{sync.measured_jitter * 1000:.3f}' if sync.measured_jitter is not None
                else 'no SYNC heard',
            'SYNCs skipped': sync.skipped,
            'Counter overflow': sync.counter_overflow or 'no counter',
            'Started': sync.starts,
            'SYNC frames heard': sync.heard,
        })

    def _drive_status(self, drive: DriveStatus) -> DiagnosticStatus:
        node_id = drive.node_id
        timeouts = self._gateway.drives.command_timeouts(node_id)
        if drive.faulted:
            level = ERROR
            message = f'{drive.state}: error 0x{drive.error_code:04X} {drive.error}'
        elif drive.state == cia402.UNKNOWN:
            level, message = WARN, 'UNKNOWN: not heard'
        else:
            level, message = OK, drive.state
            if drive.halted:
                message += ', halted'
        missed = self._gateway.drives.missed_set_point(node_id)
        if missed and level == OK:
            level, message = WARN, f'{message}; the last PP set-point streamed was missed'
        return _status(level, f'{self._prefix}: drive {node_id}', message,
                       f'canopen node {node_id} on {self._bus_id}', {
                           'Joint': self._joints[node_id].name,
                           'State': drive.state,
                           'Statusword': f'0x{drive.statusword:04X}',
                           'Mode': cia402.mode_name(drive.mode) if drive.mode else 'none',
                           'Error code': f'0x{drive.error_code:04X}',
                           'Error': drive.error or 'none',
                           'Halted': 'yes' if drive.halted else 'no',
                           'Needs enable': 'yes' if drive.needs_enable else 'no',
                           'Halted by the command timeout': timeouts,
                           'Last PP set-point streamed': missed or 'reached (or none yet)',
                           'Position (device units)': drive.position,
                       })

    def _device_statuses(self, bus_up: bool, elapsed: float) -> List[DiagnosticStatus]:
        gateway = self._gateway
        heartbeats = {status.node_id: status for status in gateway.monitor.statuses()}
        emergencies = {status.node_id: status for status in gateway.emcy.statuses()}
        sdo = gateway.sdo_statistics()
        pdo = gateway.pdo.statistics()
        boots = {state.node_id: state for state in gateway.boot.states()}
        programming = gateway.programming()
        statuses = [self._device_status(node_id,
                                        heartbeats.get(node_id) or gateway.monitor.status(node_id),
                                        emergencies.get(node_id) or EmcyStatus(node_id),
                                        sdo.get(node_id) or SdoStatistics(), bus_up,
                                        node_id in programming)
                    for node_id in sorted(set(heartbeats) | set(emergencies) | set(sdo) |
                                          set(pdo) | set(boots) | set(programming))]
        for status in statuses:
            node_id = int(status.name.rpartition(' ')[2])
            if node_id in boots:
                self._add_boot(status, boots[node_id])
            if node_id in programming:
                self._add_programming(status, programming[node_id])
            if node_id in pdo:
                operational = gateway.monitor.status(node_id).state_name == 'OPERATIONAL'
                self._add_pdo(status, pdo[node_id], self._previous_pdo.get(node_id), elapsed,
                              operational)
        self._previous_pdo = pdo
        return statuses

    @staticmethod
    def _add_boot(status: DiagnosticStatus, boot: BootState) -> None:
        """Show the device's boot: a failed one is an error, one held back a warning."""
        if boot.state == FAILED:
            status.level = bytes([max(status.level[0], ERROR)])
            status.message += (f'; boot failed (CiA 302-2 error {boot.error_status}): '
                               f'{boot.message}; not started')
        elif boot.state == WAITING and boot.message:  # held back, or its boot ended
            status.level = bytes([max(status.level[0], WARN)])
            status.message += f'; {boot.message}'
        status.values += [KeyValue(key=key, value=str(value)) for key, value in {
            'Boot state': boot.state,
            'Boot error status': boot.error_status or 'none',
            'Boot message': boot.message or 'none',
            'Boots completed': boot.boots,
            'Objects written at its last boot': boot.writes,
        }.items()]

    @staticmethod
    def _add_programming(status: DiagnosticStatus, progress: Progress) -> None:
        """Show a device being programmed: a warning, its application is not running."""
        status.level = bytes([max(status.level[0], WARN)])
        done = (f', {100 * progress.bytes_sent // progress.bytes_total} %'
                if progress.bytes_total and progress.phase == DOWNLOADING else '')
        status.message += f'; being programmed ({progress.phase or "starting"}{done})'
        status.values += [KeyValue(key=key, value=str(value)) for key, value in {
            'Program download': progress.phase or 'starting',
            'Program bytes sent': f'{progress.bytes_sent} of {progress.bytes_total}',
        }.items()]

    @staticmethod
    def _add_pdo(status: DiagnosticStatus, pdo: PdoStatistics,
                 before: Optional[PdoStatistics], elapsed: float, operational: bool) -> None:
        before = before or PdoStatistics()
        if pdo.late and operational:  # only an operational device sends PDOs
            status.level = bytes([max(status.level[0], WARN)])
            status.message += '; ' + ', '.join(
                f'TPDO {number} silent for {silent:.1f} s (event timer {timer} ms)'
                for number, timer, silent in pdo.late)
        status.values += [KeyValue(key=key, value=str(value)) for key, value in {
            'PDO mapping': pdo.mapping,
            'TPDOs / RPDOs': f'{pdo.tpdos} / {pdo.rpdos}',
            'PDOs received/s': f'{(pdo.received - before.received) / elapsed:.1f}',
            'PDOs sent/s': f'{(pdo.sent - before.sent) / elapsed:.1f}',
            'PDOs received': pdo.received,
            'PDOs sent': pdo.sent,
            'PDO frames too short': pdo.short_frames,
            'PDO frames of unusable mappings': pdo.unusable,
            'PDO writes refused': pdo.refused,
        }.items()]

    def _device_status(self, node_id: int, heartbeat: NodeStatus, emcy: EmcyStatus,
                       sdo: SdoStatistics, bus_up: bool,
                       programmed: bool) -> DiagnosticStatus:
        expected = node_id in self._expected
        heard = heartbeat.last_seen is not None
        if heartbeat.detected:
            level, message = OK, heartbeat.state_name
        elif expected:
            # Silent while a download restarts it (its bootloader, its new program): the
            # download tells whether it came back.
            level = WARN if programmed else ERROR
            message = (f'expected but silent for {heartbeat.last_seen_age:.1f} s' if heard
                       else 'expected but never heard')
        elif heard:
            level, message = STALE, f'silent for {heartbeat.last_seen_age:.1f} s'
        else:
            level, message = OK, 'no heartbeat (not an expected node)'
        if not heartbeat.detected and not bus_up:
            message += ' (the CAN bus is down)'
        if emcy.active is not None:
            level = max(level, WARN)
            message += f'; active EMCY {emcy.active.summary}'
        last = emcy.last
        latency = sdo.latency_p50
        return _status(level, f'{self._prefix}: node {node_id}', message,
                       f'canopen node {node_id} on {self._bus_id}', {
                           'NMT state': heartbeat.state_name,
                           'Expected': 'yes' if expected else 'no',
                           'Last heartbeat age (s)':
                               f'{heartbeat.last_seen_age:.2f}' if heard else 'never',
                           'Active EMCY': _emcy_text(emcy.active),
                           'Last EMCY': _emcy_text(last),
                           'Last EMCY error register':
                               f'0x{last.error_register:02X}' if last else 'none',
                           'Last EMCY manufacturer data':
                               last.manufacturer_data.hex(' ') if last else 'none',
                           'Last EMCY age (s)':
                               f'{time.time() - last.received:.1f}' if last else 'never',
                           'Malformed EMCY frames': emcy.malformed,
                           'SDO requests': sdo.requests,
                           'SDO aborts': sdo.aborts,
                           'SDO timeouts': sdo.timeouts,
                           'SDO latency p50 (ms)':
                               f'{latency * 1000:.2f}' if latency is not None else 'none',
                       })
