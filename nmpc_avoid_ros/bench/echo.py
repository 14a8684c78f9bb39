"""The floor of a Python ROS 2 node's state-to-command path: a node that publishes each `state` it receives
on `command` at once, nothing else (one subscription, one publisher, rclpy's SingleThreadedExecutor).

    python -m nmpc_avoid_ros.bench.echo

bench/node.py `measure_echo` times it with the same probe and the same DDS stamps as the controller, so that the
controller's figures can be read against what rclpy itself costs on the machine (BENCHMARKS.md).
"""

from __future__ import annotations

import rclpy
from rclpy.executors import ExternalShutdownException
from std_msgs.msg import Float64MultiArray

from ..ros.parameters import STREAM_QOS


def main() -> int:
    rclpy.init()
    node = rclpy.create_node("bench_echo")
    publisher = node.create_publisher(Float64MultiArray, "command", STREAM_QOS)

    def echo(msg: Float64MultiArray) -> None:
        publisher.publish(Float64MultiArray(data=msg.data))

    node.create_subscription(Float64MultiArray, "state", echo, STREAM_QOS)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
