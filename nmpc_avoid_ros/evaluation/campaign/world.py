"""Campaign families `world` (`campaign --world N`): the unicycle in random rooms, seeing only its lidar; and
`bicycle_world` (`--bicycle-world N`): the car-like robot (config/bicycle_world.yaml) in the same rooms, to goal poses.

A scenario is a walled room (6-12 m by 5-10 m, 0.1 m walls, 0.05 m cells), 0-4 square pillars (0.3-0.6 m)
and 0-4 walkers (discs of radius 0.25 m walking straight at 0.2-0.6 m/s across the room, held by its walls),
the robot at rest at least 1 m from walls and pillars, the goal likewise and at least 3 m away (for a model whose
output is a pose, the car's, with a heading drawn in [-pi, pi) after everything else). Each sample
runs what the world launch runs (launch/world.launch.py), offline: a scan of the room and the walkers where
they are at k Ts (core/loop/world.py: `BEAMS` beams to `RANGE_MAX`) -> the perception of the `obstacles`
node (core/perception: fitted circles and walls, tracked, with velocities) -> the controller
(config/unicycle_world.yaml or config/bicycle_world.yaml, its body `footprint_radius`) -> the plant, whose
commands act ACTUATOR_DELAY late.

A run's record: `reached` (the robot within GOAL_TOLERANCE of the goal, and for a pose within HEADING_TOLERANCE of
its heading the short way round, from some sample on, to the end) and
`time_to_goal` (s), `collision` (the body enters a wall, a pillar or a walker between the samples: the
plant integrated in pieces of Ts / 10) with `min_body_clearance` (m: the least distance of the body to
an occupied cell or a walker; < 0 inside), `perception_ms` and `solve_ms` per sample, `fallbacks`. A room
where the goal cannot be reached (pillars closing the way) is not drawn: the pillars keep a 1.5 m clear
corridor along the straight line from start to goal.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ...core.config.settings import ControllerSettings
from ...core.loop.closed_loop import DelayedPlant, make_plant, run_closed_loop
from ...core.loop.metrics import time_stats
from ...core.loop.world import FREE, OCCUPIED, World
from ...core.perception.grid import Grid
from ...core.perception.scan import Pose2D, ScanGeometry
from ...core.perception.sensing import Perception, PerceptionSettings
from ...core.problem.models import Model
from ...core.problem.regions import Region
from ...core.sample.status import StepStatus

RESOLUTION = 0.05
WALL = 0.1
BEAMS, RANGE_MAX = 360, 6.0
WALKER_RADIUS = 0.25
#: m, the goal counts as reached within this (the config's goal_tolerance 0.1 plus its hysteresis)
GOAL_TOLERANCE = 0.15
#: rad, a goal pose's heading counts as reached within this (the config's goal_tolerance 0.1 plus its hysteresis)
HEADING_TOLERANCE = 0.2
#: m, start and goal keep this from walls and pillars; the pillars keep CORRIDOR / 2 from the straight way
CLEARANCE, CORRIDOR = 1.0, 1.5
#: s, the robot's actuator delay (the plant node's input_delay in config/unicycle_world.yaml; the controller's
#: input_delay predicts it: `--sweep input_delay=0.05,0` compares compensation on and off)
ACTUATOR_DELAY = 0.05


def world_scenario(rng: np.random.Generator, settings: ControllerSettings, model: Model) -> dict[str, Any]:
    """A room, its pillars and walkers, start (at rest, facing a random way) and goal (module doc)."""
    width, height = rng.uniform(6.0, 12.0), rng.uniform(5.0, 10.0)
    low, high = np.array([-width / 2, -height / 2]), np.array([width / 2, height / 2])
    inner_low, inner_high = low + WALL + CLEARANCE, high - WALL - CLEARANCE
    while True:
        start, goal = rng.uniform(inner_low, inner_high), rng.uniform(inner_low, inner_high)
        if np.linalg.norm(goal - start) >= 3.0:
            break
    pillars = []
    for _ in range(int(rng.integers(0, 5))):
        for _attempt in range(50):
            size, centre = rng.uniform(0.3, 0.6), rng.uniform(low + WALL + 0.5, high - WALL - 0.5)
            far = min(np.linalg.norm(centre - start), np.linalg.norm(centre - goal)) > CLEARANCE + size
            if far and _segment_distance(centre, start, goal) > CORRIDOR / 2 + size:
                pillars.append([*centre.tolist(), float(size)])
                break
    walkers = []
    for _ in range(int(rng.integers(0, 5))):
        centre = rng.uniform(inner_low, inner_high)
        heading, speed = rng.uniform(0.0, 2 * math.pi), rng.uniform(0.2, 0.6)
        if np.linalg.norm(centre - start) > 1.5:
            walkers.append([*centre.tolist(), speed * math.cos(heading), speed * math.sin(heading)])
    x0 = [*start.tolist(), float(rng.uniform(-math.pi, math.pi))]
    target = goal.tolist() + ([float(rng.uniform(-math.pi, math.pi))] if model.p == 3 else [])  # a pose's heading
    return {"x0": x0, "target": target, "ellipses": [], "room": [float(width), float(height)], "pillars": pillars,
            "walkers": walkers}


def _segment_distance(point: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    t = np.clip(np.dot(point - a, b - a) / max(np.dot(b - a, b - a), 1e-12), 0.0, 1.0)
    return float(np.linalg.norm(point - (a + t * (b - a))))


def room_world(spec: Mapping[str, Any]) -> World:
    """The scenario's room as a map (walls and pillars occupied), origin at its lower-left corner."""
    width, height = spec["room"]
    cols, rows = round(width / RESOLUTION), round(height / RESOLUTION)
    cells = np.full((rows, cols), FREE, np.int8)
    wall = round(WALL / RESOLUTION)
    cells[:wall], cells[-wall:], cells[:, :wall], cells[:, -wall:] = OCCUPIED, OCCUPIED, OCCUPIED, OCCUPIED
    origin = Pose2D(-width / 2, -height / 2, 0.0)
    for cx, cy, size in spec["pillars"]:
        c0, c1 = (round((v - origin.x) / RESOLUTION) for v in (cx - size / 2, cx + size / 2))
        r0, r1 = (round((v - origin.y) / RESOLUTION) for v in (cy - size / 2, cy + size / 2))
        cells[r0:r1, c0:c1] = OCCUPIED
    return World(Grid(cells, RESOLUTION, origin))


