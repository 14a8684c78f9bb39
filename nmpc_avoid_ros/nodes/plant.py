"""`plant`: simulates a model under zero-order hold of the last command and publishes `state`.

    ros2 run nmpc_avoid_ros plant --ros-args --params-file config/van_der_pol.yaml

Real time: a timer at `publish_rate` Hz integrates the continuous dynamics over each period and publishes
the state. A command acts from the moment it arrives, as on a real plant: the period it arrives in is
integrated under the previous command up to its arrival and under the new one from there (each period
lasts exactly 1 / publish_rate of simulated time, so a bag's states and commands replay exactly:
evaluation/recorded_timing.py recovers each command's arrival within its period from the states).
Lockstep (`lockstep: true`): the plant publishes x0 once the controller listens, then after each
command advances exactly one `sample_time`, publishes `/clock` and the new state; a closed loop
runs as fast as the controller solves and reproduces the offline loop.

`interface: robot` (a model with states x, y, theta and inputs v, omega, e.g. `unicycle`): the
plant stands for a differential-drive base: it publishes nav_msgs/Odometry on `odom` (pose in
`odom_frame`, twist in `base_frame`, stamped with the node clock or, in lockstep, the simulated
time) and takes geometry_msgs/TwistStamped (or Twist, `cmd_vel_stamped: false`) on `cmd_vel`.

A plain node, not a lifecycle one: it stands for hardware, which a real robot's driver runs and
this package does not manage.
"""

from __future__ import annotations

import time

import numpy as np
from geometry_msgs.msg import Twist, TwistStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import ParameterType
from rclpy.node import Node
from rclpy.time import Time
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64MultiArray

from ..core.config.settings import INTERFACES
from ..core.errors import ConfigError, InputError
from ..core.loop.closed_loop import ContinuousPlant, DiscretePlant
from ..core.problem.models import MODELS, make_model
from ..ros.conversions import array_to_vector, vector_to_array
from ..ros.parameters import LATEST_QOS, STREAM_QOS, ParamSpec, declare, finite_vector
from ..ros.robot import check_robot_model, state_to_odometry, twist_to_command
from .runner import run_node

INTEGRATIONS = ("continuous", "euler", "rk4")

PLANT_SPECS = [
    ParamSpec("model", "van_der_pol", "model to simulate", ParameterType.PARAMETER_STRING, read_only=True,
              choices=tuple(sorted(MODELS))),
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
    ParamSpec("wait_for_subscribers", 1, "lockstep: publish x0 once this many `state` subscribers are matched "
              "(controller, recorder, ...)", ParameterType.PARAMETER_INTEGER, read_only=True, int_range=(1, 1000)),
    ParamSpec("max_steps", 0, "lockstep: advance at most this many samples, then hold and publish nothing more "
              "(0: no limit); a run of known length ends quiet, so stopping the nodes loses no message in flight",
              ParameterType.PARAMETER_INTEGER, read_only=True, int_range=(0, 10**9)),
    ParamSpec("hold_until_command", True, "real time: keep x0 until the first command arrives (the loop is closed)",
              ParameterType.PARAMETER_BOOL, read_only=True),
    ParamSpec("process_noise_std", 0.0, "std of Gaussian noise added to the state per step (state units)",
              ParameterType.PARAMETER_DOUBLE, read_only=True, float_range=(0.0, 1e3)),
    ParamSpec("noise_seed", 0, "seed of the process noise", ParameterType.PARAMETER_INTEGER, read_only=True),
    ParamSpec("interface", "array", "array: Float64MultiArray on state/command; robot: Odometry on odom, "
              "TwistStamped/Twist on cmd_vel", ParameterType.PARAMETER_STRING, read_only=True,
              choices=INTERFACES),
    ParamSpec("cmd_vel_stamped", True, "robot interface: cmd_vel is TwistStamped (else Twist)",
              ParameterType.PARAMETER_BOOL, read_only=True),
    ParamSpec("odom_frame", "odom", "robot interface: header.frame_id of the odometry",
              ParameterType.PARAMETER_STRING, read_only=True),
    ParamSpec("base_frame", "base_link", "robot interface: child_frame_id of the odometry",
              ParameterType.PARAMETER_STRING, read_only=True),
]


