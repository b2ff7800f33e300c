"""Start one CANopen gateway per CAN bus, each as /<bus>/cbcan, with parameters from a YAML.

    ros2 launch cbcan_ros cbcan.launch.py                     # /can0/cbcan, simulated devices
    ros2 launch cbcan_ros cbcan.launch.py buses:=can0,can1 params:=/path/two_buses.yaml
    ros2 launch cbcan_ros cbcan.launch.py managed:=true       # the lifecycle node instead

One parameter file serves every bus: settings under ``/**`` apply to all gateways, a section
keyed ``/can1/cbcan`` to that bus only (see config/two_buses.yaml).
"""

import os
import re

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, EmitEvent, OpaqueFunction, RegisterEventHandler
from launch.events import matches_action
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node
from launch_ros.event_handlers import OnStateTransition
from launch_ros.events.lifecycle import ChangeState
from lifecycle_msgs.msg import Transition

from launch import LaunchDescription

PACKAGE = 'cbcan_ros'
NODE_NAME = 'cbcan'
# A bus name becomes a namespace: letters, digits and underscores, not starting with a digit.
BUS_NAME = re.compile(r'[A-Za-z_][A-Za-z0-9_]*')
BOOLEAN = ['true', 'false']  # launch itself refuses other values of these arguments


def bus_names(text: str) -> list:
    """Return the bus names of the ``buses`` argument (``can0,can1``); raise on a bad one."""
    names = [name.strip() for name in text.split(',') if name.strip()]
    wrong = [name for name in names if not BUS_NAME.fullmatch(name)]
    if not names or wrong or len(set(names)) != len(names):
        raise ValueError(f'launch argument buses: {text[:60]!r} is not a list of distinct bus '
                         f'names; allowed: names such as can0, separated by commas '
                         f'(each becomes the namespace /<name>)')
    return names


def gateways(context) -> list:
    """Return the actions that start one gateway per bus (run once the arguments are known)."""
    buses = bus_names(LaunchConfiguration('buses').perform(context))
    params = LaunchConfiguration('params').perform(context)
    managed = LaunchConfiguration('managed').perform(context) == 'true'
    autostart = LaunchConfiguration('autostart').perform(context) == 'true'
    actions = []
    for bus in buses:
        options = dict(package=PACKAGE, name=NODE_NAME, namespace=f'/{bus}',
                       parameters=[params], output='screen')
        if not managed:
            actions.append(Node(executable='cbcan_node', **options))
            continue
        node = LifecycleNode(executable='cbcan_lifecycle_node', **options)
        actions.append(node)
        if autostart:  # configure now, activate once configured (as ros2_socketcan does)
            actions.append(RegisterEventHandler(OnStateTransition(
                target_lifecycle_node=node, goal_state='inactive',
                entities=[EmitEvent(event=ChangeState(
                    lifecycle_node_matcher=matches_action(node),
                    transition_id=Transition.TRANSITION_ACTIVATE))])))
            actions.append(EmitEvent(event=ChangeState(
                lifecycle_node_matcher=matches_action(node),
                transition_id=Transition.TRANSITION_CONFIGURE)))
    return actions


def generate_launch_description():
    """Return the launch description: its arguments, and the gateways they ask for."""
    default_params = os.path.join(get_package_share_directory(PACKAGE), 'config',
                                  'simulation.yaml')
    return LaunchDescription([
        DeclareLaunchArgument(
            'params', default_value=default_params,
            description='Parameter file for every gateway (examples in share/cbcan_ros/'
                        'config: socketcan_500k.yaml, pcan.yaml, slcan.yaml, two_buses.yaml)'),
        DeclareLaunchArgument(
            'buses', default_value='can0',
            description='CAN buses, comma-separated: one gateway each, as /<bus>/cbcan'),
        DeclareLaunchArgument(
            'managed', default_value='false', choices=BOOLEAN,
            description='true: the managed (lifecycle) node cbcan_lifecycle_node; '
                        'false: cbcan_node, active from the start'),
        DeclareLaunchArgument(
            'autostart', default_value='true', choices=BOOLEAN,
            description='With managed:=true: configure and activate at once; false leaves '
                        'the nodes unconfigured for a lifecycle manager'),
        OpaqueFunction(function=gateways),
    ])
