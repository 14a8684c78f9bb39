"""Campaign scenario families: what a scenario is and how each family draws its scenarios.

A scenario is a JSON-ready dict (its "spec"): id '<family>-<index>', family, index, config (the
params file), steps, plant, x0 [n], target [p], ellipses (list of {center, semi_axes, yaw,
frame}) and whatever else its family's generator adds. Each scenario is drawn from its own
generator seeded by (seed, family code, index), so it never depends on how many others there
are, which ran before, or where it runs.

Adding a family is one entry in FAMILIES: a key (the id prefix and the command-line name:
`--<key> N`, `--<key>-steps`, `--<key>-config`, its underscores as dashes), a seed code never used before, the shipped
params file, defaults, a generator `(rng, settings, model) -> spec fields`, the passage test
the scoring uses to name the cause of a stop short, and, for regions that change during the
run, a `schedule` turning the spec into the region set of each sample.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ...core.config.settings import ControllerSettings, default_config_path, load_params_file
from ...core.loop.closed_loop import RegionSchedule
from ...core.loop.metrics import keep_in_values
from ...core.problem.models import Model
from ...core.problem.regions import Ellipse, Region
from .reachability import planar_passage, trajectory_passage, vdp_passage
from .world import score_world, summarize_world, world_scenario

#: an ellipse never contains the initial point: its depth there is below -START_MARGIN
START_MARGIN = 0.2

Generator = Callable[[np.random.Generator, ControllerSettings, Model], dict[str, Any]]
#: (final state [n], final output [p], goal output [p], regions as planned around, settings) -> is there an
#: admissible way?
Passage = Callable[[np.ndarray, np.ndarray, np.ndarray, Sequence[Region], ControllerSettings], bool]


def spec_ellipses(spec: Mapping[str, Any]) -> list[Region]:
    """The spec's ellipses as core regions (a moving one: its pose at time 0 and its `velocity`)."""
    return [Ellipse(tuple(e["center"]), tuple(e["semi_axes"]), e["yaw"], e["frame"], tuple(e.get("velocity", (0, 0))))
            for e in spec["ellipses"]]


def static_schedule(spec: Mapping[str, Any]) -> RegionSchedule:
    """The spec's ellipses, set once at sample 0 (the default schedule)."""
    regions = spec_ellipses(spec)
    return lambda k: regions if k == 0 else None


@dataclass(frozen=True)
class Family:
    """One scenario family (see the module docstring); `config` and `steps` as resolved by `families`."""

    key: str
    code: int
    config_name: str
    default_count: int
    default_steps: int
    generate: Generator
    passage: Passage
    title: str
    schedule: Callable[[Mapping[str, Any]], RegionSchedule] = static_schedule
    config: Path = Path()
    steps: int = 0
    #: a family that runs and scores its scenarios its own way (world.py): (spec, family, Tools) -> record, and
    #: its records -> its summary; None: scoring.score_scenario and summary.summarize
    score: Callable[..., dict[str, Any]] | None = None
    summarize: Callable[[Sequence[dict[str, Any]]], dict[str, Any]] | None = None
    #: a necessary test asked first and recorded beside the passage, which is asked only where it holds (van der
    #: Pol: the geometric corridor of free x2 slices, which the passage asks the model's dynamics to travel); None:
    #: `passage` alone
    corridor: Passage | None = None


def moving_schedule(spec: Mapping[str, Any]) -> RegionSchedule:
    """The spec's ellipses where they are at each sample's time k Ts (Ts: the spec's `sample_time`)."""
    regions, ts = spec_ellipses(spec), float(spec["sample_time"])
    return lambda k: [r.at(k * ts) for r in regions]


def _ellipse_dict(e: Ellipse) -> dict[str, Any]:
    out = {"center": list(e.center), "semi_axes": list(e.semi_axes), "yaw": e.yaw, "frame": e.frame}
    return {**out, "velocity": list(e.velocity)} if e.moving else out


