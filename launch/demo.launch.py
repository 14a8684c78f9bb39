"""The paper's example as a ROS 2 launch: plant, controller and (optionally) the MCAP recorder.

    ros2 launch nmpc_avoid_ros demo.launch.py                      # mu = 1e8, recording into bags/
    ros2 launch nmpc_avoid_ros demo.launch.py mu:=0.0 record:=false namespace:=/vdp1

Arguments: `config` (params file; default the shipped van_der_pol.yaml), `mu` (avoidance weight),
`record` (true: run the recorder), `namespace` (one controller per plant). The controller starts
with the paper's target y_t = 5 (later targets on `target`).
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

PACKAGE = "nmpc_avoid_ros"


def generate_launch_description() -> LaunchDescription:
    config = LaunchConfiguration("config")
    namespace = LaunchConfiguration("namespace")
    return LaunchDescription([
        DeclareLaunchArgument("config", default_value=PathJoinSubstitution(
            [FindPackageShare(PACKAGE), "config", "van_der_pol.yaml"]), description="params file of the nodes"),
        DeclareLaunchArgument("mu", default_value="1.0e8", description="avoidance weight (0 disables avoidance)"),
        DeclareLaunchArgument("record", default_value="true", description="record an MCAP bag (recorder node)"),
        DeclareLaunchArgument("namespace", default_value="", description="namespace of the three nodes"),
        Node(package=PACKAGE, executable="plant", name="plant", namespace=namespace, parameters=[config],
             output="screen"),
        Node(package=PACKAGE, executable="controller", name="controller", namespace=namespace, output="screen",
             parameters=[config, {"mu": ParameterValue(LaunchConfiguration("mu"), value_type=float),
                                  "target": [5.0]}]),
        Node(package=PACKAGE, executable="recorder", name="recorder", namespace=namespace, output="screen",
             condition=IfCondition(LaunchConfiguration("record"))),
    ])
