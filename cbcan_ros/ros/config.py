"""The node's ROS parameters: declared with descriptors, checked, turned into the core's config.

Every parameter is declared here with its description and range, so ``ros2 param describe``
tells a robotics engineer what it means; a wrong value stops the node at start with one
message naming the parameter, the value and what is allowed (``parameter_checks.py``).
"""

import os
from typing import Dict, List

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter

from ..core import eds
from ..core.gateway import GatewayConfig
from ..core.program.download import ProgramSettings
from ..core.sdo.write_protection import RULE_FORMAT, WriteProtection
from ..simulation.simulated_drives import LAYOUTS
from . import boot_parameters, drive_parameters, raw_parameters
from . import parameter_checks as checks


def device_file_parameter(node_id: int) -> str:
    """Return the name of the parameter holding the EDS or DCF file of ``node_id``."""
    return f'node_{node_id}.eds'


def _between(lowest: float, highest: float) -> list:
    """Return the descriptor range of a float parameter from ``lowest`` to ``highest``."""
    return [FloatingPointRange(from_value=lowest, to_value=highest, step=0.0)]


class NodeParameters:
    """The parameters of one gateway node."""

    def __init__(self, node: Node):
        self._node = node
        self._declared: List[str] = []
        self._defaults: Dict[str, object] = {}
        self.warnings: List[str] = []  # doubtful values, logged by gateway_config()
        # First: what the bus description names decides which node_<id> parameters exist.
        boot_parameters.describe(self._declare)
        self.bus_file = boot_parameters.BusFile(self.value('bus_config'))
        self._declare_all()
        self._show_bus_file_values()

    def _show_bus_file_values(self) -> None:
        """Set the parameters the bus description fills to what it gives them.

        So ``get_parameters`` tells what the gateway runs with (``cbcan_cli`` finds a
        node's EDS there). Before any callback watches the parameters: nothing reacts.
        """
        shown = []
        for name in [*self.bus_file.values, *self.bus_file.node_lists]:
            if not self._node.has_parameter(name):
                continue
            current = self._node.get_parameter_or(name)  # a list given none is not set
            value = (self.node_ids(name) if name in self.bus_file.node_lists
                     else self.value(name))
            if current.type_ == Parameter.Type.DOUBLE:
                value = float(value)
            if value != current.value and value != []:
                shown.append(Parameter(name, value=value))
        if shown:
            self._node.set_parameters(shown)

    def _declare(self, name: str, value, description: str, **ranges) -> Parameter:
        """Declare a parameter; raise ConfigurationError if the value given for it is wrong."""
        descriptor = ParameterDescriptor(description=description, **ranges)
        if isinstance(value, Parameter.Type):
            descriptor.type = value.value
        self._declared.append(name)
        if not isinstance(value, Parameter.Type):
            self._defaults[name] = value
        return checks.declare(self._node, name, value, descriptor)

    def _declare_all(self) -> None:
        self._declare('can.interface', 'virtual',
                      'python-can interface name: socketcan, pcan, kvaser, slcan, '
                      'udp_multicast, virtual (in-process only), ...')
        self._declare('can.channel', 'can0',
                      'python-can channel: e.g. can0 for socketcan, PCAN_USBBUS1 for pcan, '
                      'a multicast group address for udp_multicast')
        self._declare('can.bitrate', 0,
                      'Bit rate in bit/s for interfaces that set it (pcan, kvaser, slcan); '
                      '0 leaves the interface as configured',
                      integer_range=[IntegerRange(from_value=0, to_value=1_000_000, step=0)])
        self._declare('sdo.timeout', 0.5,
                      'Seconds a whole SDO request may take (waiting behind other requests '
                      'to the device included), unless the request gives its own timeout',
                      floating_point_range=_between(0.001, 60.0))
        self._declare('can.options', Parameter.Type.STRING_ARRAY,
                      'Further python-can bus options as key=value, passed to the interface '
                      'as they are (values parsed as JSON when they can be), e.g. '
                      '["sleep_after_open=0", "tty_baudrate=115200"] for slcan',
                      additional_constraints='each key=value')
        self._declare('sdo.queue_limit', 64,
                      'Requests that may wait for one device; a request beyond this is '
                      'answered at once as busy (abort 0x060A0023), nothing is sent',
                      integer_range=[IntegerRange(from_value=1, to_value=10_000, step=0)])
        self._declare('sdo.read_retries', 0,
                      'Times a read that timed out is repeated within its timeout (the '
                      'timeout is shared equally among the attempts); writes are never '
                      'repeated',
                      integer_range=[IntegerRange(from_value=0, to_value=10, step=0)])
        self._declare('read_only', False,
                      'Refuse every SDO write, NMT command (abort 0x08000021) and LSS '
                      'service; nothing is sent')
        self._declare('lss.probe_timeout', 0.0,
                      'Seconds an LSS Fastscan probe waits for an answer; silence means the '
                      'probed bit is 1, so every wait costs. 0 = from can.bitrate: two frames '
                      'on the wire plus 40 ms (at 10 kbit/s when can.bitrate is 0; none on '
                      'virtual and udp_multicast)',
                      floating_point_range=_between(0.0, 1.0))
        self._declare('sdo.write_allow', Parameter.Type.STRING_ARRAY,
                      f'Objects that SDO writes may reach, each {RULE_FORMAT}; empty = all. '
                      'Other writes are refused with abort 0x08000021 and never sent',
                      additional_constraints=f'each {RULE_FORMAT}')
        self._declare('sdo.block_transfer', False,
                      'Try SDO block transfer first; devices that refuse it get segmented '
                      'transfers')
        self._declare('nodes', Parameter.Type.INTEGER_ARRAY,
                      'Node ids (1..127) the gateway expects; they are listed as '
                      'NOT_DETECTED until they send a heartbeat',
                      additional_constraints=checks.NODE_IDS)
        self._declare('heartbeat.timeout', 3.0,
                      'Seconds without heartbeat, boot-up or guarding reply after which a '
                      'node is NOT_DETECTED; a node whose heartbeat_producer the bus_config '
                      'gives: 3 of its periods when that is longer (0: never)',
                      floating_point_range=_between(0.01, 3600.0))
        self._declare('heartbeat.node_id', 0,
                      "Node id (1..127) of the gateway's own heartbeat (COB-ID 0x700 + id), "
                      'so drives can watch the gateway with their heartbeat consumer (0x1016 '
                      '= id << 16 | time in ms) and stop by themselves when it falls silent. '
                      'It says OPERATIONAL while the gateway serves, PRE_OPERATIONAL while a '
                      'managed node is inactive, and stops at shutdown. No device may use '
                      'this id. 0 = none, unless drives.nodes has drives that watch it '
                      '(drives.keep_running_if_gateway_dies false): then 127, or the highest '
                      "id no device parameter lists. Object 0x1017 of node 0 (the gateway's own "
                      'dictionary) shows heartbeat.period in ms and only informs: writing it '
                      'does not change the heartbeat',
                      integer_range=[IntegerRange(from_value=0, to_value=127, step=0)])
        self._declare('heartbeat.period', 0.1,
                      "Seconds between the gateway's own heartbeats (heartbeat.node_id); give "
                      "drives a heartbeat consumer time of 2 to 3 times this",
                      floating_point_range=_between(0.01, 60.0))
        self._declare('node_guarding', Parameter.Type.INTEGER_ARRAY,
                      'Node ids (1..127) without heartbeat producer to poll by node guarding',
                      additional_constraints=checks.NODE_IDS)
        self._declare('node_guarding_period', 1.0,
                      'Seconds between node guarding requests to each guarded node',
                      floating_point_range=_between(0.01, 60.0))
        self._declare('state_publish_period', 1.0,
                      'Seconds between publications of ~/node_states when nothing changes',
                      floating_point_range=_between(0.01, 3600.0))
        self._declare('diagnostics_period', 1.0,
                      'Seconds between publications of the bus and device status on '
                      '/diagnostics (diagnostic_msgs/DiagnosticArray), while anything '
                      'subscribes to it',
                      floating_point_range=_between(0.01, 3600.0))
        self._declare('pdo.nodes', Parameter.Type.INTEGER_ARRAY,
                      'Node ids (1..127) whose PDOs the gateway serves: their mapping is read '
                      'over SDO when first heard and after every boot-up; what they send is '
                      'published on ~/node_<id>/rpdo, what is published on ~/node_<id>/tpdo '
                      'is sent to them',
                      additional_constraints=checks.NODE_IDS)
        self._declare('pdo.configure', False,
                      'Write the PDO parameters of node_<id>.eds (0x1400-0x1BFF) to each '
                      'device of pdo.nodes whenever it boots, then read them back')
        self._declare('sync.period', 0.0,
                      'Seconds between SYNC messages the gateway produces (COB-ID 0x80); 0 = '
                      'no SYNC. Synchronous RPDOs go out right after a SYNC',
                      floating_point_range=_between(0.0, 60.0))
        self._declare('sync.counter_overflow', 0,
                      'SYNC counter (CiA 301): 0 = SYNC without counter; 2..240 = with a '
                      'counter from 1 that wraps after this value',
                      integer_range=[IntegerRange(from_value=0, to_value=240, step=0)])
        self._declare('drives.nodes', Parameter.Type.INTEGER_ARRAY,
                      'Node ids (1..127) of the devices run as CiA 402 drives: commanded on '
                      '~/drive_command and ~/move, their targets taken on ~/node_<id>/target '
                      'and ~/joint_commands, their state on ~/joint_states and '
                      '~/node_<id>/drive_state. They are watched and their PDOs served as if '
                      'also in nodes and pdo.nodes',
                      additional_constraints=checks.NODE_IDS)
        drive_parameters.declare(self._declare, self._given_ids('drives.nodes'))
        raw_parameters.declare(self._declare)
        self._declare('program_download.flash_timeout', 30.0,
                      'Seconds a program download (~/program_download) waits for the flash: '
                      'for the clear command (0x1F51 = 3) and for 0x1F57 to show the flash '
                      'no longer busy after clearing and after the image',
                      floating_point_range=_between(0.1, 60.0))
        self._declare('program_download.start_timeout', 10.0,
                      'Seconds a program download waits, after starting the new program '
                      '(0x1F51 = 1), for the boot-up message of the device',
                      floating_point_range=_between(0.1, 600.0))
        self._declare('program_download.restart_timeout', 0.0,
                      'For devices that restart into their bootloader when their program is '
                      'stopped (0x1F51 = 0), as many do: seconds a program download waits '
                      'after the stop for their boot-up message before clearing the program. '
                      '0: the device does not restart, the clear follows the stop at once',
                      floating_point_range=_between(0.0, 600.0))
        self._declare('program_download.at_boot', False,
                      "Let a boot download a device's software_file of the bus description "
                      '(bus_config) when its 0x1F56 differs from software_version; false: '
                      'such a device fails its boot with CiA 302-2 error H')
        self._declare('simulation.devices', Parameter.Type.INTEGER_ARRAY,
                      'Node ids (1..127) of simulated CANopen devices to put on the bus, for '
                      'trying the gateway without hardware; empty on a real bus',
                      additional_constraints=checks.NODE_IDS)
        self._declare('simulation.drives', Parameter.Type.INTEGER_ARRAY,
                      'Node ids (1..127) of simulated CiA 402 drives to put on the bus, with '
                      'the PDOs a drive commonly has (needs the durand package); empty on a '
                      'real bus',
                      additional_constraints=checks.NODE_IDS)
        self._declare('simulation.bootloaders', Parameter.Type.INTEGER_ARRAY,
                      'Node ids (1..127) of simulated devices with a bootloader, which take '
                      'a new program by ~/program_download (CiA 302-3; needs the durand '
                      'package); empty on a real bus',
                      additional_constraints=checks.NODE_IDS)
        self._declare('simulation.drive_layout', 'combined',
                      'PDO layout of the simulated drives: combined (controlword, target '
                      'position and mode in RPDO 1), vendor (the controlword in every RPDO, '
                      'as Maxon EPOS2 and Faulhaber EDS files ship), ros2_canopen (the '
                      'layout of its CiA 402 examples, synchronous TPDOs) or sdo_only (no '
                      'PDO: run by SDO)',
                      additional_constraints=', '.join(LAYOUTS))
        self._declare('simulation.eds', '',
                      'EDS file of the simulated devices; empty = the one shipped in config/')
        for node_id in self._listed_devices():
            self._declare(device_file_parameter(node_id), '',
                          f'EDS or DCF file of node {node_id}; empty = none. Checked at '
                          f'start. Give an absolute path: cbcan_cli reads the same file to '
                          f'name objects and decode values')

    def gateway_config(self) -> GatewayConfig:
        """Return the core's configuration; raise ConfigurationError naming a wrong parameter.

        Checks every parameter, and how they fit together; doubtful values are logged as
        warnings once.
        """
        value = self.value
        checks.check_unknown(self._node, self._declared)
        interface, channel = value('can.interface'), value('can.channel')
        checks.check_interface(interface)
        checks.check_channel(interface, channel)
        bus_options = checks.bus_options(self._strings('can.options'))
        expected, guarded = self.node_ids('nodes'), self.node_ids('node_guarding')
        simulated = self.node_ids('simulation.devices')
        simulated_drives = self.node_ids('simulation.drives')
        bootloaders = self.node_ids('simulation.bootloaders')
        checks.check_simulated({'simulation.devices': simulated,
                                'simulation.drives': simulated_drives,
                                'simulation.bootloaders': bootloaders})
        pdo_nodes = self.node_ids('pdo.nodes')
        listed = {'nodes': expected, 'node_guarding': guarded, 'pdo.nodes': pdo_nodes,
                  'simulation.devices': simulated, 'simulation.drives': simulated_drives,
                  'simulation.bootloaders': bootloaders,
                  'drives.nodes': self.node_ids('drives.nodes')}
        checks.check_own_node_id(value('heartbeat.node_id'), listed)
        own_id = drive_parameters.own_node_id(value, listed)
        drives = drive_parameters.settings(
            value, self.node_ids('drives.nodes'), own_id,
            value('heartbeat.period'), value('sync.period'))
        self.joints()
        checks.check_sync(value('sync.period'), value('sync.counter_overflow'))
        checks.check_file('simulation.eds', value('simulation.eds'))
        if value('simulation.drive_layout') not in LAYOUTS:
            raise checks.ConfigurationError(
                'simulation.drive_layout', value('simulation.drive_layout'),
                'is no layout of a simulated drive', ', '.join(LAYOUTS))
        self.check_device_files()  # the core does not use them; a bad one stops the node here
        self.warnings = [warning for warning in (
            checks.check_bitrate(interface, value('can.bitrate')),
            checks.check_guarding(guarded, expected, value('node_guarding_period'),
                                  value('heartbeat.timeout')),
            checks.simulation_warning(interface, channel,
                                      simulated + simulated_drives + bootloaders),
            checks.pdo_configure_warning(value('pdo.configure'), [
                node_id for node_id in pdo_nodes
                if not value(device_file_parameter(node_id))]),
            self.bus_file.warning) if warning]
        for warning in self.warnings:
            self._node.get_logger().warning(warning)
        return GatewayConfig(
            interface=interface,
            channel=channel,
            bitrate=value('can.bitrate'),
            sdo_timeout=value('sdo.timeout'),
            block_transfer=value('sdo.block_transfer'),
            heartbeat_timeout=value('heartbeat.timeout'),
            expected_nodes=tuple(expected),
            guarded_nodes=tuple(guarded),
            guard_period=value('node_guarding_period'),
            queue_limit=value('sdo.queue_limit'),
            read_retries=value('sdo.read_retries'),
            write_protection=WriteProtection(
                value('read_only'), checks.write_rules(self._strings('sdo.write_allow'))),
            bus_options=bus_options,
            lss_probe_timeout=value('lss.probe_timeout'),
            pdo_nodes=tuple(pdo_nodes),
            pdo_configure=value('pdo.configure'),
            device_files={node_id: value(device_file_parameter(node_id))
                          for node_id in self._listed_devices()
                          if value(device_file_parameter(node_id))},
            sync_period=value('sync.period'),
            sync_counter_overflow=value('sync.counter_overflow'),
            heartbeat_node_id=own_id,
            heartbeat_period=value('heartbeat.period'),
            drives=drives,
            raw=raw_parameters.settings(self._strings),
            bus_description=self.bus_file.description,
            program=ProgramSettings(answer_timeout=value('sdo.timeout'),
                                    flash_timeout=value('program_download.flash_timeout'),
                                    start_timeout=value('program_download.start_timeout'),
                                    restart_timeout=value('program_download.restart_timeout'),
                                    at_boot=value('program_download.at_boot')))

    def joints(self) -> Dict[int, drive_parameters.Joint]:
        """Return every drive's joint (name, scales); raise ConfigurationError when wrong."""
        return drive_parameters.joints(self.value, self.node_ids('drives.nodes'))

    def _given_ids(self, name: str) -> List[int]:
        """Return the node ids given for ``name`` that can name parameters (1..127)."""
        given = self.bus_file.node_ids(name, list(
            self._node.get_parameter_or(name, Parameter(name, value=[])).value or []))
        return [node_id for node_id in given if 1 <= node_id <= 127]

    def _strings(self, name: str) -> List[str]:
        return list(self._node.get_parameter_or(name, Parameter(name, value=[])).value or [])

    def value(self, name: str):
        """Return the value of parameter ``name`` (the bus description's, when not given)."""
        given = self._node.get_parameter(name).value
        if name == 'bus_config':
            return given
        return self.bus_file.value(name, given, self._defaults.get(name))

    def node_ids(self, name: str) -> List[int]:
        """Return the node ids of an integer-array parameter, checked to be 1..127."""
        parameter = self._node.get_parameter_or(name, Parameter(name, value=[]))
        node_ids = list(parameter.value or [])
        checks.check_node_ids(name, node_ids)
        return self.bus_file.node_ids(name, node_ids)

    def _listed_devices(self) -> List[int]:
        listed = set()
        for name in ('nodes', 'node_guarding', 'pdo.nodes', 'drives.nodes'):
            listed.update(self.bus_file.node_ids(name, list(
                self._node.get_parameter_or(name, Parameter(name, value=[])).value or [])))
        return sorted(node_id for node_id in listed if 1 <= node_id <= 127)

    def check_device_files(self) -> None:
        """Check that every EDS or DCF file given exists and canopen can parse it.

        Raises ValueError naming the parameter and the file.
        """
        files = [(device_file_parameter(node_id), node_id)
                 for node_id in self._listed_devices()]
        simulated = self.node_ids('simulation.devices')
        if simulated:
            files.append(('simulation.eds', simulated[0]))
        for name, node_id in files:
            path = self.value(name)
            if path:
                try:
                    eds.load(path, node_id, note=self._node.get_logger().warning)
                except ValueError as error:
                    where = self.bus_file.source(name, self._node.get_parameter(name).value,
                                                 self._defaults.get(name))
                    raise ValueError(f'{where}: {error}') from None

    def simulation_eds(self) -> str:
        """Return the EDS file of the simulated devices."""
        path = self.value('simulation.eds')
        if path:
            return path
        from ament_index_python.packages import get_package_share_directory
        return os.path.join(get_package_share_directory('cbcan_ros'), 'config',
                            'simulated_device.eds')