def walkers_at(spec: Mapping[str, Any], t: float) -> np.ndarray:
    """The walkers' centres [W, 2] at time t (s): straight lines, held inside the room by its walls."""
    if not spec["walkers"]:
        return np.zeros((0, 2))
    w = np.asarray(spec["walkers"], float)
    half = np.array(spec["room"]) / 2 - WALL - WALKER_RADIUS
    return np.clip(w[:, :2] + t * w[:, 2:], -half, half)


class SensedRegions:
    """The region schedule of a world run: sample k's scan from the state the plant reached -> regions."""

    def __init__(self, spec: Mapping[str, Any], world: World, settings: ControllerSettings, x0: np.ndarray) -> None:
        self.spec, self.world, self.ts = spec, world, settings.sample_time
        self.perception = Perception(PerceptionSettings(max_circles=settings.max_ellipses,
                                                        max_walls=settings.max_polygons))
        self.angles = -math.pi + 2 * math.pi / BEAMS * np.arange(BEAMS)
        self.geometry = ScanGeometry(-math.pi, float(self.angles[-1]), 2 * math.pi / BEAMS, 0.05, RANGE_MAX)
        self.x = np.asarray(x0, float)
        self.seconds: list[float] = []

    def advanced(self, x: np.ndarray) -> None:
        self.x = np.asarray(x, float)

    def __call__(self, k: int) -> Sequence[Region]:
        t = k * self.ts
        sensor = Pose2D(*self.x[:3])
        circles = [(*c, WALKER_RADIUS) for c in walkers_at(self.spec, t)]
        ranges = self.world.scan(sensor, self.angles, RANGE_MAX, 0.05, circles)  # the simulated lidar: not timed
        begin = time.perf_counter()
        seen = self.perception.from_scan(ranges, self.geometry, sensor, t)
        self.seconds.append(time.perf_counter() - begin)
        return [region for _, region in seen.regions]


