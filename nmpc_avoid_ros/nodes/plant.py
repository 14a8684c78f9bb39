"""`plant`: simulates a model under zero-order hold of the last command and publishes `state`.

    ros2 run nmpc_avoid_ros plant --ros-args --params-file config/van_der_pol.yaml

Real time: a timer at `publish_rate` Hz integrates the continuous dynamics over each period and publishes
the state. A command acts from the moment it arrives (its DDS reception, not the later moment the executor
runs its callback), as on a real plant: the period it arrives in is
integrated under the previous command up to its arrival and under the new one from there (each period
lasts exactly 1 / publish_rate of simulated time, so a bag's states and commands replay exactly:
evaluation/recorded_timing.py recovers each command's arrival within its period from the states).
Lockstep (`lockstep: true`): the plant publishes x0 once the controller listens, then after each
command advances exactly one `sample_time`, publishes `/clock` and the new state; a closed loop
runs as fast as the controller solves and reproduces the offline loop.

`input_delay` (s): the actuator's delay, a command acts that long after it arrives (real time: queued and
switched at that instant within its period; lockstep: the step integrates the previous command for it,
then the new one). The controller's own `input_delay` setting predicts it.

`interface: robot` (a model with states x, y, theta and inputs v, omega, e.g. `unicycle`): the
plant stands for a differential-drive base: it publishes nav_msgs/Odometry on `odom` (pose in
`odom_frame`, twist in `base_frame`, stamped with the node clock or, in lockstep, the simulated
time) and takes geometry_msgs/TwistStamped (or Twist, `cmd_vel_stamped: false`) on `cmd_vel`.

Views (docs/usage.md, "RViz and Foxglove"): a planar model (the unicycle; the mobile robot's
`double_integrator_2d`, which heads where it moves) also has its pose on `odom` on the array interface
and, where tf2_msgs is importable (a ROS installation: it is not among the PyPI wheels), the transform
`odom_frame` -> `base_frame` on `/tf` with each state, and on the array interface `view_frames` (the
controller's drawing frames `state` and `output`) as `odom_frame` itself on `/tf_static`. Without
tf2_msgs the node says once that it publishes no transform: the views place the robot from the odometry.

A plain node, not a lifecycle one: it stands for hardware, which a real robot's driver runs and
this package does not manage.
"""

from __future__ import annotations

import importlib
import math
import time
from collections import deque
from collections.abc import Sequence

import numpy as np
from builtin_interfaces.msg import Time as TimeMsg
from geometry_msgs.msg import TransformStamped, Twist, TwistStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import ParameterType
from rclpy.node import Node
from rclpy.time import Time
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64MultiArray

from ..core.config.settings import INTERFACES
from ..core.errors import ConfigError, InputError
from ..core.loop.closed_loop import ContinuousPlant, DiscretePlant
from ..core.problem.models import make_model, parse_model_parameters
from ..ros.conversions import array_to_vector, dds_stamp_age_ns, vector_to_array
from ..ros.parameters import LATCHED_QOS, LATEST_QOS, STREAM_QOS, ParamSpec, declare, finite_vector
from ..ros.robot import check_robot_model, state_to_odometry, twist_to_command, yaw_quaternion
from .plant_lidar import LIDAR_SPECS, SimulatedLidar
from .runner import run_node

INTEGRATIONS = ("continuous", "euler", "rk4")
#: m/s below which a model heading where it moves keeps its last heading (at rest the direction is noise)
STILL_SPEED = 1e-3

