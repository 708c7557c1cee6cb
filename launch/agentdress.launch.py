"""Start agentdress_node with config/agentdress.yaml, the demo JointState player and the web viewer (for a real ROS 2
install: `ros2 launch agentdress_ros agentdress.launch.py [motion:=wave] [demo:=false] [viewer:=false] [port:=8765]`).
The viewer prints the URL to open. The PyPI wheels used in a plain venv ship no `launch`; there, `make run` starts the
same three processes (agentdress_ros/ros/run_all.py), or run `agentdress_node --ros-args --params-file
config/agentdress.yaml` directly."""
import glob
import os
import sys

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    share = get_package_share_directory("agentdress_ros")
    default_params = os.path.join(share, "config", "agentdress.yaml")
    # the shipped garment databases, when installed: those garments are synthesised by the engine instead of skinned
    databases = [f"{os.path.basename(path)[: -len('_default.h5')]}:{path}"
                 for path in sorted(glob.glob(os.path.join(share, "data", "*_default.h5")))]
    database_params = {"garment_databases": databases, "skinned_fallback": True} if databases else {}
    params_file = LaunchConfiguration("params_file")
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "params_file", default_value=default_params, description="YAML file with the node's ros__parameters"
            ),
            DeclareLaunchArgument("demo", default_value="true", description="also play a demo motion as JointState"),
            DeclareLaunchArgument("motion", default_value="walk", description="demo motion name or CMU .bvh file"),
            DeclareLaunchArgument("viewer", default_value="true", description="also serve the web viewer"),
            DeclareLaunchArgument("port", default_value="8765", description="web viewer HTTP port"),
            Node(
                package="agentdress_ros",
                executable="agentdress_node",
                name="agentdress_node",
                parameters=[params_file, {"publish_body": True, **database_params}],
                output="screen",
                emulate_tty=True,
            ),
            # The demo and the viewer are plain Python entry points of the package (no node executables of their own).
            ExecuteProcess(
                cmd=[sys.executable, "-m", "agentdress_ros.ros.demo", "--motion", LaunchConfiguration("motion")],
                name="agentdress_demo",
                output="screen",
                condition=IfCondition(LaunchConfiguration("demo")),
            ),
            ExecuteProcess(
                cmd=[sys.executable, "-m", "agentdress_ros.ros.viewer", "--port", LaunchConfiguration("port")],
                name="agentdress_viewer",
                output="screen",
                condition=IfCondition(LaunchConfiguration("viewer")),
            ),
        ]
    )
