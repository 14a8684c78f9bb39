"""Standard robot messages <-> a planar robot model's vectors: nav_msgs/Odometry, geometry_msgs/Twist(Stamped),
geometry_msgs/PoseStamped.

Conventions (REP 103 / REP 105): SI units (m, rad, m/s, rad/s); the pose is the base frame
(`base_link`, x forward, z up) in the odometry frame (`odom`); the twist of an Odometry and a
velocity command are in the base frame (v = linear.x, omega = angular.z).

The messages carry a pose [x, y, yaw] and a velocity [linear, angular]; the model file's `planar`
section says which states they are and which inputs a velocity command is (`check_robot_model` returns
that map: the unicycle's [v, omega] directly, a car-like model's steering angle through v tan(delta) / L).
Every conversion from a message validates it and raises InputError with the reason (wrong frame,
NaN or infinite values, a quaternion of zero norm), so the node can refuse it, count it and keep its last good value.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, Quaternion, Twist, TwistStamped
from nav_msgs.msg import Odometry

from ..core.errors import ConfigError, InputError
from ..core.problem.models import Model

#: a quaternion this close to zero carries no rotation at all (a message left at its defaults)
MIN_QUATERNION_NORM = 1e-6


class RobotModelMap:
    """A planar robot model's state <-> pose [x, y, yaw] and input <-> velocity command [linear, angular]."""

    def __init__(self, model: Model) -> None:
        planar = model.planar
        self.indices = (planar.x, planar.y, planar.yaw)
        self.n = model.n
        self.command, self.from_command = planar.command, planar.from_command

    def state(self, pose: Sequence[float]) -> np.ndarray:
        """The state x[n] of a pose [x, y, yaw] (every state of a robot-interface model is part of its pose)."""
        x = np.zeros(self.n)
        x[list(self.indices)] = pose
        return x

    def pose(self, x: Sequence[float]) -> list[float]:
        return [float(x[i]) for i in self.indices]

    def twist(self, x: Sequence[float], u: Sequence[float]) -> list[float]:
        """[linear (m/s), angular (rad/s)] that the input u gives at state x."""
        return np.asarray(self.command(x, u), float).ravel().tolist()

    def inputs(self, x: Sequence[float], twist: Sequence[float]) -> np.ndarray:
        """The input u[m] a velocity command [linear, angular] means at state x; InputError if it has none."""
        u = np.asarray(self.from_command(x, twist), float).ravel()
        if not np.all(np.isfinite(u)):
            raise InputError(f"cmd_vel {list(twist)} means no finite input of the model: {u.tolist()}")
        return u


def check_robot_model(model: Model) -> RobotModelMap:
    """The map of a model the robot interface can drive; ConfigError unless its model file declares `planar` with
    the yaw a state, a command and from_command, and its state is exactly the pose (x, y, yaw)."""
    planar = model.planar
    if planar is None or planar.yaw is None or planar.command is None or model.n != 3:
        raise ConfigError(f"interface 'robot' needs a model whose state is a planar pose (x, y, yaw) with a velocity "
                          f"command declared (model file `planar`: x, y, yaw, command, from_command); model "
                          f"{model.name!r} has states {model.state_names}" + ("" if planar else " and no `planar`"))
    return RobotModelMap(model)


def _finite(name: str, *values: float) -> tuple[float, ...]:
    out = tuple(float(v) for v in values)
    if not all(math.isfinite(v) for v in out):
        raise InputError(f"{name} contains NaN or infinite values: {list(out)}")
    return out


def _check_frame(what: str, frame: str, expected: str) -> None:
    if frame != expected:
        raise InputError(f"{what} is {frame!r}, expected {expected!r} (no tf lookup here: publish in that frame)")


