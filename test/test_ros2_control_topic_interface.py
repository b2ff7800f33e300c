"""The documented ros2_control setup drives the joints, with the released plugin's logic.

ros2_control is not on this machine, so ``TopicSystem`` mirrors the ``write()`` of the
released ``joint_state_topic_hardware_interface/JointStateTopicSystem`` (Jazzy): it adds up
|state - command| over the position interfaces of all joints, publishes nothing while that sum
is at or below ``trigger_joint_command_threshold``, and fills each array of the JointState only
for the joints that have that command interface. It is configured from the ``<ros2_control>``
block of docs/drives.md as printed, and its messages go to a gateway with a simulated drive.
"""

from dataclasses import dataclass
import re
from typing import Dict, List, Optional
import xml.etree.ElementTree as ElementTree

import pytest
from sensor_msgs.msg import JointState
import test_drives
from test_drives import CSP, CSV, JOINT, joints_enabled, WAIT

from conftest import wait_until
from node_process import ROOT

rig = test_drives.rig  # a gateway with one simulated drive (a fixture)
INTERFACES = ('position', 'velocity', 'acceleration', 'effort')  # the plugin's order


def documented_hardware() -> ElementTree.Element:
    """Return the ``<ros2_control>`` element of docs/drives.md."""
    page = (ROOT / 'docs' / 'drives.md').read_text()
    block = re.search(r'```xml\n(<ros2_control.*?</ros2_control>)\n```', page, re.S)
    assert block, 'docs/drives.md has no <ros2_control> block'
    return ElementTree.fromstring(block.group(1))


@dataclass
class TopicSystem:
    """The released plugin's write(), for joints with the given command interfaces."""

    threshold: float
    command_interfaces: Dict[str, List[str]]  # joint: its command interfaces

    def __post_init__(self):
        names = list(self.command_interfaces)
        self.states = {interface: [0.0] * len(names) for interface in INTERFACES}
        self.commands = {interface: [0.0] * len(names) for interface in INTERFACES}

    def write(self) -> Optional[JointState]:
        """Return the JointState the plugin publishes this cycle, None when it skips it."""
        diff = sum(abs(state - command) for state, command
                   in zip(self.states['position'], self.commands['position'], strict=True))
        if diff <= self.threshold:
            return None
        message = JointState(name=list(self.command_interfaces))
        for n, interfaces in enumerate(self.command_interfaces.values()):
            for interface in interfaces:
                getattr(message, interface).append(self.commands[interface][n])
        return message


def documented_system(joints: Dict[str, List[str]]) -> TopicSystem:
    """Return the mirror with the documented hardware parameters, for ``joints``."""
    hardware = documented_hardware()
    parameters = {param.get('name'): param.text for param in hardware.iter('param')}
    return TopicSystem(float(parameters.get('trigger_joint_command_threshold', '1e-5')), joints)


def test_the_documented_block_names_the_gateway_topics_and_a_threshold_below_zero():
    hardware = documented_hardware()
    parameters = {param.get('name'): param.text for param in hardware.iter('param')}
    assert parameters['joint_states_topic'] == '/can0/cbcan/joint_states'
    assert parameters['joint_commands_topic'] == '/can0/cbcan/joint_commands'
    assert [joint.get('name') for joint in hardware.iter('joint')] == ['wheel']


def test_the_released_default_never_commands_a_velocity_joint_standing_at_zero():
    # Why the page sets the threshold: with the plugin's default (and with 0), a velocity
    # command is never sent while every position is 0.
    for threshold in (1e-5, 0.0):
        system = TopicSystem(threshold, {JOINT: ['velocity']})
        system.commands['velocity'][0] = 1.0
        assert system.write() is None


@pytest.mark.parametrize('mode, interface, value, reached', [
    (CSV, 'velocity', 1.0, lambda drive: drive.velocity == 1000),
    (CSP, 'position', 0.0, lambda drive: drive.position == 0),
], ids=['velocity', 'position_holding_still'])
def test_the_documented_setup_drives_the_joint_every_cycle(rig, mode, interface, value,
                                                             reached):
    axis = rig(**{'drives.command_timeout': 0.3})
    axis.enable(mode)
    system = documented_system({JOINT: [interface]})
    system.commands[interface][0] = value  # position: holding still where it stands (0)
    sent = 0

    def cycle():
        nonlocal sent
        message = system.write()
        assert message is not None, 'the plugin skipped a cycle'
        axis.commands.publish(message)
        sent += 1
        return reached(axis.drive) and sent >= 40  # past the command timeout: not halted
    wait_until(cycle, WAIT, f'the drive following the {interface} command')
    assert not axis.states[-1].halted


def test_mixed_interfaces_reach_each_drive_from_the_plugins_short_arrays(ros_context,
                                                                         start_durand):
    # An arm joint in position and a wheel in velocity, both drives of one gateway: the
    # plugin fills velocity only for the wheel and position only for the arm.
    with joints_enabled(start_durand, {7: ('arm', CSP), 8: ('wheel', CSV)}) as (
            _, drives, commands):
        system = documented_system({'arm': ['position'], 'wheel': ['velocity']})
        system.commands['position'][0] = 0.25
        system.commands['velocity'][1] = 0.5
        message = system.write()
        assert list(message.position) == [0.25] and list(message.velocity) == [0.5]

        def followed():
            commands.publish(message)
            return drives[7].position == 250 and drives[8].velocity == 500
        wait_until(followed, WAIT, 'the arm at 250 counts and the wheel at 500 counts/s')