def place_ellipses(rng: np.random.Generator, count: int, start: np.ndarray, draw: Callable[[], Ellipse]
                   ) -> list[dict[str, Any]]:
    """`count` ellipses from `draw`, redrawn while one contains `start` (depth > -START_MARGIN)."""
    out = []
    for _ in range(count):
        for _attempt in range(200):
            e = draw()
            if e.depth(start) < -START_MARGIN:
                out.append(_ellipse_dict(e))
                break
    return out


def vdp_scenario(rng: np.random.Generator, settings: ControllerSettings, model: Model) -> dict[str, Any]:
    """x0 in the box with |x1 x2| <= 2, y_t ~ U[-8, 8], 0-4 state-plane ellipses not containing x0."""
    lo, hi = np.array(settings.state_min), np.array(settings.state_max)
    while True:
        x0 = rng.uniform(lo, hi)
        if abs(x0[0] * x0[1]) <= 2.0:
            break
    y_t = float(rng.uniform(-8.0, 8.0))
    end = float(np.clip(y_t, lo[0] * settings.steady_state_scale, hi[0] * settings.steady_state_scale))

    def draw() -> Ellipse:
        if rng.random() < 0.5:  # near the way from x0 to the target's steady state
            c = (rng.uniform(min(x0[0], end), max(x0[0], end)), rng.uniform(-1.2, 1.2))
        else:
            c = (rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1]))
        return Ellipse(c, (rng.uniform(0.3, 1.5), rng.uniform(0.15, 0.8)), rng.uniform(0, math.pi), "state")

    ellipses = place_ellipses(rng, int(rng.integers(0, 5)), x0[list(settings.plane)], draw)
    return {"x0": x0.tolist(), "target": [y_t], "ellipses": ellipses}


def robot_scenario(rng: np.random.Generator, settings: ControllerSettings, model: Model) -> dict[str, Any]:
    """Start in [-9, 9]^2 with speed <= 1 m/s, goal ~ U[-11, 11]^2, 0-4 output-plane ellipses."""
    start = rng.uniform(-9.0, 9.0, 2)
    heading, speed = rng.uniform(0, 2 * math.pi), rng.uniform(0.0, 1.0)
    x0 = np.array([*start, speed * math.cos(heading), speed * math.sin(heading)])
    goal = rng.uniform(-11.0, 11.0, 2)
    end = np.clip(goal, -9.9, 9.9)

    def draw() -> Ellipse:
        if rng.random() < 0.6:  # across the straight way to the goal
            c = start + rng.uniform(0.25, 0.75) * (end - start) + rng.normal(0.0, 0.5, 2)
        else:
            c = rng.uniform(-9.0, 9.0, 2)
        return Ellipse(tuple(c), (rng.uniform(0.4, 2.0), rng.uniform(0.4, 2.0)), rng.uniform(0, math.pi), "output")

    ellipses = place_ellipses(rng, int(rng.integers(0, 5)), start, draw)
    return {"x0": x0.tolist(), "target": goal.tolist(), "ellipses": ellipses}


def unicycle_scenario(rng: np.random.Generator, settings: ControllerSettings, model: Model) -> dict[str, Any]:
    """A scene drawn as the robot family's (start, goal, 0-4 ellipses; its own seed code, so not the same
    scenes) for the unicycle (x, y, heading), at rest, facing the way the robot's initial velocity would point,
    drawn again until start and goal are inside the keep-in set (a start outside the arena is held there: every
    input predicts the violation it starts with; a goal outside it is tracked as its box projection y*, which
    the soft arena moves, so the run's end is not comparable with the campaign's y* and y~)."""
    while True:  # start and goal inside the keep-in set (config/unicycle.yaml: the arena x^2 + y^2 <= 100)
        spec = robot_scenario(rng, settings, model)
        x, y, vx, vy = spec["x0"]
        x0 = np.array([x, y, math.atan2(vy, vx)])
        goal = np.array([*spec["target"], 0.0])
        inside = keep_in_values(settings, model, np.vstack([x0, goal]), np.zeros((2, model.m)))
        if np.all(inside <= -START_MARGIN):
            return {**spec, "x0": x0.tolist()}


