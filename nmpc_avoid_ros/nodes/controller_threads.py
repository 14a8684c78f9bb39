"""How the controller node always answers: its threads, callback groups and lock, the solve
interrupt, and input logs that cost nothing when throttled.

The node spins on three threads (runner.PoolExecutor), one per callback group:

- the lifecycle services (`transitions`): a transition request is taken while a sample runs. It
  first interrupts the solver worker (core/nlp/worker.py: the call in progress is abandoned at once,
  the sample ends on its fallback), then waits for the sample (`lock`), acts, and lets the worker
  serve again. Measured (test_interrupt_dds): deactivate answered 0.06-0.17 s into a solve whose
  deadline was 40 s away; before, at that deadline;
- the latched inputs `target`, `obstacles`, `goal_pose` (`inputs`): a large MarkerArray is
  deserialised (~0.2 s of Python for 1000 markers, measured) beside a running sample, and applied
  there too, to a copy of the region store that replaces it whole under the lock (apply of 1000
  markers: 0.1-0.3 s, measured), so a sample neither waits for it nor sees half a message;
- everything else, the default group as before: the samples, `state`, the parameter services.

`lock` (reentrant: on_state runs on_sample) keeps the node's state to one callback at a time, as
the single-threaded executor did. SIGINT/SIGTERM interrupt the worker from the signal handler
(runner's on_signal), so the node exits within ~0.3 s of a signal mid-solve, not at the deadline.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import math
import threading
import time
from collections.abc import Iterator

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup

from ..core.errors import RegionError

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
    """Mixin of the controller node (a LifecycleNode with `controller`, `options`, `last_obstacle_issue`)."""

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
        self.last_obstacle_issue = f"{what}: {exc}"
        self.log_throttled("region_issue", "warning", f"{what}: {exc}")
