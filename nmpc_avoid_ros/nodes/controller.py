"""`controller`: the NMPC node. Subscribes to state, target, obstacles; publishes command every sample.

    ros2 run nmpc_avoid_ros controller --ros-args --params-file config/van_der_pol.yaml

A managed (lifecycle) node: parameters are declared at creation; `configure` reads them and builds (or loads
from the cache) the solver, its publishers and the target/obstacle subscriptions; `activate` starts the state
subscription and the samples; `deactivate` stops the samples at once and publishes one `deactivate_command`;
`cleanup`/`shutdown` release the solver and every publisher and subscription. An active node that shuts
down (the transition, SIGINT or SIGTERM, also mid-solve) publishes `deactivate_command` once first and waits
until its readers acknowledged it (controller_threads.py `stop_samples`): a robot is not left driving.
With `autostart` (default) the node walks itself to active, so `ros2 run` alone controls; with
`autostart: false` a lifecycle manager (or `ros2 lifecycle set`) drives it through the standard
lifecycle_msgs services.

Always answers (controller_threads.py): SIGINT/SIGTERM and lifecycle transitions are honoured
mid-solve; input floods do not hold the samples up.

Real-time mode: a timer on the node clock at sample_time (so use_sim_time works) solves on the latest
state; a sample without a new state since the last (lost or late messages) applies the next input of the
last plan (core `coast`) once the command in force has acted its sample_time, counted in `missed_samples`.
Lockstep mode (`lockstep: true`, with the plant in lockstep): each state message is solved once, as it
arrives, as the offline loop does. With the
`feedback` setting each sample ends by preparing the next (core/sample/feedback.py): a prepared plan answers
the next state at once, without a hold.

Diagnostics: one DiagnosticArray per sample on /diagnostics, values as strings; the keys are listed in
docs/reference.md (its **Diagnostics** paragraph). Latency compensation (nodes/command_timing.py,
core/sample/latency.py): `state_age_ms`, `predicted_delay_ms`, `expected_latency_ms`, `late_commands`;
`state` is the measured state, `planned_state` the one the plan starts from.

Stability certificate (core/loop/certificate.py, docs/certificate.md): every sample checks the decrease
of the value function (diagnostics `value_function`, `decrease`, `decrease_bound`, `certificate_margin`,
`certificate`, `certificate_violations`); a violation is WARN, `certificate_error_after` in a row ERROR.
`~/certificate` (std_msgs/Float64MultiArray) carries the same per sample (core.certificate.LAYOUT order).
"""

from __future__ import annotations

import math
import time
import traceback

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.exceptions import ParameterUninitializedException
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from std_msgs.msg import Float64MultiArray
from visualization_msgs.msg import MarkerArray

from ..core.config.settings import NODE_SETTINGS, SETTINGS, NodeSettings
from ..core.errors import ConfigError, InputError, NmpcError, RegionError
from ..core.loop.alarm import AvoidanceCheck
from ..core.loop.certificate import CertificateSample, StabilityCertificate
from ..core.sample.controller import NmpcController
from ..core.sample.step_result import StepResult
from ..ros.conversions import array_to_vector, dds_stamp_age_ns
from ..ros.markers import RegionStore
from ..ros.parameters import (
    LATEST_QOS,
    STREAM_QOS,
    declare,
    finite_vector,
    node_settings_from_values,
    node_settings_specs,
    settings_from_values,
    settings_specs,
)
from ..ros.qos import LatchedSubscription
from .command_timing import CommandTiming
from .controller_goal import GoalKeeping
from .controller_inputs import InputLedger, JudgedInputs, ObstacleIssue
from .controller_io import INTERFACES
from .controller_threads import AlwaysAnswers, locked, move_to_group, transition
from .controller_views import ControllerViews, diagnostic_array
from .runner import PoolExecutor, run_node

#: the node's own parameters (declared in core/config/settings.py NodeSettings)
NODE_SPECS = node_settings_specs()

SUCCESS, FAILURE = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE


class ControllerNode(GoalKeeping, JudgedInputs, AlwaysAnswers, LifecycleNode):
    """Thin managed node: converts messages, calls the core controller, publishes.

    The solver is built once, in `on_configure`; sample callbacks only convert, solve and publish.
    """

    def __init__(self, **kwargs) -> None:
        super().__init__("controller", **kwargs)
        self.setup_threads()
        self.values = declare(self, settings_specs() + NODE_SPECS)
        self.options = node_settings_from_values(self.values)
        self.add_on_set_parameters_callback(self.on_set_parameters)
        self.controller: NmpcController | None = None  # built in on_configure, released in on_cleanup
        self.active = False
        self.timer = self.state_subscription = None
        self.configure_error = ""
        if self.options.autostart:
            if self.trigger_configure() != SUCCESS:
                raise ConfigError(self.configure_error)
            self.trigger_activate()

    # -- lifecycle -----------------------------------------------------------------------------
    def parameter_values(self) -> dict:
        """Current value of every declared parameter (set since start-up by `ros2 param set` included)."""
        values = {}
        for name in self.values:
            try:
                values[name] = self.get_parameter(name).value
            except ParameterUninitializedException:  # declared with a type, never set
                values[name] = None
        return values

    @transition
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Read the parameters, build (or load) the solver, create publishers and latched inputs."""
        try:
            self.configure(self.parameter_values())
        except (NmpcError, ValueError) as exc:
            self.configure_error = str(exc)
            self.get_logger().error(f"configure failed: {exc}")
            self.controller = None
            return FAILURE
        except Exception:  # rclpy would turn it into ERROR without a word: say what broke
            self.configure_error = traceback.format_exc()
            self.get_logger().error(f"configure failed:\n{self.configure_error}")
            self.controller = None
            return FAILURE
        return SUCCESS

    def configure(self, values: dict) -> None:
        self.options = node_settings_from_values(values)
        build_started = time.perf_counter()
        controller = NmpcController(settings_from_values(values))  # the one NLP build
        self.build_seconds = time.perf_counter() - build_started
        model = controller.model
        self.n, self.m, self.p = model.n, model.m, model.p
        s = controller.settings
        self.io = INTERFACES[self.options.interface](self, model, self.options)  # ConfigError: wrong model
        self.store = RegionStore(max_ellipses=s.max_ellipses, max_polygons=s.max_polygons,
                                 max_polygon_vertices=s.max_polygon_vertices,
                                 output_frame_available=controller.nlp.output_frame_available,
                                 max_speed=s.max_obstacle_speed, max_stamp_skew=s.max_obstacle_stamp_skew,
                                 frame_aliases=self.io.marker_frame_aliases)
        self.obstacle_issue = ObstacleIssue()
        self.regions_revision = self.store.revision
        self.target: np.ndarray | None = None
        if self.options.target is not None:
            self.target = np.asarray(finite_vector(self.options.target, self.p, "target"))
        self.controller = controller  # _safe_input checks against its input box
        self.safe_input = self._safe_input(self.options)
        controller.set_safe_input(self.safe_input)  # also a fallback candidate
        self.lockstep = self.options.lockstep  # read-only: fixed for the node's life
        self.certificate = StabilityCertificate(controller)
        self.last_certificate: CertificateSample | None = None
        self.avoidance, self.last_alarm = AvoidanceCheck(controller), None  # inside a region, or planned to be
        self.reset_loop()
        self.last_result: StepResult | None = None
        self.last_command = np.zeros(self.m)
        self.counts = {"samples": 0, "fallbacks": 0, "rejected_inputs": 0, "deadline_overruns": 0, "stale": 0,
                       "states_received": 0, "missed_samples": 0, "stale_episodes": 0, "obstacle_resets": 0,
                       "late_samples": 0}
        self.max_state_gap = 0.0  # s, longest interval between two good states
        self.timing = CommandTiming()  # when the command leaves (latency compensation)
        self.last_stale = 0.0  # s, length of the last stale episode that ended
        self.last_rejected = ""
        self.pub_diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", STREAM_QOS)
        self.views = ControllerViews(self, self.io)
        self.latched_inputs = [LatchedSubscription(self, Float64MultiArray, "target", self.on_target),
                               LatchedSubscription(self, MarkerArray, "obstacles", self.on_obstacles)]
        targets = ["target"] + (["goal_pose"] if self.io.goal_type else [])
        self.ledger = InputLedger([*targets, "obstacles"], kept=targets)
        if self.io.goal_type is not None:
            self.latched_inputs.append(LatchedSubscription(self, self.io.goal_type, "goal_pose", self.on_goal))
        # their own group: a large MarkerArray is deserialised beside a running sample (controller_threads)
        for latched in self.latched_inputs:
            move_to_group(latched.subscriptions, self.inputs)
        self.get_logger().info(
            f"controller ready: model={s.model} N={s.horizon} Ts={s.sample_time}s {s.discretization} "
            f"solver={s.solver} mu={s.mu:g} kappa={s.kappa:g} keep_in={list(s.keep_in)} "
            f"mode={'lockstep' if self.lockstep else 'timer'} "
            f"target={None if self.target is None else self.target.tolist()} "
            f"solver built in {self.build_seconds:.2f} s{self._cache_note()}")
        for warning in self.controller.assumption_warnings:
            self.get_logger().warning(warning)
        self.startup = {"solver_build_s": f"{self.build_seconds:.6f}", "ready_time": f"{time.time():.6f}"}

    def reset_loop(self) -> None:
        """Forget the measured state: after (re)activation the loop waits for a fresh one."""
        self.state: np.ndarray | None = None
        self.state_time: float | None = None  # node-clock seconds of the last good state
        self.state_time_ns: int | None = None  # the same in ns
        self.state_solved = True  # lockstep: has the latest state been answered?
        self.solved_target: np.ndarray | None = None  # y_t of the last solved sample
        self.fresh_state = False  # a good state arrived since the last solve
        self.stale_since: float | None = None  # node-clock time the current stale episode began
        self.state_age = math.nan  # s, age of the state at the start of the last sample
        self.started = self.now()
        self.certificate.reset()  # the next sample's predecessor is not the last one solved

    @transition
    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Start the state subscription and the samples (timer, or each state in lockstep)."""
        self.reset_loop()
        self.state_subscription = self.create_subscription(self.io.state_type, self.io.state_topic, self.on_state,
                                                           LATEST_QOS)
        if not self.lockstep:
            self.timer = self.create_timer(self.controller.settings.sample_time, self.on_sample)
            self.start_late_cover(self.controller.settings.sample_time)
        self.active = True
        self.get_logger().info("controller active")
        return SUCCESS

    @transition
    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop the samples now and publish one `deactivate_command`."""
        self.stop_samples()
        self.get_logger().info("controller inactive")
        return SUCCESS

    @transition
    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Release the solver, the publishers and the latched inputs (back to unconfigured)."""
        self.release()
        return SUCCESS

    @transition
    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop the samples (one `deactivate_command`, delivered: stop_samples) and release everything.
        SIGINT and SIGTERM end here too (runner's on_stop: `exit_safely`)."""
        if self.active:
            self.stop_samples()
        self.release()
        return SUCCESS

    def release(self) -> None:
        if self.controller is None:
            return
        for latched in self.latched_inputs:
            latched.destroy()
        self.io.destroy()
        self.views.destroy()
        self.destroy_publisher(self.pub_diagnostics)
        self.latched_inputs = []
        self.controller = None
        self.get_logger().info("controller released its solver, publishers and subscriptions")

    def _cache_note(self) -> str:
        info = self.controller.nlp.solver_info
        if not info["codegen"]:
            return ""
        return f" (compiled library {'from the cache' if info['cache_hit'] else 'generated and compiled'})"

    # -- inputs ------------------------------------------------------------------------------
    def now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def state_clock(self, info: dict | None = None) -> float:
        """Node-clock time (s) of a state arriving now. Real time: when its publisher wrote it (DDS source
        stamp in `info`; a busy executor must not make it look younger: its age is predicted over), unless
        that is DDS_STAMP_SKEW off. Lockstep on sim time: its sample time, max(clock, last state's +
        sample_time) in ns (the plant's /clock tick, on another topic, may be handled after the state)."""
        clock = self.get_clock()
        now_ns = clock.now().nanoseconds
        age_ns = dds_stamp_age_ns(info, "source_timestamp", now_ns)
        if not clock.ros_time_is_active and age_ns is not None:
            now_ns -= age_ns
        if self.lockstep and clock.ros_time_is_active and self.state_time_ns is not None:
            now_ns = max(now_ns, self.state_time_ns + round(self.controller.settings.sample_time * 1e9))
        self.state_time_ns = now_ns
        return now_ns * 1e-9

    @locked
    def on_state(self, msg: Float64MultiArray | Odometry, info: dict) -> None:
        if not self.active:  # taken by the executor just before a deactivate
            return
        try:
            self.state = self.io.state_of(msg, self.state)
        except InputError as exc:
            self.reject(self.io.state_topic, str(exc))
            return
        now = self.state_clock(info)
        if self.state_time is not None:
            self.max_state_gap = max(self.max_state_gap, now - self.state_time)
        self.state_time = now
        self.state_solved = False
        self.fresh_state = True
        self.counts["states_received"] += 1
        if self.lockstep:
            self.on_sample()

    @locked
    def on_target(self, msg: Float64MultiArray) -> None:
        with self.judging("target"):  # counted; refused with the reason (controller_inputs.py)
            self.set_target(array_to_vector(msg, self.p, "target"), "target")

    @locked
    def on_goal(self, msg: PoseStamped) -> None:
        """A goal pose (RViz "2D Goal Pose"): its position is y_t, in the odometry frame only."""
        with self.judging("goal_pose"):
            self.set_target(self.io.target_of(msg), "goal_pose")

    def set_target(self, target: np.ndarray, source: str) -> None:
        """y_t [p] from the input `source` (`target`, `goal_pose`), in force from the next sample."""
        self.target = target
        self.ledger.applied(source, target)
        self.get_logger().info(f"target y_t = {self.target.tolist()}")
        if self.lockstep and self.active and not self.state_solved:
            self.on_sample()

    def on_obstacles(self, msg: MarkerArray) -> None:
        with self.applied_beside_samples(msg) as report:  # holding the lock once applied
            self.note_obstacles(report)  # controller_inputs.py
            if report.keys_changed:  # once per change of the set, not per message of a moving feed
                self.log_throttled("obstacles", "info", f"obstacles received: {len(self.store)} region(s) stored")

    @locked
    def on_set_parameters(self, params: list) -> SetParametersResult:
        """Validate the whole batch through the settings' declarations; apply it only if all is valid.

        Read-only parameters never get here (ROS refuses them first); parameters not declared by
        the settings (use_sim_time) are rclpy's own and pass through.
        """
        values = {param.name: param.value for param in params}
        settings_changes = {k: v for k, v in values.items() if k in SETTINGS}
        try:
            options = self.options.replace(**{k: v for k, v in values.items() if k in NODE_SETTINGS})
            if self.controller is None:  # unconfigured: checked here, applied by configure
                settings_from_values({**self.parameter_values(), **settings_changes})
                self.options = options
                return SetParametersResult(successful=True)
            settings = self.controller.checked_settings(**settings_changes)  # validated, not applied yet
            safe_input = self._safe_input(options)
            target = None if options.target is None else np.asarray(finite_vector(options.target, self.p, "target"))
            self.controller.update_settings(**settings_changes)  # = settings; a new region_margin repacks the regions
        except ValueError as exc:  # ConfigError is a ValueError; it names the setting and the rule
            return SetParametersResult(successful=False, reason=str(exc))
        self.options, self.safe_input = options, safe_input
        self.store.motion.max_speed = settings.max_obstacle_speed
        self.store.motion.max_stamp_skew = settings.max_obstacle_stamp_skew
        self.controller.set_safe_input(safe_input)
        if "target" in values and target is not None:
            self.target = target
        return SetParametersResult(successful=True)

    def _safe_input(self, options: NodeSettings) -> np.ndarray:
        """The model's safe input [m] (zeros when unset); ValueError for a wrong size or outside the input box."""
        if options.safe_input is None:
            return np.zeros(self.m)
        safe = np.asarray(finite_vector(options.safe_input, self.m, "safe_input"))
        self.controller.check_safe_input(safe)
        return safe

    # -- the sample ----------------------------------------------------------------------------
    @locked
    def on_sample(self) -> None:
        if not self.active:  # taken by the executor just before a deactivate
            return
        now, started, since_tick = self.now(), time.perf_counter(), self.since_tick()  # state_age's instant
        self.counts["samples"] += 1
        if self.target is None or self.state is None:
            # idle until the loop can close: no command, so a waiting plant does not start drifting
            if not self.lockstep:
                waiting = "a target" if self.target is None else "a first state"
                level = DiagnosticStatus.ERROR if self.target is not None and now - self.started > \
                    self.options.state_timeout else DiagnosticStatus.WARN
                self.publish_diagnostics(level, f"idle: waiting for {waiting}", None, 0.0)
            return
        self.state_age = max(0.0, now - self.state_time)  # lockstep: the state may be ahead of the /clock tick
        if not self.lockstep and self.state_age > self.options.state_timeout:
            if self.stale_since is None:
                self.stale_since = self.state_time + self.options.state_timeout  # when it became stale
                self.counts["stale_episodes"] += 1
            self.publish_safe("state stale")
            return
        if self.stale_since is not None:  # a fresh state again: the episode ends
            self.last_stale = now - self.stale_since
            self.stale_since = None
            self.get_logger().info(f"state fresh again after {self.last_stale:.2f} s stale: control resumes")
        if not self.lockstep and not self.fresh_state and self.last_result is not None:
            # no new state since the last solve (lost or late): re-solving the old state would
            # repeat an outdated u(0); the next input of the last plan is what the plan predicted
            # for now (measured in a 1 s blackout on the boundary: max |x1 x2| 2.08 -> 1.85)
            self.counts["missed_samples"] += 1
            result = self.controller.coast()
            self.publish_certificate(self.certificate.skip("no new state"))
            if result is not None:
                self.last_result = result
                self.send_coast(*self.goal_command(result))  # zeros while the goal holds
                self.publish_diagnostics(DiagnosticStatus.WARN, "no new state: next input of the last plan",
                                         result, 0.0)
                return
        regions = self.store.active(now)  # drops expired regions
        if self.store.revision != self.regions_revision:
            try:
                count = len(self.controller.regions)
                self.controller.set_regions(regions)
                if len(regions) != count:  # moving obstacles update every message: log changes of the set only
                    self.get_logger().info(f"{len(regions)} obstacle region(s) active")
            except NmpcError as exc:
                self.reject("obstacles", str(exc))
            self.regions_revision = self.store.revision
        # real time: the state is state_age old now and the command leaves a solve later (core/sample/latency.py)
        compensate = self.options.latency_compensation and not self.lockstep
        self.cover_hold = self.options.command_latency if compensate else 0.0
        # held from the timer's tick (command_timing.py), a prepared plan's answer too: each plan assumes the last
        # command in force until then (one sent at once, then a searched one held: |x2| 2.12 through DDS)
        hold = self.timing.hold_after_tick(self.cover_hold, since_tick)
        ahead = self.timing.predicted(self.state_age, hold) + self.options.transport_delay if compensate else 0.0
        self.cover_due = now + (hold or self.timing.expected())  # the plan assumes the last command until then
        quick = self.timing.predicted(self.state_age, 0.0, True) + self.options.transport_delay \
            if compensate and not self.cover_hold else ahead
        self.solved_target = self.target  # the diagnostics name it: a bag's log times cannot order it and the sample
        result = self.controller.step(self.state, self.target, time=self.state_time, latency=quick,
                                      search_latency=ahead,
                                      command=self.last_command if compensate and self.last_result else None)
        self.state_solved, self.fresh_state, self.last_result = True, False, result
        waited = self.timing.hold_until(started, hold)  # the instant the plan was predicted for
        self.send_command(*self.goal_command(result))  # the late cover's inputs; zeros while the goal holds
        latency = time.perf_counter() - started
        self.timing.record(latency, waited, hold, self.cover_hold, result.answered)
        if compensate:
            self.controller.command_sent(self.state_time + self.state_age + latency + self.options.transport_delay)
        if result.is_fallback:
            self.counts["fallbacks"] += 1
        if result.solve_time > self.controller.settings.sample_time:
            self.counts["deadline_overruns"] += 1
        self.views.publish(result, self.controller.settings, self.controller.regions, self.state_time, self.target)
        level = DiagnosticStatus.WARN if result.is_fallback else DiagnosticStatus.OK
        message = str(result.status)
        if result.region_unavoidable:  # bad input: a region the plan cannot avoid from this state
            level = DiagnosticStatus.ERROR
            message = f"{result.status}: {result.fallback_reason}"
            self.get_logger().error(message, throttle_duration_sec=self.options.log_throttle)
        self.last_alarm = alarm = self.avoidance.check(result, self.state_time)
        if alarm.message:  # never a plain ok while inside a region or planning to enter one
            level, message = max(level, DiagnosticStatus.WARN), f"{message}; {alarm.message}"
        try:
            certificate = self.certificate.observe(result, self.target, self.state_time)
        except RegionError as exc:
            certificate = self.certificate.skip(f"regions not comparable: {exc}")
            self.region_issue("certificate not checked", exc)
        self.publish_certificate(certificate)
        if certificate.violated:
            note = f"certificate violated by {-certificate.margin:.3g} ({certificate.consecutive} in a row)"
            message = f"{message}; {note}"
            if level != DiagnosticStatus.ERROR:
                level = DiagnosticStatus.ERROR if certificate.level == "error" else DiagnosticStatus.WARN
            self.get_logger().warning(f"{result.status}; {note}", throttle_duration_sec=self.options.log_throttle)
        self.publish_diagnostics(*self.goal_note(level, message), result, latency)
        self.controller.prepare(quick)  # the next sample solved ahead, after everything of this one went out

    def publish_safe(self, why: str) -> None:
        """No solve: command the configured safe behaviour and report an ERROR (every sample)."""
        behavior = self.options.stale_behavior
        self.send_command(self.safe_command(behavior))
        self.counts["stale"] += 1
        self.publish_certificate(self.certificate.skip(why))
        self.publish_diagnostics(DiagnosticStatus.ERROR, f"{why}: applying {behavior}", None, 0.0)
        self.get_logger().error(f"{why}: applying {behavior} {self.last_command.tolist()}",
                                throttle_duration_sec=self.options.log_throttle)

    def publish_certificate(self, sample: CertificateSample) -> None:
        self.last_certificate = sample
        self.views.publish_certificate(sample)

    def publish_diagnostics(self, level: bytes, message: str, result: StepResult | None, latency: float) -> None:
        s = self.controller.settings
        values = {**{k: str(v) for k, v in self.counts.items()}, "mu": f"{s.mu:g}", "kappa": f"{s.kappa:g}",
                  "nlp_builds": str(self.controller.nlp_builds), "regions": str(len(self.controller.regions)),
                  "command": str(np.asarray(self.last_command).tolist()),
                  "target": "" if self.solved_target is None else str(self.solved_target.tolist()),
                  "state_age_ms": f"{self.state_age * 1e3:.1f}",
                  "predicted_delay_ms": f"{(result.delay if result else 0.0) * 1e3:.2f}",
                  "expected_latency_ms": f"{self.timing.expected() * 1e3:.2f}",
                  "late_commands": str(self.timing.late_commands),
                  "max_state_gap_ms": f"{self.max_state_gap * 1e3:.1f}",
                  "stale_for_s": f"{0.0 if self.stale_since is None else self.now() - self.stale_since:.3f}",
                  "last_stale_s": f"{self.last_stale:.3f}", "cover_wake_delay_ms": f"{self.cover_wake_delay * 1e3:.1f}",
                  "mismatch_margin": f"{self.controller.mismatch_margin:.6g}",
                  "mismatch_error": f"{self.controller.memory.mismatch.last_error:.6g}",
                  "moving_regions": str(sum(r.moving for r in self.controller.regions)),
                  **self.obstacle_issue.values(), "last_rejected": self.last_rejected,
                  **self.ledger.values(), **self.goal_values(), **self.startup,
                  **({"state_depth": f"{a.state_depth:.6g}", "plan_depth": f"{a.plan_depth:.6g}"}
                     if (a := self.last_alarm) else {})}
        msg = diagnostic_array(self.get_fully_qualified_name(), self.get_clock().now().to_msg(), level, message,
                               values, result, latency, self.state_time, self.last_certificate)
        self.pub_diagnostics.publish(msg)


def main(argv: list[str] | None = None) -> int:
    return run_node(ControllerNode, argv, "controller", __doc__, on_stop=ControllerNode.exit_safely,
                    on_signal=ControllerNode.interrupt, executor_factory=lambda: PoolExecutor(3))