PLANT_SPECS = [
    ParamSpec("model", "van_der_pol", "model to simulate: a shipped or registered model's name, or a model file's "
              "path (docs/own_model.md)", ParameterType.PARAMETER_STRING, read_only=True),
    ParamSpec("model_parameters", None, "values of the model file's parameters, 'name=value' each (e.g. "
              "'wheelbase=0.6'): the simulated robot may differ from the controller's model; unset: the file's",
              ParameterType.PARAMETER_STRING_ARRAY, read_only=True),
    ParamSpec("initial_state", None, "initial state x0 (n values; default zeros)", ParameterType.PARAMETER_DOUBLE_ARRAY,
              read_only=True),
    ParamSpec("sample_time", 0.5, "lockstep: time advanced per command, s", ParameterType.PARAMETER_DOUBLE,
              read_only=True, float_range=(1e-6, 3600.0)),
    ParamSpec("integration", "continuous", "continuous: ZOH + DOP853 (rtol 1e-10); euler/rk4: one discrete step "
              "per sample (lockstep only)", ParameterType.PARAMETER_STRING, read_only=True, choices=INTEGRATIONS),
    ParamSpec("publish_rate", 20.0, "real time: integration and state publication rate, Hz",
              ParameterType.PARAMETER_DOUBLE, read_only=True, float_range=(0.1, 10000.0)),
    ParamSpec("lockstep", False, "advance one sample_time per command and publish /clock",
              ParameterType.PARAMETER_BOOL, read_only=True),
    ParamSpec("wait_for_subscribers", 1, "lockstep: publish x0 once this many `state` subscribers have stayed "
              "matched for 0.5 s (controller, recorder, ...)", ParameterType.PARAMETER_INTEGER, read_only=True,
              int_range=(1, 1000)),
    ParamSpec("max_steps", 0, "lockstep: advance at most this many samples, then hold and publish nothing more "
              "(0: no limit); a run of known length ends quiet, so stopping the nodes loses no message in flight",
              ParameterType.PARAMETER_INTEGER, read_only=True, int_range=(0, 10**9)),
    ParamSpec("hold_until_command", True, "real time: keep x0 until the first command arrives (the loop is closed)",
              ParameterType.PARAMETER_BOOL, read_only=True),
    ParamSpec("input_delay", 0.0, "s a command acts after it arrives (the actuator's delay; the controller's "
              "input_delay predicts it); lockstep: below sample_time, with integration continuous",
              ParameterType.PARAMETER_DOUBLE, read_only=True, float_range=(0.0, 10.0)),
    ParamSpec("process_noise_std", 0.0, "std of Gaussian noise added to the state per step (state units)",
              ParameterType.PARAMETER_DOUBLE, read_only=True, float_range=(0.0, 1e3)),
    ParamSpec("noise_seed", 0, "seed of the process noise", ParameterType.PARAMETER_INTEGER, read_only=True),
    ParamSpec("interface", "array", "array: Float64MultiArray on state/command; robot: Odometry on odom, "
              "TwistStamped/Twist on cmd_vel", ParameterType.PARAMETER_STRING, read_only=True,
              choices=INTERFACES),
    ParamSpec("cmd_vel_stamped", True, "robot interface: cmd_vel is TwistStamped (else Twist)",
              ParameterType.PARAMETER_BOOL, read_only=True),
    ParamSpec("odom_frame", "odom", "planar models: header.frame_id of the odometry, parent frame of the /tf "
              "transform", ParameterType.PARAMETER_STRING, read_only=True),
    ParamSpec("base_frame", "base_link", "planar models: child_frame_id of the odometry and of the /tf transform",
              ParameterType.PARAMETER_STRING, read_only=True),
    ParamSpec("publish_tf", True, "planar models: publish odom_frame -> base_frame on /tf with each state (needs "
              "tf2_msgs, i.e. a ROS installation; without it the node says so once)",
              ParameterType.PARAMETER_BOOL, read_only=True),
    ParamSpec("view_frames", ["state", "output"], "array interface, planar model, publish_tf: frames published on "
              "/tf_static as odom_frame itself: the controller draws its plan in `state` and the regions in "
              "`output`, which are the odometry frame when its plane and output_plane pick the position (the "
              "mobile robot configs); [''] for none", ParameterType.PARAMETER_STRING_ARRAY, read_only=True),
    *LIDAR_SPECS,
]


#: s the lockstep plant's `state` readers stay matched before it publishes x0, its only publication until a command:
#: DDS discovery is asymmetric, the writer sees a reader before the reader sees the writer, and a volatile reader
#: drops what was written before it matched it (the world's lockstep loop never started, twice in full suites:
#: the controller up, the target applied, no command in 240 s)
INITIAL_SETTLE = 0.5


