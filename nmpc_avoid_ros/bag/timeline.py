"""What the controller heard, read back from a bag: its interface, the targets it accepted or refused, the regions.

A bag records every message on the controller's input topics, also those the controller refused. The
timeline here keeps only what the controller took, by the controller's own rules: a `target`
(Float64MultiArray) of exactly p finite values within +-1e12 (core/sample/step_result.validate_vector),
and on the robot interface a `goal_pose` (PoseStamped) in its odometry frame with a finite position
(ros/robot.goal_to_target). The refused ones stay in the timeline with the reason, so a tool can say
what was sent and not tracked. The controller's `target` parameter (recorded with its parameters)
is the target in force before any message.

Regions are fed through the controller's own RegionStore, with the capacities and the frame aliases
of its settings (a robot's markers in its odometry frame are positions), so the regions in force at
any time are those the controller held then.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core.config.settings import ControllerSettings
from ..core.errors import InputError
from ..core.problem.regions import Region
from ..core.sample.step_result import validate_vector
from .mcap_io import Bag

#: the types of the robot interface's odometry and goals (nodes/controller_io.RobotInterface)
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
#: the array interface's state and command
ARRAY_TYPE = "std_msgs/msg/Float64MultiArray"
GOAL_TYPE = "geometry_msgs/msg/PoseStamped"


def topic_named(bag: Bag, suffix: str, node: str | None = None) -> str | None:
    """The bag's topic `suffix` (a relative name): the one in `node`'s namespace when the bag has it,
    else the first /suffix or /<ns>/suffix in name order."""
    if node:
        namespace = node.rsplit("/", 1)[0]
        if f"{namespace}/{suffix}" in bag.topics:
            return f"{namespace}/{suffix}"
    for name in sorted(bag.topics):
        if name == f"/{suffix}" or name.endswith(f"/{suffix}"):
            return name
    return None


@dataclass
class Interface:
    """The controller node's interface to the plant (nodes/controller_io.py) and where that was read.

    `name`: "array" or "robot"; `odom_frame`: the robot's odometry frame (goals and markers in it);
    `initial_target`: the node's `target` parameter (None: unset or not recorded); `source`: the
    controller's recorded parameters, or what was inferred from the bag's topics and why.
    """

    name: str = "array"
    odom_frame: str = "odom"
    initial_target: list[float] | None = None
    source: str = "the controller's recorded parameters"


def controller_interface(bag: Bag, node_params: dict[str, Any] | None) -> Interface:
    """The interface the controller ran with: its recorded parameters, else inferred from the topics: the array
    interface's `command` or `state` with messages (a planar model's plant publishes Odometry on odom for the
    views on the array interface too), else an Odometry topic named odom: the robot interface."""
    params = node_params or {}
    target = params.get("target")
    initial = list(target) if isinstance(target, list | tuple) else None
    if "interface" in params:
        return Interface(str(params["interface"]), str(params.get("odom_frame", "odom")), initial)
    arrays = [t for t in (topic_named(bag, "command"), topic_named(bag, "state"))
              if t is not None and bag.topics.get(t) and bag.types.get(t) == ARRAY_TYPE]
    if arrays:
        return Interface("array", initial_target=initial,
                         source=f"inferred: no recorded interface parameter, and {arrays[0]} carries arrays")
    odom = topic_named(bag, "odom")
    if odom is not None and bag.types.get(odom) == ODOMETRY_TYPE:
        return Interface("robot", str(params.get("odom_frame", "odom")), initial,
                         f"inferred: no recorded interface parameter, and {odom} is Odometry")
    return Interface("array", initial_target=initial,
                     source="inferred: no recorded interface parameter and no Odometry on odom")


@dataclass
class TargetEvent:
    """One target message: log time (ns), topic, the target the controller took ([p]) or None with the reason."""

    time_ns: int
    topic: str
    value: np.ndarray | None
    reason: str | None = None

    @property
    def accepted(self) -> bool:
        return self.value is not None


def _checked(topic: str, check: Any) -> tuple[np.ndarray | None, str | None]:
    try:
        return np.asarray(check(), float), None
    except (InputError, AttributeError, TypeError) as exc:
        return None, str(exc) or f"{topic}: not a valid target"


def target_events(bag: Bag, p: int, interface: Interface, node: str | None = None,
                  with_heading: bool = False) -> list[TargetEvent]:
    """Every target message of the bag by log time, each accepted or refused as the controller would
    (module doc); the `target` parameter first, at time -1 (before any message). `with_heading`: a goal's
    yaw is part of the target, as the controller takes it for a model with an angle output (unicycle_pose)."""
    events = []
    if interface.initial_target is not None:
        value, reason = _checked("target", lambda: validate_vector("target parameter", interface.initial_target, p))
        events.append(TargetEvent(-1, "parameter target", value, reason))
    name = topic_named(bag, "target", node)
    for stamp, msg in bag.topics.get(name, []) if name else []:
        value, reason = _checked(name, lambda m=msg: validate_vector("target", list(m.data), p))
        events.append(TargetEvent(stamp, name, value, reason))
    goal = topic_named(bag, "goal_pose", node) if interface.name == "robot" else None
    if goal is not None and bag.types.get(goal) == GOAL_TYPE:
        from ..ros.robot import goal_to_target  # message-free: reads the decoded fields

        for stamp, msg in bag.topics.get(goal, []):
            value, reason = _checked(goal, lambda m=msg: goal_to_target(m, interface.odom_frame, with_heading))
            if value is not None and len(value) != p:
                value, reason = None, f"goal_pose: a target of {len(value)} values, the model's output has {p}"
            events.append(TargetEvent(stamp, goal, value, reason))
    events.sort(key=lambda e: e.time_ns)
    return events


def targets_at(events: Sequence[TargetEvent], stamps_ns: Sequence[int], p: int) -> np.ndarray:
    """The target in force at each stamp [len(stamps), p]: the last accepted one logged at or before it
    (nan before any)."""
    accepted = [e for e in events if e.accepted]
    times = np.array([e.time_ns for e in accepted], dtype=np.int64)
    out = np.full((len(stamps_ns), p), math.nan)
    for i, stamp in enumerate(stamps_ns):
        k = int(np.searchsorted(times, stamp, side="right")) - 1
        if k >= 0:
            out[i] = accepted[k].value
    return out


@dataclass
class RegionFeed:
    """The obstacle messages of a bag replayed into the controller's RegionStore, queried in time order."""

    messages: list[tuple[int, Any]]
    store: Any
    cursor: int = 0

    def at(self, stamp_ns: int) -> tuple[Region, ...]:
        """The regions in force at `stamp_ns` (log time; calls in non-decreasing time)."""
        while self.cursor < len(self.messages) and self.messages[self.cursor][0] <= stamp_ns:
            time_ns, msg = self.messages[self.cursor]
            self.store.apply(msg, time_ns * 1e-9)
            self.cursor += 1
        return self.store.active(stamp_ns * 1e-9)


def region_feed(bag: Bag, settings: ControllerSettings, interface: Interface, node: str | None = None) -> RegionFeed:
    """A fresh feed of the bag's `obstacles` into a store as the controller's (module doc)."""
    from ..ros.markers import RegionStore  # duck-typed on decoded messages

    aliases = {interface.odom_frame: "output"} if interface.name == "robot" else {}
    store = RegionStore(max_ellipses=settings.max_ellipses, max_polygons=settings.max_polygons,
                        max_polygon_vertices=settings.max_polygon_vertices,
                        output_frame_available=settings.build_model().p >= 2, max_markers_per_message=10**6,
                        max_speed=settings.max_obstacle_speed, max_stamp_skew=settings.max_obstacle_stamp_skew,
                        frame_aliases=aliases)
    name = topic_named(bag, "obstacles", node)
    return RegionFeed(list(bag.topics.get(name, [])) if name else [], store)


def regions_at(bag: Bag, settings: ControllerSettings, interface: Interface, stamps_ns: Sequence[int],
               node: str | None = None) -> list[tuple[Region, ...]]:
    """The regions in force at each of the non-decreasing log times `stamps_ns`."""
    feed = region_feed(bag, settings, interface, node)
    return [feed.at(int(s)) for s in stamps_ns]
