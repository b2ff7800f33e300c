"""Start one gateway per CAN bus: ros2 launch cbcan_ros cbcan.launch.py params:=<yaml>."""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription


def generate_launch_description():
    """Return the launch description: the gateway node in namespace ``bus``."""
    default_params = os.path.join(get_package_share_directory('cbcan_ros'), 'config',
                                  'simulation.yaml')
    return LaunchDescription([
        DeclareLaunchArgument('bus', default_value='can0',
                              description='Namespace of the gateway, one per CAN bus'),
        DeclareLaunchArgument('params', default_value=default_params,
                              description='Parameter file (see config/gateway.yaml)'),
        Node(package='cbcan_ros', executable='cbcan_node', name='cbcan',
             namespace=LaunchConfiguration('bus'),
             parameters=[LaunchConfiguration('params')], output='screen'),
    ])
