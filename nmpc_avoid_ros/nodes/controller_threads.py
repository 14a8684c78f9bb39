"""How the controller node always answers: its threads, callback groups and lock, the solve
interrupt, and input logs that cost nothing when throttled.

The node spins on three threads (runner.PoolExecutor), one per callback group, and has a fourth:

- the lifecycle services (`transitions`): a transition request is taken while a sample runs. It
  first interrupts the solver worker (core/nlp/worker.py: the call in progress is abandoned at once,
  the sample ends on its fallback), then waits for the sample (`lock`), acts, and lets the worker
  serve again. Measured (test_interrupt_dds): deactivate answered 0.06-0.17 s into a solve whose
  deadline was 40 s away; before, at that deadline;
- the latched inputs `target`, `obstacles`, `goal_pose` (`inputs`): a large MarkerArray is
  deserialised (~0.2 s of Python for 1000 markers, measured) beside a running sample, and applied
  there too, to a copy of the region store that replaces it whole under the lock (apply of 1000
  markers: 0.1-0.3 s, measured), so a sample neither waits for it nor sees half a message;
- everything else, the default group as before: the samples, `state`, the parameter services;
- the late cover (timer mode; a thread of its own, not an executor's timer, which waited for the
  busy executor under a 200 Hz flood): a command every sample even when the sample is late (a
  step may take 10x max_solve_time on a cold start, core/sample/controller.py; a flood of 1000-marker
  arrays competes for the interpreter). Each plan's inputs act one sample_time each from when its
  command left: when the command in force has acted its sample_time (COVER_SLACK past it) and the
  running sample's command is not out by the instant that sample's plan predicted for it (`cover_due`:
  the plan assumes the command in force until then), the cover publishes the plan's next input (the
  shifted plan, as `coast` would; then its u_a), counted in `late_samples`, and so on every sample_time.
  So the plant never runs a plan's input longer than planned beyond what the running plan predicts:
  extending it to the next tick's sample plus a late-cover allowance let the mobile robot reach 1.224
  m/s against its 1.2 m/s limit after a target reversal (one real-time DDS run). Every command of a
  sample re-arms it with the rest of its plan; a safe-behaviour command (stale state, deactivate)
  disarms it. Gaps between two commands stay below one sample period plus the predicted departure and
  the interpreter's latency.

`lock` (reentrant: on_state runs on_sample) keeps the node's state to one callback at a time, as
the single-threaded executor did. SIGINT/SIGTERM interrupt the worker from the signal handler
(runner's on_signal), so the node exits within ~0.3 s of a signal mid-solve, not at the deadline;
once the interrupted sample ended, the node shuts down through its lifecycle (`exit_safely`): an
active node publishes `deactivate_command` once and waits until its readers acknowledged it
(`stop_samples`), so a signal never leaves the plant on the last command.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import math
import sys
import threading
import time
from collections.abc import Iterator

import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.duration import Duration

from ..core.errors import RegionError
from .controller_inputs import ObstacleIssue, ObstacleKind

#: the late cover (see the module docstring): its longest sleep, sample periods / LATE_CHECKS, and how late (s)
#: past its due instant it publishes (the running sample's command leaving within it wins)
LATE_CHECKS = 16
COVER_SLACK = 3e-3
#: s, the cover's shortest sleep (it wakes at the due instant, not in a busy loop)
COVER_MIN_SLEEP = 5e-4
#: s, the interpreter's thread switch interval while the late cover runs (Python's
#: default 0.005; the flood test measured its longest wake-up delay 180 ms at 0.005, 58 ms at 0.001)
COVER_SWITCH_INTERVAL = 0.001

#: s an exiting controller waits at most for its readers to acknowledge the deactivate command (DDS
#: delivers in a few ms on one host; the bound only counts when a reader is gone without a word)
STOP_DELIVERY_TIMEOUT = 0.5
#: lifecycle states from which a shutdown transition starts
SHUTDOWN_FROM = ("unconfigured", "inactive", "active")

#: the standard lifecycle_msgs services of a managed node
LIFECYCLE_SERVICES = ("change_state", "get_state", "get_available_states", "get_available_transitions",
                      "get_transition_graph")


def move_to_group(entities, group) -> None:
    """Serve `entities` (subscriptions, services) in callback `group` instead of the one they were
    created in (LatchedSubscription and rclpy's LifecycleNode, which does not pass its mixin's
    callback_group on, create theirs in the default group)."""
    for entity in entities:
        entity.callback_group = group
        group.add_entity(entity)


def locked(method):
    """Run the callback holding the node's lock: a lifecycle transition (another thread) waits for it."""

    @functools.wraps(method)
    def run_locked(self, *args, **kwargs):
        with self.lock:
            return method(self, *args, **kwargs)

    return run_locked


