"""The unicycle in a world: the plant drives it in a map with walkers and a simulated lidar, the `obstacles`
node fits regions to the scans, and the controller drives to the goal seeing only those.

    ros2 launch nmpc_avoid_ros world.launch.py
    ros2 launch nmpc_avoid_ros world.launch.py world:=worlds/pillars.yaml walkers:=""

Arguments: `config` (params file of the three nodes; default the shipped unicycle_world.yaml: its controller
starts with the goal (3, 2), later goals on `goal_pose`), `world` (a map_server YAML, relative to the shipped
config folder or a path), `walkers` (a scene file whose obstacles the lidar sees moving; "" for none),
`namespace`. Topics: `map`, `scan`, `odom`, `cmd_vel`, `obstacles` (docs/usage.md, 'A world to drive in').
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

PACKAGE = "nmpc_avoid_ros"


def generate_launch_description() -> LaunchDescription:
    config = LaunchConfiguration("config")
    namespace = LaunchConfiguration("namespace")
    world = {"world": LaunchConfiguration("world"), "walkers": LaunchConfiguration("walkers")}
    return LaunchDescription([
        DeclareLaunchArgument("config", default_value=PathJoinSubstitution(
            [FindPackageShare(PACKAGE), "config", "unicycle_world.yaml"]), description="params file of the nodes"),
        DeclareLaunchArgument("world", default_value="worlds/room.yaml", description="map_server YAML of the world"),
        DeclareLaunchArgument("walkers", default_value="worlds/room_walkers.yaml",
                              description="scene file of the walkers the lidar sees ('' for none)"),
        DeclareLaunchArgument("namespace", default_value="", description="namespace of the robot's nodes"),
        Node(package=PACKAGE, executable="plant", name="plant", namespace=namespace, parameters=[config, world],
             output="screen"),
        Node(package=PACKAGE, executable="obstacles", name="obstacles", namespace=namespace, parameters=[config],
             output="screen"),
        Node(package=PACKAGE, executable="controller", name="controller", namespace=namespace,
             parameters=[config], output="screen"),
    ])
