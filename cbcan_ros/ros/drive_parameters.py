"""The drive parameters: which devices run as CiA 402 drives, their joints, the safety stops.

Declared with descriptors by :class:`~.config.NodeParameters`, checked here, and turned into
the core's :class:`~cbcan_ros.core.drives.status.DriveSettings` and one :class:`Joint` per
drive, which converts between the drive's units and the joint's (radians or metres, as the
robot description has them).
"""

from dataclasses import dataclass
import math
from typing import Callable, Dict, List

from rcl_interfaces.msg import FloatingPointRange

from ..core.drives import cia402
from ..core.drives.safety import ABORT_CONNECTION, ON_SHUTDOWN
from ..core.drives.status import DriveSettings
from .parameter_checks import ConfigurationError

# The feedback cycle without SYNC: ~/joint_states at 50 Hz.
FEEDBACK_PERIOD = 0.02

SCALES = (
    ('position_scale', 'device position units (e.g. encoder counts) per joint unit (rad or m)'),
    ('velocity_scale', 'device velocity units per joint unit per second'),
    ('torque_scale', "the drive's torque units (often thousandths of rated torque) per N·m "
                     '(or N for a linear joint)'),
)


@dataclass(frozen=True)
class Joint:
    """A drive as a joint: joint = device / scale + offset, device = (joint - offset) * scale."""

    node_id: int
    name: str
    position_scale: float = 1.0
    velocity_scale: float = 1.0
    torque_scale: float = 1.0
    position_offset: float = 0.0

    def position(self, device: int) -> float:
        """Return a device position in joint units."""
        return device / self.position_scale + self.position_offset

    def velocity(self, device: int) -> float:
        """Return a device velocity in joint units per second."""
        return device / self.velocity_scale

    def effort(self, device: int) -> float:
        """Return a device torque in joint units (N·m or N)."""
        return device / self.torque_scale

    def to_device(self, mode: int, value: float, relative: bool = False) -> float:
        """Return the target ``value`` (joint units) of ``mode`` in device units (unrounded).

        A relative position is a distance: the offset does not apply.
        """
        index = cia402.TARGET_OF_MODE.get(mode)
        if index == cia402.TARGET_POSITION:
            return value * self.position_scale if relative else (
                (value - self.position_offset) * self.position_scale)
        if index == cia402.TARGET_VELOCITY:
            return value * self.velocity_scale
        return value * self.torque_scale


def _between(lowest: float, highest: float) -> list:
    return [FloatingPointRange(from_value=lowest, to_value=highest, step=0.0)]


def declare(declare_parameter: Callable, drive_ids: List[int]) -> None:
    """Declare the drive parameters (``declare_parameter(name, default, text, **ranges)``)."""
    declare_parameter('drives.command_timeout', 0.5,
                      'Seconds a drive in a streaming mode (PV, CSP, CSV, CST) may go without a '
                      'new target on ~/node_<id>/target or ~/joint_commands before it is '
                      'halted (controlword bit 8: it decelerates and holds); the next target '
                      'resumes it. 0 = off',
                      floating_point_range=_between(0.0, 60.0))
    declare_parameter('drives.on_shutdown', 'quick_stop',
                      'What every powered drive is sent when the gateway stops (SIGINT, '
                      'SIGTERM, lifecycle deactivate or shutdown), before the bus closes: '
                      'quick_stop (ramp down, per its 0x605A), disable (power stage off at '
                      'once: the motor coasts unless it has a brake) or none',
                      additional_constraints='quick_stop, disable or none')
    declare_parameter('drives.consumer_time', 0.5,
                      'Seconds after which each drive stops by itself (its own 0x6007 '
                      'reaction) when it no longer hears the gateway heartbeat: written to '
                      "the drive's 0x1016:1 when it is first heard and after every boot; "
                      'a few heartbeat.period long',
                      floating_point_range=_between(0.0, 60.0))
    declare_parameter('drives.keep_running_if_gateway_dies', False,
                      'true gives up the drives stopping by themselves when the gateway, its '
                      'computer or the bus dies: no heartbeat consumer (0x1016) and no abort '
                      'connection option (0x6007) is written, and no heartbeat is sent for '
                      'them. Only for drives another safety chain stops')
    declare_parameter('drives.abort_connection', 'quick_stop',
                      'What a drive whose abort connection option (0x6007) is 0 (no '
                      'reaction: it runs on when it loses the gateway) is set to when it is '
                      'first heard and after every boot: quick_stop (3), disable (2, power '
                      'stage off), fault (1); or none: 0x6007 is left at 0 and enable is '
                      'refused, saying why',
                      additional_constraints='quick_stop, disable, fault or none')
    for node_id in drive_ids:
        declare_parameter(f'node_{node_id}.joint', f'node_{node_id}',
                          f'Name of drive {node_id} as a joint in ~/joint_states and '
                          f'~/joint_commands (as in the robot description)')
        for name, unit in SCALES:
            declare_parameter(f'node_{node_id}.{name}', 1.0,
                              f'Drive {node_id}: {unit}; negative turns the direction round',
                              floating_point_range=_between(-1e12, 1e12))
        declare_parameter(f'node_{node_id}.hold_torque', 0.0,
                          f'Drive {node_id}: torque (N·m, or N) set as the target when it is '
                          f'enabled in profile or cyclic torque (PT, CST) and when the command '
                          f'timeout stops it there. 0 lets a gravity-loaded axis fall unless '
                          f'its brake holds it: give the torque that holds the load',
                          floating_point_range=_between(-1e12, 1e12))
        declare_parameter(f'node_{node_id}.position_offset', 0.0,
                          f'Drive {node_id}: joint position (joint units) where the drive '
                          f'reads 0',
                          floating_point_range=_between(-1e12, 1e12))