def bicycle_scenario(rng: np.random.Generator, settings: ControllerSettings, model: Model) -> dict[str, Any]:
    """The unicycle family's kind of scene (at rest, start and goal inside the arena, 0-4 ellipses; its own seed
    code) for the car-like robot, whose goal is a pose: a heading drawn uniformly in [-pi, pi)."""
    spec = unicycle_scenario(rng, settings, model)
    return {**spec, "target": [*spec["target"][:2], float(rng.uniform(-math.pi, math.pi))]}


#: robot speed the crossing times of the moving family are planned with (the config's limit is 1.2 m/s)
NOMINAL_SPEED = 1.0
#: obstacle speeds of the moving family, m/s
CROSSING_SPEEDS = (0.2, 0.6)


def moving_scenario(rng: np.random.Generator, settings: ControllerSettings, model: Model) -> dict[str, Any]:
    """The robot at rest crosses 16 m straight (start on a circle of radius 8, goal opposite) while 1-4
    ellipses cross its straight path at 0.2-0.6 m/s, within +-30 degrees of square to it, each
    timed to reach the path within +-2.5 s of when the robot would at NOMINAL_SPEED; none starts
    within 1.5 m of the robot. The robot is twice as fast as any of them: an evasion is dynamically
    possible, by braking, waiting or going round."""
    heading = rng.uniform(0, 2 * math.pi)
    start = 8.0 * np.array([math.cos(heading), math.sin(heading)])
    goal = -start
    along = (goal - start) / np.linalg.norm(goal - start)
    normal = np.array([-along[1], along[0]])

    def draw() -> Ellipse:
        s = rng.uniform(0.2, 0.8)
        crossing = start + s * (goal - start)
        arrive = 1.0 + s * 16.0 / NOMINAL_SPEED + rng.uniform(-2.5, 2.5)
        angle = rng.uniform(-math.pi / 6, math.pi / 6)
        side = rng.choice((-1.0, 1.0))
        direction = side * (math.cos(angle) * normal + math.sin(angle) * along)
        velocity = rng.uniform(*CROSSING_SPEEDS) * direction
        center = crossing - velocity * arrive
        return Ellipse(tuple(center), (rng.uniform(0.4, 0.9), rng.uniform(0.4, 0.9)), rng.uniform(0, math.pi),
                       "output", tuple(velocity))

    ellipses = []
    while not ellipses:  # 1-4 of them, none within 1.5 m of the start
        wanted = int(rng.integers(1, 5))
        for _ in range(200 * wanted):
            e = draw()
            if np.linalg.norm(np.asarray(e.center) - start) - max(e.semi_axes) > 1.5:
                ellipses.append(_ellipse_dict(e))
            if len(ellipses) == wanted:
                break
    return {"x0": [*start.tolist(), 0.0, 0.0], "target": goal.tolist(), "ellipses": ellipses,
            "sample_time": settings.sample_time}


def _planar_way(x_end: np.ndarray, y_end: np.ndarray, y_goal: np.ndarray, regions: Sequence[Region],
                settings: ControllerSettings) -> bool:
    """The planar families' Passage: a free path between the outputs (reachability.planar_passage)."""
    return planar_passage(y_end, y_goal, regions)


