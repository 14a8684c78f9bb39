"""Scene files: a run (config, x0, steps, plant), target changes and moving obstacles, as YAML.

    scene:
      config: mobile_robot.yaml   # params file: relative to the scene file, else a shipped config
      x0: [-8.0, -6.0, 0.0, 0.0]
      steps: 120
      plant: euler                # or continuous
      targets:                    # target changes over time (s)
        - {t: 0.0, y: [8.0, 6.0]}
      obstacles:                  # appear at t, vanish at until (optional), move at velocity
        - {id: walker, t: 0.0, until: 25.0, shape: ellipse, center: [0.0, -4.0],
           semi_axes: [0.7, 0.7], yaw: 0.0, velocity: [0.0, 0.4], frame: output}

`shape` is ellipse (`center`, `semi_axes`), box (`center`, `size`) or polygon (`vertices`); the
pose given is the one at the obstacle's appearance time `t`; `velocity` (plane units/s) is
constant. Optional keys: `description` (text) and `controller` (a mapping of controller
parameters that override the config's). A malformed scene raises SceneError with one line that
names the key and the problem.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ..config.settings import ControllerSettings, default_config_path
from ..errors import ConfigError, RegionError
from ..problem.models import Model
from ..problem.regions import Ellipse, Polygon, Region, rotated_box

SHAPES = ("ellipse", "box", "polygon")
PLANTS = ("euler", "continuous")
_SCENE_KEYS = {"config", "x0", "steps", "plant", "targets", "obstacles", "description", "controller"}
_OBSTACLE_KEYS = {"id", "t", "until", "shape", "center", "semi_axes", "size", "vertices", "yaw", "velocity", "frame"}
_SHAPE_KEYS = {"ellipse": ("center", "semi_axes"), "box": ("center", "size"), "polygon": ("vertices",)}


class SceneError(ConfigError):
    """A scene file that cannot be read or is malformed (one line: key and problem)."""


@dataclass(frozen=True)
class SceneObstacle:
    """One obstacle: its region at its appearance time `appear` (s), alive until `vanish` (s)."""

    name: str
    region: Region
    appear: float
    vanish: float = math.inf

    def alive(self, t: float) -> bool:
        return self.appear <= t < self.vanish

    def at(self, t: float) -> Region:
        """The region where it is at time t (s), with its velocity and stamp t."""
        return self.region.at(t)


@dataclass(frozen=True)
class Scene:
    """A parsed scene; times in s from the start of the run."""

    path: Path
    config: Path
    x0: tuple[float, ...]
    steps: int
    plant: str
    targets: tuple[tuple[float, tuple[float, ...]], ...]  # (t, y) sorted by t
    obstacles: tuple[SceneObstacle, ...]
    controller: Mapping[str, Any]
    description: str = ""

    def target_at(self, t: float) -> tuple[float, ...]:
        """The target in force at time t: the last change at or before t (the first one before it)."""
        current = self.targets[0][1]
        for when, y in self.targets:
            if when <= t + 1e-12:
                current = y
        return current

    def regions_at(self, t: float) -> list[Region]:
        """The obstacles alive at t, where they are at t (moving ones keep their velocity)."""
        return [o.at(t) for o in self.obstacles if o.alive(t)]

    def named_regions_at(self, t: float) -> list[tuple[str, Region]]:
        return [(o.name, o.at(t)) for o in self.obstacles if o.alive(t)]


def _numbers(key: str, value: Any, size: int | None = None) -> tuple[float, ...]:
    if isinstance(value, (str, bytes, Mapping)) or not isinstance(value, Sequence):
        raise SceneError(f"{key}: expected a list of numbers, got {value!r}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise SceneError(f"{key}: expected numbers, got {v!r}")
        if not math.isfinite(v):
            raise SceneError(f"{key}: values must be finite, got {v!r}")
        out.append(float(v))
    if size is not None and len(out) != size:
        raise SceneError(f"{key}: expected {size} numbers, got {len(out)}")
    return tuple(out)


def _number(key: str, value: Any) -> float:
    return _numbers(key, [value])[0] if not isinstance(value, (list, tuple)) else _numbers(key, value, 1)[0]


def _mapping(key: str, value: Any, allowed: set[str]) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise SceneError(f"{key}: expected a mapping, got {type(value).__name__}")
    unknown = sorted(map(str, set(value) - allowed))
    if unknown:
        raise SceneError(f"{key}: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(allowed))}")
    return value


def _obstacle(key: str, spec: Any, index: int) -> SceneObstacle:
    spec = _mapping(key, spec, _OBSTACLE_KEYS)
    shape = spec.get("shape")
    if shape not in SHAPES:
        raise SceneError(f"{key}.shape: must be one of {', '.join(SHAPES)}, got {shape!r}")
    for needed in _SHAPE_KEYS[shape]:
        if needed not in spec:
            raise SceneError(f"{key}.{needed}: missing (a {shape} needs {' and '.join(_SHAPE_KEYS[shape])})")
    appear = _number(f"{key}.t", spec.get("t", 0.0))
    vanish = _number(f"{key}.until", spec["until"]) if spec.get("until") is not None else math.inf
    if vanish <= appear:
        raise SceneError(f"{key}.until: must be later than t = {appear:g}, got {vanish:g}")
    velocity = _numbers(f"{key}.velocity", spec.get("velocity", [0.0, 0.0]), 2)
    yaw = _number(f"{key}.yaw", spec.get("yaw", 0.0))
    frame = spec.get("frame", "state")
    try:
        if shape == "ellipse":
            region: Region = Ellipse(_numbers(f"{key}.center", spec["center"], 2),
                                     _numbers(f"{key}.semi_axes", spec["semi_axes"], 2), yaw, frame, velocity, appear)
        elif shape == "box":
            region = rotated_box(_numbers(f"{key}.center", spec["center"], 2), _numbers(f"{key}.size", spec["size"], 2),
                                 yaw, frame, velocity, appear)
        else:
            raw = spec["vertices"]
            if not isinstance(raw, Sequence) or isinstance(raw, str):
                raise SceneError(f"{key}.vertices: expected a list of [x, y] points, got {raw!r}")
            vertices = tuple(_numbers(f"{key}.vertices[{i}]", v, 2) for i, v in enumerate(raw))
            region = Polygon(vertices, frame, velocity, appear)
    except RegionError as exc:
        raise SceneError(f"{key}: {exc}") from None
    name = str(spec.get("id", index))
    return SceneObstacle(name, region, appear, vanish)


def find_config(name: str, scene_dir: Path) -> Path:
    """A params file named in a scene: relative to the scene file, else a shipped config."""
    candidate = Path(name)
    if candidate.is_absolute() and candidate.exists():
        return candidate
    for base in (scene_dir, default_config_path().parent):
        if (base / candidate).exists():
            return base / candidate
    raise SceneError(f"scene.config: cannot find {name!r} next to the scene ({scene_dir}) or among the shipped configs")


def parse_scene(data: Any, path: Path) -> Scene:
    """A Scene from the loaded YAML; SceneError naming the key and the problem."""
    if not isinstance(data, Mapping) or "scene" not in data:
        raise SceneError("scene: the file needs a top-level 'scene' mapping")
    body = _mapping("scene", data["scene"], _SCENE_KEYS)
    for needed in ("config", "x0", "steps", "targets"):
        if needed not in body:
            raise SceneError(f"scene.{needed}: missing")
    if not isinstance(body["config"], str):
        raise SceneError(f"scene.config: expected a file name, got {body['config']!r}")
    config = find_config(body["config"], path.parent)
    x0 = _numbers("scene.x0", body["x0"])
    steps = body["steps"]
    if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= 100000:
        raise SceneError(f"scene.steps: expected an integer in [1, 100000], got {steps!r}")
    plant = body.get("plant", "euler")
    if plant not in PLANTS:
        raise SceneError(f"scene.plant: must be one of {', '.join(PLANTS)}, got {plant!r}")
    raw_targets = body["targets"]
    if not isinstance(raw_targets, Sequence) or isinstance(raw_targets, str) or not raw_targets:
        raise SceneError("scene.targets: expected a non-empty list of {t, y}")
    targets = []
    for i, spec in enumerate(raw_targets):
        spec = _mapping(f"scene.targets[{i}]", spec, {"t", "y"})
        if "y" not in spec:
            raise SceneError(f"scene.targets[{i}].y: missing")
        targets.append((_number(f"scene.targets[{i}].t", spec.get("t", 0.0)), _numbers(f"scene.targets[{i}].y",
                                                                                     spec["y"])))
    if len({len(y) for _, y in targets}) != 1:
        raise SceneError("scene.targets: every y must have the same length")
    raw_obstacles = body.get("obstacles") or []
    if not isinstance(raw_obstacles, Sequence) or isinstance(raw_obstacles, str):
        raise SceneError("scene.obstacles: expected a list")
    obstacles = tuple(_obstacle(f"scene.obstacles[{i}]", spec, i) for i, spec in enumerate(raw_obstacles))
    names = [o.name for o in obstacles]
    if len(set(names)) != len(names):
        raise SceneError(f"scene.obstacles: ids must be unique, got {names}")
    controller = body.get("controller") or {}
    if not isinstance(controller, Mapping):
        raise SceneError("scene.controller: expected a mapping of controller parameters")
    return Scene(path, config, x0, steps, plant, tuple(sorted(targets, key=lambda e: e[0])), obstacles,
                 dict(controller), str(body.get("description", "")))


def load_scene(path: str | Path) -> Scene:
    """Read and parse a scene file; SceneError (one line) for anything wrong with it."""
    p = Path(path)
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise SceneError(f"cannot read scene {p}: {getattr(exc, 'strerror', None) or exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        line = f" at line {where.line + 1}" if where is not None else ""
        raise SceneError(f"scene {p}: not valid YAML{line}: {getattr(exc, 'problem', None) or exc}") from None
    except RecursionError:
        raise SceneError(f"scene {p}: nested too deeply") from None
    return parse_scene(data, p)


def region_pose(region: Region) -> dict[str, Any]:
    """JSON pose of a region: ellipse centre, semi-axes, yaw; polygon vertices; velocity of both."""
    if isinstance(region, Ellipse):
        return {"center": list(region.center), "semi_axes": list(region.semi_axes), "yaw": region.yaw,
                "velocity": list(region.velocity)}
    return {"vertices": [list(v) for v in region.vertices], "velocity": list(region.velocity)}


def plane_point(region: Region, x: np.ndarray, u: np.ndarray, model: Model, settings: ControllerSettings
                ) -> tuple[float, float]:
    """The point of state x [n] (with input u [m]) in the region's plane, as the controller maps it."""
    if region.frame == "state":
        return float(x[settings.plane[0]]), float(x[settings.plane[1]])
    y = np.asarray(model.output(x, u), float).ravel()
    return float(y[settings.output_plane[0]]), float(y[settings.output_plane[1]])


def obstacle_track(scene: Scene, x: np.ndarray, u: np.ndarray, sample_time: float, model: Model,
                   settings: ControllerSettings) -> tuple[list[dict[str, Any]], dict[str, float | None]]:
    """Per sample k = 0..K (states x [K+1, n], inputs u [K, m]) the pose of every obstacle alive at
    k Ts, and per obstacle the minimum clearance -g over the samples (None if never alive).

    g is the region's depth (> 0 inside: 1 - normalised squared radius for an ellipse, distance to
    the nearest edge for a polygon), evaluated where the obstacle is at each sample's time.
    """
    poses: list[dict[str, Any]] = []
    clearance: dict[str, float | None] = {o.name: None for o in scene.obstacles}
    for k, state in enumerate(x):
        t = k * sample_time
        command = u[min(k, len(u) - 1)]
        sample = {}
        for name, region in scene.named_regions_at(t):
            sample[name] = region_pose(region)
            value = -region.depth(plane_point(region, state, command, model, settings))
            clearance[name] = value if clearance[name] is None else min(clearance[name], value)
        poses.append(sample)
    return poses, clearance