def arrival_instant(info: dict | None) -> float:
    """Monotonic s at which a command reached this process: its DDS reception stamp (`received_timestamp`,
    taken by the middleware's receive thread), not the moment Python's executor ran the callback. A real
    actuator does not wait for an interpreter: on a loaded 2-core machine the executor ran commands up to
    17 ms after their reception, and the plant acting from then broke the box |x2| <= 2 by 0.02 where the
    controller had predicted the command's arrival to the millisecond (test/test_send_dds.py)."""
    now = time.monotonic()
    age_ns = dds_stamp_age_ns(info, "received_timestamp", time.time_ns())  # None: untrusted, the callback's time
    return now - (age_ns or 0) * 1e-9


def tf_message_type() -> type | None:
    """tf2_msgs/TFMessage, or None where tf2_msgs is not importable: the PyPI wheels do not carry it, a ROS
    installation does. Looked up by name when a node starts: the node runs without it."""
    try:
        return importlib.import_module("tf2_msgs.msg").TFMessage
    except ImportError:
        return None


def transform_stamped(parent: str, child: str, pose: Sequence[float], stamp: TimeMsg) -> TransformStamped:
    """The transform parent -> child of a planar pose (x, y, yaw), in the plane z = 0."""
    msg = TransformStamped(child_frame_id=child)
    msg.header.stamp, msg.header.frame_id = stamp, parent
    msg.transform.translation.x, msg.transform.translation.y = float(pose[0]), float(pose[1])
    msg.transform.rotation = yaw_quaternion(float(pose[2]))
    return msg


