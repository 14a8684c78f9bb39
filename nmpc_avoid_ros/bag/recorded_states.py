"""The truth of a run: every plant state the bag recorded, at the plant's own rate, and every command.

The controller's samples see the plant once per sample; the plant publishes its state at its own
rate (`state`, or `odom` on the robot interface), and between two samples it may leave the set the
controller keeps it in. Here each recorded state is read back (the array's n values; an Odometry's
x, y and yaw, unwrapped) and placed on the controller's clock:

* anchors: the recorded state each sample solved on (equal to the diagnostic's `state`, the measured
  one also where the controller planned from it predicted forward; the last such message logged before
  that diagnostic);
* each recorded state's time is its anchor's controller time plus the log time elapsed since the
  anchor (moving regions are evaluated there); the command in force is the anchor sample's, or a
  later sample's whose diagnostic was logged before the state (a sample whose state was not found);
* the states checked are those from the first sample's state to one sample time after the last
  sample's (what the plant did while the controller drove it).

A bag in which no recorded state equals a sample's (e.g. a controller that solved on a predicted
state) falls back to the recorder's clock over the same span of diagnostics, and says so.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field

import numpy as np

from ..core.errors import InputError
from ..core.problem.models import Model
from .analysis import RecordedRun
from .mcap_io import Bag
from .timeline import ODOMETRY_TYPE, topic_named

#: the robot interface's command type names (nodes/controller_io.RobotInterface)
TWIST_TYPES = ("geometry_msgs/msg/TwistStamped", "geometry_msgs/msg/Twist")


@dataclass
class RecordedStates:
    """The plant's recorded states in the controller's span (module doc).

    `topic`: where they were read; `log_ns` [J] their log times; `t` [J] s on the controller's clock
    (run.times's); `x` [J, n]; `sample` [J] the sample whose command held (its anchor); `skipped`:
    messages of the wrong size or with NaN/inf; `notes`: how the span and the clock were found.
    """

    topic: str
    log_ns: np.ndarray
    t: np.ndarray
    x: np.ndarray
    sample: np.ndarray
    skipped: int = 0
    notes: list[str] = field(default_factory=list)

    @property
    def rate_hz(self) -> float | None:
        """The median rate of the recorded states (None with fewer than 2)."""
        gaps = np.diff(self.log_ns)
        gaps = gaps[gaps > 0]
        return float(1e9 / np.median(gaps)) if len(gaps) else None


def _odometry_states(messages: list) -> tuple[list[int], list[np.ndarray], int]:
    from ..ros.robot import unwrap, yaw_of  # message-free: reads the decoded fields

    stamps, states, skipped, theta = [], [], 0, None
    for stamp, msg in messages:
        try:
            position = msg.pose.pose.position
            theta = unwrap(yaw_of(msg.pose.pose.orientation), theta)
            x = np.array([float(position.x), float(position.y), theta])
        except (InputError, AttributeError):
            skipped += 1
            continue
        if np.all(np.isfinite(x)):
            stamps.append(stamp)
            states.append(x)
        else:
            skipped += 1
    return stamps, states, skipped


def _array_states(messages: list, n: int) -> tuple[list[int], list[np.ndarray], int]:
    stamps, states, skipped = [], [], 0
    for stamp, msg in messages:
        x = np.array([float(v) for v in getattr(msg, "data", [])])
        if x.shape == (n,) and np.all(np.isfinite(x)):
            stamps.append(stamp)
            states.append(x)
        else:
            skipped += 1
    return stamps, states, skipped


def _anchors(stamps: np.ndarray, states: np.ndarray, run: RecordedRun) -> list[tuple[int, int]]:
    """(sample k, recorded index j) of every sample whose state was recorded, j non-decreasing in k."""
    index: dict[bytes, list[int]] = {}
    for j, x in enumerate(states):
        index.setdefault(x.tobytes(), []).append(j)
    out: list[tuple[int, int]] = []
    logged = run.log_times_ns if run.log_times_ns is not None else np.full(len(run.x), np.iinfo(np.int64).max)
    for k, x in enumerate(np.asarray(run.x, float)):
        hits = index.get(x.tobytes(), [])
        first = bisect.bisect_left(hits, out[-1][1] if out else 0)  # indices and stamps both ascend
        if first == len(hits):
            continue
        last = bisect.bisect_right(hits, logged[k], lo=first, key=lambda j: stamps[j]) - 1
        out.append((k, hits[last] if last >= first else hits[first]))
    return out


def recorded_states(bag: Bag, run: RecordedRun, model: Model, sample_time: float) -> RecordedStates | None:
    """The plant's recorded states while the controller drove it (module doc); None when the bag has none."""
    robot = run.interface.name == "robot"
    topic = topic_named(bag, "odom" if robot else "state", run.controller_node)
    if topic is None or not bag.topics.get(topic):
        return None
    if robot and bag.types.get(topic) == ODOMETRY_TYPE:
        stamps, states, skipped = _odometry_states(bag.topics[topic])
    else:
        stamps, states, skipped = _array_states(bag.topics[topic], model.n)
    if not states:
        return None
    log_ns, x = np.array(stamps, dtype=np.int64), np.array(states)
    notes = []
    anchors = _anchors(log_ns, x, run)
    times = run.times if run.times is not None else np.asarray(run.t, float)
    if anchors:
        ks = np.array([k for k, _ in anchors])
        js = np.array([j for _, j in anchors])
        owner = np.clip(np.searchsorted(js, np.arange(len(x)), side="right") - 1, 0, None)
        t = times[ks[owner]] + (log_ns - log_ns[js[owner]]) * 1e-9
        keep = (np.arange(len(x)) >= js[0]) & (t <= times[-1] + sample_time + 1e-9)
        sample = ks[owner]
        if run.log_times_ns is not None:  # a sample whose state was not found: its diagnostic's log time
            logged = np.clip(np.searchsorted(run.log_times_ns, log_ns, side="right") - 1, 0, None)
            sample = np.maximum(sample, logged)
        notes.append(f"{len(anchors)} of {len(run.x)} samples' states found among the recorded ones; the states "
                     f"from the first sample's to {sample_time:g} s after the last sample's")
    else:
        logged = run.log_times_ns if run.log_times_ns is not None else np.asarray(times) * 1e9
        t = log_ns * 1e-9
        keep = (log_ns >= logged[0] - sample_time * 1e9) & (log_ns <= logged[-1] + sample_time * 1e9)
        sample = np.clip(np.searchsorted(np.asarray(logged), log_ns, side="right") - 1, 0, None)
        notes.append("no recorded state equals a sample's: the states logged from one sample time before the first "
                     "diagnostic to one after the last, on the recorder's clock")
    if not np.any(keep):
        return None
    return RecordedStates(topic, log_ns[keep], t[keep], x[keep], sample[keep], skipped, notes)


def recorded_commands(bag: Bag, run: RecordedRun, m: int) -> tuple[str, np.ndarray]:
    """(source, commands [C, m]) as the plant received them: the `command` (array) or `cmd_vel` (robot) topic,
    else the commands the samples' diagnostics report."""
    robot = run.interface.name == "robot"
    topic = topic_named(bag, "cmd_vel" if robot else "command", run.controller_node)
    rows = []
    for _, msg in bag.topics.get(topic, []) if topic else []:
        if robot and bag.types.get(topic) in TWIST_TYPES:
            twist = getattr(msg, "twist", msg)
            rows.append([float(twist.linear.x), float(twist.angular.z)])
        elif not robot:
            rows.append([float(v) for v in getattr(msg, "data", [])])
    rows = [r for r in rows if len(r) == m and all(math.isfinite(v) for v in r)]
    if rows:
        return topic, np.array(rows)
    return "the samples' diagnostics (no recorded command topic)", np.asarray(run.u, float)