#: every family of the campaign, in the order they are listed and summarised
FAMILIES: tuple[Family, ...] = (
    Family("vdp", 1, "van_der_pol.yaml", 500, 80, vdp_scenario,
           lambda x_end, y_end, y_goal, regions, settings: trajectory_passage(x_end, y_goal, regions, settings),
           "van der Pol",
           corridor=lambda x_end, y_end, y_goal, regions, settings: vdp_passage(x_end, y_goal, regions, settings)),
    Family("robot", 2, "mobile_robot.yaml", 200, 140, robot_scenario, _planar_way, "mobile robot"),
    # not run unless asked for (--moving N): compare with --sweep predict_obstacles=true,false
    Family("moving", 3, "mobile_robot.yaml", 0, 100, moving_scenario, _planar_way,
           "robot among moving ellipses", schedule=moving_schedule),
    # not run unless asked for (--unicycle N): scenes of the robot family's kind with config/unicycle.yaml
    Family("unicycle", 4, "unicycle.yaml", 0, 200, unicycle_scenario, _planar_way, "unicycle"),
    # not run unless asked for (--bicycle N): the car-like robot (config/bicycle.yaml) to goal poses
    Family("bicycle", 5, "bicycle.yaml", 0, 200, bicycle_scenario, _planar_way, "car-like robot"),
    # not run unless asked for (--world N): the unicycle in random rooms, seeing only its lidar (world.py)
    Family("world", 6, "unicycle_world.yaml", 0, 150, world_scenario, _planar_way, "unicycle in a room",
           score=score_world, summarize=summarize_world),
    # not run unless asked for (--bicycle-world N): the car-like robot in the same rooms, to goal poses (world.py)
    Family("bicycle_world", 7, "bicycle_world.yaml", 0, 150, world_scenario, _planar_way, "car-like robot in a room",
           score=score_world, summarize=summarize_world),
)


def families(configs: Mapping[str, Path | str | None] | None = None,
             steps: Mapping[str, int | None] | None = None) -> dict[str, Family]:
    """FAMILIES by key with their params file (default: the shipped one) and samples per run resolved."""
    configs, steps = configs or {}, steps or {}
    unknown = sorted((set(configs) | set(steps)) - {f.key for f in FAMILIES})
    if unknown:
        raise KeyError(f"unknown campaign families {unknown}")
    shipped = default_config_path().parent
    return {f.key: replace(f, config=Path(configs.get(f.key) or shipped / f.config_name),
                           steps=int(steps.get(f.key) or f.default_steps)) for f in FAMILIES}


def load_settings(config: Path, max_solve_time: float | None = None) -> ControllerSettings:
    """Controller settings of a params file, optionally with another solver wall-time budget (s)."""
    return settings_from_params(load_params_file(config).section("controller"), max_solve_time)


def settings_from_params(params: Mapping[str, Any], max_solve_time: float | None = None,
                         overrides: Mapping[str, Any] | None = None) -> ControllerSettings:
    """Controller settings of a params section, with the campaign's budget and run-time overrides."""
    # offline: the compiled solvers from the first solve (a live config's background compile is for a node)
    settings = ControllerSettings.from_params(dict(params)).replace(codegen_background=False)
    if max_solve_time:
        settings = settings.replace(max_solve_time=max_solve_time)
    return settings.replace(**overrides) if overrides else settings


def make_specs(fam: Family, count: int, seed: int, settings: ControllerSettings, plant: str) -> list[dict[str, Any]]:
    """Scenario specs 0..count-1 of one family (ids '<family>-0000', ...), reproducible from seed."""
    model = settings.build_model()
    specs = []
    for i in range(count):
        rng = np.random.default_rng([seed, fam.code, i])
        spec = fam.generate(rng, settings, model)
        specs.append({"id": f"{fam.key}-{i:04d}", "family": fam.key, "index": i, "config": str(fam.config),
                      "steps": fam.steps, "plant": plant, **spec})
    return specs


def interleave(groups: Sequence[list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """The families mixed in proportion (each group keeps its order), so the bar's rate is even."""
    keyed = [((i + 0.5) / len(g), gi, spec) for gi, g in enumerate(groups) for i, spec in enumerate(g)]
    return [spec for _, _, spec in sorted(keyed, key=lambda t: (t[0], t[1]))]