def transition(method):
    """A lifecycle transition: interrupt a solve in progress, wait for its sample, act, serve solves again."""

    @functools.wraps(method)
    def run_transition(self, *args, **kwargs):
        worker = self.solve_worker()
        if worker is not None:
            worker.interrupt()
        try:
            with self.lock:
                return method(self, *args, **kwargs)
        finally:
            if worker is not None and not self.stopping:
                worker.resume()

    return run_transition


class AlwaysAnswers:
    """Mixin of the controller node (a LifecycleNode with `controller`, `options`, `io`, `counts`,
    `last_result`, `safe_input`, `obstacle_issue`, `timing`)."""

    def setup_threads(self) -> None:
        """Right after LifecycleNode.__init__: the lock, the flags, the callback groups."""
        #: one sample (or input callback) or one transition at a time
        self.lock = threading.RLock()
        #: SIGINT/SIGTERM seen (`interrupt`): the worker stays interrupted until the node exits
        self.stopping = False
        self._logged: dict[str, float] = {}  # log_throttled: monotonic s each kind was last logged
        self.transitions = MutuallyExclusiveCallbackGroup()
        move_to_group([s for s in self.services if s.srv_name.rsplit("/", 1)[-1] in LIFECYCLE_SERVICES],
                      self.transitions)
        #: the latched inputs' readers: one at a time, beside the samples (configure moves them here)
        self.inputs = MutuallyExclusiveCallbackGroup()
        #: the late cover's thread and its stop flag (timer mode, while active)
        self._late_thread: threading.Thread | None = None
        self._late_stop = threading.Event()
        # the command publication and the cover's state, one thread at a time (never held across a step)
        self._command_lock = threading.Lock()
        self._cover_inputs = None  # the rest of the plan in force (inputs [m]), None: no cover
        self._last_command_at = -math.inf  # node-clock s of the last command published
        #: s a sample holds its command back on purpose (command_latency)
        self.cover_hold = 0.0
        #: node-clock s at which the running sample's plan assumed its command leaves (the cover waits for it)
        self.cover_due = -math.inf
        #: longest delay, s, of the late cover's wake-ups beyond its period (what it could not control)
        self.cover_wake_delay = 0.0

    def start_late_cover(self, sample_time: float) -> None:
        """Timer mode, on activate: check every sample_time / LATE_CHECKS (wall clock; the gap itself is
        measured on the node clock) for a sample running late."""
        self._late_stop = threading.Event()
        period, stop = sample_time / LATE_CHECKS, self._late_stop
        # the cover must get the interpreter lock soon after it wakes, while the executor threads parse a
        # flood of messages: a shorter switch interval than Python's 5 ms (process-wide)
        sys.setswitchinterval(min(sys.getswitchinterval(), COVER_SWITCH_INTERVAL))

        def watch() -> None:
            while True:
                begin = time.monotonic()
                sleep = min(max(self.cover_wait(), COVER_MIN_SLEEP), period)
                if stop.wait(sleep):
                    return
                # how late this thread woke (the interpreter lock or the CPU were elsewhere): diagnostics
                self.cover_wake_delay = max(self.cover_wake_delay, time.monotonic() - begin - sleep)
                try:
                    self.on_late_check()
                except Exception as exc:  # noqa: BLE001 - a node being torn down; the cover must not die silently
                    if not (stop.is_set() or self.stopping):
                        self.log_throttled("late_cover", "warning", f"late cover: {exc!r}")

        self._late_thread = threading.Thread(target=watch, name="late_cover", daemon=True)
        self._late_thread.start()

    def stop_late_cover(self) -> None:
        self._late_stop.set()
        if self._late_thread is not None and self._late_thread is not threading.current_thread():
            self._late_thread.join(timeout=1.0)
        self._late_thread = None
        with self._command_lock:
            self._cover_inputs = None

    def send_command(self, u: np.ndarray, next_inputs: np.ndarray | None = None) -> None:
        """Publish the command u [m] and keep it as the last one; `next_inputs` [k, m] (the rest of the
        plan it comes from) arm the late cover, None disarms it."""
        with self._command_lock:
            self.io.publish_command(u)
            self._last_command_at = self.now()
            self._cover_inputs = None if next_inputs is None or len(next_inputs) == 0 else list(next_inputs)
        self.last_command = np.asarray(u, float)

    def stop_samples(self) -> None:
        """Stop the samples and publish `deactivate_command` once, then wait (at most
        STOP_DELIVERY_TIMEOUT) until every matched reader acknowledged it: a process about to exit
        would otherwise take the message with it. Called holding the lock (a transition): no sample
        runs; one already taken by the executor finds `active` False and does nothing."""
        self.active = False
        self.stop_late_cover()  # before the timer it reads goes
        if self.timer is not None:
            self.destroy_timer(self.timer)
            self.timer = None
        if self.state_subscription is not None:
            self.destroy_subscription(self.state_subscription)
            self.state_subscription = None
        u = self.safe_command(self.options.deactivate_command)
        self.send_command(u)
        delivered = self.io.publisher.wait_for_all_acked(Duration(seconds=STOP_DELIVERY_TIMEOUT))
        self.get_logger().info(f"samples stopped: sent {self.options.deactivate_command} {u.tolist()}"
                               + ("" if delivered else f", not acknowledged by every reader in "
                                  f"{STOP_DELIVERY_TIMEOUT:g} s"))

    def exit_safely(self) -> None:
        """runner's on_stop (after SIGINT/SIGTERM; no callback runs any more): the lifecycle shutdown,
        so an active node publishes its deactivate command (delivered) before it goes away."""
        if self._state_machine.current_state[1] in SHUTDOWN_FROM:
            self.trigger_shutdown()

    def safe_command(self, behavior: str) -> np.ndarray:
        """The command [m] of a stale-state or deactivate `behavior` (one of STALE_BEHAVIORS)."""
        if behavior == "hold_steady" and self.last_result is not None and np.all(np.isfinite(self.last_result.u_a)):
            return np.asarray(self.last_result.u_a, float)
        if behavior == "last":
            return np.asarray(self.last_command, float)
        if behavior == "safe_input":
            return np.asarray(self.safe_input, float)
        return np.zeros(self.m)

    def since_tick(self) -> float:
        """s since the sample timer's last tick (0 without a timer: lockstep, or not active)."""
        until_next = None if self.timer is None else self.timer.time_until_next_call()
        if until_next is None:
            return 0.0
        period = self.controller.settings.sample_time
        return min(max(period - until_next * 1e-9, 0.0), period)

    def cover_due_at(self) -> float:
        """Node-clock s at which the late cover publishes the plan's next input unless a command leaves first:
        the command in force has acted its sample_time and the running sample's predicted departure has passed,
        plus COVER_SLACK."""
        return max(self._last_command_at + self.controller.settings.sample_time, self.cover_due) + COVER_SLACK

    def cover_wait(self) -> float:
        """s until the cover may have to publish (inf without a plan in force)."""
        if self._cover_inputs is None:
            return math.inf
        return self.cover_due_at() - self.now()

    def send_coast(self, u: np.ndarray, next_inputs: np.ndarray | None) -> None:
        """A coasting sample's command (`send_command`'s arguments), held until the command in force has acted its
        sample_time: the instant its plan assumed for the next input. At the tick it left command_latency early (the
        crane of docs/own_model.md, 0.12 s of a 0.2 s sample: its rope swung to 0.168 rad past the 0.15 bound after
        one sample without a state). The late cover waits meanwhile (a hold that woke 3 ms late let it publish the
        same input first: two commands in one sample)."""
        due = self._last_command_at + self.controller.settings.sample_time  # node clock
        self.cover_due = math.inf
        try:
            self.timing.hold_until(time.perf_counter(), due - self.now())
            self.send_command(u, next_inputs)
        finally:
            self.cover_due = due

    def on_late_check(self) -> None:
        """The late cover's check: a plan in force whose current input has acted its sample_time, and the running
        sample's command not out by its predicted departure: the plan's next input now. Takes only the command
        lock."""
        with self._command_lock:
            inputs = self._cover_inputs
            if inputs is None or self.stopping or not self.active or self.now() < self.cover_due_at():
                return
            u = inputs.pop(0) if len(inputs) > 1 else inputs[0]  # the plan's inputs, then its last (u_a)
            self.io.publish_command(u)
            self._last_command_at = self.now()
            self.last_command = np.asarray(u, float)
            self.counts["late_samples"] += 1
        self.log_throttled("late", "warning", "a sample is late: applying the next input of the last plan")

    @contextlib.contextmanager
    def applied_beside_samples(self, msg) -> Iterator:
        """Apply the MarkerArray `msg` to a copy of `store` without the lock, swap the copy in and
        yield the ApplyReport holding the lock. A transition that replaced the store meanwhile
        wins: the message went to the old one (the report is still yielded, for the counters)."""
        with self.lock:
            original = self.store
            store = copy.deepcopy(original)
        report = store.apply(msg, self.now())
        with self.lock:
            if self.store is original:
                # run-time parameters may have changed the original's motion limits meanwhile
                store.motion.max_speed, store.motion.max_stamp_skew = (original.motion.max_speed,
                                                                       original.motion.max_stamp_skew)
                self.store = store
                if report.changed:
                    self.regions_revision = -1  # the next sample repacks (a new store's count may repeat)
            yield report

    def solve_worker(self):
        """The controller's solver worker (core/nlp/worker.py), None when unconfigured."""
        controller = getattr(self, "controller", None)
        return None if controller is None else getattr(controller, "worker", None)

    def interrupt(self) -> None:
        """SIGINT/SIGTERM (runner's on_signal, in the signal handler): abandon a solve in progress now,
        and every later one, so the sample ends on its fallback and the node exits. Takes no lock."""
        self.stopping = True
        worker = self.solve_worker()
        if worker is not None:
            worker.interrupt()

    def log_throttled(self, kind: str, level: str, message: str) -> None:
        """Log `message` at `level` ("info" or "warning") at most once every log_throttle s per `kind`.

        Checked here, before rclpy is called: rclpy's own throttle looks up the caller's source
        first (inspect, ~2 ms a call, measured), so 1000 rejected markers of one MarkerArray cost
        the node 1.3 s even when all but one were throttled; now ~0.1 s."""
        now = time.monotonic()
        if now - self._logged.get(kind, -math.inf) < self.options.log_throttle:
            return
        self._logged[kind] = now
        if level == "info":  # one call per severity: rclpy refuses two severities from one line
            self.get_logger().info(message)
        else:
            self.get_logger().warning(message)

    def region_issue(self, what: str, exc: RegionError) -> None:
        """A stored region that a view or the certificate cannot move to another time: Polygon.at
        raises for a moving polygon of huge coordinates whose translated vertices merge in floating
        point (met in test_flood_dds: "a polygon needs at least 3 distinct vertices, got 2")."""
        self.obstacle_issue = ObstacleIssue(ObstacleKind.REGION, what, str(exc))
        self.log_throttled("region_issue", "warning", f"{what}: {exc}")