class PlantNode(Node):
    """Thin node around core.closed_loop plants."""

    def __init__(self, **kwargs) -> None:
        super().__init__("plant", **kwargs)
        values = declare(self, PLANT_SPECS)
        self.model = make_model(values["model"])
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
        self.wait_for_subscribers = int(values["wait_for_subscribers"])
        self.max_steps = int(values["max_steps"])
        self.holding = bool(values["hold_until_command"])
        self.noise_std = float(values["process_noise_std"])
        self.rng = np.random.default_rng(int(values["noise_seed"]))
        self.sim_time_ns = 0
        self.steps = 0
        self.rejected = 0

        self.robot = values["interface"] == "robot"
        if self.robot:
            check_robot_model(self.model)
            self.odom_frame, self.base_frame = values["odom_frame"], values["base_frame"]
            self.pub_state = self.create_publisher(Odometry, "odom", STREAM_QOS)
            twist_type = TwistStamped if values["cmd_vel_stamped"] else Twist
            self.create_subscription(twist_type, "cmd_vel", self.on_command, LATEST_QOS)
        else:
            self.pub_state = self.create_publisher(Float64MultiArray, "state", STREAM_QOS)
            self.create_subscription(Float64MultiArray, "command", self.on_command, LATEST_QOS)
        if self.lockstep:
            self.pub_clock = self.create_publisher(Clock, "/clock", STREAM_QOS)
            # publish x0 once the controller's subscription is matched (then exactly once per command)
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

    def publish_state(self) -> None:
        if not self.robot:
            self.pub_state.publish(vector_to_array(self.x))
            return
        stamp = Time(nanoseconds=self.sim_time_ns).to_msg() if self.lockstep else self.get_clock().now().to_msg()
        self.pub_state.publish(state_to_odometry(self.x, self.u, stamp, self.odom_frame, self.base_frame))

    def publish_initial_when_heard(self) -> None:
        if self.pub_state.get_subscription_count() >= self.wait_for_subscribers:
            self.waiting_timer.cancel()
            self.publish_clock()
            self.publish_state()

    def publish_clock(self) -> None:
        self.pub_clock.publish(Clock(clock=Time(nanoseconds=self.sim_time_ns).to_msg()))

    def on_command(self, msg: Float64MultiArray | Twist | TwistStamped) -> None:
        previous = self.u
        try:
            self.u = twist_to_command(msg) if self.robot else array_to_vector(msg, self.model.m, "command")
        except InputError as exc:
            self.rejected += 1
            self.get_logger().warning(f"rejected command: {exc}", throttle_duration_sec=2.0)
            return
        if not self.lockstep:
            if self.holding:  # held so far: the plant moves from now on
                self.period_done = min(time.monotonic() - self.period_started, self.period)
            else:
                self.advance_to_now(previous)  # the period so far under the command that was in force
        self.holding = False
        if self.lockstep:
            if self.max_steps and self.steps >= self.max_steps:
                self.get_logger().info(f"max_steps {self.max_steps} reached: holding", once=True)
                return
            self.advance(self.sample_time)
            self.sim_time_ns += round(self.sample_time * 1e9)
            self.publish_clock()
            self.publish_state()

    def on_timer(self) -> None:
        now = time.monotonic()
        # a period lasts exactly 1/publish_rate (so a bag replays exactly), unless the timer fired more than half a
        # period off (a stalled process, then a burst of missed ticks): the plant does not pause, it moved for the
        # wall time that passed (a 350 ms stall under load had it stand still, then jump, the loop predicting neither)
        span = self.span(now - self.period_started)
        if not self.holding and span > self.period_done:
            self.advance(span - self.period_done)
        self.period_started, self.period_done = now, 0.0
        self.publish_state()

    def span(self, elapsed: float) -> float:
        """Simulated seconds of a period whose tick came `elapsed` wall seconds after the last: exactly the period,
        unless that is more than half a period off (then the wall time)."""
        return self.period if abs(elapsed - self.period) <= self.period / 2 else elapsed

    def advance_to_now(self, u: np.ndarray) -> None:
        """Integrate the current period up to now (at most its nominal end) under u [m], without noise or a step
        count."""
        elapsed = time.monotonic() - self.period_started
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