def yaw_of(q: Quaternion) -> float:
    """Yaw (rad, in [-pi, pi]) of a quaternion of any non-zero norm (normalised first).

    Raises InputError for NaN/inf components or a norm below MIN_QUATERNION_NORM: the all-zero
    quaternion is not a rotation, and reading it as identity would steer by a made-up heading.
    """
    x, y, z, w = _finite("orientation", q.x, q.y, q.z, q.w)
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if norm < MIN_QUATERNION_NORM:
        raise InputError(f"orientation quaternion has zero norm ({norm:.3g}): no heading")
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def yaw_quaternion(yaw: float) -> Quaternion:
    """Rotation by `yaw` rad about z."""
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0))


def unwrap(yaw: float, reference: float | None) -> float:
    """`yaw` shifted by a multiple of 2 pi to lie within pi of `reference` (the last heading).

    The model's theta is continuous while a quaternion's yaw jumps at +-pi; without this a robot
    turning through pi would see its heading jump by 2 pi between two samples.
    """
    if reference is None:
        return yaw
    return yaw + 2.0 * math.pi * round((reference - yaw) / (2.0 * math.pi))


def odometry_to_state(msg: Odometry, odom_frame: str, base_frame: str, last_theta: float | None = None) -> np.ndarray:
    """[x, y, theta] of an Odometry (theta unwrapped against `last_theta`); InputError with the reason."""
    _check_frame("odometry header.frame_id", msg.header.frame_id, odom_frame)
    _check_frame("odometry child_frame_id", msg.child_frame_id, base_frame)
    position = msg.pose.pose.position
    x, y = _finite("odometry position", position.x, position.y)
    theta = unwrap(yaw_of(msg.pose.pose.orientation), last_theta)
    return np.array([x, y, theta])


def goal_to_target(msg: PoseStamped, frame: str, with_heading: bool = False) -> np.ndarray:
    """The goal's position [x, y] as y_t, and with `with_heading` (a model whose outputs are the pose,
    unicycle_pose) its yaw [x, y, yaw] (rad, in [-pi, pi]; the controller turns the short way); InputError for a
    goal in another frame, NaN or infinite values or, with the heading, an orientation of zero norm."""
    _check_frame("goal_pose header.frame_id", msg.header.frame_id, frame)
    position = msg.pose.position
    xy = _finite("goal_pose position", position.x, position.y)
    return np.array([*xy, yaw_of(msg.pose.orientation)] if with_heading else xy)


def velocity_command(u: Sequence[float], stamped: bool, stamp: Time, base_frame: str) -> Twist | TwistStamped:
    """[v, omega] -> Twist, or TwistStamped in `base_frame` (Jazzy's diff_drive_controller default)."""
    twist = Twist()
    twist.linear.x, twist.angular.z = float(u[0]), float(u[1])
    if not stamped:
        return twist
    msg = TwistStamped(twist=twist)
    msg.header.stamp = stamp
    msg.header.frame_id = base_frame
    return msg


def twist_to_command(msg: Twist | TwistStamped) -> np.ndarray:
    """[v, omega] of a Twist or TwistStamped; InputError for NaN/inf (lateral and 3-D parts ignored)."""
    twist = msg.twist if isinstance(msg, TwistStamped) else msg
    return np.array(_finite("cmd_vel", twist.linear.x, twist.angular.z))


def state_to_odometry(x: Sequence[float], u: Sequence[float], stamp: Time, odom_frame: str,
                      base_frame: str) -> Odometry:
    """[x, y, theta] and the applied [v, omega] -> Odometry (pose in odom, twist in the base frame)."""
    msg = Odometry()
    msg.header.stamp = stamp
    msg.header.frame_id = odom_frame
    msg.child_frame_id = base_frame
    msg.pose.pose.position.x, msg.pose.pose.position.y = float(x[0]), float(x[1])
    msg.pose.pose.orientation = yaw_quaternion(float(x[2]))
    msg.twist.twist.linear.x, msg.twist.twist.angular.z = float(u[0]), float(u[1])
    return msg