def settings(value: Callable, drive_ids: List[int], heartbeat_node_id: int,
             heartbeat_period: float, sync_period: float) -> DriveSettings:
    """Return the core's drive settings; raise ConfigurationError naming a wrong parameter."""
    on_shutdown = value('drives.on_shutdown')
    if on_shutdown not in ON_SHUTDOWN:
        raise ConfigurationError('drives.on_shutdown', on_shutdown, 'is no stop the gateway '
                                 'knows', ', '.join(ON_SHUTDOWN))
    abort_connection = value('drives.abort_connection')
    if abort_connection not in ABORT_CONNECTION:
        raise ConfigurationError('drives.abort_connection', abort_connection, 'is no reaction '
                                 'the gateway knows', ', '.join(ABORT_CONNECTION))
    unwatched = value('drives.keep_running_if_gateway_dies')
    consumer_time = 0.0 if unwatched else value('drives.consumer_time')
    if drive_ids and not unwatched and not consumer_time:
        raise ConfigurationError('drives.consumer_time', consumer_time, 'turns off the '
                                 'drives stopping by themselves when the gateway dies',
                                 'more than heartbeat.period; or give that up with '
                                 'drives.keep_running_if_gateway_dies: true')
    if drive_ids and consumer_time and consumer_time <= heartbeat_period:
        raise ConfigurationError('drives.consumer_time', consumer_time, 'is not longer than '
                                 f'heartbeat.period ({heartbeat_period}): the drives would '
                                 'stop between two heartbeats',
                                 f'more than {heartbeat_period}, best 3 periods or more')
    return DriveSettings(node_ids=tuple(drive_ids),
                         command_timeout=value('drives.command_timeout'),
                         on_shutdown=on_shutdown,
                         consumer_time=consumer_time if drive_ids else 0.0,
                         heartbeat_node_id=heartbeat_node_id if drive_ids else 0,
                         abort_connection=(None if unwatched
                                           else ABORT_CONNECTION[abort_connection]),
                         hold_torques={node_id: hold_torque(value, node_id)
                                       for node_id in drive_ids},
                         feedback_period=sync_period or FEEDBACK_PERIOD)


def hold_torque(value: Callable, node_id: int) -> int:
    """Return ``node_<id>.hold_torque`` in the drive's units; raise when it does not fit."""
    torque = value(f'node_{node_id}.hold_torque') * value(f'node_{node_id}.torque_scale')
    if not -(1 << 15) <= round(torque) < 1 << 15:
        raise ConfigurationError(f'node_{node_id}.hold_torque',
                                 value(f'node_{node_id}.hold_torque'), 'does not fit the '
                                 "drive's target torque (INTEGER16) at its torque_scale",
                                 f'{-(1 << 15)}..{(1 << 15) - 1} drive units')
    return round(torque)


def own_node_id(value: Callable, listed: Dict[str, List[int]]) -> int:
    """Return the gateway's heartbeat node id: ``heartbeat.node_id``, else one for the drives.

    Drives that watch the gateway (``drives.keep_running_if_gateway_dies`` false) need its
    heartbeat: without ``heartbeat.node_id`` it beats as 127, or the highest id no device
    parameter in ``listed`` uses.
    """
    given = value('heartbeat.node_id')
    if given or not listed['drives.nodes'] or value('drives.keep_running_if_gateway_dies'):
        return given
    used = {node_id for node_ids in listed.values() for node_id in node_ids}
    return next(node_id for node_id in range(127, 0, -1) if node_id not in used)


def joints(value: Callable, drive_ids: List[int]) -> Dict[int, Joint]:
    """Return every drive's joint; raise ConfigurationError for a zero scale or a name twice."""
    result: Dict[int, Joint] = {}
    names: Dict[str, int] = {}
    for node_id in drive_ids:
        name = value(f'node_{node_id}.joint')
        if not name:
            raise ConfigurationError(f'node_{node_id}.joint', name, 'is empty',
                                     'a joint name')
        if name in names:
            raise ConfigurationError(f'node_{node_id}.joint', name, f'is the joint of node '
                                     f'{names[name]} as well', 'a name no other drive has')
        names[name] = node_id
        scales = {}
        for scale, _ in SCALES:
            scales[scale] = value(f'node_{node_id}.{scale}')
            if not math.isfinite(scales[scale]) or scales[scale] == 0:
                raise ConfigurationError(f'node_{node_id}.{scale}', scales[scale],
                                         'cannot convert units', 'a number other than 0')
        result[node_id] = Joint(node_id, name, position_offset=value(
            f'node_{node_id}.position_offset'), **scales)
    return result
