"""Start agentdress_node with config/agentdress.yaml (for a real ROS 2 install: `ros2 launch agentdress_ros
agentdress.launch.py`). The PyPI wheels used in a plain venv ship no `launch`; there, run `agentdress_node` directly:
`agentdress_node --ros-args --params-file config/agentdress.yaml`."""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory("agentdress_ros"), "config", "agentdress.yaml")
    params_file = LaunchConfiguration("params_file")
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "params_file", default_value=default_params, description="YAML file with the node's ros__parameters"
            ),
            Node(
                package="agentdress_ros",
                executable="agentdress_node",
                name="agentdress_node",
                parameters=[params_file],
                output="screen",
                emulate_tty=True,
            ),
        ]
    )
