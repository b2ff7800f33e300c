"""The bus description (``bus_config``): a ros2_canopen ``bus.yml`` read as parameters.

The file names the devices, their drivers, files and identity, and the master's heartbeat
and SYNC. What it says of the gateway's parameters is taken as their value when the parameter
is not given; a parameter given with another value refuses the start with a message naming
both. The boots themselves (checks, writes, start) are the core's (``core/boot``).
"""

import math
from typing import Dict, List, Optional, Tuple

from ..core.boot.description import BusDescription, DescriptionError, load
from .parameter_checks import ConfigurationError

# Which node list a device's ros2_canopen driver puts it in (all are watched: ``nodes``).
DRIVER_LISTS = {'drive': 'drives.nodes', 'proxy': 'pdo.nodes'}
# ros2_canopen's defaults for its CiA 402 driver when the file gives no scale: a ros2_canopen
# user's drive moved with these, so it moves the same here.
ROS2_CANOPEN_SCALES = {'scale_pos_to_dev': 1000.0, 'scale_vel_to_dev': 1000.0,
                       'scale_eff_from_dev': 0.001}
RELATIVE_TOLERANCE = 1e-9


def describe(declare_parameter) -> None:
    """Declare ``bus_config`` (``declare_parameter(name, default, text, **ranges)``)."""
    declare_parameter('bus_config', '',
                      "Bus description file in ros2_canopen's bus.yml format: the devices, "
                      'their EDS/DCF files, drivers and identity, and what each one is '
                      'configured with (DCF values, sdo list, PDOs, heartbeats) and checked '
                      'for each time it boots, before it is started (CiA 302-2; see '
                      'docs/boot_configuration.md). Its values fill the parameters not given '
                      '(heartbeat.node_id, heartbeat.period, sync.period, nodes, drives.nodes, '
                      'pdo.nodes, node_<id>.eds, node_<id>.joint and scales); empty = none')


class BusFile:
    """What a bus description gives the gateway's parameters."""

    def __init__(self, path: str):
        self.description: Optional[BusDescription] = None
        self.values: Dict[str, Tuple[object, str]] = {}  # parameter: (value, the file's key)
        self.node_lists: Dict[str, List[int]] = {}
        if not path:
            return
        try:
            self.description = load(path)
        except DescriptionError as error:
            raise ConfigurationError('bus_config', path, f'cannot be used: {error}',
                                     "a bus description in ros2_canopen's bus.yml format") \
                from None
        self._read(self.description)

    @property
    def warning(self) -> str:
        """Return the one warning naming every key of the file the gateway does not use."""
        description = self.description
        if description is None or not description.unsupported:
            return ''
        return (f'bus_config {description.path}: not used by this gateway (see '
                f'docs/boot_configuration.md): {", ".join(description.unsupported)}')

    def _read(self, description: BusDescription) -> None:
        master = description.master
        given = master.given
        if 'node_id' in given:
            self.values['heartbeat.node_id'] = (master.node_id, 'master.node_id')
        if 'heartbeat_producer' in given and master.heartbeat_producer:
            self.values['heartbeat.period'] = (master.heartbeat_producer / 1000,
                                               'master.heartbeat_producer (ms)')
        if 'sync_period' in given:
            self.values['sync.period'] = (master.sync_period / 1e6, 'master.sync_period (µs)')
        self.node_lists = {'nodes': [], 'drives.nodes': [], 'pdo.nodes': []}
        for device in description.devices:
            node_id, where = device.node_id, f'nodes.{device.name}'
            self.node_lists['nodes'].append(node_id)
            if device.driver in DRIVER_LISTS:
                self.node_lists[DRIVER_LISTS[device.driver]].append(node_id)
            if device.dcf:
                self.values[f'node_{node_id}.eds'] = (device.dcf, f'{where}.dcf')
            if device.driver == 'drive':
                self._drive_values(node_id, where, dict(device.scales), device.name)

    def _drive_values(self, node_id: int, where: str, scales: Dict[str, float],
                      name: str) -> None:
        """Map ros2_canopen's scales onto the drive's (one scale each way, our offset)."""
        self.values[f'node_{node_id}.joint'] = (name, f'{where} (its name)')
        given = {**ROS2_CANOPEN_SCALES, **scales}
        for to_key, from_key, parameter in (
                ('scale_pos_to_dev', 'scale_pos_from_dev', 'position_scale'),
                ('scale_vel_to_dev', 'scale_vel_from_dev', 'velocity_scale')):
            scale = given[to_key]
            if not math.isfinite(scale) or scale == 0:
                raise ConfigurationError('bus_config', f'{where}.{to_key}: {scale}',
                                         'cannot convert units', 'a number other than 0')
            back = scales.get(from_key)
            if back is not None and not math.isclose(back * scale, 1.0,
                                                     rel_tol=RELATIVE_TOLERANCE):
                raise ConfigurationError(
                    'bus_config', f'{where}.{from_key}: {back}', f'is not 1 / {to_key} '
                    f'({scale}): the gateway converts both ways with one scale',
                    f'{1 / scale!r}, or leave {from_key} out')
            self.values[f'node_{node_id}.{parameter}'] = (scale, f'{where}.{to_key}')
        torque = given['scale_eff_from_dev']
        if torque and math.isfinite(torque):
            self.values[f'node_{node_id}.torque_scale'] = (1 / torque,
                                                           f'{where}.scale_eff_from_dev')
        offset = scales.get('offset_pos_to_dev', 0.0)
        back = scales.get('offset_pos_from_dev')
        if back is not None and not math.isclose(back, -offset / given['scale_pos_to_dev'],
                                                 rel_tol=RELATIVE_TOLERANCE, abs_tol=1e-12):
            raise ConfigurationError(
                'bus_config', f'{where}.offset_pos_from_dev: {back}', 'does not undo '
                f'offset_pos_to_dev ({offset}) at scale_pos_to_dev '
                f"({given['scale_pos_to_dev']}): the gateway converts both ways with one offset",
                f"{-offset / given['scale_pos_to_dev']!r}, or leave offset_pos_from_dev out")
        if offset:
            self.values[f'node_{node_id}.position_offset'] = (
                -offset / given['scale_pos_to_dev'], f'{where}.offset_pos_to_dev')

    def value(self, name: str, given, default):
        """Return parameter ``name``: ``given``, or the file's when it is the ``default``.

        Raises ConfigurationError when both say something and differ.
        """
        if name not in self.values:
            return given
        from_file, key = self.values[name]
        if given == default:
            return from_file
        same = (math.isclose(given, from_file, rel_tol=RELATIVE_TOLERANCE)
                if isinstance(given, float) and isinstance(from_file, float)
                else given == from_file)
        if not same:
            raise ConfigurationError(name, given, f'contradicts {key} = {from_file!r} of the '
                                     f'bus description {self.description.path}',
                                     f'{from_file!r}, or leave the parameter out')
        return given

    def source(self, name: str, given, default) -> str:
        """Return where parameter ``name``'s value comes from, for a message naming it."""
        if name in self.values and given in (default, self.values[name][0]):
            return f'{self.values[name][1]} of the bus description {self.description.path}'
        return f'parameter {name}'

    def node_ids(self, name: str, given: List[int]) -> List[int]:
        """Return the node list ``name``: the ids ``given`` and those the file adds."""
        return given + [node_id for node_id in self.node_lists.get(name, ())
                        if node_id not in given]
