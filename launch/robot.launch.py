"""A differential-drive robot: the unicycle plant (Odometry on `odom`, TwistStamped on `cmd_vel`)
and the controller, which takes goals on `goal_pose` (RViz "2D Goal Pose") and obstacles as
markers on `obstacles` in the `odom` frame.

    ros2 launch nmpc_avoid_ros robot.launch.py
    ros2 launch nmpc_avoid_ros robot.launch.py namespace:=/robot1

With a real robot, run only the controller with the same params file: its driver (e.g.
diff_drive_controller) provides `odom` and takes `cmd_vel`.
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
    return LaunchDescription([
        DeclareLaunchArgument("config", default_value=PathJoinSubstitution(
            [FindPackageShare(PACKAGE), "config", "unicycle.yaml"]), description="params file of the nodes"),
        DeclareLaunchArgument("namespace", default_value="", description="namespace of the robot's nodes"),
        Node(package=PACKAGE, executable="plant", name="plant", namespace=namespace, parameters=[config],
             output="screen"),
        Node(package=PACKAGE, executable="controller", name="controller", namespace=namespace,
             parameters=[config], output="screen"),
    ])