class TrackedPlant(DelayedPlant):
    """The robot: a plant whose command acts `delay` s late, its states every `dense` s kept (DelayedPlant: the
    run's truth between the samples), telling the region schedule where the robot is after each sample."""

    def __init__(self, plant, regions: SensedRegions, delay: float, dense: float) -> None:
        super().__init__(plant, delay, dense)
        self.regions = regions

    def advance(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        x = super().advance(x, u, dt)
        self.regions.advanced(x)
        return x


def body_clearance(spec: Mapping[str, Any], world: World, xy: np.ndarray, times: np.ndarray, body: float) -> float:
    """The least distance (m) of a disc of radius `body` at the positions xy [J, 2] (times [J], s) to an occupied
    cell (its centre less half a cell) or a walker; < 0: inside."""
    g = world.grid
    rows, cols = np.nonzero(g.cells >= OCCUPIED)
    centres = g.origin.apply(np.column_stack([cols + 0.5, rows + 0.5]) * g.resolution)
    walls = cKDTree(centres).query(xy)[0] - g.resolution / 2
    least = float(walls.min()) - body
    for j, t in enumerate(times):
        walkers = walkers_at(spec, float(t))
        if len(walkers):
            least = min(least, float(np.min(np.linalg.norm(walkers - xy[j], axis=1))) - WALKER_RADIUS - body)
    return least


def score_world(spec: dict[str, Any], family: Any, tools: Any) -> dict[str, Any]:
    """Run one world scenario (module doc) and return its record."""
    begin = time.perf_counter()
    controller = tools.controller
    controller.reset()
    settings, model = controller.settings, controller.model
    world = room_world(spec)
    x0 = np.asarray(spec["x0"], float)
    regions = SensedRegions(spec, world, settings, x0)
    plant = TrackedPlant(make_plant(spec["plant"], model, settings), regions, ACTUATOR_DELAY,
                         settings.sample_time / 10)
    run = run_closed_loop(controller, spec["x0"], spec["target"], spec["steps"], plant, regions=regions)
    ts = settings.sample_time
    dense, times = np.vstack([x0, *plant.path]), np.array([0.0, *plant.times])
    body = settings.body_radius
    target = np.asarray(spec["target"], float)
    # the planar robots' outputs are their first states (position, and a goal pose's heading, wrapped by the model)
    error = np.array([model.output_error(x[:len(target)], target) for x in run.x])
    distance = np.linalg.norm(error[:, :2], axis=1)
    within = distance < GOAL_TOLERANCE
    if len(target) == 3:  # a goal pose: the heading too, the short way round
        within &= np.abs(error[:, 2]) < HEADING_TOLERANCE
    reached_at = next((k for k in range(len(within)) if within[k:].all()), None)
    clearance = body_clearance(spec, world, dense[:, :2], times, body)
    return {"id": spec["id"], "family": spec["family"], "index": spec["index"],
            "spec": {k: spec[k] for k in ("x0", "target", "ellipses", "steps", "plant", "room", "pillars",
                                          "walkers")},
            "reached": reached_at is not None, "time_to_goal": None if reached_at is None else reached_at * ts,
            "final_distance": float(distance[-1]), "collision": clearance < 0.0, "min_body_clearance": clearance,
            "perception_ms": time_stats(np.array(regions.seconds) * 1e3),
            "solve_ms": time_stats(np.asarray(run.solve_time) * 1e3),
            "fallbacks": sum(StepStatus(s).is_fallback for s in run.status), "wall_s": time.perf_counter() - begin}


def summarize_world(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The world family's summary: success, collisions, time to goal, clearance, perception and solve time."""
    crashed = [r for r in records if r.get("crashed")]
    done = [r for r in records if not r.get("crashed")]
    if not done:
        return {"scenarios": 0, "crashed": len(crashed)}
    reached = [r for r in done if r["reached"]]
    return {
        "scenarios": len(done), "crashed": len(crashed),
        "reached": len(reached) / len(done), "collisions": sum(r["collision"] for r in done) / len(done),
        "time_to_goal_s": time_stats(np.array([r["time_to_goal"] for r in reached])) if reached else None,
        "min_body_clearance_m": min(r["min_body_clearance"] for r in done),
        "perception_ms_median": float(np.median([r["perception_ms"]["median"] for r in done])),
        "perception_ms_max": max(r["perception_ms"]["max"] for r in done),
        "solve_ms_median": float(np.median([r["solve_ms"]["median"] for r in done])),
        "solve_ms_max": max(r["solve_ms"]["max"] for r in done),
        "fallback_samples": sum(r["fallbacks"] for r in done),
    }