class PlantNode(Node):
    """Thin node around core.closed_loop plants."""

    def __init__(self, **kwargs) -> None:
        super().__init__("plant", **kwargs)
        values = declare(self, PLANT_SPECS)
        self.model = make_model(values["model"], parse_model_parameters(values["model_parameters"] or ()))
        n = self.model.n
        self.x = np.zeros(n) if values["initial_state"] is None else \
            np.asarray(finite_vector(values["initial_state"], n, "initial_state"))
        self.u = np.zeros(self.model.m)
        self.sample_time = float(values["sample_time"])
        self.lockstep = bool(values["lockstep"])
        integration = values["integration"]
        if integration not in INTEGRATIONS:
            raise ConfigError(f"integration must be one of {INTEGRATIONS}, got {integration!r}")
        if integration != "continuous" and not self.lockstep:
            raise ConfigError("integration euler/rk4 steps by sample_time: use it with lockstep: true")
        self.sim = ContinuousPlant(self.model) if integration == "continuous" else \
            DiscretePlant(self.model, self.sample_time, integration)
        self.input_delay = float(values["input_delay"])
        if self.lockstep and self.input_delay > 0 and (integration != "continuous"
                                                        or self.input_delay >= self.sample_time):
            raise ConfigError(f"input_delay {self.input_delay:g} s in lockstep needs integration continuous and a "
                              f"delay below sample_time ({self.sample_time:g} s)")
        #: real time, input_delay > 0: commands arrived and not acting yet, as (monotonic s they act, u [m])
        self.pending: deque[tuple[float, np.ndarray]] = deque()
        self.wait_for_subscribers = int(values["wait_for_subscribers"])
        self.max_steps = int(values["max_steps"])
        self.holding = bool(values["hold_until_command"])
        self.noise_std = float(values["process_noise_std"])
        self.rng = np.random.default_rng(int(values["noise_seed"]))
        self.sim_time_ns = 0
        self.steps = 0
        self.rejected = 0

        self.robot = values["interface"] == "robot"
        self.odom_frame, self.base_frame = values["odom_frame"], values["base_frame"]
        # a planar model (its file's `planar`) has a pose for the views: heading a state (the unicycle's theta) or
        # the direction of motion (the mobile robot's double integrator, which has no heading of its own)
        self.planar = self.model.planar
        self.heading = None if self.planar is None else ("motion" if self.planar.yaw is None else "state")
        self.yaw = 0.0  # the heading of a model heading where it moves: kept while it stands still
        self.pub_odom = self.pub_tf = None
        if self.robot:
            self.robot_map = check_robot_model(self.model)
            self.pub_state = self.pub_odom = self.create_publisher(Odometry, "odom", STREAM_QOS)
            twist_type = TwistStamped if values["cmd_vel_stamped"] else Twist
            self.create_subscription(twist_type, "cmd_vel", self.on_command_received, LATEST_QOS)
        else:
            self.pub_state = self.create_publisher(Float64MultiArray, "state", STREAM_QOS)
            self.create_subscription(Float64MultiArray, "command", self.on_command_received, LATEST_QOS)
            if self.heading is not None:  # the pose of a planar robot, for the views (the controller reads `state`)
                self.pub_odom = self.create_publisher(Odometry, "odom", STREAM_QOS)
        if self.heading is not None and values["publish_tf"]:
            self.create_tf_publishers([] if self.robot else [f for f in values["view_frames"] or [] if f])
        #: the world's map and the simulated lidar (nodes/plant_lidar.py), with a `world`
        self.lidar = SimulatedLidar(self, values) if values["world"] else None
        if values["walkers"] and self.lidar is None:
            raise ConfigError("walkers are seen by the lidar of a world: set world too")
        if self.lockstep:
            self.pub_clock = self.create_publisher(Clock, "/clock", STREAM_QOS)
            # publish x0 once the controller's subscription is matched (then exactly once per command)
            self.heard_since: float | None = None  # monotonic s since the readers are matched
            self.waiting_timer = self.create_timer(0.05, self.publish_initial_when_heard)
        else:
            self.period = 1.0 / float(values["publish_rate"])
            #: wall time the current period began, and how much of it (s) is integrated already
            self.period_started, self.period_done = time.monotonic(), 0.0
            self.timer = self.create_timer(self.period, self.on_timer)
        mode = f"lockstep Ts={self.sample_time:g}s" if self.lockstep else f"real time {1 / self.period:g} Hz"
        self.get_logger().info(
            f"plant ready: model={self.model.name} x0={self.x.tolist()} integration={integration} mode={mode}"
        )

    def create_tf_publishers(self, view_frames: list[str]) -> None:
        """/tf for odom -> base with each state; /tf_static for `view_frames` as odom itself (once, latched)."""
        self.tf_message = tf_message_type()
        if self.tf_message is None:
            self.get_logger().info(f"tf2_msgs is not importable (no ROS installation): no {self.odom_frame} -> "
                                   f"{self.base_frame} on /tf; views place the robot from the odometry on odom")
            return
        self.pub_tf = self.create_publisher(self.tf_message, "/tf", STREAM_QOS)
        if view_frames:
            self.pub_tf_static = self.create_publisher(self.tf_message, "/tf_static", LATCHED_QOS)
            self.pub_tf_static.publish(self.tf_message(transforms=[
                transform_stamped(self.odom_frame, frame, (0.0, 0.0, 0.0), self.stamp()) for frame in view_frames]))

    def stamp(self) -> TimeMsg:
        """Now: the simulated time in lockstep, else the node clock."""
        return Time(nanoseconds=self.sim_time_ns).to_msg() if self.lockstep else self.get_clock().now().to_msg()

    def pose_and_velocity(self) -> tuple[list[float], list[float]]:
        """A planar model's pose [x, y, yaw] and velocity [v, omega] in its base frame (the unicycle's: the
        command in force; a model heading where it moves: its speed and the turn rate of its velocity)."""
        planar = self.planar
        pose = [float(self.x[planar.x]), float(self.x[planar.y]), self.yaw]
        if self.heading == "state":
            pose[2] = float(self.x[planar.yaw])
            return pose, ([0.0, 0.0] if planar.command is None else
                          np.asarray(planar.command(self.x, self.u), float).ravel().tolist())
        vx, vy = (float(self.x[i]) for i in planar.velocity)
        speed, omega = math.hypot(vx, vy), 0.0
        if speed > STILL_SPEED:
            self.yaw = math.atan2(vy, vx)
            ax, ay = np.asarray(self.model.dynamics(self.x, self.u), float).ravel()[list(planar.velocity)]
            omega = (vx * ay - vy * ax) / speed**2
            pose[2] = self.yaw
        return pose, [speed, omega]

    def publish_state(self) -> None:
        if not self.robot:
            self.pub_state.publish(vector_to_array(self.x))
        if self.pub_odom is None:
            return
        stamp = self.stamp()
        pose, velocity = self.pose_and_velocity()
        self.pub_odom.publish(state_to_odometry(pose, velocity, stamp, self.odom_frame, self.base_frame))
        if self.pub_tf is not None:
            self.pub_tf.publish(self.tf_message(transforms=[
                transform_stamped(self.odom_frame, self.base_frame, pose, stamp)]))

    def publish_initial_when_heard(self) -> None:
        """Lockstep: x0, once `wait_for_subscribers` readers have stayed matched for INITIAL_SETTLE s."""
        now = time.monotonic()
        if self.pub_state.get_subscription_count() < self.wait_for_subscribers:
            self.heard_since = None
            return
        self.heard_since = now if self.heard_since is None else self.heard_since
        if now - self.heard_since >= INITIAL_SETTLE:
            self.waiting_timer.cancel()
            self.publish_clock()
            self.publish_state()

    def publish_clock(self) -> None:
        self.pub_clock.publish(Clock(clock=Time(nanoseconds=self.sim_time_ns).to_msg()))

    def on_command_received(self, msg: Float64MultiArray | Twist | TwistStamped, info: dict) -> None:
        """The subscription's callback: two parameters, so that rclpy hands over the message info."""
        self.on_command(msg, info)

    def on_command(self, msg: Float64MultiArray | Twist | TwistStamped, info: dict | None = None) -> None:
        try:
            u = self.robot_map.inputs(self.x, twist_to_command(msg)) if self.robot else \
                array_to_vector(msg, self.model.m, "command")
        except InputError as exc:
            self.rejected += 1
            self.get_logger().warning(f"rejected command: {exc}", throttle_duration_sec=2.0)
            return
        if not self.lockstep:
            arrived = arrival_instant(info)
            if self.input_delay > 0:
                self.pending.append((arrived + self.input_delay, u))
            else:
                self.act(u, arrived)
            return
        previous, self.u, self.holding = self.u, u, False
        if self.max_steps and self.steps >= self.max_steps:
            self.get_logger().info(f"max_steps {self.max_steps} reached: holding", once=True)
            return
        if self.input_delay > 0:  # the previous command acts on for the actuator's delay
            self.x = self.sim.advance(self.x, previous, self.input_delay)
        self.advance(self.sample_time - self.input_delay)
        self.sim_time_ns += round(self.sample_time * 1e9)
        self.publish_clock()
        self.publish_state()

    def act(self, u: np.ndarray, at: float) -> None:
        """Real time: u [m] acts from the monotonic instant `at` (in the current period): the period up to it is
        integrated under the command in force."""
        if self.holding:  # held so far: the plant moves from `at` on
            self.period_done = min(max(at - self.period_started, 0.0), self.period)
        else:
            self.advance_to(at, self.u)
        self.u, self.holding = u, False

    def on_timer(self) -> None:
        now = time.monotonic()
        # a period lasts exactly 1/publish_rate (so a bag replays exactly), unless the timer fired more than half a
        # period off (a stalled process, then a burst of missed ticks): the plant does not pause, it moved for the
        # wall time that passed (a 350 ms stall under load had it stand still, then jump, the loop predicting neither)
        while self.pending and self.pending[0][0] <= now:  # delayed commands acting in this period, at their instant
            at, u = self.pending.popleft()
            self.act(u, at)
        span = self.span(now - self.period_started)
        if not self.holding and span > self.period_done:
            self.advance(span - self.period_done)
        self.period_started, self.period_done = now, 0.0
        self.publish_state()

    def span(self, elapsed: float) -> float:
        """Simulated seconds of a period whose tick came `elapsed` wall seconds after the last: exactly the period,
        unless that is more than half a period off (then the wall time)."""
        return self.period if abs(elapsed - self.period) <= self.period / 2 else elapsed

    def advance_to(self, at: float, u: np.ndarray) -> None:
        """Integrate the current period up to the monotonic instant `at` (at most its nominal end) under u [m],
        without noise or a step count."""
        elapsed = at - self.period_started
        upto = min(elapsed, self.span(elapsed))
        if upto > self.period_done:
            self.x = self.sim.advance(self.x, u, upto - self.period_done)
            self.period_done = upto

    def advance(self, dt: float) -> None:
        self.x = self.sim.advance(self.x, self.u, dt)
        if self.noise_std > 0:
            self.x = self.x + self.rng.normal(0.0, self.noise_std, self.x.shape)
        self.steps += 1


def main(argv: list[str] | None = None) -> int:
    return run_node(PlantNode, argv, "plant", __doc__)
